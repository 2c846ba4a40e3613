"""Export (File > Export, and the buttons of the Frames, Jacobians, Boards panel): the taxel map (JSON), the
MuJoCo scene (folder), a URDF, the GenTact taxel CSV and the FPC fabrication files (folder). Its operators register
with the others' (addon/__init__.py); `register` adds the File > Export entries."""
import warnings
from pathlib import Path

import bpy
from bpy.props import StringProperty
from bpy_extras.io_utils import ExportHelper

from skinsafe.addon import blender_to_core as b2c
from skinsafe.addon.shared import fail, has_skin, ok
from skinsafe.core.skin import taxel_map
from skinsafe.core.skin.model import DesignError


class _ExportToFolder:
    """An export of the design into a folder the file browser picks."""

    directory: StringProperty(name="Folder", subtype="DIR_PATH")

    poll = classmethod(lambda cls, context: has_skin(context))

    def invoke(self, context, event):
        context.window_manager.fileselect_add(self)
        return {"RUNNING_MODAL"}


class SKINSAFE_OT_export_taxel_map(bpy.types.Operator, ExportHelper):
    """Save the skin design as a taxel map (JSON)"""

    bl_idname = "skinsafe.export_taxel_map"
    bl_label = "Export Taxel Map"
    filename_ext = ".json"

    poll = classmethod(lambda cls, context: has_skin(context))

    def execute(self, context):
        scene = context.scene
        try:
            path = taxel_map.save(b2c.design_of(scene), self.filepath, b2c.robot_for(scene).body_names)
        except (DesignError, OSError) as e:
            return fail(self, scene, e)
        return ok(self, scene, f"wrote {path}")


class SKINSAFE_OT_export_mjcf(_ExportToFolder, bpy.types.Operator):
    """Export the robot with its skin as a MuJoCo scene (scene.xml, meshes/, taxel_map.json)"""

    bl_idname = "skinsafe.export_mjcf"
    bl_label = "Export MuJoCo Scene"

    def execute(self, context):
        from skinsafe.exporters.mjcf import export_scene


        scene = context.scene
        try:
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                path = export_scene(b2c.design_of(scene), b2c.robot_for(scene), bpy.path.abspath(self.directory))
        except (DesignError, OSError) as e:
            return fail(self, scene, e)
        for w in caught:  # e.g. taxels farther than 1 mm from the contact surface: said in the UI, not only stderr
            self.report({"WARNING"}, str(w.message))
        return ok(self, scene, f"wrote {path}" + (f" ({len(caught)} warnings)" if caught else ""))


class _ExportSkinFile(ExportHelper):
    """An export of the design on its robot to one file by an exporter `export(design, robot, path) -> path`."""

    poll = classmethod(lambda cls, context: has_skin(context))

    def execute(self, context):
        scene = context.scene
        try:
            path = self.exporter()(b2c.design_of(scene), b2c.robot_for(scene), bpy.path.abspath(self.filepath))
        except (ValueError, OSError) as e:  # DesignError is a ValueError
            return fail(self, scene, e)
        return ok(self, scene, f"wrote {path}")


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


class SKINSAFE_OT_export_fab(_ExportToFolder, bpy.types.Operator):
    """Export every FPC module's flat pattern for fabrication into FOLDER/fab: a KiCad board, DXF and SVG per
    module, one PDF page each, bom.csv and fab.json (an older fab folder is replaced whole)"""

    bl_idname = "skinsafe.export_fab"
    bl_label = "Export FPC Fabrication Files"

    def execute(self, context):
        from skinsafe.exporters.fab import count_files, write_fab

        scene = context.scene
        try:
            design = b2c.design_of(scene)
            path = write_fab(design, bpy.path.abspath(self.directory), name=Path(bpy.data.filepath).stem or None,
                             source=f"scene '{scene.name}'")
        except (DesignError, OSError) as e:
            return fail(self, scene, e)
        n = len(design.modules)
        return ok(self, scene, f"wrote {path}: {n} FPC module{'s' * (n != 1)}, {count_files(path)} files")


OPERATORS = (SKINSAFE_OT_export_taxel_map, SKINSAFE_OT_export_mjcf, SKINSAFE_OT_export_urdf,
             SKINSAFE_OT_export_taxel_csv, SKINSAFE_OT_export_fab)
EXPORTS = ((SKINSAFE_OT_export_taxel_map, "skinsafe Taxel Map (.json)"),
           (SKINSAFE_OT_export_mjcf, "skinsafe MuJoCo Scene (folder)"), (SKINSAFE_OT_export_urdf, "skinsafe URDF (.urdf)"),
           (SKINSAFE_OT_export_taxel_csv, "skinsafe Taxel CSV, GenTact (.csv)"),
           (SKINSAFE_OT_export_fab, "skinsafe FPC fabrication (folder)"))


def export_menu(self, context):
    """File > Export entries."""
    for op, text in EXPORTS:
        self.layout.operator(op.bl_idname, text=text)


def register():
    bpy.types.TOPBAR_MT_file_export.append(export_menu)


def unregister():
    bpy.types.TOPBAR_MT_file_export.remove(export_menu)
