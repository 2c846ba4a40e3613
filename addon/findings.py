"""The Check panel (View3D > N > Skin > Check): a coverage bar per skinned link, and every finding of the
last `skinsafe.check` in a list; Select makes the module it names the active object, Frame also puts the 3D
cursor on the taxel it names and frames it in the viewport. A finding names its taxel ("taxel ID", or the
first of "taxels ID and ID": a stretched module's worst pad) or module ("module ID") in its text
(core/design/audit.py): the taxel's module and place come from the design. Stretched modules come worst
first (`audit.strain_problems`); the coverage bars are the cells' union on each link (`coverage.covered_area`).
*Show uncovered area* draws, over the viewport, the surface points of each skinned link of the last coverage
report that no module covers (core/design/coverage.py `uncovered_points`), in orange."""
import re

import bpy
import numpy as np
from bpy.props import BoolProperty, CollectionProperty, FloatVectorProperty, IntProperty, StringProperty

from skinsafe.addon import blender_to_core as b2c
from skinsafe.core.design.coverage import uncovered_points

_TAXEL, _MODULE = re.compile(r"taxels? (\d+)"), re.compile(r"module (\d+)")
WARN = (1.0, 0.55, 0.0, 1.0)  # the uncovered area's colour
_overlay = None  # the uncovered area's draw handler
_uncovered: dict = {}  # scene name -> (design revision, {link: body-frame points})


class SkinsafeFinding(bpy.types.PropertyGroup):
    text: StringProperty()
    module_id: IntProperty(default=-1)  # the module it names (-1: none)
    location: FloatVectorProperty(size=3, subtype="TRANSLATION")  # world: the taxel's, else the module's anchor
    has_location: BoolProperty(default=False)


def fill(scene, problems: list[str]) -> None:
    """The scene's findings: one per problem, with the module and world place it names."""
    design = b2c.design_of(scene)
    bodies = b2c.body_objects(scene)
    items = scene.skinsafe_findings
    items.clear()
    t = design.taxels if design is not None else None
    for text in problems:
        f = items.add()
        f.text = text
        m, p = _TAXEL.search(text), None
        if m and t is not None and (hit := np.flatnonzero(t.ids == int(m.group(1)))).size:
            f.module_id, p = int(t.module[hit[0]]), t.positions[hit[0]]
        elif (m := _MODULE.search(text)) and design is not None:
            f.module_id = int(m.group(1))
            mod = next((x for x in design.modules if x.id == f.module_id), None)
            p = np.asarray(mod.placement["anchor"]) if mod is not None and "anchor" in mod.placement else None
        mod = next((x for x in design.modules if x.id == f.module_id), None) if design is not None else None
        if p is not None and mod is not None and mod.body in bodies:
            W = np.array(bodies[mod.body].matrix_world)
            f.location, f.has_location = tuple(W[:3, :3] @ p + W[:3, 3]), True
    scene.skinsafe_finding_index = 0


def uncovered_world(scene) -> np.ndarray:
    """(k, 3) world positions of the surface points no module covers, on each link with taxels in the
    design's coverage report (the last Check, Cover or Coverage); none without a report."""
    design = b2c.design_of(scene) if scene.skinsafe.robot_kind else None
    if design is None or not design.coverage:
        return np.zeros((0, 3))
    hit = _uncovered.get(scene.name)
    if hit is None or hit[0] != scene.skinsafe.design_rev:
        model = b2c.robot_for(scene).model
        hit = _uncovered[scene.name] = (scene.skinsafe.design_rev, {
            body: uncovered_points(design, model, design.bodies.index(body))
            for body, r in design.coverage.items() if body in design.bodies and r["taxels"]})
    bodies = b2c.body_objects(scene)
    world = [p @ W[:3, :3].T + W[:3, 3] for body, p in hit[1].items() if body in bodies
             for W in (np.array(bodies[body].matrix_world),)]
    return np.concatenate(world) if world else np.zeros((0, 3))


def _draw_uncovered():
    scene = bpy.context.scene
    if not scene.skinsafe_show_uncovered:
        return
    pts = uncovered_world(scene)
    if not len(pts):
        return
    import gpu
    from gpu_extras.batch import batch_for_shader
    shader = gpu.shader.from_builtin("UNIFORM_COLOR")
    batch = batch_for_shader(shader, "POINTS", {"pos": pts.astype(np.float32)})
    gpu.state.point_size_set(4.0)
    shader.bind()
    shader.uniform_float("color", WARN)
    batch.draw(shader)


def overlay_on() -> None:
    """Add the uncovered area's draw handler to the 3D viewports (once)."""
    global _overlay
    if _overlay is None:
        _overlay = bpy.types.SpaceView3D.draw_handler_add(_draw_uncovered, (), "WINDOW", "POST_VIEW")


def overlay_off() -> None:
    """Remove it (a handler left registered keeps a bpy process from exiting)."""
    global _overlay
    if _overlay is not None:
        bpy.types.SpaceView3D.draw_handler_remove(_overlay, "WINDOW")
        _overlay = None
    _uncovered.clear()


def _redraw(self, context) -> None:
    for area in context.screen.areas if context.screen else ():
        if area.type == "VIEW_3D":
            area.tag_redraw()


def bar_text(body: str, r: dict) -> str:
    """A link's coverage bar: the area its cells cover (overlaps once) of the link's."""
    return (f"{body}: {r['fraction']:.0%} covered ({r['skinned_area_m2'] * 1e4:.0f} of {r['link_area_m2'] * 1e4:.0f} "
            f"cm2), {r['taxels']} taxels")


class SKINSAFE_UL_findings(bpy.types.UIList):
    def draw_item(self, context, layout, data, item, icon, active_data, active_property, index=0, flt_flag=0):
        layout.label(text=item.text, icon="ERROR")


class SKINSAFE_OT_show_finding(bpy.types.Operator):
    """Select the module a finding names (Frame: and frame its taxel in the viewport)"""

    bl_idname = "skinsafe.show_finding"
    bl_label = "Show Finding"
    bl_options = {"REGISTER", "UNDO"}

    index: IntProperty(default=-1, description="the finding (default: the list's active one)")
    frame: BoolProperty(default=False)

    @classmethod
    def poll(cls, context):
        return len(context.scene.skinsafe_findings) > 0

    def execute(self, context):
        scene = context.scene
        i = self.index if self.index >= 0 else scene.skinsafe_finding_index
        if not 0 <= i < len(scene.skinsafe_findings):
            self.report({"ERROR"}, f"finding {i} does not exist; pick one of the list's {len(scene.skinsafe_findings)}")
            return {"CANCELLED"}
        f = scene.skinsafe_findings[i]
        objs = [o for o in b2c.module_objects(scene) if o.skinsafe_module.module_id == f.module_id]
        if not objs:
            self.report({"WARNING"}, "this finding names no module of the scene (re-run Check after edits)")
            return {"CANCELLED"}
        for o in context.view_layer.objects.selected:
            o.select_set(False)
        objs[0].select_set(True)
        context.view_layer.objects.active = objs[0]
        if self.frame and f.has_location:
            scene.cursor.location = f.location
            for area in context.screen.areas if context.screen else ():
                if area.type == "VIEW_3D":
                    region = next(r for r in area.regions if r.type == "WINDOW")
                    with context.temp_override(area=area, region=region):
                        bpy.ops.view3d.view_center_cursor()
        self.report({"INFO"}, f"{objs[0].name}: {f.text}")
        return {"FINISHED"}


class SKINSAFE_PT_findings(bpy.types.Panel):
    bl_space_type, bl_region_type, bl_category = "VIEW_3D", "UI", "Skin"
    bl_idname = "SKINSAFE_PT_findings"
    bl_label = "Check"

    def draw(self, context):
        scene, col = context.scene, self.layout.column()
        col.operator("skinsafe.check")
        design = b2c.design_of(scene) if scene.skinsafe.robot_kind else None
        for body, r in sorted((design.coverage if design is not None else {}).items()):
            if body != "total":  # per-link coverage of the last check or coverage report
                col.progress(factor=min(r["fraction"], 1.0), type="BAR", text=bar_text(body, r))
        if design is not None and design.coverage:
            col.prop(scene, "skinsafe_show_uncovered")
        if not len(scene.skinsafe_findings):
            col.label(text="no findings (run Check)")
            return
        col.template_list("SKINSAFE_UL_findings", "", scene, "skinsafe_findings", scene, "skinsafe_finding_index", rows=4)
        row = col.row(align=True)
        row.operator("skinsafe.show_finding", text="Select").frame = False
        row.operator("skinsafe.show_finding", text="Frame").frame = True


CLASSES = (SkinsafeFinding, SKINSAFE_UL_findings, SKINSAFE_OT_show_finding, SKINSAFE_PT_findings)
_register, _unregister = bpy.utils.register_classes_factory(CLASSES)


def register():
    _register()
    bpy.types.Scene.skinsafe_findings = CollectionProperty(type=SkinsafeFinding)
    bpy.types.Scene.skinsafe_finding_index = IntProperty(default=0)
    bpy.types.Scene.skinsafe_show_uncovered = BoolProperty(
        name="Show uncovered area", default=False, update=_redraw,
        description="draw the surface points of the skinned links that no module covers (orange)")
    if not bpy.app.background:  # no viewport draws in background mode
        overlay_on()


def unregister():
    overlay_off()
    del bpy.types.Scene.skinsafe_show_uncovered
    del bpy.types.Scene.skinsafe_finding_index
    del bpy.types.Scene.skinsafe_findings
    _unregister()
