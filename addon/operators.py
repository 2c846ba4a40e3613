"""Operators: each a thin call into designer / core with poll(), undo and a report."""
import warnings
from pathlib import Path

import bpy
import numpy as np
from bpy.props import EnumProperty, FloatProperty, FloatVectorProperty, StringProperty
from bpy_extras.io_utils import ExportHelper, ImportHelper

from skinsafe.addon import background, designer, findings
from skinsafe.addon import blender_to_core as b2c
from skinsafe.addon import core_to_blender as c2b
from skinsafe.core.design.coverage import format_report
from skinsafe.core.robot.urdf_import import parse_xacro_args
from skinsafe.core.skin import taxel_map
from skinsafe.core.skin.model import DesignError, RobotRef


def _fail(op, scene, e: Exception):
    scene.skinsafe.error = str(e)
    op.report({"ERROR"}, str(e))
    return {"CANCELLED"}


def _ok(op, scene, msg: str):
    scene.skinsafe.error = ""
    scene.skinsafe.message = msg
    op.report({"INFO"}, msg)
    return {"FINISHED"}


def _has_robot(context):
    return bool(context.scene.skinsafe.robot_kind)


def _has_skin(context):
    return _has_robot(context) and any(o.skinsafe_module.is_module for o in context.scene.objects)


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
            return _fail(self, scene, e)
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
            return _fail(self, scene, e)
        return _ok(self, scene, f"imported {root['skinsafe_robot']}: {len(b2c.body_objects(scene)) - 1} bodies, "
                                f"{len(scene.skinsafe.joints)} joints")


class SKINSAFE_OT_set_pose(bpy.types.Operator):
    """Set one joint, or all joints to the home or zero pose (the scene follows)"""

    bl_idname = "skinsafe.set_pose"
    bl_label = "Set Pose"
    bl_options = {"REGISTER", "UNDO"}

    preset: EnumProperty(items=[("JOINT", "Joint", ""), ("HOME", "Home", ""), ("ZERO", "Zero", "")], default="HOME")
    joint: StringProperty()
    value: FloatProperty()

    poll = classmethod(lambda cls, context: _has_robot(context))

    def execute(self, context):
        scene = context.scene
        joints = scene.skinsafe.joints
        robot = b2c.robot_for(scene)
        if self.preset == "JOINT":
            if self.joint not in joints:
                return _fail(self, scene, DesignError(f"pose: joint '{self.joint}' is unknown; use one of "
                                                      f"{[j.name for j in joints]}"))
            joints[self.joint]["value"] = self.value
        else:
            for j in joints:
                jid = robot.model.joint(j.name).id
                j["value"] = float(robot.home[robot.model.jnt_qposadr[jid]]) if self.preset == "HOME" else 0.0
        c2b.apply_pose(scene)
        if any(o.skinsafe_module.is_module for o in scene.objects):
            designer.map_jacobians(scene)
        return _ok(self, scene, "pose set")


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

    poll = classmethod(lambda cls, context: _has_robot(context))

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
            return _fail(self, scene, e)
        return _ok(self, scene, f"placed {obj.name}: {len(placed)} taxels on {body}")


class SKINSAFE_OT_regenerate(bpy.types.Operator):
    """Re-generate moved/rotated/resized modules (or the active one) on the surface"""

    bl_idname = "skinsafe.regenerate"
    bl_label = "Re-generate Modules"
    bl_options = {"REGISTER", "UNDO"}

    poll = classmethod(lambda cls, context: _has_skin(context))

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
            return _fail(self, scene, e)
        if errors:
            return _fail(self, scene, DesignError("; ".join(errors)))
        return _ok(self, scene, "modules re-generated")


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
        return _ok(self, context.scene, f"removed {name}")


class SKINSAFE_OT_assign_boards(bpy.types.Operator):
    """Assign whole modules to interface boards of the given channel capacity"""

    bl_idname = "skinsafe.assign_boards"
    bl_label = "Assign Boards"
    bl_options = {"REGISTER", "UNDO"}

    poll = classmethod(lambda cls, context: _has_skin(context))

    def execute(self, context):
        try:
            d = designer.assign_boards(context.scene)
        except DesignError as e:
            return _fail(self, context.scene, e)
        return _ok(self, context.scene, f"{len(d.modules)} modules on {len(d.boards)} boards")


class SKINSAFE_OT_map_jacobians(bpy.types.Operator):
    """Heat map of per-taxel retractability |J_p^T z| at the current pose"""

    bl_idname = "skinsafe.map_jacobians"
    bl_label = "Map Jacobians"
    bl_options = {"REGISTER", "UNDO"}

    poll = classmethod(lambda cls, context: _has_skin(context))

    def execute(self, context):
        try:
            v = designer.map_jacobians(context.scene)
        except DesignError as e:
            return _fail(self, context.scene, e)
        for area in context.screen.areas if context.screen else ():
            for space in area.spaces:
                if space.type == "VIEW_3D":
                    space.shading.color_type = "VERTEX"
        return _ok(self, context.scene, f"retractability min {v.min():.3f}, median {np.median(v):.3f} m/s per rad/s")


class SKINSAFE_OT_coverage(bpy.types.Operator):
    """Coverage report: skinned area, taxel count and density per link"""

    bl_idname = "skinsafe.coverage"
    bl_label = "Coverage Report"
    bl_options = {"REGISTER", "UNDO"}

    poll = classmethod(lambda cls, context: _has_skin(context))

    def execute(self, context):
        rep = designer.coverage(context.scene)
        context.scene.skinsafe.coverage_text = format_report(rep)
        t = rep["total"]
        return _ok(self, context.scene, f"{t['taxels']} taxels, {t['modules']} modules, {t['boards']} boards")


class SKINSAFE_OT_check(background.Modal, bpy.types.Operator):
    """Check the skin as `skinsafe check` does: taxels on their link's surface, outlines not
    overhanging, anchors on the link, none buried inside another link at sampled poses; coverage"""

    bl_idname = "skinsafe.check"
    bl_label = "Check Skin"
    bl_options = {"REGISTER", "UNDO"}  # it stores the coverage report with the design

    poses: bpy.props.IntProperty(name="Poses", default=16, min=1, max=1000,
                                 description="sampled poses for the buried-taxel check (home first)")

    poll = classmethod(lambda cls, context: _has_skin(context))

    def execute(self, context):
        """The check runs off Blender's thread (seconds at many poses; Esc cancels) where there is an event loop."""
        scene = context.scene
        try:
            job = background.Job(designer.check_work, designer.need_design(scene), b2c.robot_for(scene), self.poses)
        except DesignError as e:
            findings.fill(scene, [str(e)])
            return _fail(self, scene, e)
        self.rev = scene.skinsafe.design_rev
        return self.run(context, job, "checking the skin")

    def finish(self, context, job):
        scene = context.scene
        try:
            problems = designer.keep_check(scene, self.rev, job.outcome())
        except DesignError as e:
            findings.fill(scene, [str(e)])
            return _fail(self, scene, e)
        scene.skinsafe.coverage_text = format_report(job.result[1])
        findings.fill(scene, problems)
        if problems:
            return _fail(self, scene, DesignError(f"{len(problems)} problems, listed in Skin > Check; the first: "
                                                  f"{problems[0]}"))
        return _ok(self, scene, f"skin valid: {b2c.design_of(scene).n_taxels} taxels checked at {self.poses} poses")


class SKINSAFE_OT_export_taxel_map(bpy.types.Operator, ExportHelper):
    """Save the skin design as a taxel map (JSON)"""

    bl_idname = "skinsafe.export_taxel_map"
    bl_label = "Export Taxel Map"
    filename_ext = ".json"

    poll = classmethod(lambda cls, context: _has_skin(context))

    def execute(self, context):
        scene = context.scene
        try:
            path = taxel_map.save(b2c.design_of(scene), self.filepath, b2c.robot_for(scene).body_names)
        except (DesignError, OSError) as e:
            return _fail(self, scene, e)
        return _ok(self, scene, f"wrote {path}")


class SKINSAFE_OT_export_mjcf(bpy.types.Operator):
    """Export the robot with its skin as a MuJoCo scene (scene.xml, meshes/, taxel_map.json)"""

    bl_idname = "skinsafe.export_mjcf"
    bl_label = "Export MuJoCo Scene"

    directory: StringProperty(name="Folder", subtype="DIR_PATH")

    poll = classmethod(lambda cls, context: _has_skin(context))

    def invoke(self, context, event):
        context.window_manager.fileselect_add(self)
        return {"RUNNING_MODAL"}

    def execute(self, context):
        from skinsafe.exporters.mjcf import export_scene


        scene = context.scene
        try:
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                path = export_scene(b2c.design_of(scene), b2c.robot_for(scene), bpy.path.abspath(self.directory))
        except (DesignError, OSError) as e:
            return _fail(self, scene, e)
        for w in caught:  # e.g. taxels farther than 1 mm from the contact surface: said in the UI, not only stderr
            self.report({"WARNING"}, str(w.message))
        return _ok(self, scene, f"wrote {path}" + (f" ({len(caught)} warnings)" if caught else ""))


class _ExportSkinFile(ExportHelper):
    """An export of the design on its robot to one file by an exporter `export(design, robot, path) -> path`."""

    poll = classmethod(lambda cls, context: _has_skin(context))

    def execute(self, context):
        scene = context.scene
        try:
            path = self.exporter()(b2c.design_of(scene), b2c.robot_for(scene), bpy.path.abspath(self.filepath))
        except (ValueError, OSError) as e:  # DesignError is a ValueError
            return _fail(self, scene, e)
        return _ok(self, scene, f"wrote {path}")


class SKINSAFE_OT_export_urdf(_ExportSkinFile, bpy.types.Operator):
    """Export the robot with its skin as a URDF (the robot's links with their meshes beside it, a link and a
    tactile sensor per taxel)"""

    bl_idname = "skinsafe.export_urdf"
    bl_label = "Export URDF"
    filename_ext = ".urdf"

    @staticmethod
    def exporter():
        from skinsafe.exporters.urdf import export_urdf

        return export_urdf


class SKINSAFE_OT_export_taxel_csv(_ExportSkinFile, bpy.types.Operator):
    """Export the taxels as the CSV the GenTact Toolbox writes for Isaac Sim (Index, X, Y, Z, Radius, Parent:
    link-frame positions, the link's path)"""

    bl_idname = "skinsafe.export_taxel_csv"
    bl_label = "Export Taxel CSV (GenTact)"
    filename_ext = ".csv"

    @staticmethod
    def exporter():
        from skinsafe.exporters.gentact import export_csv

        return export_csv


class SKINSAFE_OT_export_fab(bpy.types.Operator):
    """Export every FPC module's flat pattern for fabrication into FOLDER/fab: a KiCad board, DXF and SVG per
    module, one PDF page each, bom.csv and fab.json (an older fab folder is replaced whole)"""

    bl_idname = "skinsafe.export_fab"
    bl_label = "Export FPC Fabrication Files"

    directory: StringProperty(name="Folder", subtype="DIR_PATH")

    poll = classmethod(lambda cls, context: _has_skin(context))

    def invoke(self, context, event):
        context.window_manager.fileselect_add(self)
        return {"RUNNING_MODAL"}

    def execute(self, context):
        from skinsafe.exporters.fab import count_files, write_fab

        scene = context.scene
        try:
            design = b2c.design_of(scene)
            path = write_fab(design, bpy.path.abspath(self.directory), name=Path(bpy.data.filepath).stem or None,
                             source=f"scene '{scene.name}'")
        except (DesignError, OSError) as e:
            return _fail(self, scene, e)
        n = len(design.modules)
        return _ok(self, scene, f"wrote {path}: {n} FPC module{'s' * (n != 1)}, {count_files(path)} files")


class SKINSAFE_OT_toggle_frames(bpy.types.Operator):
    """Draw the taxel frames (axes or normals) in the viewport"""

    bl_idname = "skinsafe.toggle_frames"
    bl_label = "Toggle Taxel Frames"

    poll = classmethod(lambda cls, context: _has_skin(context))

    def execute(self, context):
        s = context.scene.skinsafe
        s.show_frames = not s.show_frames
        for area in context.screen.areas if context.screen else ():
            area.tag_redraw()
        return {"FINISHED"}


CLASSES = (SKINSAFE_OT_import_robot, SKINSAFE_OT_set_pose, SKINSAFE_OT_place_module, SKINSAFE_OT_regenerate,
           SKINSAFE_OT_remove_module, SKINSAFE_OT_assign_boards, SKINSAFE_OT_map_jacobians, SKINSAFE_OT_coverage,
           SKINSAFE_OT_check, SKINSAFE_OT_export_taxel_map, SKINSAFE_OT_export_mjcf, SKINSAFE_OT_export_urdf,
           SKINSAFE_OT_export_taxel_csv, SKINSAFE_OT_export_fab, SKINSAFE_OT_toggle_frames)
EXPORTS = ((SKINSAFE_OT_export_taxel_map, "skinsafe Taxel Map (.json)"),
           (SKINSAFE_OT_export_mjcf, "skinsafe MuJoCo Scene (folder)"), (SKINSAFE_OT_export_urdf, "skinsafe URDF (.urdf)"),
           (SKINSAFE_OT_export_taxel_csv, "skinsafe Taxel CSV, GenTact (.csv)"),
           (SKINSAFE_OT_export_fab, "skinsafe FPC fabrication (folder)"))


def export_menu(self, context):
    """File > Export entries."""
    for op, text in EXPORTS:
        self.layout.operator(op.bl_idname, text=text)


_register, _unregister = bpy.utils.register_classes_factory(CLASSES)


def register():
    _register()
    bpy.types.TOPBAR_MT_file_export.append(export_menu)


def unregister():
    bpy.types.TOPBAR_MT_file_export.remove(export_menu)
    _unregister()
