"""The collaboration experiment's scenarios (core/experiments/collaboration.py, paper Fig. 15): its typed options
(`CollabConfig`), each scenario's person and robot plan (`layout`), the scene (`build`), the person as the PFL
cap sees it (`person_now`), the stacks (`make_stack`) and one run of a scenario with a stack (`episode`)."""
from __future__ import annotations

from dataclasses import asdict, dataclass, fields
from typing import Callable

import numpy as np

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


@dataclass(frozen=True)
class CollabConfig:
    """The options every cell of the experiment needs (`skinsafe experiment collaboration`'s flags, the same
    defaults); as JSON (`to_json`) in each Ray task and in the result file's `config`."""

    pitch: float = 0.01  # m, the skin's pitch
    duration: float = 1.0  # s, the delivery sweep and the placing motion
    stay: float = 1.5  # s the person stays in the path (the robot holds as long)
    finish: float = 2.0  # s for the robot to complete its task afterwards
    presence: float = 0.5  # fraction of deliveries with the person at the bench (scales the learned danger)
    pfl_factor: float = 0.8  # the PFL cap as a fraction of v_max
    pfl_regions: tuple[str, ...] | None = None  # regions the PFL cap protects (None: the person's)
    samples: int = 3000  # static contact samples for the TDM
    steps: int = 1500  # TDM training steps
    source: str = "planner"  # the delivery's command source: planner or teleoperation
    person_speed: float = 0.5  # m/s, the person's hand into the still robot
    push_N: float = 200.0  # N, the most the person's muscles push or pull a part
    seed: int = 0

    @classmethod
    def from_json(cls, doc: dict) -> CollabConfig:
        """From a task's or a result file's `config`; a key it does not know is refused by name."""
        unknown = sorted(set(doc) - {f.name for f in fields(cls)})
        if unknown:
            raise ValueError(f"collaboration config: unknown keys {unknown}; this skinsafe knows "
                             f"{[f.name for f in fields(cls)]} (re-run `skinsafe experiment collaboration`)")
        return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in doc.items()})

    def to_json(self) -> dict:
        """Its fields as JSON values (lists for tuples), in field order."""
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}


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


def layout(scenario: str, kin, cfg: CollabConfig) -> Layout:
    """The scenario's geometry and motions (module docstring) for the UR5 of `kin`."""
    from skinsafe.core.sim.human import Part

    T = cfg.duration
    if scenario == "clamp":
        top = _tool_down(kin.model, CLAMP_AT, 0.15)
        low = _tool_down(kin.model, CLAMP_AT, 2 * FIST - CLAMP_DEPTH)
        out = np.r_[CLAMP_AT / np.linalg.norm(CLAMP_AT), 0.0]  # away from the robot's base
        hand = np.r_[CLAMP_AT, FIST]  # resting on the table, the forearm behind it
        parts = [Part("lower_arm", "capsule", (0.035, 0.12), pos=tuple(hand + out * 0.2 + [0, 0, 0.035 - FIST]),
                      quat=_capsule_quat(out)),
                 Part("hand", "sphere", (FIST,), pos=tuple(hand))]
        hold = cfg.stay + 4.0  # long enough for a robot slowed near the table to reach the hand

        def desired(t):  # down in T, hold, up in T
            s1, d1 = _smooth(t, T)
            s2, d2 = _smooth(t - T - hold, T)
            return top + (low - top) * (s1 - s2), (low - top) * (d1 - d2)

        home = [np.array(p.pos, float) for p in parts]
        return Layout(scenario, parts, lambda t: home, desired, home,
                      lambda rng, n: top + (low - top) * rng.uniform(0, 1, (n, 1)) + rng.normal(0, 0.03, (n, 6)),
                      t_end=2 * T + hold + cfg.finish, plan_end=2 * T + hold, goal=top, regions=("lower_arm", "hand"))
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
        t_in, t_out = 0.1 * T, 0.1 * T + REACH_S + cfg.stay

        def targets(t):  # reach in (smooth), stay, withdraw
            u = np.clip((t - t_in) / REACH_S, 0, 1) * (1 - np.clip((t - t_out) / REACH_S, 0, 1))
            u = 3 * u ** 2 - 2 * u ** 3
            return [a + (h - a) * u for a, h in zip(away, home)]

        def sample(rng, n):
            Q = np.array([_delivery(t, T)[0] for t in rng.uniform(0, T, n)])
            Q[:, :4] += rng.normal(0, 0.05, (n, 4))
            return Q

        return Layout(scenario, parts, targets, lambda t: _delivery(t, T), home, sample,
                      t_end=t_out + REACH_S + cfg.finish, plan_end=T, goal=_delivery(T, T)[0],
                      regions=("lower_arm", "hand"))
    # person: the hand comes at the still wrist from the side the delivery sweeps toward, the lower
    # arm behind it along the reach
    hand0 = spot - side * 0.3
    arm0 = hand0 - side * 0.17
    parts = [Part("lower_arm", "capsule", (0.035, 0.12), pos=tuple(arm0), quat=_capsule_quat(side)),
             Part("hand", "sphere", (0.045,), pos=tuple(hand0))]
    speed, t0, hold = cfg.person_speed, 0.2, 0.3
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

def build(lay: Layout, design, damping: float, attach: float, dt_ms: float, cfg: CollabConfig):
    """The scene of a layout: UR5 + skin + the person (+ the table as a fixture)."""
    from skinsafe.core.experiments.arm_scene import Scene
    from skinsafe.core.sim.human import Human

    human = Human(lay.parts, attach_N_per_m=attach, contact_damping=damping, push_N=cfg.push_N)
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


def servo_lag_s(model, actuators) -> float:
    """The slowest of the position servos' velocity lags (s): tracking a command moving at v, a servo with
    stiffness kp, damping kv and the joint's damping b trails it by (kv + b) v / kp (the sim's UR5 pan: 69 ms)."""
    dof = model.jnt_dofadr[model.actuator_trnid[actuators, 0]]
    return float(np.max((-model.actuator_biasprm[actuators, 2] + model.dof_damping[dof]) / model.actuator_gainprm[actuators, 0]))


def make_stack(sc, stack: str, pot, cfg: CollabConfig, regions):
    """One of `STACKS` for the scene (module docstring); the cap (or None) alongside."""
    from skinsafe.core.safety.modulation import ModulationLayer
    from skinsafe.core.safety.pfl import PFLCap
    from skinsafe.core.sim.body_regions import contact_areas

    defens = sc.defensiveness() if stack != "none" else None
    mod = ModulationLayer(pot, tangent_gain=0.0) if stack.startswith("full") and pot is not None else None
    cap = None
    if stack == "full+pfl":  # braking as the stack does, through the servos' lag
        cap = PFLCap(sc.kin, tuple(cfg.pfl_regions or regions), factor=cfg.pfl_factor,
                     area=contact_areas(sc.design), fixtures=[((0, 0, 0), (0, 0, 1))], stop_s=2 * sc.control_dt,
                     acc=sc.robot.acc_limits, lag_s=servo_lag_s(sc.model, sc.act))
    return sc.stack(defens, mod, cap), cap


def episode(sc, lay: Layout, stack: str, pot, cfg: CollabConfig, person: bool = True, on_tick=None) -> dict:
    """One run of a scenario with one stack: the person trace (physics steps), the layers that acted
    per tick, the robot's pan joint and the task time. `on_tick(t, source, force, v, st, cap)`, if
    given, sees every control tick after the stack ran (to record the episode for the view)."""
    from skinsafe.core.safety.stack import TeleopStream, TrajectorySource

    st, cap = make_stack(sc, stack, pot, cfg, lay.regions)
    h = sc.human
    sc.reset(lay.desired(0.0)[0])
    if lay.scenario == "delivery" and cfg.source == "teleoperation":  # recorded at 125 Hz, replayed 50 ms late
        times = np.arange(0, lay.t_end + 0.5, 1 / 125)
        noise = np.random.default_rng(cfg.seed).normal(0, 0.002, (len(times), 6))
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


