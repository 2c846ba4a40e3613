"""The add-on run headless (the bpy module, no screen): open a skin scene, re-generate its
modules, map Jacobians, export the taxel map and render pictures. The demo runs this in its
own process (`python -m skinsafe.addon.headless`), so bpy never shares a process with pymeshlab.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import bpy  # first: before anything that could import pymeshlab
import numpy as np

from skinsafe.addon import blender_to_core as b2c
from skinsafe.addon import edits, register, unregister
from skinsafe.addon.core_to_blender import srgb_to_linear

PALETTE = np.array([[0.12, 0.47, 0.71], [1.0, 0.5, 0.05], [0.17, 0.63, 0.17], [0.84, 0.15, 0.16],
                    [0.58, 0.4, 0.74], [0.55, 0.34, 0.29], [0.89, 0.47, 0.76], [0.5, 0.5, 0.5]])  # sRGB, per board


def _world_points(objs) -> np.ndarray:
    """(k, 3) world coordinates of every vertex of the objects (the evaluated meshes)."""
    deps = bpy.context.evaluated_depsgraph_get()
    pts = []
    for o in objs:
        me = o.evaluated_get(deps).data
        co = np.empty(len(me.vertices) * 3)
        me.vertices.foreach_get("co", co)
        M = np.array(o.matrix_world)
        pts.append(co.reshape(-1, 3) @ M[:3, :3].T + M[:3, 3])
    return np.vstack(pts) if pts else np.zeros((1, 3))


class _CellTiles:
    """For a picture only: each taxel hexagon grown to its cell's width (corners at half the module
    pitch, so neighbours never overlap) and lifted `lift` m off the link, so the skin reads as
    coloured hexagonal dots that never z-fight with the surface. `restore()` puts the meshes back."""

    def __init__(self, modules, pitch: dict, lift: float = 0.0015):
        self.saved = []
        for o in modules:
            me = o.data
            co = np.empty(len(me.vertices) * 3)
            me.vertices.foreach_get("co", co)
            self.saved.append((o, co.copy()))
            hexes = co.reshape(-1, 6, 3)
            c = hexes.mean(axis=1, keepdims=True)
            n = np.cross(hexes[:, 0] - c[:, 0], hexes[:, 2] - c[:, 0])
            n /= np.linalg.norm(n, axis=1, keepdims=True)
            r = np.linalg.norm(hexes[:, :1] - c, axis=2, keepdims=True)
            grown = c + (hexes - c) * (0.5 * pitch[o.skinsafe_module.module_id] / r) + lift * n[:, None]
            me.vertices.foreach_set("co", grown.ravel())
            me.update()

    def restore(self) -> None:
        for o, co in self.saved:
            o.data.vertices.foreach_set("co", co)
            o.data.update()


def _frame(scene, objs, view, size: int):
    """An orthographic camera looking along -`view` at the objects, fitted to all their vertices
    with a 4 % margin; the image's aspect follows theirs (its long side `size` pixels)."""
    cam_data = bpy.data.cameras.get("skinsafe_cam") or bpy.data.cameras.new("skinsafe_cam")
    cam_data.type = "ORTHO"
    cam = bpy.data.objects.get("skinsafe_cam") or bpy.data.objects.new("skinsafe_cam", cam_data)
    if cam.name not in scene.collection.objects:
        scene.collection.objects.link(cam)
    d = np.asarray(view, float) / np.linalg.norm(view)
    yaw, pitch = math.atan2(d[0], -d[1]), math.acos(d[2])  # camera -Z toward the objects, +Y up
    cam.rotation_euler = (pitch, 0.0, yaw)
    R = np.array(cam.rotation_euler.to_matrix())
    pts = _world_points(objs)
    x, y, depth = pts @ R[:, 0], pts @ R[:, 1], pts @ d
    w, h = np.ptp(x) * 1.08, np.ptp(y) * 1.08
    centre = R[:, 0] * (x.max() + x.min()) / 2 + R[:, 1] * (y.max() + y.min()) / 2
    cam.location = centre + d * (depth.max() + 1.0)
    cam_data.clip_start, cam_data.clip_end = 0.01, float(np.ptp(depth) + 2.0)
    cam_data.ortho_scale = max(w, h)
    r = scene.render
    long = max(w, h)
    r.resolution_x = int(round(size * w / long))
    r.resolution_y = int(round(size * h / long))
    scene.camera = cam


def _heat_range(modules) -> float:
    """The largest value of the modules' heat attribute (the top of the colour scale), 0 if none."""
    top = 0.0
    for o in modules:
        attr = o.data.attributes.get("retractability")
        if attr is not None and len(attr.data):
            v = np.empty(len(attr.data))
            attr.data.foreach_get("value", v)
            top = max(top, float(v.max()))
    return top


def add_key(path: Path, vmax: float = 0.0, label: str = "", swatches=(), cmap="viridis") -> None:
    """Put a key beside the picture at `path` (rewritten in place): a colour bar (`cmap`) from 0 to
    `vmax` named `label`, or a legend of (sRGB colour, text) `swatches`."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Patch

    img = plt.imread(str(path))
    h, w = img.shape[:2]
    fig = plt.figure(figsize=(w / 100 * 1.22, h / 100), dpi=100)
    ax = fig.add_axes((0, 0, 1 / 1.22, 1))
    ax.imshow(img)
    ax.axis("off")
    if vmax > 0:
        cax = fig.add_axes((0.86, 0.15, 0.025, 0.7))
        cb = fig.colorbar(matplotlib.cm.ScalarMappable(matplotlib.colors.Normalize(0, vmax), cmap), cax=cax)
        cb.set_label(label, fontsize=15)
        cb.ax.tick_params(labelsize=13)
    if swatches:
        fig.legend(handles=[Patch(color=c, label=t) for c, t in swatches], loc="center right", frameon=False,
                   fontsize=14)
    tmp = path.with_suffix(".tmp.png")
    fig.savefig(tmp, dpi=100)
    plt.close(fig)
    tmp.replace(path)


def render(scene, path: Path, color: str = "heat", size: int = 1000, view=(0.6, -1.0, 0.7),
           vmax: float | None = None) -> Path:
    """A Workbench picture of the whole robot and its skin (orthographic, fitted to every vertex).

    color "heat": the modules' heat-map colour attribute; "board": a colour per interface board; "live": the
    live link's force colours (addon/live.py), keyed on the view's scale up to `vmax` N.
    The taxels are drawn as hexagonal dots as wide as their cells, lifted off the link (see `_CellTiles`).
    """
    robot_objs = [o for o in scene.objects if o.type == "MESH" and not o.skinsafe_module.is_module
                  and o.visible_get() and not o.hide_render]
    modules = [o for o in scene.objects if o.skinsafe_module.is_module]
    design = b2c.design_of(scene)
    if color == "board":
        board_of = {m.id: m.board for m in design.modules}
        for o in modules:
            o.color = (*srgb_to_linear(PALETTE[board_of[o.skinsafe_module.module_id] % len(PALETTE)]), 1.0)
    _frame(scene, robot_objs + modules, view, size)
    r = scene.render
    r.engine = "BLENDER_WORKBENCH"
    r.resolution_percentage = 100
    r.film_transparent = False
    r.image_settings.file_format = "PNG"
    scene.view_settings.view_transform = "Standard"  # the colours as given, not tone-mapped pale
    sh = scene.display.shading
    sh.light = "STUDIO"
    sh.color_type = "OBJECT" if color == "board" else "VERTEX"
    for o in modules:  # the colour attribute shown: "heat" or "live" (addon/live.py makes its own the active one)
        attrs = o.data.color_attributes
        if attrs.get(color) is not None:
            attrs.active_color = attrs[color]
    sh.show_cavity = True
    sh.show_object_outline = True
    for o in robot_objs:
        o.color = (0.72, 0.73, 0.76, 1.0)
    with edits.paused():  # the tiles are the picture's, not an edit of the modules
        tiles = _CellTiles(modules, {m.id: m.pitch for m in design.modules})
        try:
            r.filepath = str(path)
            bpy.ops.render.render(write_still=True)
        finally:
            tiles.restore()
    if color == "heat" and _heat_range(modules) > 0:
        add_key(path, _heat_range(modules), "retractability |J_p^T z|, m/s per rad/s")
    if color == "live":
        add_key(path, vmax, "force, N (the live view's scale)", cmap=_view_scale())
    if color == "board":
        t = design.taxels
        add_key(path, swatches=[(PALETTE[b.id % len(PALETTE)], f"{b.name}: {int((t.board == b.id).sum())} taxels")
                                for b in design.boards])
    return path


def _view_scale():
    """The live view's colour scale (core/runtime/view_scale.py) as a matplotlib colour map."""
    from matplotlib.colors import LinearSegmentedColormap

    from skinsafe.core.runtime.view_scale import COLOURS, STOPS

    return LinearSegmentedColormap.from_list("skinsafe_view", list(zip(STOPS, COLOURS / 255.0)))


def run(blend: Path, out: Path) -> dict:
    """Open the scene, re-generate every module, map Jacobians, export the map, render."""
    register()
    try:
        bpy.ops.wm.open_mainfile(filepath=str(blend))
        scene = bpy.context.scene
        modules = [o for o in scene.objects if o.skinsafe_module.is_module]
        for o in modules:
            bpy.context.view_layer.objects.active = o
            bpy.ops.skinsafe.regenerate()
        bpy.ops.skinsafe.assign_boards()
        bpy.ops.skinsafe.map_jacobians()
        design = b2c.design_of(scene)
        out.mkdir(parents=True, exist_ok=True)
        map_path = out / "ur5_skin.json"
        bpy.ops.skinsafe.export_taxel_map(filepath=str(map_path))
        pics = [render(scene, out / "skin_heat.png", "heat"), render(scene, out / "skin_boards.png", "board")]
        return {"taxel_map": str(map_path), "taxels": design.n_taxels, "modules": len(modules),
                "boards": len(design.boards), "pictures": [str(p) for p in pics]}
    finally:
        unregister()


def designer_path(out: Path) -> dict:
    """The designer's path on the UR5, as the docs show it (docs/design/blender.md), its pictures under `out`:
    three 8x8 modules placed with the Place Skin tool along rays (designer_place.png, a board each), one
    duplicated along the upper arm and mirrored (designer_edit.png), the Jacobian heat map
    (designer_heat.png); then checked and exported (taxel map, MuJoCo scene, URDF under out/export)."""

    register()
    try:
        bpy.ops.wm.read_homefile(use_empty=True)
        scene = bpy.context.scene
        bpy.ops.skinsafe.import_robot(source="ur5")
        s = scene.skinsafe
        s.board_capacity = 64  # a board per module: the pictures tell them apart
        st = s.new_module
        st.rows, st.cols, st.pitch, st.taxel_diameter, st.margin = 8, 8, 0.01, 0.006, 0.002
        out.mkdir(parents=True, exist_ok=True)
        for body, x, top in (("forearm_link", -0.3, 0.13585 - 0.1197 + 0.04), ("forearm_link", -0.12,
                                                                                0.13585 - 0.1197 + 0.04),
                             ("upper_arm_link", -0.3, 0.13585 + 0.06)):
            W = np.array(b2c.body_objects(scene)[body].matrix_world)
            origin, direction = W[:3, :3] @ (x, 0.0, top + 0.05) + W[:3, 3], -W[:3, 2]
            assert bpy.ops.skinsafe.place_skin(ray_origin=origin, ray_direction=direction) == {"FINISHED"}, s.error
        pics = [render(scene, out / "designer_place.png", "board")]
        along = np.array(b2c.body_objects(scene)["upper_arm_link"].matrix_world)[:3, 0]
        bpy.ops.object.duplicate_move(TRANSFORM_OT_translate={"value": tuple(along * 0.15)})
        bpy.ops.transform.mirror(constraint_axis=(True, False, False), orient_type="LOCAL")
        bpy.context.view_layer.update()
        pics.append(render(scene, out / "designer_edit.png", "board"))
        bpy.ops.skinsafe.map_jacobians()
        pics.append(render(scene, out / "designer_heat.png", "heat"))
        bpy.ops.skinsafe.check(poses=8)
        checked = s.message
        exp = out / "export"
        bpy.ops.skinsafe.export_taxel_map(filepath=str(exp / "skin.json"))
        bpy.ops.skinsafe.export_mjcf(directory=str(exp / "scene"))
        bpy.ops.skinsafe.export_urdf(filepath=str(exp / "skin.urdf"))
        design = b2c.design_of(scene)
        return {"modules": len(design.modules), "taxels": design.n_taxels, "boards": len(design.boards),
                "check": checked, "pictures": [str(p) for p in pics]}
    finally:
        unregister()


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--blend", default=str(Path(__file__).resolve().parents[1] / "blend_assets" / "ur5_skin.blend"))
    p.add_argument("--out", default="out/blender")
    p.add_argument("--designer-path", action="store_true", help="the docs' designer's path instead (designer_path)")
    a = p.parse_args(argv)
    print(json.dumps(designer_path(Path(a.out)) if a.designer_path else run(Path(a.blend), Path(a.out))))
    return 0


if __name__ == "__main__":
    sys.exit(main())
