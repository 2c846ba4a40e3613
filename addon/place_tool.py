"""Place Skin: a modal tool that places the scene's new-module settings where the mouse points. Each mouse
move casts a ray from the view: the link it meets (a module counts for its link) and the point there are
the anchor, a preview draws the module's taxels green where it fits or the failing taxel red with the
reason in the header (a stretched FPC: its worst pad, the strain and the cut that fits); the wheel turns the rows by 15 degrees, X toggles the X-mirror (the mirrored module
also goes to the symmetric place on the robot's other side), a click places it and makes it active, Esc or
right-click leaves. `preview` and the operator's `execute` take a given ray, so scripts and tests drive
the same work without a mouse. Its benchmark: addon/bench_tool.py."""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import bpy
import numpy as np
from bpy.props import BoolProperty, FloatProperty, FloatVectorProperty
from mathutils import Vector

from skinsafe.addon import blender_to_core as b2c
from skinsafe.addon import designer
from skinsafe.core.design.placement import PlacementError, place_module
from skinsafe.core.skin.model import DesignError, frames_from_normals

STEP = math.radians(15)  # the wheel's turn of the rows
GREEN, RED = (0.2, 0.85, 0.3, 1.0), (0.95, 0.15, 0.1, 1.0)


@dataclass
class Preview:
    """Where a module would go: body and body-frame anchor and row direction; the taxels' world positions
    when it fits; else the reason, its kind (`PlacementError.kind`: "strain", "off_surface", ...) and the
    failing taxel's world position (None: none to show)."""

    body: str | None = None
    anchor: np.ndarray | None = None
    direction: np.ndarray | None = None
    world: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    bad: np.ndarray | None = None
    reason: str = ""
    kind: str = ""


def hit(scene, origin, direction):
    """(body, body-frame point, body-frame normal) where the ray first meets a link of the robot (a module
    object counts for its link; anything else is passed through), or None."""
    deps = bpy.context.evaluated_depsgraph_get()
    bodies = b2c.body_objects(scene)
    link_of = {o.name: b for b, o in bodies.items()}
    o, d = Vector(origin), Vector(direction).normalized()
    for _ in range(16):
        ok, loc, normal, _, obj, _ = scene.ray_cast(deps, o, d)
        if not ok:
            return None
        body = link_of.get(obj.name) or (obj.skinsafe_module.body if obj.skinsafe_module.is_module else None)
        if body in bodies:
            W = np.linalg.inv(np.array(bodies[body].matrix_world))
            n = W[:3, :3] @ np.array(normal)
            return body, W[:3, :3] @ np.array(loc) + W[:3, 3], n / np.linalg.norm(n)
        o = loc + d * 1e-6
    return None


def rows_direction(normal: np.ndarray, angle: float) -> np.ndarray:
    """The rows' direction at a surface point: the body's x axis in the tangent plane, turned by `angle`
    about the normal."""
    x = frames_from_normals(normal[None], np.array([1.0, 0.0, 0.0]))[0][:, 0]
    return math.cos(angle) * x + math.sin(angle) * np.cross(normal, x)


def preview(scene, origin, direction, angle: float = 0.0, rows=None) -> Preview:
    """What placing the scene's new-module settings where the ray points would give (nothing is changed);
    `rows`: the rows' world direction instead of the link's x axis turned by `angle`."""
    h = hit(scene, origin, direction)
    if h is None:
        return Preview(reason="the ray meets no link of the robot; point at a link")
    body, p, n = h
    body_obj = b2c.body_objects(scene)[body]
    W = np.array(body_obj.matrix_world)
    x = rows_direction(n, angle) if rows is None else np.linalg.solve(W[:3, :3], np.asarray(rows, float))
    st = scene.skinsafe.new_module
    design = b2c.design_of(scene)
    module = b2c.settings_module(st, designer.fresh_module_id(scene, design), "new module", body)
    try:
        placed = place_module(b2c.surface_of(body_obj), module, p, x, st.method, b2c.outline_of(st),
                              designer.others_on(design, body))
    except PlacementError as e:
        bad = None if e.where is None else W[:3, :3] @ np.asarray(e.where[2]) + W[:3, 3]
        return Preview(body, p, x, bad=bad, reason=str(e), kind=e.kind)
    except DesignError as e:
        return Preview(body, p, x, reason=str(e))
    return Preview(body, p, x, world=placed.positions @ W[:3, :3].T + W[:3, 3])


def header(pv: Preview, mirror_x: bool) -> str:
    """The viewport header's line for a preview: what fits, or why not (a stretched FPC: the strain and the pads
    where, with the cut that fits)."""
    red = " (red: the worst pad)" if pv.kind == "strain" else " (red: the failing taxel)" if pv.bad is not None else ""
    what = ("stretched" if pv.kind == "strain" else "refused") + red + ": "
    line = (what + pv.reason) if pv.reason else (f"fits: {len(pv.world)} taxels on {pv.body}; click places, wheel "
                                                 "turns the rows")
    return line + f"; X-mirror {'on' if mirror_x else 'off'} (X)"


def x_mirror(scene) -> np.ndarray:
    """(4,4) the world's reflection across the robot's YZ plane (its root frame's x -> -x: Blender's X-mirror)."""
    root = next(o for o in b2c.body_objects(scene).values() if "skinsafe_robot" in o)
    R = np.array(root.matrix_world)
    return R @ np.diag([-1.0, 1.0, 1.0, 1.0]) @ np.linalg.inv(R)


def mirror_preview(scene, pv: Preview, origin, direction) -> Preview:
    """The mirror image of the previewed module (`pv`) on the robot's other side: the ray mirrored, the rows
    along minus the mirrored rows, so the mirrored FPC (`mirrored` settings) lies as the image of the first."""
    F = x_mirror(scene)
    W = np.array(b2c.body_objects(scene)[pv.body].matrix_world)
    return preview(scene, F[:3, :3] @ np.asarray(origin) + F[:3, 3], F[:3, :3] @ np.asarray(direction),
                   rows=-(F[:3, :3] @ (W[:3, :3] @ pv.direction)))


def place(context, pv: Preview):
    """Place the previewed module and make it the active, only selected object; the new object."""
    obj, _ = designer.place(context.scene, pv.body, pv.anchor, pv.direction)
    for o in context.view_layer.objects.selected:
        o.select_set(False)
    obj.select_set(True)
    context.view_layer.objects.active = obj
    return obj


def _draw(op) -> None:
    import gpu
    from gpu_extras.batch import batch_for_shader

    pv = op.pv
    if pv is None:
        return
    pts, colour, size = (pv.world, GREEN, 6.0) if not pv.reason else (
        (pv.bad[None], RED, 14.0) if pv.bad is not None else (np.zeros((0, 3)), RED, 0.0))
    if not len(pts):
        return
    shader = gpu.shader.from_builtin("POINT_UNIFORM_COLOR")
    batch = batch_for_shader(shader, "POINTS", {"pos": [tuple(p) for p in pts]})
    gpu.state.point_size_set(size)
    gpu.state.depth_test_set("NONE")
    shader.uniform_float("color", colour)
    batch.draw(shader)


class SKINSAFE_OT_place_skin(bpy.types.Operator):
    """Place the new-module settings where the mouse points: green where it fits, red at the failing taxel
    with the reason; the wheel turns the rows, a click places, Esc leaves"""

    bl_idname = "skinsafe.place_skin"
    bl_label = "Place Skin"
    bl_options = {"REGISTER", "UNDO"}

    ray_origin: FloatVectorProperty(name="Ray origin", size=3, subtype="TRANSLATION")
    ray_direction: FloatVectorProperty(name="Ray direction", size=3, default=(0.0, 0.0, -1.0))
    angle: FloatProperty(name="Row angle", subtype="ANGLE", default=0.0,
                         description="the rows' turn about the surface normal from the link's x axis")
    mirror_x: BoolProperty(name="X-mirror", default=False,
                           description="also place the mirrored module at the symmetric place on the robot's other "
                                       "side (across its YZ plane; X toggles it)")

    poll = classmethod(lambda cls, context: bool(context.scene.skinsafe.robot_kind))
    pv = None

    def execute(self, context):
        """Place along the given ray (scripts, tests, the redo panel)."""
        return self._commit(context, preview(context.scene, self.ray_origin, self.ray_direction, self.angle))

    def _commit(self, context, pv: Preview):
        scene = context.scene
        try:
            if pv.reason:
                raise DesignError(pv.reason)
            obj = place(context, pv)
        except DesignError as e:
            scene.skinsafe.error = str(e)
            self.report({"ERROR"}, str(e))
            return {"CANCELLED"}
        scene.skinsafe.error, scene.skinsafe.message = "", f"placed {obj.name}: {len(pv.world)} taxels on {pv.body}"
        if self.mirror_x:
            scene.skinsafe.message += "; " + self._mirror_copy(context, obj, pv)
        self.report({"INFO"}, scene.skinsafe.message)
        return {"FINISHED"}

    def _mirror_copy(self, context, first, pv: Preview) -> str:
        """Place the mirrored module at the symmetric place (the first stays active); what happened, in words."""
        st = context.scene.skinsafe.new_module
        st.mirrored = not st.mirrored
        try:
            pv = mirror_preview(context.scene, pv, self.ray_origin, self.ray_direction)
            if pv.reason:
                return f"its mirror copy was refused: {pv.reason}"
            obj = place(context, pv)
        except DesignError as e:
            return f"its mirror copy was refused: {e}"
        finally:
            st.mirrored = not st.mirrored
        for o in (obj, first):
            o.select_set(True)
        context.view_layer.objects.active = first
        return f"its mirror copy {obj.name}: {len(pv.world)} taxels on {pv.body}"

    def invoke(self, context, event):
        if context.area is None or context.area.type != "VIEW_3D":
            self.report({"ERROR"}, "Place Skin: run it from a 3D viewport")
            return {"CANCELLED"}
        self.pv = None
        self._handle = bpy.types.SpaceView3D.draw_handler_add(_draw, (self,), "WINDOW", "POST_VIEW")
        context.window_manager.modal_handler_add(self)
        context.area.header_text_set("Place Skin: point at a link; wheel turns the rows, click places, Esc leaves")
        return {"RUNNING_MODAL"}

    def modal(self, context, event):
        if event.type in {"MOUSEMOVE", "WHEELUPMOUSE", "WHEELDOWNMOUSE"}:
            if event.type != "MOUSEMOVE":
                self.angle += STEP if event.type == "WHEELUPMOUSE" else -STEP
            self._aim(context, event)
            return {"RUNNING_MODAL"}
        if event.type == "LEFTMOUSE" and event.value == "PRESS":
            self._end(context)
            return self._commit(context, self.pv or Preview(reason="move the mouse over a link first"))
        if event.type == "X" and event.value == "PRESS":
            self.mirror_x = not self.mirror_x
            self._aim(context, event)
            return {"RUNNING_MODAL"}
        if event.type in {"RIGHTMOUSE", "ESC"}:
            self._end(context)
            return {"CANCELLED"}
        return {"PASS_THROUGH"}  # navigation keeps working

    def _aim(self, context, event) -> None:
        from bpy_extras.view3d_utils import region_2d_to_origin_3d, region_2d_to_vector_3d

        # the viewport's main region, not context.region: started from the sidebar, that is the sidebar's
        region = next(r for r in context.area.regions if r.type == "WINDOW")
        view = context.area.spaces.active.region_3d
        xy = (event.mouse_x - region.x, event.mouse_y - region.y)
        self.ray_origin = region_2d_to_origin_3d(region, view, xy)
        self.ray_direction = region_2d_to_vector_3d(region, view, xy)
        self.pv = preview(context.scene, self.ray_origin, self.ray_direction, self.angle)
        context.area.header_text_set(header(self.pv, self.mirror_x))
        context.workspace.status_text_set(self.pv.reason or None)  # the whole reason, where the header cuts it
        context.area.tag_redraw()

    def _end(self, context) -> None:
        bpy.types.SpaceView3D.draw_handler_remove(self._handle, "WINDOW")
        context.area.header_text_set(None)
        context.workspace.status_text_set(None)
        context.area.tag_redraw()


register, unregister = bpy.utils.register_classes_factory((SKINSAFE_OT_place_skin,))

