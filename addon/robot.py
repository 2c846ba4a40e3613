"""Robot (View3D > N > Skin > Robot): Import Robot (the built-in UR5 or Panda, or a URDF, xacro or MJCF file, read
off Blender's thread: addon/background.py) and Set Pose (one joint, home or zero), and the Robot panel with the
joint sliders. Its operators and panel register with the others' (addon/__init__.py)."""
from pathlib import Path

import bpy
from bpy.props import EnumProperty, FloatProperty, StringProperty
from bpy_extras.io_utils import ImportHelper

from skinsafe.addon import background, designer
from skinsafe.addon import blender_to_core as b2c
from skinsafe.addon import core_to_blender as c2b
from skinsafe.addon.shared import fail, has_robot, ok
from skinsafe.core.robot.urdf_import import parse_xacro_args
from skinsafe.core.skin.model import DesignError, RobotRef


def _n_modules(context) -> int:
    return len(b2c.module_objects(context.scene)) if context.scene is not None else 0


class SKINSAFE_OT_import_robot(background.Modal, bpy.types.Operator, ImportHelper):
    """Import the built-in UR5 or Panda, or a URDF, xacro or MJCF file (one object per body; meshes
    STL/OBJ/DAE are read by the core, `package://` resolved in the package folders given)"""

    bl_idname = "skinsafe.import_robot"
    bl_label = "Import Robot"
    bl_options = {"REGISTER", "UNDO"}

    source: EnumProperty(name="Robot", items=[("ur5", "UR5", "built-in UR5"), ("panda", "Panda", "built-in 7-DoF arm"),
                                              ("FILE", "URDF/xacro/MJCF file", "a robot file")], default="ur5")
    filter_glob: StringProperty(default="*.urdf;*.xacro;*.xml;*.mjcf", options={"HIDDEN"})
    package_dirs: StringProperty(name="ROS package folders", default="",
                                 description="folders holding the ROS packages the file names (package://, $(find)), ';'-separated")
    xacro_args: StringProperty(name="xacro arguments", default="",
                               description="NAME:=VALUE arguments for a xacro file, ';'-separated (e.g. ur_type:=ur5e;name:=ur5e)")

    poll = classmethod(lambda cls, context: context.scene is not None)

    def invoke(self, context, event):
        if self.source == "FILE":  # the file browser shows the warning (`draw`)
            return ImportHelper.invoke(self, context, event)
        n = _n_modules(context)
        if n:
            return context.window_manager.invoke_confirm(
                self, event, title="Replace the robot?", message=f"Importing replaces the robot and deletes the skin "
                f"({n} modules); undo brings them back", confirm_text="Replace", icon="WARNING")
        return self.execute(context)

    def draw(self, context):
        layout = self.layout
        for k in ("package_dirs", "xacro_args"):
            layout.prop(self, k)
        n = _n_modules(context)
        if n:
            layout.label(text=f"Replaces the robot and deletes the skin ({n} modules)", icon="WARNING")

    def execute(self, context):
        scene = context.scene
        try:
            if self.source == "FILE":
                path = Path(bpy.path.abspath(self.filepath))
                kind = "mjcf" if path.suffix.lower() in (".xml", ".mjcf") else "urdf"
                dirs = tuple(str(Path(bpy.path.abspath(d))) for d in self.package_dirs.split(";") if d)
                self.ref = RobotRef(kind, path.name.split(".")[0], str(path), dirs, parse_xacro_args(self.xacro_args))
            else:
                self.ref = RobotRef("builtin", self.source)
        except DesignError as e:
            return fail(self, scene, e)
        # one validation (joints, every mesh by link and file) before the scene changes; with a window the
        # reading runs off Blender's thread (xacro and meshes take seconds), Esc cancels
        job = background.Job(b2c.preload, self.ref, True)
        return self.run(context, job, f"importing {self.ref.name}", modal=self.source == "FILE")

    def finish(self, context, job):
        scene = context.scene
        try:
            job.outcome()
            root = c2b.build_robot(scene, self.ref)
        except DesignError as e:
            return fail(self, scene, e)
        return ok(self, scene, f"imported {root['skinsafe_robot']}: {len(b2c.body_objects(scene)) - 1} bodies, "
                                f"{len(scene.skinsafe.joints)} joints")


class SKINSAFE_OT_set_pose(bpy.types.Operator):
    """Set one joint, or all joints to the home or zero pose (the scene follows)"""

    bl_idname = "skinsafe.set_pose"
    bl_label = "Set Pose"
    bl_options = {"REGISTER", "UNDO"}

    preset: EnumProperty(items=[("JOINT", "Joint", ""), ("HOME", "Home", ""), ("ZERO", "Zero", "")], default="HOME")
    joint: StringProperty()
    value: FloatProperty()

    poll = classmethod(lambda cls, context: has_robot(context))

    def execute(self, context):
        scene = context.scene
        joints = scene.skinsafe.joints
        robot = b2c.robot_for(scene)
        if self.preset == "JOINT":
            if self.joint not in joints:
                return fail(self, scene, DesignError(f"pose: joint '{self.joint}' is unknown; use one of "
                                                      f"{[j.name for j in joints]}"))
            joints[self.joint]["value"] = self.value
        else:
            for j in joints:
                jid = robot.model.joint(j.name).id
                j["value"] = float(robot.home[robot.model.jnt_qposadr[jid]]) if self.preset == "HOME" else 0.0
        c2b.apply_pose(scene)
        if any(o.skinsafe_module.is_module for o in scene.objects):
            designer.map_jacobians(scene)
        return ok(self, scene, "pose set")


class SKINSAFE_PT_robot(bpy.types.Panel):
    bl_space_type, bl_region_type, bl_category = "VIEW_3D", "UI", "Skin"
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


OPERATORS = (SKINSAFE_OT_import_robot, SKINSAFE_OT_set_pose)
PANELS = (SKINSAFE_PT_robot,)
