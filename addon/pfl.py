"""ISO/TS 15066 in the designer: a viewport heat map of each taxel's highest safe approach speed
(v_max, m/s) for a body region at the current pose (View3D > N > Skin > PFL).

The numbers come from `skinsafe.core.safety.pfl` (the same as `skinsafe pfl`); each module mesh
gets a face attribute `pfl_vmax` and its `heat` colours (low v_max dark)."""
import bpy
import numpy as np
from bpy.props import EnumProperty

from skinsafe.addon import blender_to_core as b2c
from skinsafe.addon import core_to_blender as c2b
from skinsafe.core.robot.kinematics import TaxelKinematics
from skinsafe.core.sim.body_regions import REGIONS
from skinsafe.core.skin.model import DesignError

ATTRIBUTE = "pfl_vmax"
_ITEMS = [(name, r.label, f"{r.label}: {r.quasi_static_N:.0f} N quasi-static, {r.mass_kg} kg, "
           f"{r.k_N_per_m / 1e3:.0f} N/mm") for name, r in REGIONS.items() if r.transient_N is not None]


def map_vmax(scene, region: str) -> np.ndarray:
    """v_max (m/s) of every taxel for `region` at the scene's pose, shown on the module meshes."""
    design = b2c.design_of(scene)
    if design is None or not design.n_taxels:
        raise DesignError("skin: no modules placed yet; place a module first (skinsafe panel > Modules)")
    from skinsafe.core.safety.pfl import taxel_speed_limits  # imports numba: loaded by this map only

    kin = TaxelKinematics(b2c.robot_for(scene).model, design)
    values = taxel_speed_limits(kin, [region], b2c.pose(scene))[region]
    rgba = c2b.heat_colors(values)
    for obj in scene.objects:
        mm = obj.skinsafe_module
        if not mm.is_module:
            continue
        on = np.flatnonzero(design.taxels.module == mm.module_id)
        me = obj.data
        if len(me.polygons) != len(on):
            continue
        attr = me.attributes.get(ATTRIBUTE) or me.attributes.new(ATTRIBUTE, "FLOAT", "FACE")
        attr.data.foreach_set("value", values[on].astype(np.float32))
        me.color_attributes["heat"].data.foreach_set("color", np.repeat(rgba[on], 6, axis=0).astype(np.float32).ravel())
        me.color_attributes.active_color = me.color_attributes["heat"]
        me.update()
    return values


class SKINSAFE_OT_map_pfl(bpy.types.Operator):
    """Heat map of each taxel's highest safe approach speed (ISO/TS 15066) for a body region"""

    bl_idname = "skinsafe.map_pfl"
    bl_label = "Map Safe Speed"
    bl_options = {"REGISTER", "UNDO"}

    region: EnumProperty(name="Body region", items=_ITEMS, default="hand")

    @classmethod
    def poll(cls, context):
        s = context.scene.skinsafe
        return bool(s.robot_kind) and any(o.skinsafe_module.is_module for o in context.scene.objects)

    def execute(self, context):
        scene = context.scene
        try:
            v = map_vmax(scene, self.region)
        except DesignError as e:
            scene.skinsafe.error = str(e)
            self.report({"ERROR"}, str(e))
            return {"CANCELLED"}
        for area in context.screen.areas if context.screen else ():
            for space in area.spaces:
                if space.type == "VIEW_3D":
                    space.shading.color_type = "VERTEX"
        msg = f"{REGIONS[self.region].label}: safe approach speed min {v.min():.2f}, median {np.median(v):.2f} m/s"
        scene.skinsafe.error, scene.skinsafe.message = "", msg
        self.report({"INFO"}, msg)
        return {"FINISHED"}


class SKINSAFE_PT_pfl(bpy.types.Panel):
    bl_idname = "SKINSAFE_PT_pfl"
    bl_label = "PFL (ISO/TS 15066)"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "Skin"

    def draw(self, context):
        col = self.layout.column()
        col.label(text="Safe approach speed per taxel:")
        for name in ("hand", "lower_arm", "chest", "neck"):
            col.operator("skinsafe.map_pfl", text=REGIONS[name].label).region = name


register, unregister = bpy.utils.register_classes_factory((SKINSAFE_OT_map_pfl, SKINSAFE_PT_pfl))
