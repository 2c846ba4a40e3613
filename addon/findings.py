"""The Check panel (View3D > N > Skin > Check): a coverage bar per skinned link, and every finding of the
last `skinsafe.check` in a list; Select makes the module it names the active object, Frame also puts the 3D
cursor on the taxel it names and frames it in the viewport. A finding names its taxel ("taxel ID") or module
("module ID") in its text (core/design/audit.py): the taxel's module and place come from the design."""
import re

import bpy
import numpy as np
from bpy.props import BoolProperty, CollectionProperty, FloatVectorProperty, IntProperty, StringProperty

from skinsafe.addon import blender_to_core as b2c

_TAXEL, _MODULE = re.compile(r"taxel (\d+)"), re.compile(r"module (\d+)")


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
                col.progress(factor=min(r["fraction"], 1.0), type="BAR",
                             text=f"{body}: {r['fraction']:.0%} covered, {r['taxels']} taxels")
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


def unregister():
    del bpy.types.Scene.skinsafe_finding_index
    del bpy.types.Scene.skinsafe_findings
    _unregister()
