"""Check Skin: the skin checked as `skinsafe check` does, off Blender's thread (addon/background.py); its findings
fill the Check panel's list (addon/findings.py). Its operator registers with the others' (addon/__init__.py)."""
import bpy

from skinsafe.addon import background, designer, findings
from skinsafe.addon import blender_to_core as b2c
from skinsafe.addon.shared import fail, has_skin, ok
from skinsafe.core.design.coverage import format_report
from skinsafe.core.skin.model import DesignError


class SKINSAFE_OT_check(background.Modal, bpy.types.Operator):
    """Check the skin as `skinsafe check` does: taxels on their link's surface, outlines not
    overhanging, anchors on the link, none buried inside another link at sampled poses; coverage"""

    bl_idname = "skinsafe.check"
    bl_label = "Check Skin"
    bl_options = {"REGISTER", "UNDO"}  # it stores the coverage report with the design

    poses: bpy.props.IntProperty(name="Poses", default=16, min=1, max=1000,
                                 description="sampled poses for the buried-taxel check (home first)")

    poll = classmethod(lambda cls, context: has_skin(context))

    def execute(self, context):
        """The check runs off Blender's thread (seconds at many poses; Esc cancels) where there is an event loop."""
        scene = context.scene
        try:
            job = background.Job(designer.check_work, designer.need_design(scene), b2c.robot_for(scene), self.poses)
        except DesignError as e:
            findings.fill(scene, [str(e)])
            return fail(self, scene, e)
        self.rev = scene.skinsafe.design_rev
        return self.run(context, job, "checking the skin")

    def finish(self, context, job):
        scene = context.scene
        try:
            problems = designer.keep_check(scene, self.rev, job.outcome())
        except DesignError as e:
            findings.fill(scene, [str(e)])
            return fail(self, scene, e)
        scene.skinsafe.coverage_text = format_report(job.result[1])
        findings.fill(scene, problems)
        if problems:
            return fail(self, scene, DesignError(f"{len(problems)} problems, listed in Skin > Check; the first: "
                                                  f"{problems[0]}"))
        return ok(self, scene, f"skin valid: {b2c.design_of(scene).n_taxels} taxels checked at {self.poses} poses")


OPERATORS = (SKINSAFE_OT_check,)
