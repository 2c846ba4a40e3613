"""Coverage fill in the add-on: cover the active link with copies of the new-module settings
(`skinsafe.core.design.cover`), around the modules already placed; one module object each."""
from dataclasses import replace

import bpy
import numpy as np
from bpy.props import StringProperty

from skinsafe.addon import blender_to_core as b2c
from skinsafe.addon import core_to_blender as c2b
from skinsafe.core.design.cover import cover_design, cover_report
from skinsafe.core.design.placement import placed_from_design
from skinsafe.core.skin.model import DesignError, frames_from_normals


def cover(scene, body: str):
    """Fill `body` with the scene's new-module settings; returns (new module objects, the link's
    cover report row)."""
    bodies = b2c.body_objects(scene)
    if body not in bodies:
        raise DesignError(f"cover: no link selected; select a link of the robot or give body= one of {sorted(bodies)}")
    s = scene.skinsafe
    robot, design = b2c.robot_for(scene), b2c.design_of(scene)
    template = b2c.settings_module(s.new_module, 0, "cover", body)
    surface = b2c.surface_of(bodies[body])
    new, _ = cover_design(robot, b2c.robot_ref(scene), [body], template, board_capacity=s.board_capacity,
                          force_threshold=s.force_threshold, keep=design, surfaces={body: surface})
    old = {m.id for m in design.modules} if design is not None else set()
    objects = {m.id: c2b.new_module_object(scene, bodies[body], m, _placed(new, m, surface), s.new_module)
               for m in new.modules if m.id not in old}
    new.modules = [replace(m, name=objects[m.id].name) if m.id in objects else m for m in new.modules]
    c2b.store_design(scene, new)
    return list(objects.values()), cover_report(new, robot.model, robot.home)[body]


def _placed(design, module, surface):
    """A covering module of `design` as placed, its anchor frame from its placement record."""
    p = placed_from_design(design, module.id)
    p.origin = np.asarray(module.placement["anchor"], float)
    normal = surface.closest(p.origin)[1]
    p.origin_frame = frames_from_normals(normal, np.asarray(module.placement["direction"], float)[None])[0]
    return p


class SKINSAFE_OT_cover_link(bpy.types.Operator):
    """Cover the active link with modules of the settings above, as densely as its surface allows
    (whole modules, then trimmed ones; none on hidden surface or over another module)"""

    bl_idname = "skinsafe.cover_link"
    bl_label = "Cover Link"
    bl_options = {"REGISTER", "UNDO"}

    body: StringProperty(name="Body", description="link to cover (default: the active object's)")

    poll = classmethod(lambda cls, context: bool(context.scene.skinsafe.robot_kind))

    def execute(self, context):
        scene = context.scene
        act = context.active_object
        body = self.body or (act.get("skinsafe_body", "") if act is not None else "")
        try:
            objects, r = cover(scene, body)
        except DesignError as e:
            scene.skinsafe.error = str(e)
            self.report({"ERROR"}, str(e))
            return {"CANCELLED"}
        scene.skinsafe.error = ""
        scene.skinsafe.message = (f"covered {body}: {len(objects)} modules, {r['taxels']} taxels, "
                                  f"{r['covered'] * 100:.0f}% of its open surface, largest gap {r['largest_gap_mm']:.0f} mm, "
                                  f"{r['overlaps']} overlapping, {r['buried']} buried")
        self.report({"INFO"}, scene.skinsafe.message)
        return {"FINISHED"}


register, unregister = bpy.utils.register_classes_factory((SKINSAFE_OT_cover_link,))
