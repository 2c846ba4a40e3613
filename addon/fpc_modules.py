"""FPC Modules (View3D > N > Skin > FPC Modules): Place Module (at the 3D cursor or a given anchor), Re-generate
(moved, rotated or resized modules), Remove Module, and the panel with the new-module settings, the active
module's, and the last message or error (its Place Skin and Cover Active Link buttons run addon/place_tool.py and
addon/cover.py). Its operators and panel register with the others' (addon/__init__.py)."""
import bpy
import numpy as np
from bpy.props import FloatVectorProperty, StringProperty

from skinsafe.addon import blender_to_core as b2c
from skinsafe.addon import designer
from skinsafe.addon.shared import fail, has_robot, has_skin, ok
from skinsafe.core.skin.model import DesignError


class SKINSAFE_OT_place_module(bpy.types.Operator):
    """Wrap a new FPC module onto the link at the picked point (the 3D cursor) or a given anchor"""

    bl_idname = "skinsafe.place_module"
    bl_label = "Place Module"
    bl_options = {"REGISTER", "UNDO"}

    body: StringProperty(name="Body", description="body to place on (default: the active object's)")
    anchor: FloatVectorProperty(name="Anchor", size=3, subtype="TRANSLATION",
                                description="point in the body frame (used when 'Use cursor' is off)")
    direction: FloatVectorProperty(name="Row direction", size=3, default=(1.0, 0.0, 0.0),
                                   description="body-frame hint for the rows (projected onto the surface)")
    use_cursor: bpy.props.BoolProperty(name="Use cursor", default=True)

    poll = classmethod(lambda cls, context: has_robot(context))

    def execute(self, context):
        scene = context.scene
        body = self.body
        if not body:
            act = context.active_object
            body = act.get("skinsafe_body", "") if act is not None else ""
        try:
            bodies = b2c.body_objects(scene)
            if body not in bodies:
                raise DesignError(f"place: no body selected; select a link of the robot or give body= one of "
                                  f"{sorted(bodies)}")
            anchor = np.array(self.anchor)
            if self.use_cursor:
                W = np.linalg.inv(np.array(bodies[body].matrix_world))
                anchor = W[:3, :3] @ np.array(scene.cursor.location) + W[:3, 3]
            obj, placed = designer.place(scene, body, anchor, np.array(self.direction))
        except DesignError as e:
            return fail(self, scene, e)
        return ok(self, scene, f"placed {obj.name}: {len(placed)} taxels on {body}")


class SKINSAFE_OT_regenerate(bpy.types.Operator):
    """Re-generate moved/rotated/resized modules (or the active one) on the surface"""

    bl_idname = "skinsafe.regenerate"
    bl_label = "Re-generate Modules"
    bl_options = {"REGISTER", "UNDO"}

    poll = classmethod(lambda cls, context: has_skin(context))

    def execute(self, context):
        scene = context.scene
        act = context.active_object
        try:
            if act is not None and act.skinsafe_module.is_module:
                designer.regenerate(scene, act)
                errors = []
            else:
                errors = designer.regenerate_moved(scene)
        except DesignError as e:
            return fail(self, scene, e)
        if errors:
            return fail(self, scene, DesignError("; ".join(errors)))
        return ok(self, scene, "modules re-generated")


class SKINSAFE_OT_remove_module(bpy.types.Operator):
    """Remove the active skin module"""

    bl_idname = "skinsafe.remove_module"
    bl_label = "Remove Module"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        return context.active_object is not None and context.active_object.skinsafe_module.is_module

    def execute(self, context):
        name = context.active_object.name
        designer.remove(context.scene, context.active_object)
        return ok(self, context.scene, f"removed {name}")


class SKINSAFE_PT_modules(bpy.types.Panel):
    bl_space_type, bl_region_type, bl_category = "VIEW_3D", "UI", "Skin"
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


def _wrap(text: str, width: int = 60):
    words, line = text.split(), ""
    for w in words:
        if len(line) + len(w) > width:
            yield line
            line = ""
        line += w + " "
    if line:
        yield line


OPERATORS = (SKINSAFE_OT_place_module, SKINSAFE_OT_regenerate, SKINSAFE_OT_remove_module)
PANELS = (SKINSAFE_PT_modules,)
