"""The collaboration experiment's skin (`collaboration_skin`): the sample skin plus modules placed where the person
meets the robot in the scenarios, found by simulating them (`contact_points`, `cover`)."""
from __future__ import annotations

import numpy as np
from tqdm.auto import tqdm

from skinsafe.core.experiments.collaboration_person import learn_person
from skinsafe.core.experiments.collaboration_scenario import (
    NOMINAL,
    SCENARIOS,
    STACKS,
    CollabConfig,
    Layout,
    build,
    episode,
    layout,
)


def contact_points(sc, lay: Layout, stacks, pot, cfg: CollabConfig) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """Where the person meets the robot (body, point and outward normal in the body frame) in the
    scenario with each of `stacks`, every physics step."""
    pts = []
    m = sc.model
    geoms = set(sc.human.geom.tolist())
    step = sc.step

    def record(v, lead=0.2):
        out = step(v, lead)
        d = sc.data
        for i in range(d.ncon):
            c = d.contact[i]
            g1, g2 = c.geom
            sign = 1.0 if g2 in geoms else -1.0 if g1 in geoms else 0.0
            robot = g1 if sign > 0 else g2
            if sign and robot not in sc.human.fixture_geoms and c.dist < 0:
                b = int(m.geom_bodyid[robot])
                R = d.xmat[b].reshape(3, 3)
                pts.append((m.body(b).name, R.T @ (c.pos - d.xpos[b]), sign * (R.T @ c.frame[:3])))
        return out

    sc.step = record
    try:
        for stack in stacks:
            episode(sc, lay, stack, pot, cfg)
    finally:
        sc.step = step
    return pts


def _covered(design, body: str, p, n, radius: float) -> bool:
    """Whether a taxel of `body` within `radius` of p faces the contact normal n (the readout's test)."""
    if body not in design.bodies:
        return False
    t = design.taxels
    on = t.body == design.bodies.index(body)
    d = np.linalg.norm(t.positions[on] - p, axis=1)
    return bool(np.any((d < radius) & (t.frames[on][:, :, 2] @ n > 0)))


def cover(design, robot, points, pitch: float):
    """`design` plus modules placed (`placement.place_module`, geodesic) where `points` (body,
    point, normal) are not sensed: a small module anchored at the point or a pitch beside it,
    the largest that fits; returns the design and the points still bare."""
    from dataclasses import replace

    from skinsafe.core.design.placement import (
        PlacementError,
        build_design,
        place_module,
        placed_from_design,
        placement_record,
    )
    from skinsafe.core.design.surface import cached_surfaces
    from skinsafe.core.skin.model import Module

    placed = [placed_from_design(design, m.id) for m in design.modules]
    bare = []
    new = 0
    for body, p, n in _distinct(points, pitch / 2):
        if _covered(design, body, p, n, pitch) or any(
                pm.module.body == body and np.any((np.linalg.norm(pm.positions - p, axis=1) < pitch)
                                                  & (pm.frames[:, :, 2] @ n > 0)) for pm in placed):
            continue
        surf = cached_surfaces(robot.model, [body])[body]
        q0 = surf.closest(p[None])[0][0]
        axis = _body_axis(robot.model, body)  # rows along it where the surface allows
        t1 = axis if abs(axis @ n) < 0.9 else np.eye(3)[int(np.argmin(np.abs(n)))]
        t1 = t1 - (t1 @ n) * n  # anchors around the point across the contact normal: at an edge, onto the face it presses
        t1 /= np.linalg.norm(t1)
        t2 = np.cross(n, t1)
        done = False
        for mp in (pitch, 0.6 * pitch):  # a finer module fits closer to an edge and to the modules there
            for rows, cols in ((3, 3), (2, 3), (3, 2), (2, 2), (1, 2), (2, 1), (1, 1)):
                for du, dv in SHIFTS:
                    anchor = q0 + mp * (du * t1 + dv * t2)
                    mod = Module(id=len(placed), name=f"{body}_person_m{len(placed)}", body=body, rows=rows, cols=cols,
                                 pitch=mp, taxel_diameter=0.6 * mp, margin=0.1 * mp, min_bend_radius=min(0.01, mp))
                    try:
                        pm = place_module(surf, mod, anchor, t1, others=[o for o in placed if o.module.body == body])
                    except PlacementError:
                        continue
                    if np.any((np.linalg.norm(pm.positions - p, axis=1) < pitch) & (pm.frames[:, :, 2] @ n > 0)):
                        pm.module = replace(mod, placement=placement_record(pm.origin, pm.origin_frame[:, 0],
                                                                            "geodesic"))
                        placed.append(pm)
                        new += 1
                        done = True
                        break
                if done:
                    break
            if done:
                break
        if not done:
            bare.append((body, p, n))
    if not new:
        return design, bare
    bodies = list(dict.fromkeys(list(design.bodies) + [pm.module.body for pm in placed]))
    return build_design(design.robot, placed, 512, float(np.median(design.taxels.thresholds["force"])),
                        bodies=bodies), bare


SHIFTS = [(0.0, 0.0)] + [(r * np.cos(a), r * np.sin(a)) for r in (0.5, 1.0, 1.5) for a in np.arange(8) * np.pi / 4]


def _distinct(points, cell: float):
    """One point per body and `cell`-sized voxel (the first met)."""
    seen, out = set(), []
    for body, p, n in points:
        key = (body, *np.floor(p / cell).astype(int))
        if key not in seen:
            seen.add(key)
            out.append((body, p, n / np.linalg.norm(n)))
    return out


def _body_axis(model, body: str) -> np.ndarray:
    """The axis of a body's first capsule/cylinder geom (body frame), else its x axis."""
    import mujoco

    bid = model.body(body).id
    for g in np.flatnonzero(model.geom_bodyid == bid):
        if int(model.geom_type[g]) in (int(mujoco.mjtGeom.mjGEOM_CAPSULE), int(mujoco.mjtGeom.mjGEOM_CYLINDER)):
            R = np.zeros(9)
            mujoco.mju_quat2Mat(R, model.geom_quat[g])
            return R.reshape(3, 3)[:, 2].copy()
    return np.array([1.0, 0.0, 0.0])


def collaboration_skin(cfg: CollabConfig, rounds: int = 3, progress: bool = False):
    """The sample skin covered where the person meets the robot (module docstring): each round
    simulates every scenario with every stack on the skin so far and places modules at the contact
    points no taxel senses. Returns the design and the points still bare."""
    from skinsafe.core.design.sample import make_sample_design
    from skinsafe.core.robot.kinematics import TaxelKinematics
    from skinsafe.core.robot.models import build_ur5

    robot = build_ur5()
    design = make_sample_design("ur5", pitch=cfg.pitch, robot=robot)
    bare = []
    for _ in tqdm(range(rounds), desc="covering the contacts", disable=not progress, leave=False):
        kin = TaxelKinematics(robot.model, design)
        points = []
        for scenario in SCENARIOS:
            lay = layout(scenario, kin, cfg)
            sc = build(lay, design, NOMINAL["damping_ratio"], NOMINAL["attachment_N_m"], NOMINAL["dt_ms"], cfg)
            points += contact_points(sc, lay, STACKS, learn_person(sc, lay, cfg), cfg)
        before = design.n_taxels
        design, bare = cover(design, robot, points, cfg.pitch)
        if design.n_taxels == before:
            break
    return design, bare


