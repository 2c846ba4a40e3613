"""Properties: the scene's robot, pose and new-module settings; each module object's template."""
import bpy
from bpy.props import (
    BoolProperty,
    CollectionProperty,
    EnumProperty,
    FloatProperty,
    FloatVectorProperty,
    IntProperty,
    PointerProperty,
    StringProperty,
)

TEMPLATES = [("rect", "Rectangle", "rows x cols grid"), ("strip", "Strip", "one row of taxels"),
             ("curve", "Curve outline", "the grid cells inside a closed curve")]
METHODS = [("geodesic", "Geodesic", "walk the surface: spacing on the surface equals the pitch"),
           ("projection", "Projection", "drop a flat grid onto the surface")]


def _pose_changed(self, context):
    from skinsafe.addon.core_to_blender import apply_pose
    apply_pose(context.scene)


class SkinsafeJoint(bpy.types.PropertyGroup):
    value: FloatProperty(name="Angle", update=_pose_changed, precision=4)
    lower: FloatProperty()
    upper: FloatProperty()


def _settings_changed(self, context):
    """A module object's own settings edited: mark it stale, so the next update re-generates it."""
    obj = self.id_data
    if isinstance(obj, bpy.types.Object) and obj.skinsafe_module.is_module:
        obj.skinsafe_module.placed_matrix = [0.0] * 16


class SkinsafeTemplate(bpy.types.PropertyGroup):
    """An FPC module template (on the scene: for new modules; on a module object: its own)."""

    template: EnumProperty(name="Template", items=TEMPLATES, default="rect", update=_settings_changed)
    method: EnumProperty(name="Wrap", items=METHODS, default="geodesic", update=_settings_changed)
    rows: IntProperty(name="Rows", default=8, min=1, max=256, update=_settings_changed)
    cols: IntProperty(name="Cols", default=8, min=1, max=256, update=_settings_changed)
    pitch: FloatProperty(name="Pitch", default=0.01, min=1e-4, max=0.2, unit="LENGTH", precision=4, update=_settings_changed)
    taxel_diameter: FloatProperty(name="Taxel diameter", default=0.006, min=1e-4, max=0.2, unit="LENGTH", precision=4, update=_settings_changed)
    margin: FloatProperty(name="Margin", default=0.002, min=0.0, max=0.1, unit="LENGTH", precision=4, update=_settings_changed)
    min_bend_radius: FloatProperty(name="Min bend radius", default=0.01, min=0.0, max=10.0, unit="LENGTH", precision=4, update=_settings_changed)
    max_strain: FloatProperty(name="Max strain", default=0.01, min=1e-4, max=0.2, precision=4, update=_settings_changed,
                              description="the in-plane strain the wrapped FPC tolerates (fraction: 0.01 = 1%; "
                                          "polyimide yields near 3%, copper traces earlier)")
    outline: PointerProperty(name="Outline", type=bpy.types.Object, description="closed curve for the 'curve' template")
    mirrored: BoolProperty(name="Mirrored", default=False,
                           description="the mirror image of the template (taxel k at the mirror of its place)")


class SkinsafeLink(bpy.types.PropertyGroup):
    """One body of the imported robot and its object: a pointer, so a deleted link object survives (unlinked,
    its children still parented to it) to be put back, and a copy claiming the body is told apart."""

    body: StringProperty()
    object: PointerProperty(type=bpy.types.Object)
    mesh_key: FloatVectorProperty(size=5)  # its mesh as built (blender_to_core.mesh_key)


class SkinsafeModule(bpy.types.PropertyGroup):
    is_module: BoolProperty(default=False)
    module_id: IntProperty(default=-1)  # the module's uid in the design (its taxels' ids: designer.stable_ids)
    owner: IntProperty(default=-1)  # session_uid of the object owning module_id (a duplicate's differs)
    body: StringProperty()
    settings: PointerProperty(type=SkinsafeTemplate)
    placed_matrix: FloatVectorProperty(size=16)  # matrix_local at the last placement (to detect moves)
    mesh_key: FloatVectorProperty(size=5)  # its mesh at the last placement (blender_to_core.mesh_key)
    error: StringProperty()
    error_rev: IntProperty(default=0)  # the design revision its error was found at (a changed design retries it)


class SkinsafeScene(bpy.types.PropertyGroup):
    robot_kind: StringProperty(default="")
    robot_name: StringProperty(default="")
    robot_path: StringProperty(default="", subtype="FILE_PATH")
    robot_package_dirs: StringProperty(default="", description="ROS package folders for package:// and $(find), ';'-separated")
    robot_xacro_args: StringProperty(default="", description="the robot file's xacro arguments, NAME:=VALUE ';'-separated")
    joints: CollectionProperty(type=SkinsafeJoint)
    links: CollectionProperty(type=SkinsafeLink)
    next_module_id: IntProperty(default=0)  # ids below it were used in this design's history: never given again
    new_module: PointerProperty(type=SkinsafeTemplate)
    board_capacity: IntProperty(name="Board channels", default=256, min=1, max=65536)
    force_threshold: FloatProperty(name="Force threshold (N)", default=2.0, min=0.0)
    auto_regenerate: BoolProperty(name="Re-generate on move", default=True)
    show_frames: BoolProperty(name="Show frames", default=False)
    frame_style: EnumProperty(name="Draw", items=[("AXES", "Axes", "x, y, z per taxel"),
                                                  ("NORMALS", "Normals", "z only")], default="AXES")
    frame_scale: FloatProperty(name="Axis length", default=0.01, min=1e-4, unit="LENGTH")
    message: StringProperty(default="")
    error: StringProperty(default="")
    coverage_text: StringProperty(default="")
    design_rev: IntProperty(default=0)  # a fresh random value with every stored design (undo-safe cache key)


CLASSES = (SkinsafeJoint, SkinsafeTemplate, SkinsafeLink, SkinsafeModule, SkinsafeScene)


_register_classes, _unregister_classes = bpy.utils.register_classes_factory(CLASSES)


def register():
    _register_classes()
    bpy.types.Scene.skinsafe = PointerProperty(type=SkinsafeScene)
    bpy.types.Object.skinsafe_module = PointerProperty(type=SkinsafeModule)


def unregister():
    del bpy.types.Object.skinsafe_module
    del bpy.types.Scene.skinsafe
    _unregister_classes()
