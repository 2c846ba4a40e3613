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
from skinsafe.addon import register, unregister


def _bounds(objs) -> tuple[np.ndarray, np.ndarray]:
    pts = []
    for o in objs:
        M = np.array(o.matrix_world)
        corners = np.array([list(c) + [1.0] for c in o.bound_box])
        pts.append((corners @ M.T)[:, :3])
    pts = np.vstack(pts)
    return pts.min(axis=0), pts.max(axis=0)


def render(scene, path: Path, color: str = "heat", size: int = 1000, view=(0.6, -1.0, 1.2)) -> Path:
    """A Workbench picture of the robot and its skin, framed on the robot (orthographic).

    color "heat": the modules' heat-map colour attribute; "board": a colour per interface board.
    """
    robot_objs = [o for o in scene.objects if o.type == "MESH" and not o.skinsafe_module.is_module]
    modules = [o for o in scene.objects if o.skinsafe_module.is_module]
    if color == "board":
        design = b2c.design_of(scene)
        palette = np.array([[0.12, 0.47, 0.71], [1.0, 0.5, 0.05], [0.17, 0.63, 0.17], [0.84, 0.15, 0.16],
                            [0.58, 0.4, 0.74], [0.55, 0.34, 0.29], [0.89, 0.47, 0.76], [0.5, 0.5, 0.5]])
        board_of = {m.id: m.board for m in design.modules}
        for o in modules:
            o.color = (*palette[board_of[o.skinsafe_module.module_id] % len(palette)], 1.0)
    lo, hi = _bounds(modules or robot_objs)  # frame the skin
    centre, extent = (lo + hi) / 2, float(np.linalg.norm(hi - lo))
    cam_data = bpy.data.cameras.get("skinsafe_cam") or bpy.data.cameras.new("skinsafe_cam")
    cam_data.type = "ORTHO"
    cam_data.ortho_scale = 0.75 * extent
    cam = bpy.data.objects.get("skinsafe_cam") or bpy.data.objects.new("skinsafe_cam", cam_data)
    if cam.name not in scene.collection.objects:
        scene.collection.objects.link(cam)
    d = np.asarray(view, float) / np.linalg.norm(view)
    cam.location = centre + 3 * extent * d
    # look at the centre: camera -Z toward it, +Y up
    yaw, pitch = math.atan2(d[0], -d[1]), math.acos(d[2])
    cam.rotation_euler = (pitch, 0.0, yaw)
    scene.camera = cam
    r = scene.render
    r.engine = "BLENDER_WORKBENCH"
    r.resolution_x, r.resolution_y, r.resolution_percentage = size, size, 100
    r.film_transparent = False
    r.image_settings.file_format = "PNG"
    sh = scene.display.shading
    sh.light = "STUDIO"
    sh.color_type = "VERTEX" if color == "heat" else "OBJECT"
    sh.show_cavity = True
    for o in robot_objs:
        o.color = (0.75, 0.75, 0.78, 1.0)
    r.filepath = str(path)
    bpy.ops.render.render(write_still=True)
    return path


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


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--blend", default=str(Path(__file__).resolve().parents[1] / "blend_assets" / "ur5_skin.blend"))
    p.add_argument("--out", default="out/blender")
    a = p.parse_args(argv)
    print(json.dumps(run(Path(a.blend), Path(a.out))))
    return 0


if __name__ == "__main__":
    sys.exit(main())
