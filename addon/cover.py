"""Coverage fill in the add-on: cover the active link with copies of the new-module settings
(`skinsafe.core.design.cover`), around the modules already placed; one module object each. The fill runs
off Blender's thread (addon/background.py): `cover_inputs` reads the scene, `cover_work` fills, `keep_cover`
makes the objects."""
from dataclasses import replace

import bpy
import numpy as np
from bpy.props import StringProperty

from skinsafe.addon import background, designer
from skinsafe.addon import blender_to_core as b2c
from skinsafe.addon import core_to_blender as c2b
from skinsafe.core.design.cover import cover_design, cover_report
from skinsafe.core.design.placement import placed_from_design
from skinsafe.core.skin.model import DesignError, frames_from_normals


def cover_inputs(scene, body: str) -> tuple:
    """What `cover_work` needs, read from the scene (Blender's thread): robot, its reference, the body, the
    new-module template, board capacity, force threshold, the design to keep, the body's surface, the first new
    module id (`fresh_module_id`: none the design's history has used)."""
    bodies = b2c.body_objects(scene)
    if body not in bodies:
        raise DesignError(f"cover: no link selected; select a link of the robot or give body= one of {sorted(bodies)}")
    s = scene.skinsafe
    return (b2c.robot_for(scene), b2c.robot_ref(scene), body, b2c.settings_module(s.new_module, 0, "cover", body),
            s.board_capacity, s.force_threshold, b2c.design_of(scene), b2c.surface_of(bodies[body]),
            designer.fresh_module_id(scene))


def cover_work(robot, ref, body, template, capacity, threshold, design, surface, first_id):
    """The covered design (`skinsafe.core.design.cover`; no bpy: it may run in a worker thread)."""
    return cover_design(robot, ref, [body], template, board_capacity=capacity, force_threshold=threshold,
                        keep=design, surfaces={body: surface}, first_id=first_id)[0]


def keep_cover(scene, body: str, rev: int, new):
    """One module object per new module of the covered design `new`, stored as the scene's design, which must
    be the one it covered (`rev`: its revision when the cover started); (the new objects, the link's cover
    report row)."""
    if scene.skinsafe.design_rev != rev:
        raise DesignError("cover: the skin changed while the link was being covered; run Cover again")
    bodies, design, robot = b2c.body_objects(scene), b2c.design_of(scene), b2c.robot_for(scene)
    surface = b2c.surface_of(bodies[body])
    old = {m.id for m in design.modules} if design is not None else set()
    objects = {m.id: c2b.new_module_object(scene, bodies[body], m, _placed(new, m, surface), scene.skinsafe.new_module)
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


class SKINSAFE_OT_cover_link(background.Modal, bpy.types.Operator):
    """Cover the active link with modules of the settings above, as densely as its surface allows
    (whole modules, then trimmed ones; none on hidden surface or over another module)"""

    bl_idname = "skinsafe.cover_link"
    bl_label = "Cover Link"
    bl_options = {"REGISTER", "UNDO"}

    body: StringProperty(name="Body", description="link to cover (default: the active object's)")

    poll = classmethod(lambda cls, context: bool(context.scene.skinsafe.robot_kind))

    def execute(self, context):
        """The fill runs off Blender's thread (seconds on a long link; Esc cancels) where there is an event loop."""
        scene = context.scene
        act = context.active_object
        self.link = self.body or (act.get("skinsafe_body", "") if act is not None else "")
        try:
            job = background.Job(cover_work, *cover_inputs(scene, self.link))
        except DesignError as e:
            return self._fail(scene, e)
        self.rev = scene.skinsafe.design_rev
        return self.run(context, job, f"covering {self.link}")

    def finish(self, context, job):
        scene = context.scene
        try:
            objects, r = keep_cover(scene, self.link, self.rev, job.outcome())
        except DesignError as e:
            return self._fail(scene, e)
        scene.skinsafe.error = ""
        scene.skinsafe.message = (f"covered {self.link}: {len(objects)} modules, {r['taxels']} taxels, "
                                  f"{r['covered'] * 100:.0f}% of its open surface, largest gap {r['largest_gap_mm']:.0f} mm, "
                                  f"{r['overlaps']} overlapping, {r['buried']} buried")
        self.report({"INFO"}, scene.skinsafe.message)
        return {"FINISHED"}

    def _fail(self, scene, e):
        scene.skinsafe.error = str(e)
        self.report({"ERROR"}, str(e))
        return {"CANCELLED"}


register, unregister = bpy.utils.register_classes_factory((SKINSAFE_OT_cover_link,))
