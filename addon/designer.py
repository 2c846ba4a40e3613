"""Design edits that the operators and the app handlers share: place, re-generate, keep the design in step
with the module objects (`sync`), remove, assign boards, map Jacobians. Geometry and checks are
skinsafe.core's; this glues them to objects."""
from dataclasses import replace

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


def others_on(design, body: str, skip: int | None = None):
    """The placed modules of `design` on `body` (but `skip`): what a new placement must not overlap."""
    if design is None:
        return []
    return [placed_from_design(design, m.id) for m in design.modules if m.body == body and m.id != skip]


def fresh_module_id(scene, design=None) -> int:
    """A module id never used: by no object of the scene, no module of its design, and none retired from its
    history (below `next_module_id`: boards and records keep ids, which must never mean another module)."""
    design = design if design is not None else b2c.design_of(scene)
    used = {o.skinsafe_module.module_id for o in b2c.module_objects(scene)}
    used |= {m.id for m in design.modules} | set(design.retired_modules) if design is not None else set()
    return max(1 + max(used, default=-1), scene.skinsafe.next_module_id)


def place(scene, body: str, anchor, direction):
    """Place a new module (the scene's new-module settings) on `body` at `anchor` (body frame)."""
    bodies = b2c.body_objects(scene)
    if body not in bodies:
        raise DesignError(f"place: body '{body}' is not part of the imported robot; pick one of {sorted(bodies)}")
    settings = scene.skinsafe.new_module
    design = b2c.design_of(scene)
    mid = fresh_module_id(scene, design)
    module = b2c.settings_module(settings, mid, f"{body}_module{mid}", body)
    outline = b2c.outline_of(settings)
    placed = _mirror(place_module(b2c.surface_of(bodies[body]), module, anchor, direction, settings.method, outline,
                                  others_on(design, body)), settings.mirrored)
    placed.module = _with_record(placed, settings, outline)
    obj = c2b.new_module_object(scene, bodies[body], placed.module, placed, settings)
    placed.module = _with_record(placed, settings, outline, obj.name)
    c2b.store_design(scene, _with(scene, design, placed))
    return obj, placed


def _with(scene, design, placed):
    """The design with `placed` added or swapped in (a new design when there is none)."""
    if design is not None:
        return replace_module(design, placed)
    return build_design(b2c.robot_ref(scene), [placed], scene.skinsafe.board_capacity, scene.skinsafe.force_threshold)


def _mirror(placed, mirrored: bool):
    """A mirrored module: taxel k at the mirror image (u -> -u) of its place in the template. Placed
    with the mirrored outline (a curve's; a rect's grid is symmetric), its taxels are re-ordered so."""
    if not mirrored:
        return placed
    k = np.lexsort((-placed.col, placed.row))
    placed.positions, placed.frames, placed.row, placed.col = (placed.positions[k], placed.frames[k], placed.row[k],
                                                               placed.col[k])
    return placed


def _with_record(placed, settings, outline, name=None):
    m = placed.module
    rec = placement_record(placed.origin, placed.origin_frame[:, 0], settings.method, outline)
    if settings.mirrored:
        rec["mirrored"] = True
    return replace(m, name=name or m.name, placement=rec)


def _scaled(obj) -> bool:
    """Whether the object carries a scale to apply (float32 round-off of 1 is none)."""
    return any(abs(s - 1) > 1e-6 for s in obj.scale)


def attach(obj, body_obj) -> None:
    """Parent a module object to its body object with an identity parent inverse, keeping where it is
    (a pasted or appended module arrives without its parent, a re-parented one with an inverse)."""
    if obj.parent is body_obj and obj.matrix_parent_inverse == obj.matrix_parent_inverse.Identity(4):
        return
    W = obj.matrix_world.copy()
    obj.parent = body_obj
    obj.matrix_parent_inverse.identity()
    obj.matrix_basis = body_obj.matrix_world.inverted() @ W


def regenerate(scene, obj):
    """Re-place a module object where it now is (its transform), with its current settings. Its scale is
    applied once: x scales the columns, y the rows, a negative x or y scale mirrors the module; the scale
    is then reset to 1. A refused placement keeps the module's last taxels and settings (the message in
    its `error`)."""
    mm = obj.skinsafe_module
    st = mm.settings
    bodies = b2c.body_objects(scene)
    if mm.body not in bodies:
        mm.error = (f"module '{obj.name}': its body '{mm.body}' is not a link of this scene's robot; delete the module "
                    "or import the robot it was designed for")
        raise DesignError(mm.error)
    attach(obj, bodies[mm.body])
    anchor, direction = b2c.placement_of(obj)
    old = (st.cols, st.rows, st.mirrored)
    if _scaled(obj):
        sx, sy = obj.scale[0], obj.scale[1]
        st.cols, st.rows = max(1, round(st.cols * abs(sx))), max(1, round(st.rows * abs(sy)))
        if sx * sy < 0:  # x-mirror: the template's u -> -u; y-mirror: that and a half turn
            st.mirrored = not st.mirrored
            direction = -direction
        obj.scale = (1.0, 1.0, 1.0)
    design = b2c.design_of(scene)
    module = b2c.settings_module(st, mm.module_id, obj.name, mm.body)
    outline = b2c.outline_of(st)
    try:
        placed = _mirror(place_module(b2c.surface_of(bodies[mm.body]), module, anchor, direction, st.method, outline,
                                      others_on(design, mm.body, skip=mm.module_id)), st.mirrored)
    except DesignError as e:
        st.cols, st.rows, st.mirrored = old
        mm.error, mm.error_rev = str(e), scene.skinsafe.design_rev
        mm.placed_matrix = b2c.matrix_key(obj)  # do not retry the same refused pose on every update
        raise
    mm.error = ""
    placed.module = _with_record(placed, st, outline, obj.name)
    c2b.set_module_transform(obj, placed)
    c2b.store_design(scene, _with(scene, design, placed))
    return placed


def regenerate_moved(scene, apply_scale: bool = True) -> list[str]:
    """One step of the live re-generation: re-place every module object moved (or scaled) since its last
    placement. `apply_scale` False (a transform is running): a scaled object waits for its end. Returns
    the refusal messages (the modules keep their last valid taxels)."""
    errors = []
    for obj in b2c.module_objects(scene):
        if _scaled(obj) and not apply_scale:
            continue
        if b2c.moved(obj) or _scaled(obj):
            try:
                regenerate(scene, obj)
            except DesignError as e:
                errors.append(str(e))
    return errors


def sync(scene) -> list[str]:
    """Make the design follow the module objects after any edit: a module whose object is gone (deleted,
    undone) leaves the design; a renamed object renames its module; an object sharing its module id with
    another (duplicated, pasted, appended), or holding a retired one, gets a fresh id and its own taxels where it
    is; a module object without taxels in the design is placed. Returns the problems (each also in its object's `error`)."""
    design = b2c.design_of(scene)
    known = {m.id: m for m in design.modules} if design is not None else {}
    claims: dict[int, list] = {}
    for o in b2c.module_objects(scene):
        claims.setdefault(o.skinsafe_module.module_id, []).append(o)
    owners, copies = {}, []
    for mid, group in claims.items():
        owner = _owner(group, known.get(mid))
        owners[mid] = owner
        copies += [o for o in group if o is not owner]
    retired = set(design.retired_modules) if design is not None else set()
    copies += [owners.pop(mid) for mid in list(owners) if mid in retired]  # e.g. appended: a retired id stays so
    kept = {mid: o for mid, o in owners.items() if mid in known}
    if design is not None and (len(kept) < len(known) or any(o.name != known[mid].name for mid, o in kept.items())):
        parts = []
        for m in design.modules:
            if m.id in kept:
                p = placed_from_design(design, m.id)
                p.module = replace(m, name=kept[m.id].name)
                parts.append(p)
        if parts:
            c2b.store_design(scene, build_design(design.robot, parts, scene.skinsafe.board_capacity,
                                                 scene.skinsafe.force_threshold))
        else:
            c2b.clear_text(scene)
    for o in owners.values():
        if o.skinsafe_module.owner != o.session_uid:
            o.skinsafe_module.owner = o.session_uid
    problems = []
    stray = b2c.stray_bodies(scene)
    if stray:
        problems.append(f"objects {', '.join(stray)} are copies of robot links (they came with a pasted or appended "
                        "module, whose module now rides on the robot's own link); delete them")
    for o in copies:
        o.skinsafe_module.module_id = fresh_module_id(scene)
        o.skinsafe_module.owner = o.session_uid
        o.skinsafe_module.error = ""
    rev = scene.skinsafe.design_rev  # one refused before the design last changed is tried again
    for o in copies + [o for mid, o in owners.items() if mid not in known and
                       (not o.skinsafe_module.error or o.skinsafe_module.error_rev != rev)]:
        try:
            regenerate(scene, o)
        except DesignError as e:
            problems.append(str(e))
    return problems


def mismatches(scene) -> list[str]:
    """Where the module objects and the design disagree, each with what to do (Check lists them first): a module
    object whose last edit was refused (it shows where the design does not have it), copies of robot links."""
    out = [f"module object '{o.name}' is not where the design has it: {o.skinsafe_module.error}"
           for o in b2c.module_objects(scene) if o.skinsafe_module.error]
    stray = b2c.stray_bodies(scene)
    if stray:
        out.append(f"objects {', '.join(stray)} are copies of robot links, not part of the robot; delete them")
    return out


def _owner(group: list, module):
    """Which of the objects claiming one module id keeps it: the one that owned it (its session uid), else
    the one named as the design's module, else the first by name (after a file reload uids are new)."""
    for o in group:
        if o.skinsafe_module.owner == o.session_uid:
            return o
    named = [o for o in group if module is not None and o.name == module.name]
    return (named or sorted(group, key=lambda o: o.name))[0]


def remove(scene, obj) -> None:
    """Delete a module object; its module leaves the design (`sync`)."""
    import bpy
    bpy.data.objects.remove(obj, do_unlink=True)
    sync(scene)


def assign_boards(scene):
    """Re-assign whole modules to boards of the scene's channel capacity (error when a module
    has more taxels than a board has channels)."""
    design = need_design(scene)
    parts = [placed_from_design(design, m.id) for m in design.modules]
    new = build_design(design.robot, parts, scene.skinsafe.board_capacity, scene.skinsafe.force_threshold)
    c2b.store_design(scene, new)
    return new


def map_jacobians(scene) -> np.ndarray:
    """Per-taxel retractability |J_p^T z| at the scene's pose, shown as the modules' heat map.
    One `mj_jac` per taxel (9 ms at 2,149 taxels): no compiler in Blender, where the compiled
    all-taxel pass would cost its first call's 0.7 s import and compile for one map."""
    design = need_design(scene)
    robot = b2c.robot_for(scene)
    kin = TaxelKinematics(robot.model, design)
    J = kin.jacobians_loop(b2c.pose(scene))
    values = retractability(J, kin.frames)
    c2b.show_heat(scene, design, values)
    return values


def coverage(scene) -> dict:
    design = need_design(scene)
    design.coverage = coverage_report(design, b2c.robot_for(scene).model)
    c2b.store_design(scene, design)
    return design.coverage


def check_work(design, robot, poses: int = 16, tol: float = SURFACE_TOL) -> tuple[list[str], dict]:
    """What `skinsafe check` does, on a design (no bpy: it may run in a worker thread): validation against
    the robot, the geometric audit (taxels off their link's surface, overhanging outlines, far anchors, taxels
    buried inside another link at `poses` sampled poses, home first) and the coverage report. Returns the
    problems, one line each (empty: the skin passes), and the report (`keep_check` keeps it)."""
    design.validate("skin", robot.body_names)
    return audit(design, robot.model, robot.home, poses, tol), coverage_report(design, robot.model)


def keep_check(scene, rev: int, result: tuple[list[str], dict]) -> list[str]:
    """Keep a finished `check_work`'s coverage report with the scene's design, which must be the one it checked
    (`rev`: the scene's design revision when the check started); its problems, the objects' `mismatches` first."""
    if scene.skinsafe.design_rev != rev:
        raise DesignError("check: the skin changed while it was being checked; run Check again")
    problems, report = result
    design = need_design(scene)
    design.coverage = report
    c2b.store_design(scene, design)
    return mismatches(scene) + problems


def need_design(scene):
    """The scene's design, or a DesignError saying to place a module first."""
    design = b2c.design_of(scene)
    if design is None or not design.n_taxels:
        raise DesignError("skin: no modules placed yet; place a module first (skinsafe panel > Modules)")
    return design


__all__ = ["PlacementError", "place", "regenerate", "regenerate_moved", "sync", "remove", "assign_boards", "map_jacobians",
           "coverage", "check_work", "keep_check", "need_design"]
