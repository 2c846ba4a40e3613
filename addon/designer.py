"""Design edits that the operators and the move handler share: place, re-generate, remove,
assign boards, map Jacobians. Geometry and checks are skinsafe.core's; this glues them to objects."""
import numpy as np

from skinsafe.addon import blender_to_core as b2c
from skinsafe.addon import core_to_blender as c2b
from skinsafe.core.design.audit import SURFACE_TOL, audit
from skinsafe.core.design.coverage import coverage_report
from skinsafe.core.design.placement import (
    PlacementError,
    build_design,
    place_module,
    placed_from_design,
    placement_record,
    replace_module,
)
from skinsafe.core.robot.kinematics import TaxelKinematics, retractability
from skinsafe.core.skin.model import DesignError


def _others(design, body: str, skip: int | None = None):
    if design is None:
        return []
    return [placed_from_design(design, m.id) for m in design.modules if m.body == body and m.id != skip]


def place(scene, body: str, anchor, direction):
    """Place a new module (the scene's new-module settings) on `body` at `anchor` (body frame)."""
    bodies = b2c.body_objects(scene)
    if body not in bodies:
        raise DesignError(f"place: body '{body}' is not part of the imported robot; pick one of {sorted(bodies)}")
    settings = scene.skinsafe.new_module
    design = b2c.design_of(scene)
    mid = 1 + max([m.id for m in design.modules], default=-1) if design else 0
    module = b2c.settings_module(settings, mid, f"{body}_module{mid}", body)
    outline = b2c.outline_of(settings)
    placed = place_module(b2c.surface_of(bodies[body]), module, anchor, direction, settings.method, outline,
                          _others(design, body))
    placed.module = _with_record(placed, settings.method, outline)
    obj = c2b.new_module_object(scene, bodies[body], placed.module, placed, settings)
    placed.module = _with_record(placed, settings.method, outline, obj.name)
    new = replace_module(design, placed) if design else build_design(
        b2c.robot_ref(scene), [placed], scene.skinsafe.board_capacity, scene.skinsafe.force_threshold)
    c2b.store_design(scene, new)
    return obj, placed


def _with_record(placed, method, outline, name=None):
    from dataclasses import replace
    m = placed.module
    return replace(m, name=name or m.name, placement=placement_record(placed.origin, placed.origin_frame[:, 0],
                                                                      method, outline))


def regenerate(scene, obj):
    """Re-place a module object where it now is (its transform), with its current settings;
    object scale resizes it (x scales the columns, y the rows) and is then reset."""
    mm = obj.skinsafe_module
    st = mm.settings
    sx, sy = obj.scale[0], obj.scale[1]
    if abs(sx - 1) > 1e-6 or abs(sy - 1) > 1e-6:
        st.cols, st.rows = max(1, round(st.cols * sx)), max(1, round(st.rows * sy))
        obj.scale = (1.0, 1.0, 1.0)
    anchor, direction = b2c.placement_of(obj)
    design = b2c.design_of(scene)
    module = b2c.settings_module(st, mm.module_id, obj.name, mm.body)
    outline = b2c.outline_of(st)
    try:
        placed = place_module(b2c.surface_of(b2c.body_objects(scene)[mm.body]), module, anchor, direction, st.method,
                              outline, _others(design, mm.body, skip=mm.module_id))
    except DesignError as e:
        mm.error = str(e)
        mm.placed_matrix = b2c.matrix_key(obj)  # do not retry the same refused pose on every update
        raise
    mm.error = ""
    placed.module = _with_record(placed, st.method, outline, obj.name)
    c2b.set_module_transform(obj, placed)
    c2b.store_design(scene, replace_module(design, placed))
    return placed


def regenerate_moved(scene) -> list[str]:
    """One step of the live re-generation: re-place every module object moved since its last
    placement. Returns the refusal messages (the modules keep their last valid taxels)."""
    errors = []
    for obj in b2c.module_objects(scene):
        if b2c.moved(obj) or abs(obj.scale[0] - 1) > 1e-6 or abs(obj.scale[1] - 1) > 1e-6:  # float32 round-off: no rescale
            try:
                regenerate(scene, obj)
            except DesignError as e:
                errors.append(str(e))
    return errors


def remove(scene, obj) -> None:
    design = b2c.design_of(scene)
    mid = obj.skinsafe_module.module_id
    import bpy
    bpy.data.objects.remove(obj, do_unlink=True)
    if design is None:
        return
    parts = [placed_from_design(design, m.id) for m in design.modules if m.id != mid]
    if parts:
        c2b.store_design(scene, build_design(design.robot, parts, scene.skinsafe.board_capacity,
                                             scene.skinsafe.force_threshold, bodies=None))
    else:
        c2b.clear_design(scene)


def assign_boards(scene):
    """Re-assign whole modules to boards of the scene's channel capacity (error when a module
    has more taxels than a board has channels)."""
    design = _need_design(scene)
    parts = [placed_from_design(design, m.id) for m in design.modules]
    new = build_design(design.robot, parts, scene.skinsafe.board_capacity, scene.skinsafe.force_threshold)
    c2b.store_design(scene, new)
    return new


def map_jacobians(scene) -> np.ndarray:
    """Per-taxel retractability |J_p^T z| at the scene's pose, shown as the modules' heat map.
    One `mj_jac` per taxel (9 ms at 2,149 taxels): no compiler in Blender, where the compiled
    all-taxel pass would cost its first call's 0.7 s import and compile for one map."""
    design = _need_design(scene)
    robot = b2c.robot_for(scene)
    kin = TaxelKinematics(robot.model, design)
    J = kin.jacobians_loop(b2c.pose(scene))
    values = retractability(J, kin.frames)
    c2b.show_heat(scene, design, values)
    return values


def coverage(scene) -> dict:
    design = _need_design(scene)
    design.coverage = coverage_report(design, b2c.robot_for(scene).model)
    c2b.store_design(scene, design)
    return design.coverage


def check(scene, poses: int = 16, tol: float = SURFACE_TOL) -> list[str]:
    """What `skinsafe check` does, on the scene's design: validation against the robot, the
    geometric audit (taxels off their link's surface, overhanging outlines, far anchors, taxels
    buried inside another link at `poses` sampled poses, home first) and the coverage report
    (stored with the design). Returns the problems, one line each (empty: the skin passes)."""
    design = _need_design(scene)
    robot = b2c.robot_for(scene)
    design.validate("skin", robot.body_names)
    problems = audit(design, robot.model, robot.home, poses, tol)
    design.coverage = coverage_report(design, robot.model)
    c2b.store_design(scene, design)
    return problems


def _need_design(scene):
    design = b2c.design_of(scene)
    if design is None or not design.n_taxels:
        raise DesignError("skin: no modules placed yet; place a module first (skinsafe panel > Modules)")
    return design


__all__ = ["PlacementError", "place", "regenerate", "regenerate_moved", "remove", "assign_boards", "map_jacobians",
           "coverage", "check"]
