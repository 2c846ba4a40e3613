"""`skinsafe experiment collaboration` (paper Fig. 15) as an ISO/TS 15066 power-and-force-limiting
test of the skin and the three layers, run the way a safety assessor would.

Scenarios (`SCENARIOS`), each with a person (`core.sim.human`: ISO/TS 15066 masses and springs per
region, force-limited muscles) beside the UR5 on its table:

- `delivery` (robot-driven): the UR5 delivers a part with a fast pan sweep (`--duration`) while the
  person's lower arm and hand reach radially into the wrist's path, stay `--stay` s and withdraw;
  the planner (or a teleoperation stream, `--source teleoperation`) then completes the delivery;
- `clamp` (robot-driven): the hand rests flat on the table and the robot lowers its flange onto it
  (a part placed on the table): the hand can be trapped against the table;
- `person` (person-driven): the robot holds still where the delivery meets the hand and the person
  moves the hand into the wrist at `--person-speed` (0.5 m/s), pushing on past the surface for a
  moment before withdrawing.

Stacks: `none` (the joint velocity limits only), `retraction` (defensiveness), `full`
(defensiveness + modulation by a TDM learned from static contacts with the person, scaled by
`--presence`), `full+pfl` (`full` + the PFL cap, `core.safety.pfl.PFLCap`: the person's regions at
`--pfl-factor` of v_max, pressure from the taxels' cells, clamping against the table, the person's
parts and velocities observed). Every stack ticks at the scene's control period (`Scene.stack`).

The skin (`collaboration_skin`): the sample skin plus modules placed (`design.placement`) where the
person meets the robot in these scenarios, found by simulating them; every contact row says
whether the skin sensed it (`sensed`, `sensed_ms` after its start), which layers acted during it
(`acted`), and a contact on bare surface is named in `findings`.

Contacts (`contact_events`) come from the physics steps: a run of robot force on a body part (gaps
under `GAP_S` merged). Its kind is the contact's kinematics: `clamp` when the robot pressed the part
against the table, `quasi_static` when it pinched it between links, `transient` when the part could
recoil (the transient limits for its first `TRANSIENT_S`, the quasi-static ones for any longer
push). `ratio` is the worst of peak force and peak pressure over their limits.

The robustness sweep (`--sweep`, Ray over `--workers`): contact damping ratio x the person's
attachment stiffness x physics timestep, for every scenario, the `--sweep-stacks`; each cell's
`worst_ratio`, and for the person-driven scenario its peak against the `none` run's.
"""
from __future__ import annotations

import argparse
import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch
from tqdm.auto import tqdm

TRANSIENT_S = 0.5  # ISO/TS 15066: transient contact lasts up to 0.5 s; a longer push is quasi-static
GAP_S = 0.1  # force-free gaps shorter than this do not end a contact event
GOAL_TOL = 0.02  # rad: a robot task is complete when every joint is this close to its goal
REACH_S = 0.4  # s: the person reaches in (or withdraws) 0.5 m, smoothly
STACKS = ("none", "retraction", "full", "full+pfl")
SCENARIOS = ("delivery", "clamp", "person")
ROBOT_DRIVEN = ("delivery", "clamp")
SWEEP = {"damping_ratio": (0.0, 0.25, 0.5), "attachment_N_m": (1500.0, 3000.0), "dt_ms": (2.0, 1.0, 0.5)}
NOMINAL = {"damping_ratio": 0.1, "attachment_N_m": 1500.0, "dt_ms": 2.0}
TABLE = "table"  # the UR5 model's table top (z = 0): the fixture a hand can be clamped against
PERSON_SPREAD = 0.15  # rad: the person-driven scenario's TDM samples around the held pose (see `layout`)
FIST = 0.02  # m: the radius of a hand (a fist) resting on the table (a flat box rocks at a 2 ms step)
CLAMP_AT = np.array([-0.45, -0.12])  # m: where on the table the hand rests and the flange comes down
CLAMP_DEPTH = 0.015  # m: the placing motion ends this far into the resting hand (4 cm thick)
MODULATED = 0.05  # danger potential above which modulation counts as acting


# ------------------------------------------------------------------------------------ motions

def _delivery(t: float, duration: float):
    """The delivery motion: pan from -0.8 to 0.8 rad (smooth), the rest at home."""
    from skinsafe.core.robot.models import UR5_HOME

    q = UR5_HOME.copy()
    s, ds = _smooth(t, duration)
    q[0] = -0.8 + 1.6 * s
    v = np.zeros(6)
    v[0] = 1.6 * ds
    return q, v


def _smooth(t: float, duration: float) -> tuple[float, float]:
    """Quintic 0 -> 1 over `duration` and its rate."""
    u = float(np.clip(t / duration, 0, 1))
    s = 10 * u ** 3 - 15 * u ** 4 + 6 * u ** 5
    ds = (30 * u ** 2 - 60 * u ** 3 + 30 * u ** 4) / duration if 0 < t < duration else 0.0
    return s, ds


def _tool_down(model, xy, z: float) -> np.ndarray:
    """UR5 joints with the flange pointing down, its end face centred over `xy` at height `z`."""
    import mujoco
    from scipy.optimize import least_squares

    d = mujoco.MjData(model)
    g = model.geom("wrist_3_link_0").id

    def q_of(x):
        pan, lift, elbow = x
        return np.array([pan, lift, elbow, -np.pi / 2 - lift - elbow, -np.pi / 2, 0.0])

    def err(x):
        d.qpos[:] = q_of(x)
        mujoco.mj_kinematics(model, d)
        axis = d.geom_xmat[g].reshape(3, 3)[:, 2]
        end = d.geom_xpos[g] - np.sign(axis[2]) * axis * model.geom_size[g][1]  # the lower end face
        return np.r_[end[:2] - xy, end[2] - z]

    pan = float(np.arctan2(-xy[1], -xy[0]))
    sol = least_squares(err, [pan, -1.0, 1.8], bounds=([pan - 1, -np.pi, 0.2], [pan + 1, 0.0, np.pi - 0.2]))
    return q_of(sol.x)


@dataclass
class Layout:
    """A scenario: the person's parts, where they mean to be over time, and the robot's plan."""

    scenario: str
    parts: list
    targets: Callable[[float], list]  # t -> intended part positions (world)
    desired: Callable[[float], tuple]  # t -> (q_d, qd_d) of the robot's plan
    present: list  # part positions while the person is in the way (for the TDM's samples)
    sample: Callable  # (rng, n) -> (n, 6) robot configurations along the plan
    t_end: float
    plan_end: float  # when the plan is done (its goal reached, at the earliest)
    goal: np.ndarray | None  # the robot's goal, for the task time (None: no task)
    regions: tuple


def _wrist_spot(kin, q):
    """The wrist housings' centre at q (area-weighted, whatever skin covers them)."""
    kin.poses(q)
    m, d = kin.model, kin.data
    tubes = [m.body(b).geomadr[0] for b in ("wrist_1_link", "wrist_2_link")]
    area = np.array([m.geom_size[g][0] * m.geom_size[g][1] for g in tubes])
    return area @ d.geom_xpos[tubes] / area.sum()


def _capsule_quat(direction) -> tuple:
    """Quaternion turning a capsule's axis (local z) onto the horizontal `direction`."""
    ang = np.arctan2(direction[1], direction[0])
    return (np.cos(np.pi / 4) * np.cos(ang / 2), -np.sin(np.pi / 4) * np.sin(ang / 2),
            np.sin(np.pi / 4) * np.cos(ang / 2), np.cos(np.pi / 4) * np.sin(ang / 2))


def _reach(t: float, t0: float, dist: float, speed: float, accel: float = 5.0) -> float:
    """Distance covered at t along a move of `dist` starting at t0 (trapezoid: accel, speed)."""
    ta = speed / accel
    if dist < speed * ta:  # never reaches full speed
        ta = np.sqrt(dist / accel)
        speed = accel * ta
    tc = dist / speed - ta
    u = t - t0
    if u <= 0:
        return 0.0
    if u < ta:
        return 0.5 * accel * u * u
    if u < ta + tc:
        return 0.5 * accel * ta * ta + speed * (u - ta)
    if u < 2 * ta + tc:
        w = 2 * ta + tc - u
        return dist - 0.5 * accel * w * w
    return dist


def layout(scenario: str, kin, cfg: dict) -> Layout:
    """The scenario's geometry and motions (module docstring) for the UR5 of `kin`."""
    from skinsafe.core.sim.human import Part

    T = cfg["duration"]
    if scenario == "clamp":
        top = _tool_down(kin.model, CLAMP_AT, 0.15)
        low = _tool_down(kin.model, CLAMP_AT, 2 * FIST - CLAMP_DEPTH)
        out = np.r_[CLAMP_AT / np.linalg.norm(CLAMP_AT), 0.0]  # away from the robot's base
        hand = np.r_[CLAMP_AT, FIST]  # resting on the table, the forearm behind it
        parts = [Part("lower_arm", "capsule", (0.035, 0.12), pos=tuple(hand + out * 0.2 + [0, 0, 0.035 - FIST]),
                      quat=_capsule_quat(out)),
                 Part("hand", "sphere", (FIST,), pos=tuple(hand))]
        hold = cfg["stay"] + 4.0  # long enough for a robot slowed near the table to reach the hand

        def desired(t):  # down in T, hold, up in T
            s1, d1 = _smooth(t, T)
            s2, d2 = _smooth(t - T - hold, T)
            return top + (low - top) * (s1 - s2), (low - top) * (d1 - d2)

        home = [np.array(p.pos, float) for p in parts]
        return Layout(scenario, parts, lambda t: home, desired, home,
                      lambda rng, n: top + (low - top) * rng.uniform(0, 1, (n, 1)) + rng.normal(0, 0.03, (n, 6)),
                      t_end=2 * T + hold + cfg["finish"], plan_end=2 * T + hold, goal=top, regions=("lower_arm", "hand"))
    q = _delivery(0.6 * T, T)[0]  # where the wrist passes at 60% of the delivery
    spot = _wrist_spot(kin, q)
    pan = q[0]
    side = np.array([np.sin(pan), -np.cos(pan), 0.0])  # where the sweep goes (d/dpan of -r(cos, sin))
    out = np.array([-np.cos(pan), -np.sin(pan), 0.0])  # radially outward at the wrist (the arm points along -x)
    quat = _capsule_quat(out)
    if scenario == "delivery":
        at = spot + side * 0.03 + out * 0.27  # the hand by the tool, the lower arm beyond the robot's reach
        parts = [Part("lower_arm", "capsule", (0.035, 0.12), pos=tuple(at), quat=quat),
                 Part("hand", "sphere", (0.045,), pos=tuple(at - out * 0.17))]
        home = [np.array(p.pos, float) for p in parts]
        away = [p + out * 0.5 for p in home]
        t_in, t_out = 0.1 * T, 0.1 * T + REACH_S + cfg["stay"]

        def targets(t):  # reach in (smooth), stay, withdraw
            u = np.clip((t - t_in) / REACH_S, 0, 1) * (1 - np.clip((t - t_out) / REACH_S, 0, 1))
            u = 3 * u ** 2 - 2 * u ** 3
            return [a + (h - a) * u for a, h in zip(away, home)]

        def sample(rng, n):
            Q = np.array([_delivery(t, T)[0] for t in rng.uniform(0, T, n)])
            Q[:, :4] += rng.normal(0, 0.05, (n, 4))
            return Q

        return Layout(scenario, parts, targets, lambda t: _delivery(t, T), home, sample,
                      t_end=t_out + REACH_S + cfg["finish"], plan_end=T, goal=_delivery(T, T)[0],
                      regions=("lower_arm", "hand"))
    # person: the hand comes at the still wrist from the side the delivery sweeps toward, the lower
    # arm behind it along the reach
    hand0 = spot - side * 0.3
    arm0 = hand0 - side * 0.17
    parts = [Part("lower_arm", "capsule", (0.035, 0.12), pos=tuple(arm0), quat=_capsule_quat(side)),
             Part("hand", "sphere", (0.045,), pos=tuple(hand0))]
    speed, t0, hold = cfg["person_speed"], 0.2, 0.3
    dist = 0.3  # to the wrist's centre: the person means to reach through it
    t_back = t0 + dist / speed + speed / 5.0 + hold

    def targets(t):
        s = _reach(t, t0, dist, speed) - _reach(t, t_back, dist, speed)
        return [p + side * s for p in (arm0, hand0)]

    present = [arm0 + side * (dist - 0.09), hand0 + side * (dist - 0.09)]  # the hand against the wrist
    # the TDM's samples span where the retraction takes the held arm (~0.3 rad of pan), not only the held pose:
    # from 0.05 rad it extrapolated a rising danger along the retraction, and the modulation slowed it
    return Layout(scenario, parts, targets, lambda t: (q, np.zeros(6)), present,
                  lambda rng, n: q + np.c_[rng.normal(0, PERSON_SPREAD, (n, 4)), np.zeros((n, 2))],
                  t_end=t_back + dist / speed + 0.5, plan_end=0.0, goal=None, regions=("lower_arm", "hand"))


# ------------------------------------------------------------------------------------ the scene

def build(lay: Layout, design, damping: float, attach: float, dt_ms: float, cfg: dict):
    """The scene of a layout: UR5 + skin + the person (+ the table as a fixture)."""
    from skinsafe.core.experiments.arm_scene import Scene
    from skinsafe.core.sim.human import Human

    human = Human(lay.parts, attach_N_per_m=attach, contact_damping=damping, push_N=cfg["push_N"])
    return Scene([], design=design, human=human, timestep=dt_ms / 1e3, fixtures=(TABLE,))


def person_now(sc):
    """The person as the PFL cap sees it (`pfl.Person`): each part's core, radius and velocity."""
    from skinsafe.core.safety.pfl import Person

    h, m, d = sc.human, sc.model, sc.data
    ends = [sc._segment(k) for k in range(len(h.parts))]
    radius = [float(m.geom_size[g][0]) if m.geom_type[g] != 6 else float(np.linalg.norm(m.geom_size[g]))
              for g in h.geom]
    return Person(tuple(p.region for p in h.parts), np.array([e[0] for e in ends]), np.array([e[1] for e in ends]),
                  np.array(radius), np.array([h.velocity(d, k) for k in range(len(h.parts))]))


def make_stack(sc, stack: str, pot, cfg: dict, regions):
    """One of `STACKS` for the scene (module docstring); the cap (or None) alongside."""
    from skinsafe.core.safety.modulation import ModulationLayer
    from skinsafe.core.safety.pfl import PFLCap
    from skinsafe.core.sim.body_regions import contact_areas

    defens = sc.defensiveness() if stack != "none" else None
    mod = ModulationLayer(pot, tangent_gain=0.0) if stack.startswith("full") and pot is not None else None
    cap = None
    if stack == "full+pfl":
        cap = PFLCap(sc.kin, tuple(cfg.get("pfl_regions") or regions), factor=cfg["pfl_factor"],
                     area=contact_areas(sc.design), fixtures=[((0, 0, 0), (0, 0, 1))], stop_s=2 * sc.control_dt)
    return sc.stack(defens, mod, cap), cap


def episode(sc, lay: Layout, stack: str, pot, cfg: dict, person: bool = True, on_tick=None) -> dict:
    """One run of a scenario with one stack: the person trace (physics steps), the layers that acted
    per tick, the robot's pan joint and the task time. `on_tick(t, source, force, v, st, cap)`, if
    given, sees every control tick after the stack ran (to record the episode for the view)."""
    from skinsafe.core.safety.stack import TeleopStream, TrajectorySource

    st, cap = make_stack(sc, stack, pot, cfg, lay.regions)
    h = sc.human
    sc.reset(lay.desired(0.0)[0])
    if lay.scenario == "delivery" and cfg["source"] == "teleoperation":  # recorded at 125 Hz, replayed 50 ms late
        times = np.arange(0, lay.t_end + 0.5, 1 / 125)
        noise = np.random.default_rng(cfg["seed"]).normal(0, 0.002, (len(times), 6))
        source = TeleopStream(times, np.array([lay.desired(t)[0] for t in times]) + noise, latency=0.05)
    else:
        source = TrajectorySource(lay.desired)
    far = [p + np.array([0.0, 0.0, 2.0]) for p in lay.targets(0.0)]  # no person: out of the room
    for i, p in enumerate(lay.targets(0.0) if person else far):
        h.place(sc.data, i, p)
    v, acted, pan, done = np.zeros(6), [], [], None
    steps = int(round(lay.t_end / sc.control_dt))
    for k in range(steps):
        t = k * sc.control_dt
        if person:
            for i, p in enumerate(lay.targets(t)):
                h.move(i, p)
        if cap is not None:
            cap.observe(person_now(sc) if person else None)
        force = sc.step(v)
        pan.append(float(sc.q[0]))
        v = st.run(source, t, sc.q, {"force": force}, sc.control_dt, qdot=sc.qdot)  # the measured velocity
        d = st.defensiveness
        acted.append(((d is not None and d.active), cap is not None and cap.last_mode != "free",
                      st.modulation is not None and st.last_f >= MODULATED))
        if on_tick is not None:
            on_tick(t, source, force, v, st, cap)
        if done is None and lay.goal is not None and t >= lay.plan_end and np.max(np.abs(sc.q - lay.goal)) < GOAL_TOL:
            done = t
            if not person:
                break
    import mujoco

    return {"trace": sc.trace.arrays(), "acted": np.array(acted, bool).reshape(-1, 3), "pan": np.array(pan),
            "done": done, "cap_retreats": cap.retreats if cap is not None else 0,
            "unstable": int(sc.data.warning[mujoco.mjtWarning.mjWARN_BADQACC].number)}  # MuJoCo reset a blow-up


# ------------------------------------------------------------------------------------ contacts

def contact_events(trace: dict, regions: list[str], control_dt: float, acted=None, body_names=None) -> list[dict]:
    """Contact events per body part from a person trace (`arm_scene.PersonTrace.arrays`): module
    docstring. `acted` (ticks, 3) bool: defensiveness, pfl, modulation acting per control tick."""
    from skinsafe.core.sim.body_regions import region

    t = trace["time_s"]
    if not len(t):
        return []
    dt = float(np.median(np.diff(t))) if len(t) > 1 else control_dt
    gap = max(1, int(round(GAP_S / dt)))
    n_tr = int(round(TRANSIENT_S / dt))
    out = []
    for j, name in enumerate(regions):
        reg = region(name)
        f = trace["force_N"][:, j]
        on = np.flatnonzero(f > 0)
        if not len(on):
            continue
        breaks = np.flatnonzero(np.diff(on) > gap)
        for a, b in zip(np.r_[on[0], on[breaks + 1]], np.r_[on[breaks], on[-1]]):
            sl = slice(a, b + 1)
            fe, pe = f[sl], trace["pressure_N_cm2"][sl, j]
            kind = ("clamp" if trace["trapped"][sl, j].any() else
                    "quasi_static" if trace["pinched"][sl, j].any() else "transient")
            first = slice(0, n_tr) if kind == "transient" else slice(None)
            rest = slice(n_tr, None) if kind == "transient" else slice(0, 0)
            peak, peak_p = float(fe[first].max()), float(pe[first].max())
            qs = float(fe[rest].max()) if len(fe[rest]) else 0.0
            qs_p = float(pe[rest].max()) if len(pe[rest]) else 0.0
            lim, lim_p = reg.force_limit(kind), reg.pressure_limit(kind)
            ratios = [_ratio(peak, lim), _ratio(qs, reg.quasi_static_N), _ratio(peak_p, lim_p),
                      _ratio(qs_p, reg.pressure_N_cm2)]
            sensed = np.flatnonzero(trace["sensed"][sl, j])
            bare = (fe > 0) & ~trace["touched"][sl, j]
            bodies = trace["body"][sl, j]
            link = int(bodies[np.argmax(fe)])
            ticks = slice(int(t[a] // control_dt), int(t[b] // control_dt) + 2)
            layers = [n for n, on_ in zip(("defensiveness", "pfl", "modulation"),
                                          acted[ticks].any(axis=0) if acted is not None and len(acted[ticks]) else ())
                      if on_]
            out.append({"region": name, "kind": kind, "start_s": round(float(t[a]), 4),
                        "duration_s": round(float(t[b] - t[a] + dt), 4),
                        "peak_N": peak, "limit_N": lim, "quasi_static_N": qs, "quasi_static_limit_N": reg.quasi_static_N,
                        "peak_pressure_N_cm2": peak_p, "pressure_limit_N_cm2": lim_p,
                        "quasi_static_pressure_N_cm2": qs_p, "quasi_static_pressure_limit_N_cm2": reg.pressure_N_cm2,
                        "ratio": max(ratios), "within": bool(max(ratios) <= 1.0),
                        "sensed": bool(len(sensed)), "sensed_ms": round(1e3 * float(t[a + sensed[0]] - t[a]), 2)
                        if len(sensed) else None,
                        "bare_ms": round(1e3 * float(bare.sum()) * dt, 2),
                        "robot_link": body_names[link] if body_names is not None and link >= 0 else str(link),
                        "acted": "+".join(layers) or "none"})
    return sorted(out, key=lambda e: e["start_s"])


def _ratio(value: float, limit: float) -> float:
    if value <= 0:
        return 0.0
    return value / limit if limit > 0 else float("inf")


# ------------------------------------------------------------------------------------ the skin

def contact_points(sc, lay: Layout, stacks, pot, cfg: dict) -> list[tuple[str, np.ndarray, np.ndarray]]:
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


def collaboration_skin(cfg: dict, rounds: int = 3, progress: bool = False):
    """The sample skin covered where the person meets the robot (module docstring): each round
    simulates every scenario with every stack on the skin so far and places modules at the contact
    points no taxel senses. Returns the design and the points still bare."""
    from skinsafe.core.design.sample import make_sample_design
    from skinsafe.core.robot.kinematics import TaxelKinematics
    from skinsafe.core.robot.models import build_ur5

    robot = build_ur5()
    design = make_sample_design("ur5", pitch=cfg["pitch"], robot=robot)
    bare = []
    for _ in tqdm(range(rounds), desc="covering the contacts", disable=not progress, leave=False):
        kin = TaxelKinematics(robot.model, design)
        points = []
        for scenario in SCENARIOS:
            lay = layout(scenario, kin, cfg)
            sc = build(lay, design, NOMINAL["damping_ratio"], NOMINAL["attachment_N_m"], NOMINAL["dt_ms"], cfg)
            points += contact_points(sc, lay, STACKS, learn_person(sc, lay, cfg), cfg)
        before = design.n_taxels
        design, bare = cover(design, robot, points, cfg["pitch"])
        if design.n_taxels == before:
            break
    return design, bare


# ------------------------------------------------------------------------------------ the TDM

class _Presence(torch.nn.Module):
    """danger = presence x f_phi: the person is at the bench in a fraction of the deliveries."""

    def __init__(self, f, presence: float):
        super().__init__()
        self.f, self.presence = f, float(presence)

    def forward(self, s, a):
        return self.presence * self.f(s, a)


_POTENTIALS: dict = {}


def learn_person(sc, lay: Layout, cfg: dict):
    """A TDM from static contacts with the person where they are in the way, at configurations along
    the robot's plan (labels from the skin readout), as the modulation potential `presence x f_phi`;
    one per scenario, skin and options in a process."""
    import mujoco

    from skinsafe.core.experiments.arm_scene import STATE, static_contact_tdm
    from skinsafe.core.safety.potential import DangerPotential

    key = (lay.scenario, sc.design.n_taxels, float(np.sum(sc.design.taxels.positions)),
           json.dumps({k: cfg[k] for k in ("seed", "samples", "steps", "presence", "duration",
                                           "person_speed")}, sort_keys=True))
    if key in _POTENTIALS:
        return _POTENTIALS[key]
    rng = np.random.default_rng(cfg["seed"])
    n = cfg["samples"]
    Q = lay.sample(rng, n)
    A = rng.uniform(-1, 1, (n, len(STATE)))
    D = np.zeros((n, sc.design.n_taxels), np.float32)
    m, d, h = sc.model, sc.data, sc.human
    for i in range(n):
        mujoco.mj_resetData(m, d)
        for k, p in enumerate(lay.present):
            h.place(d, k, p)
        d.qpos[sc.qadr] = Q[i]
        mujoco.mj_forward(m, d)
        D[i] = sc.readout.read(d) > 0
    args = type("Args", (), {"seed": cfg["seed"], "steps": cfg["steps"]})
    pot = _Presence(DangerPotential(static_contact_tdm(Q[:, STATE], A, D, args)), cfg["presence"])
    _POTENTIALS[key] = pot
    return pot


# ------------------------------------------------------------------------------------ one cell

def cell(method: str, seed: int, scenario: str, damping_ratio: float, attachment_N_m: float, dt_ms: float,
         stacks: list, config: dict, skin: str, detail: bool = False) -> dict:
    """One scenario at one (damping, attachment, timestep) with each stack: its contact events, and
    with `detail` the force and pan traces and the task times (with and without the person)."""
    from skinsafe.core.robot.kinematics import TaxelKinematics
    from skinsafe.core.skin.taxel_map import load
    from skinsafe.core.timing import single_thread_blas

    torch.set_num_threads(1)
    single_thread_blas()
    cfg = dict(config, seed=seed)
    if not detail:  # no task time: the run ends soon after the last contact can happen
        cfg["finish"] = 0.3
    design = load(skin)
    sc = None
    out = {"scenario": scenario, "damping_ratio": damping_ratio, "attachment_N_m": attachment_N_m, "dt_ms": dt_ms,
           "stacks": {}}
    for stack in stacks:
        if sc is None:
            kin = TaxelKinematics(_ur5().model, design)
            lay = layout(scenario, kin, cfg)
            sc = build(lay, design, damping_ratio, attachment_N_m, dt_ms, cfg)
            pot = learn_person(sc, lay, cfg) if any(s.startswith("full") for s in stacks) else None
        run = episode(sc, lay, stack, pot, cfg)
        names = [sc.model.body(b).name for b in range(sc.model.nbody)]
        events = contact_events(run["trace"], [p.region for p in lay.parts], sc.control_dt, run["acted"], names)
        res = {"events": events, "task_time_s": run["done"], "cap_retreats": run["cap_retreats"],
               "unstable": run["unstable"]}
        if detail:
            tr = run["trace"]
            every = _every(dt_ms)  # the force trace at 1 ms, or at the step where it is coarser
            res["force_N"] = tr["force_N"].sum(axis=1)[::every].round(2).tolist() if len(tr["time_s"]) else []
            res["pan_rad"] = run["pan"].round(4).tolist()
            res["no_person_task_time_s"] = episode(sc, lay, stack, pot, cfg, person=False)["done"] \
                if lay.goal is not None else None
        out["stacks"][stack] = res
    return out


def _every(dt_ms: float) -> int:
    """Physics steps per sample of the detail cells' force trace (about 1 ms)."""
    return max(1, int(round(1.0 / dt_ms)))


def _ur5():
    from skinsafe.core.robot.models import build_ur5

    return build_ur5()


# ------------------------------------------------------------------------------------ the experiment

def config(args) -> dict:
    """The options every cell needs (JSON: part of each Ray task)."""
    return {"pitch": args.pitch, "duration": args.duration, "stay": args.stay, "finish": args.finish,
            "presence": args.presence, "pfl_factor": args.pfl_factor, "pfl_regions": args.pfl_regions,
            "samples": args.samples, "steps": args.steps, "source": args.source, "person_speed": args.person_speed,
            "push_N": args.push}


def run_experiment(args) -> dict:
    """Nominal runs of every scenario with every stack, then the sweep (module docstring)."""
    from skinsafe.core.experiments.runner import run_tasks
    from skinsafe.core.skin.taxel_map import load, save

    out_dir = Path(args.out or "results/collaboration")
    cfg = config(args)
    cfg["seed"] = args.seed
    skin = Path(args.skin) if args.skin else out_dir / "collaboration_skin.json"
    if args.skin and not skin.is_file():
        raise SystemExit(f"--skin: '{skin}' is not a file; give a taxel map (or leave --skin out to design one)")
    if not args.skin and (args.redesign or not skin.exists()):
        save(collaboration_skin(cfg, args.cover_rounds, progress=not args.no_progress)[0], skin)
    design = load(skin)
    tasks = [_task(s, NOMINAL, list(args.stacks), cfg, skin, args.seed, detail=True) for s in SCENARIOS]
    if args.sweep:
        for s in SCENARIOS:
            for z in args.sweep_damping:
                for k in args.sweep_attach:
                    for dt in args.sweep_dt:
                        tasks.append(_task(s, {"damping_ratio": z, "attachment_N_m": k, "dt_ms": dt},
                                           list(args.sweep_stacks), cfg, skin, args.seed))
    results = run_tasks(cell, tasks, out_dir / "tasks", address=args.address, workers=args.workers,
                        progress=not args.no_progress, desc="collaboration", fresh=args.fresh,
                        cost=lambda t: (3 if t["detail"] else 1) * len(t["stacks"]) / t["dt_ms"])
    return summarise(results[:len(SCENARIOS)], results[len(SCENARIOS):], design, cfg)


def _task(scenario, cell_cfg, stacks, cfg, skin, seed, detail=False) -> dict:
    tag = f"{scenario}_z{cell_cfg['damping_ratio']:g}_k{cell_cfg['attachment_N_m']:g}_dt{cell_cfg['dt_ms']:g}"
    return {"method": tag + ("_detail" if detail else ""), "seed": seed, "scenario": scenario, **cell_cfg,
            "stacks": stacks, "config": cfg, "skin": str(skin), "detail": detail}


def summarise(nominal: list, sweep: list, design, cfg: dict) -> dict:
    """The result file: contact rows and run summaries of the nominal cells, the sweep table, the
    findings (contacts the skin did not sense; limits exceeded by full+pfl)."""
    out = {"config": cfg, "nominal": NOMINAL, "skin_taxels": design.n_taxels, "skin_modules": len(design.modules),
           "contacts": [], "runs": {}, "sweep": [], "findings": []}
    for r in nominal:
        for stack, res in r["stacks"].items():
            for e in res["events"]:
                out["contacts"].append({"scenario": r["scenario"], "stack": stack, **e})
            ev = res["events"]
            out["runs"][f"{r['scenario']}/{stack}"] = {
                "events": len(ev), "within": all(e["within"] for e in ev), "sensed": all(e["sensed"] for e in ev),
                "peak_N": max((max(e["peak_N"], e["quasi_static_N"]) for e in ev), default=0.0),
                "worst_ratio": max((e["ratio"] for e in ev), default=0.0),
                "task_time_s": res["task_time_s"], "no_person_task_time_s": res.get("no_person_task_time_s"),
                "force_N": res["force_N"], "pan_rad": res["pan_rad"]}
    none_peak = {}
    for r in sweep:
        for stack, res in r["stacks"].items():
            ev = res["events"]
            worst = max(ev, key=lambda e: e["ratio"], default=None)
            row = {"scenario": r["scenario"], "stack": stack, "damping_ratio": r["damping_ratio"],
                   "attachment_N_m": r["attachment_N_m"], "dt_ms": r["dt_ms"],
                   "worst_ratio": worst["ratio"] if worst else 0.0,
                   "peak_N": max((max(e["peak_N"], e["quasi_static_N"]) for e in ev), default=0.0),
                   "peak_pressure_N_cm2": max((e["peak_pressure_N_cm2"] for e in ev), default=0.0),
                   "kind": worst["kind"] if worst else None, "events": len(ev),
                   "sensed": all(e["sensed"] for e in ev), "unstable": res.get("unstable", 0)}
            key = (r["scenario"], r["damping_ratio"], r["attachment_N_m"], r["dt_ms"])
            if stack == "none":
                none_peak[key] = row["peak_N"]
            out["sweep"].append(row)
    for row in out["sweep"]:
        base = none_peak.get((row["scenario"], row["damping_ratio"], row["attachment_N_m"], row["dt_ms"]))
        row["peak_vs_none"] = row["peak_N"] / base if base else None
    for e in out["contacts"]:
        if not e["sensed"]:
            out["findings"].append(f"{e['scenario']}/{e['stack']}: {e['region']} contact at {e['start_s']} s on "
                                   f"{e['robot_link']} was not sensed (bare surface {e['bare_ms']} ms)")
    for r in nominal + sweep:
        for stack, res in r["stacks"].items():
            if res.get("unstable"):
                out["findings"].append(f"{r['scenario']}/{stack} zeta {r['damping_ratio']} attach {r['attachment_N_m']} "
                                       f"dt {r['dt_ms']} ms: the simulation blew up and MuJoCo reset it")
    for row in out["sweep"]:
        if row["stack"] == "full+pfl" and row["scenario"] in ROBOT_DRIVEN and row["worst_ratio"] > 1:
            out["findings"].append(f"sweep {row['scenario']} zeta {row['damping_ratio']} attach {row['attachment_N_m']} "
                                   f"dt {row['dt_ms']} ms: full+pfl at {row['worst_ratio']:.2f} of its limit")
    return out


# ------------------------------------------------------------------------------------ command

def add_arguments(p) -> None:
    import os

    p.add_argument("--out", default=None, help="output folder (default results/collaboration)")
    p.add_argument("--pitch", type=float, default=0.01, help="skin pitch (m)")
    p.add_argument("--duration", type=float, default=1.0, help="the delivery sweep and the placing motion (s)")
    p.add_argument("--stay", type=float, default=1.5, help="seconds the person stays in the path (the robot holds as long)")
    p.add_argument("--finish", type=float, default=2.0, help="seconds for the robot to complete its task afterwards")
    p.add_argument("--presence", type=float, default=0.5,
                   help="fraction of deliveries with the person at the bench (scales the learned danger)")
    p.add_argument("--samples", type=int, default=3000, help="static contact samples for the TDM")
    p.add_argument("--steps", type=int, default=1500, help="TDM training steps (batch 64)")
    p.add_argument("--source", choices=["planner", "teleoperation"], default="planner",
                   help="the command source the stack filters in the delivery")
    p.add_argument("--person-speed", type=float, default=0.5, help="the person's hand speed into the still robot (m/s)")
    p.add_argument("--push", type=float, default=200.0, help="the most the person's muscles push or pull a part (N)")
    p.add_argument("--pfl-regions", nargs="+", default=None,
                   help="body regions the PFL cap protects (default: the person's regions)")
    p.add_argument("--pfl-factor", type=float, default=0.8,
                   help="PFL cap as a fraction of v_max (margin for the servos and the sampling)")
    p.add_argument("--sweep", action=argparse.BooleanOptionalAction, default=True,
                   help="run the robustness sweep (--no-sweep: the nominal runs only)")
    p.add_argument("--stacks", nargs="+", default=list(STACKS), choices=STACKS, help="the stacks of the nominal runs")
    p.add_argument("--sweep-stacks", nargs="+", default=["none", "full+pfl"], choices=STACKS)
    p.add_argument("--sweep-damping", type=float, nargs="+", default=list(SWEEP["damping_ratio"]),
                   help="contact damping ratios of the sweep")
    p.add_argument("--sweep-attach", type=float, nargs="+", default=list(SWEEP["attachment_N_m"]),
                   help="the person's attachment stiffnesses of the sweep (N/m)")
    p.add_argument("--sweep-dt", type=float, nargs="+", default=list(SWEEP["dt_ms"]), help="physics timesteps of the sweep (ms)")
    p.add_argument("--cover-rounds", type=int, default=3,
                   help="rounds of simulating the scenarios and covering where the person is met")
    p.add_argument("--redesign", action="store_true", help="place the skin's person modules again")
    p.add_argument("--skin", default=None,
                   help="a taxel map to run on as it is (default: OUT/collaboration_skin.json, designed when missing)")
    p.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1), help="local Ray CPUs (default %(default)s)")
    p.add_argument("--address", default=None, help="join this Ray cluster instead of starting a local Ray")
    p.add_argument("--fresh", action="store_true", help="re-run every cell instead of reusing finished ones")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--no-progress", action="store_true")


def check_args(args) -> None:
    """Refuse out-of-range options with a message naming the option and the fix."""
    from skinsafe.core.sim.body_regions import REGIONS

    checks = (("--pfl-factor", args.pfl_factor, 0 < args.pfl_factor <= 1, "a fraction of v_max in (0, 1]"),
              ("--presence", args.presence, 0 <= args.presence <= 1, "a fraction in [0, 1]"),
              ("--duration", args.duration, args.duration > 0, "seconds > 0"),
              ("--stay", args.stay, args.stay >= 0, "seconds >= 0"),
              ("--finish", args.finish, args.finish > 0, "seconds > 0"),
              ("--pitch", args.pitch, 0.005 <= args.pitch <= 0.05, "a pitch in [0.005, 0.05] m"),
              ("--person-speed", args.person_speed, 0 < args.person_speed <= 2, "m/s in (0, 2]"),
              ("--push", args.push, args.push > 0, "a force > 0 (N)"),
              ("--samples", args.samples, args.samples >= 10, "at least 10 static samples"),
              ("--steps", args.steps, args.steps >= 1, "at least 1 training step"),
              ("--workers", args.workers, args.workers >= 1, "at least 1"),
              ("--cover-rounds", args.cover_rounds, args.cover_rounds >= 0, "0 or more rounds"))
    for name, value, ok, want in checks:
        if not (np.isfinite(value) and ok):
            raise SystemExit(f"{name} is {value}; give {want}")
    for name, values, lo, hi in (("--sweep-damping", args.sweep_damping, 0, 2), ("--sweep-attach", args.sweep_attach, 1, 1e5),
                                 ("--sweep-dt", args.sweep_dt, 0.05, 10)):
        for v in values:
            if not (np.isfinite(v) and lo <= v <= hi):
                raise SystemExit(f"{name} has {v}; give values in [{lo:g}, {hi:g}]")
    for r in args.pfl_regions or ():
        if r not in REGIONS:
            raise SystemExit(f"--pfl-regions: '{r}' is unknown; use one of {', '.join(REGIONS)}")


def run(args) -> int:
    from skinsafe.core.skin.files import atomic_write

    check_args(args)
    out_dir = Path(args.out or "results/collaboration")
    t0 = time.perf_counter()
    res = run_experiment(args)
    res["seconds"] = time.perf_counter() - t0
    atomic_write(out_dir / "collaboration.json", json.dumps(res, indent=1))
    atomic_write(out_dir / "collaboration.md", tables(res))
    _save_plot(res, out_dir / "collaboration.png")
    for k, r in res["runs"].items():
        print(f"{k}: events={r['events']} within={r['within']} sensed={r['sensed']} peak_N={r['peak_N']:.0f} "
              f"worst_ratio={r['worst_ratio']:.2f} task_time_s={r['task_time_s']}")
    for row in res["sweep"]:
        if row["stack"] == "full+pfl":
            print(f"sweep {row['scenario']} zeta={row['damping_ratio']} attach={row['attachment_N_m']:g} "
                  f"dt={row['dt_ms']}ms: worst_ratio={row['worst_ratio']:.2f} peak_vs_none={row['peak_vs_none']}")
    for f in res["findings"]:
        print("finding:", f)
    print(f"wrote {out_dir / 'collaboration.json'}, collaboration.md and collaboration.png")
    return 0


def tables(res: dict) -> str:
    """The result as Markdown (collaboration.md): `nominal_table` and `sweep_table`."""
    sweep = sweep_table(res)
    return nominal_table(res) + ("\n\n" + sweep if sweep else "") + "\n"


def nominal_table(res: dict) -> str:
    """The nominal runs per scenario and stack: contacts, the worst ratio and its contact, peaks,
    sensing, the layers that acted, task times."""
    lines = ["| scenario | stack | contacts | worst ratio (kind, region) | peak N | peak N/cm^2 | sensed (latest, ms) "
             "| layers that acted | task s (no person) |", "| --- | --- | ---: | --- | ---: | ---: | --- | --- | ---: |"]
    for key, r in res["runs"].items():
        scenario, stack = key.split("/")
        ev = [e for e in res["contacts"] if e["scenario"] == scenario and e["stack"] == stack]
        worst = max(ev, key=lambda e: e["ratio"], default=None)
        late = max((e["sensed_ms"] or 0 for e in ev), default=0)
        acted = sorted({a for e in ev for a in e["acted"].split("+")} - {"none"}) or ["none"]
        task = "-" if r["task_time_s"] is None else f"{r['task_time_s']:.2f}"
        if r["no_person_task_time_s"] is not None:
            task += f" ({r['no_person_task_time_s']:.2f})"
        lines.append(f"| {scenario} | {stack} | {len(ev)} | "
                     + (f"{worst['ratio']:.2f} ({worst['kind']}, {worst['region']})" if worst else "-")
                     + f" | {r['peak_N']:.0f} | {max((e['peak_pressure_N_cm2'] for e in ev), default=0):.0f} | "
                     + ("all" if r["sensed"] else "**not all**") + f" ({late:.1f}) | {'+'.join(acted)} | {task} |")
    return "\n".join(lines)


def sweep_table(res: dict) -> str:
    """The sweep's worst ratio per cell (`none` / `full+pfl`), with the person-driven cells'
    full+pfl peak over the `none` run's; empty without a sweep."""
    rows, lines = res["sweep"], []
    cells = sorted({(r["damping_ratio"], r["attachment_N_m"]) for r in rows})
    if cells:
        lines = ["| scenario | dt ms | " + " | ".join(f"zeta {z:g}, {k:g} N/m" for z, k in cells) + " |",
                 "| --- | ---: | " + " | ".join("---:" for _ in cells) + " |"]
        for scenario in SCENARIOS:
            for dt in sorted({r["dt_ms"] for r in rows}, reverse=True):
                out = []
                for z, k in cells:
                    by = {r["stack"]: r for r in rows if (r["scenario"], r["dt_ms"], r["damping_ratio"],
                                                          r["attachment_N_m"]) == (scenario, dt, z, k)}
                    txt = " / ".join(f"{by[s]['worst_ratio']:.2f}" for s in ("none", "full+pfl") if s in by)
                    if scenario not in ROBOT_DRIVEN and by.get("full+pfl", {}).get("peak_vs_none") is not None:
                        txt += f" (x{by['full+pfl']['peak_vs_none']:.2f})"
                    out.append(txt or "-")
                lines.append(f"| {scenario} | {dt:g} | " + " | ".join(out) + " |")
    return "\n".join(lines)


def _save_plot(res: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")

    from skinsafe.core.skin.files import write_png

    fig = plot(res)
    write_png(fig, path)


def plot(res: dict):
    """Force on the person per scenario and stack (nominal cell), and every contact's and sweep
    cell's worst ratio to its ISO/TS 15066 limit."""
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 3, figsize=(15, 7.5))
    dt_ms = res["nominal"]["dt_ms"]
    period = _every(dt_ms) * dt_ms / 1e3  # s per sample of the force traces
    for ax, scenario in zip(axes[0], SCENARIOS):
        hit = [e["start_s"] for e in res["contacts"] if e["scenario"] == scenario]
        for stack in STACKS:
            f = res["runs"].get(f"{scenario}/{stack}", {}).get("force_N", [])
            ax.plot(np.arange(len(f)) * period, f, label=stack, lw=1)
        if hit:
            ax.set_xlim(min(hit) - 0.1, max(hit) + 0.6)
        ax.set_title(f"{scenario}: force on the person")
        ax.set_xlabel("time (s)")
        ax.set_ylabel("normal force on the person (N)")
        ax.legend(fontsize=7)
    ax = axes[1, 0]
    rows = res["contacts"]
    ax.bar(range(len(rows)), [min(e["ratio"], 3) for e in rows],
           color=["tab:red" if not e["within"] else "tab:green" for e in rows])
    ax.set_xticks(range(len(rows)), [f"{e['scenario'][:5]}/{e['stack']}\n{e['region']}" for e in rows], fontsize=5,
                  rotation=90)
    ax.axhline(1, color="k", lw=0.8)
    ax.set_ylabel("peak / ISO/TS 15066 limit (ratio, force or pressure)")
    ax.set_xlabel("contact (scenario/stack, region)")
    ax.set_title("nominal contacts")
    ax = axes[1, 1]
    for k, scenario in enumerate(SCENARIOS):
        for stack, marker in (("none", "x"), ("full+pfl", "o")):
            rows = [r for r in res["sweep"] if r["scenario"] == scenario and r["stack"] == stack]
            ax.scatter(np.arange(len(rows)) + 0.25 * k, [r["worst_ratio"] for r in rows], marker=marker, s=14,
                       label=f"{scenario} {stack}")
    ax.axhline(1, color="k", lw=0.8)
    ax.set_xlabel("sweep cell (number: damping x attachment x timestep)")
    ax.set_ylabel("worst peak / limit (ratio)")
    ax.set_title("robustness sweep")
    ax.legend(fontsize=6)
    ax = axes[1, 2]
    rows = [r for r in res["sweep"] if r["scenario"] == "person" and r["stack"] != "none"]
    ax.bar(range(len(rows)), [r["peak_vs_none"] or 0 for r in rows], color="tab:blue")
    ax.axhline(1, color="k", lw=0.8)
    ax.set_xlabel("sweep cell (number: damping x attachment x timestep)")
    ax.set_ylabel("peak with full+pfl / without safety (ratio)")
    ax.set_title("person moving into the still robot")
    if not res["sweep"]:  # a nominal-only run (--no-sweep): say so instead of drawing empty axes
        for ax in axes[1, 1:]:
            ax.cla()
            ax.set_axis_off()
            ax.text(0.5, 0.5, "sweep not run here (--no-sweep);\nthe full run: skinsafe experiment collaboration",
                    ha="center", va="center", fontsize=9, transform=ax.transAxes)
    fig.tight_layout()
    return fig
