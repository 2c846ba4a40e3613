"""Frames, Jacobians, Boards (View3D > N > Skin): Assign Boards (whole modules onto interface boards), Map
Jacobians (the retractability heat map), Coverage Report, and the panel that holds them with the frames' toggle
(addon/frames.py) and the export buttons (addon/export.py). Its operators and panel register with the others'
(addon/__init__.py)."""
import bpy
import numpy as np

from skinsafe.addon import designer
from skinsafe.addon.shared import fail, has_skin, ok
from skinsafe.core.design.coverage import format_report
from skinsafe.core.skin.model import DesignError


class SKINSAFE_OT_assign_boards(bpy.types.Operator):
    """Assign whole modules to interface boards of the given channel capacity"""

    bl_idname = "skinsafe.assign_boards"
    bl_label = "Assign Boards"
    bl_options = {"REGISTER", "UNDO"}

    poll = classmethod(lambda cls, context: has_skin(context))

    def execute(self, context):
        try:
            d = designer.assign_boards(context.scene)
        except DesignError as e:
            return fail(self, context.scene, e)
        return ok(self, context.scene, f"{len(d.modules)} modules on {len(d.boards)} boards")


class SKINSAFE_OT_map_jacobians(bpy.types.Operator):
    """Heat map of per-taxel retractability |J_p^T z| at the current pose"""

    bl_idname = "skinsafe.map_jacobians"
    bl_label = "Map Jacobians"
    bl_options = {"REGISTER", "UNDO"}

    poll = classmethod(lambda cls, context: has_skin(context))

    def execute(self, context):
        try:
            v = designer.map_jacobians(context.scene)
        except DesignError as e:
            return fail(self, context.scene, e)
        for area in context.screen.areas if context.screen else ():
            for space in area.spaces:
                if space.type == "VIEW_3D":
                    space.shading.color_type = "VERTEX"
        return ok(self, context.scene, f"retractability min {v.min():.3f}, median {np.median(v):.3f} m/s per rad/s")


class SKINSAFE_OT_coverage(bpy.types.Operator):
    """Coverage report: skinned area, taxel count and density per link"""

    bl_idname = "skinsafe.coverage"
    bl_label = "Coverage Report"
    bl_options = {"REGISTER", "UNDO"}

    poll = classmethod(lambda cls, context: has_skin(context))

    def execute(self, context):
        rep = designer.coverage(context.scene)
        context.scene.skinsafe.coverage_text = format_report(rep)
        t = rep["total"]
        return ok(self, context.scene, f"{t['taxels']} taxels, {t['modules']} modules, {t['boards']} boards")


class SKINSAFE_PT_analysis(bpy.types.Panel):
    bl_space_type, bl_region_type, bl_category = "VIEW_3D", "UI", "Skin"
    bl_idname = "SKINSAFE_PT_analysis"
    bl_label = "Frames, Jacobians, Boards"

    def draw(self, context):
        s, col = context.scene.skinsafe, self.layout.column()
        row = col.row(align=True)
        row.operator("skinsafe.toggle_frames", text="Hide Frames" if s.show_frames else "Show Frames")
        row.prop(s, "frame_style", text="")
        col.prop(s, "frame_scale")
        col.operator("skinsafe.map_jacobians")
        col.prop(s, "board_capacity")
        col.operator("skinsafe.assign_boards")
        col.operator("skinsafe.coverage")
        for line in s.coverage_text.splitlines():
            col.label(text=line)
        col.operator("skinsafe.export_taxel_map")
        col.operator("skinsafe.export_mjcf")
        col.operator("skinsafe.export_urdf")
        col.operator("skinsafe.export_taxel_csv")


OPERATORS = (SKINSAFE_OT_assign_boards, SKINSAFE_OT_map_jacobians, SKINSAFE_OT_coverage)
PANELS = (SKINSAFE_PT_analysis,)
