"""Sidebar panels (View3D > N > Skin): robot and pose, modules, boards and coverage, export."""
import bpy


class _Panel:
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "Skin"


class SKINSAFE_PT_robot(_Panel, bpy.types.Panel):
    bl_idname = "SKINSAFE_PT_robot"
    bl_label = "Robot"

    def draw(self, context):
        s, col = context.scene.skinsafe, self.layout.column()
        row = col.row(align=True)
        for src, label in (("ur5", "UR5"), ("panda", "Panda"), ("FILE", "URDF/MJCF...")):
            row.operator("skinsafe.import_robot", text=label).source = src
        if not s.robot_kind:
            return
        col.label(text=f"{s.robot_name} ({s.robot_kind})")
        for j in s.joints:
            col.prop(j, "value", text=j.name, slider=False)
        row = col.row(align=True)
        row.operator("skinsafe.set_pose", text="Home").preset = "HOME"
        row.operator("skinsafe.set_pose", text="Zero").preset = "ZERO"


class SKINSAFE_PT_modules(_Panel, bpy.types.Panel):
    bl_idname = "SKINSAFE_PT_modules"
    bl_label = "FPC Modules"

    def draw(self, context):
        s, col = context.scene.skinsafe, self.layout.column()
        t = s.new_module
        for k in ("template", "method", "rows", "cols", "pitch", "taxel_diameter", "margin", "min_bend_radius",
                  "max_strain"):
            col.prop(t, k)
        if t.template == "curve":
            col.prop(t, "outline")
        col.operator("skinsafe.place_skin", icon="RESTRICT_SELECT_OFF")
        col.operator("skinsafe.place_module", text="Place at 3D Cursor")
        col.operator("skinsafe.cover_link", text="Cover Active Link")
        col.prop(s, "auto_regenerate")
        col.operator("skinsafe.regenerate")
        act = context.active_object
        if act is not None and act.skinsafe_module.is_module:
            box = col.box()
            box.label(text=f"{act.name} on {act.skinsafe_module.body}")
            for k in ("rows", "cols", "pitch", "min_bend_radius", "max_strain"):
                box.prop(act.skinsafe_module.settings, k)
            if act.skinsafe_module.error:
                box.label(text=act.skinsafe_module.error, icon="ERROR")
            box.operator("skinsafe.remove_module")
        if s.error:
            for line in _wrap(s.error):
                col.label(text=line, icon="ERROR")
        elif s.message:
            col.label(text=s.message, icon="INFO")


class SKINSAFE_PT_analysis(_Panel, bpy.types.Panel):
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


def _wrap(text: str, width: int = 60):
    words, line = text.split(), ""
    for w in words:
        if len(line) + len(w) > width:
            yield line
            line = ""
        line += w + " "
    if line:
        yield line


CLASSES = (SKINSAFE_PT_robot, SKINSAFE_PT_modules, SKINSAFE_PT_analysis)


register, unregister = bpy.utils.register_classes_factory(CLASSES)
