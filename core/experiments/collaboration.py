"""`skinsafe experiment collaboration` (paper Fig. 15) as an ISO/TS 15066 power-and-force-limiting test.

The UR5 delivers a part with a fast pan sweep (`--duration`, default 1 s) while a person
(`core.sim.human`: lower arm and hand, the table's masses and spring constants, held by a
compliant attachment) reaches radially into the wrist's path, stays `--stay` seconds and withdraws; the
planner (or a teleoperation stream, `--source teleoperation`: the delivery recorded at 125 Hz,
replayed 50 ms late) then completes the delivery. The same scene runs with each stack:

- `none`: the joint velocity limits only (what the scene does without safety);
- `retraction`: the tactile defensiveness layer;
- `full`: defensiveness + modulation by a danger potential learned from static contacts with the
  person (a TDM; the person is at the bench in a fraction `--presence` of past deliveries, so the
  danger of a configuration is presence x p(contact), graded instead of a wall);
- `full+pfl`: `full` + the PFL speed cap (`core.safety.pfl.PFLCap`, the person's regions).

Forces are measured physically: the normal contact force between the robot's geoms and each body
region's geom (`mj_contactForce`) at every physics step. A contact event is a run of force on a
region (gaps under 0.1 s merged). Its transient phase is its first 0.5 s (ISO/TS 15066: transient
contact up to 0.5 s, quasi-static beyond), checked against the transient limit (`peak_N` vs
`limit_N`); the force after that (clamping or a sustained push) is `quasi_static_N` against the
quasi-static limit. Task time: until the arm is within 0.02 rad of the delivery goal; the cost of
safety (`safety_cost_s`) is that minus the task time without a person and without safety;
`no_person_task_time_s` is the stack's own task time without a person (what the cap costs always).
"""
from __future__ import annotations

import numpy as np
import torch
from tqdm.auto import tqdm

TRANSIENT_S = 0.5  # ISO/TS 15066: transient contact lasts up to 0.5 s; after that it is quasi-static
GAP_S = 0.1  # force-free gaps shorter than this do not end a contact event
GOAL_TOL = 0.02  # rad: the delivery is complete when every joint is this close to the goal
REACH_S = 0.4  # s: the person reaches in (or withdraws) 0.5 m, smoothly
STACKS = ("none", "retraction", "full", "full+pfl")


def _delivery(t: float, duration: float):
    """The delivery motion: pan from -0.8 to 0.8 rad (smooth), the rest at home."""
    from skinsafe.core.robot.models import UR5_HOME

    u = np.clip(t / duration, 0, 1)
    s = 10 * u ** 3 - 15 * u ** 4 + 6 * u ** 5
    ds = (30 * u ** 2 - 60 * u ** 3 + 30 * u ** 4) / duration if 0 < t < duration else 0.0
    q = UR5_HOME.copy()
    q[0] = -0.8 + 1.6 * s
    v = np.zeros(6)
    v[0] = 1.6 * ds
    return q, v


def _person(kin, design, T: float, attach: float = 1500.0):
    """The person's parts where the wrist passes at 60% of the delivery: the lower arm along the
    robot's radius, the hand ahead of it toward the robot's base (the person reaches in radially,
    across the sweep); the reach direction (outward, for withdrawing) and the effective robot mass
    there (for the contact springs)."""
    from skinsafe.core.safety.pfl import effective_mass
    from skinsafe.core.sim.human import Human, Part

    q = _delivery(0.6 * T, T)[0]
    kin.poses(q)  # kinematics at q in kin.data
    m, d = kin.model, kin.data
    tubes = [m.body(b).geomadr[0] for b in ("wrist_1_link", "wrist_2_link")]
    area = np.array([m.geom_size[g][0] * m.geom_size[g][1] for g in tubes])  # lateral areas (2 pi r 2h) / 4 pi
    spot = area @ d.geom_xpos[tubes] / area.sum()  # the wrist housings' centre, whatever skin covers them
    wrist = np.isin(design.taxels.body, [design.bodies.index(b) for b in ("wrist_1_link", "wrist_2_link")
                                         if b in design.bodies])
    pan = q[0]
    side = np.array([np.sin(pan), -np.cos(pan), 0.0])  # where the sweep goes (d/dpan of -r(cos, sin))
    out = np.array([-np.cos(pan), -np.sin(pan), 0.0])  # radially outward at the wrist (the arm points along -x)
    m_r = float(np.median(np.minimum(effective_mass(kin, q)[wrist], 100.0)))
    ang = np.arctan2(out[1], out[0])  # capsule axis (local z) along `out`: z -> x, then about z
    quat = (np.cos(np.pi / 4) * np.cos(ang / 2), -np.sin(np.pi / 4) * np.sin(ang / 2),
            np.sin(np.pi / 4) * np.cos(ang / 2), np.cos(np.pi / 4) * np.sin(ang / 2))
    at = spot + side * 0.03 + out * 0.27  # the hand by the tool, the lower arm beyond the robot's reach
    parts = [Part("lower_arm", "capsule", (0.035, 0.12), pos=tuple(at), quat=quat),
             Part("hand", "sphere", (0.045,), pos=tuple(at - out * 0.17))]
    return Human(parts, robot_mass=m_r, attach_N_per_m=attach), out, m_r


def check_args(args) -> None:
    """Refuse out-of-range options with a message naming the option and the fix."""
    from skinsafe.core.sim.body_regions import REGIONS

    checks = (("--pfl-factor", args.pfl_factor, 0 < args.pfl_factor <= 1, "a fraction of v_max in (0, 1]"),
              ("--presence", args.presence, 0 <= args.presence <= 1, "a fraction in [0, 1]"),
              ("--stay", args.stay, args.stay >= 0, "seconds >= 0"),
              ("--finish", args.finish, args.finish > 0, "seconds > 0"),
              ("--attach", args.attach, args.attach > 0, "a stiffness > 0 (N/m)"),
              ("--samples", args.samples, args.samples >= 10, "at least 10 static samples"))
    for name, value, ok, want in checks:
        if not (np.isfinite(value) and ok):
            raise SystemExit(f"{name} is {value}; give {want}")
    for r in args.pfl_regions or ():
        if r not in REGIONS:
            raise SystemExit(f"--pfl-regions: '{r}' is unknown; use one of {', '.join(REGIONS)}")


def run_scene(args) -> dict:
    from skinsafe.core.design.sample import make_sample_design
    from skinsafe.core.experiments.scenes import STATE, Scene
    from skinsafe.core.robot.kinematics import TaxelKinematics
    from skinsafe.core.robot.models import build_ur5
    from skinsafe.core.safety.modulation import ModulationLayer
    from skinsafe.core.safety.pfl import PFLCap
    from skinsafe.core.safety.stack import SafetyStack, TeleopStream, TrajectorySource

    T = args.duration
    robot = build_ur5()
    design = make_sample_design("ur5", pitch=args.pitch, robot=robot)
    kin = TaxelKinematics(robot.model, design)
    human, out_dir, m_r = _person(kin, design, T, args.attach)
    sc = Scene([], args.pitch, human=human)
    home = [np.array(p.pos, float) for p in human.parts]
    away = [p + out_dir * 0.5 for p in home]
    t_in, t_out = 0.1 * T, 0.1 * T + REACH_S + args.stay
    t_end = t_out + REACH_S + args.finish
    goal = _delivery(T, T)[0]
    if args.source == "teleoperation":  # the same delivery recorded at 125 Hz, replayed 50 ms late
        times = np.arange(0, t_end + 0.5, 1 / 125)
        noise = np.random.default_rng(args.seed).normal(0, 0.002, (len(times), 6))
        source = TeleopStream(times, np.array([_delivery(t, T)[0] for t in times]) + noise, latency=0.05)
    else:
        source = TrajectorySource(lambda t: _delivery(t, T))
    pot = _learn_person(sc, home, away, T, args)
    regions = tuple(args.pfl_regions or [p.region for p in human.parts])

    def make(stack: str):
        defens = sc.defensiveness() if stack != "none" else None
        mod = ModulationLayer(pot, tangent_gain=0.0) if stack.startswith("full") else None
        cap = PFLCap(sc.kin, regions, factor=args.pfl_factor) if stack == "full+pfl" else None
        return SafetyStack(sc.robot.vel_limits, defens, mod, joints=STATE, pfl=cap, dt=sc.control_dt)

    def episode(stack: str, person: bool):
        st = make(stack)
        sc.reset(_delivery(0, T)[0])
        for i in range(len(human.parts)):
            human.move(i, away[i])
            sc.data.qpos[human.slide[i]:human.slide[i] + 3] = away[i] - home[i]
        v, forces, pan, done = np.zeros(6), [], [], None
        steps = int(t_end / sc.control_dt)
        for k in tqdm(range(steps), desc=stack, disable=args.no_progress, leave=False):
            t = k * sc.control_dt
            if person:  # reach in (smooth), stay, withdraw
                u = np.clip((t - t_in) / REACH_S, 0, 1) * (1 - np.clip((t - t_out) / REACH_S, 0, 1))
                u = 3 * u ** 2 - 2 * u ** 3
                for i in range(len(human.parts)):
                    human.move(i, away[i] + (home[i] - away[i]) * u)
            force = sc.step(v)
            forces.append(sc.human_peak.copy())
            pan.append(float(sc.q[0]))
            v = st.run(source, t, sc.q, {"force": force}, sc.control_dt)
            if done is None and t >= T and np.max(np.abs(sc.q - goal)) < GOAL_TOL:
                done = t
                if not person:
                    break
        return np.array(forces), np.array(pan), done

    out = {"duration_s": T, "source": args.source, "robot_mass_at_contact_kg": m_r, "pfl_regions": list(regions),
           "pfl_factor": args.pfl_factor, "contacts": [], "runs": {}, "force_N": {}, "pan_rad": {}}
    _, _, bare = episode("none", person=False)  # the task itself: no person, no safety
    out["task_time_no_person_no_safety_s"] = bare
    for stack in STACKS:
        nominal = episode(stack, person=False)[2] if stack != "none" else bare
        forces, pan, done = episode(stack, person=True)
        events = contact_events(forces, [p.region for p in human.parts], sc.control_dt)
        for e in events:
            out["contacts"].append({"stack": stack, **e})
        out["runs"][stack] = {
            "events": len(events), "within": all(e["within"] for e in events),
            "peak_N": max((e["peak_N"] for e in events), default=0.0),
            "quasi_static_N": max((e["quasi_static_N"] for e in events), default=0.0),
            "task_time_s": done, "no_person_task_time_s": nominal,
            "safety_cost_s": None if done is None or bare is None else done - bare}
        out["force_N"][stack] = forces.sum(1).round(2).tolist()
        out["pan_rad"][stack] = pan.round(4).tolist()
    out["person_in_s"], out["person_out_s"] = t_in, t_out
    return out


def contact_events(forces: np.ndarray, regions: list[str], dt: float) -> list[dict]:
    """Contact events per region from per-tick peak forces (ticks, parts): a run of force > 0
    (gaps < GAP_S merged); transient phase the first TRANSIENT_S, quasi-static after."""
    from skinsafe.core.sim.body_regions import region

    out = []
    gap = int(round(GAP_S / dt))
    for j, name in enumerate(regions):
        reg = region(name)
        on = np.flatnonzero(forces[:, j] > 0)
        if not len(on):
            continue
        breaks = np.flatnonzero(np.diff(on) > gap)
        for a, b in zip(np.r_[on[0], on[breaks + 1]], np.r_[on[breaks], on[-1]]):
            f = forces[a:b + 1, j]
            n_tr = int(round(TRANSIENT_S / dt))
            peak = float(f[:n_tr].max())
            qs = float(f[n_tr:].max()) if len(f) > n_tr else 0.0
            limit = reg.transient_limit()
            out.append({"region": name, "start_s": round(a * dt, 3), "duration_s": round((b - a + 1) * dt, 3),
                        "peak_N": peak, "limit_N": limit, "quasi_static_N": qs,
                        "quasi_static_limit_N": reg.quasi_static_N,
                        "within": bool(peak <= limit and qs <= reg.quasi_static_N)})
    return sorted(out, key=lambda e: e["start_s"])


class _Presence(torch.nn.Module):
    """danger = presence x f_phi: the person is at the bench in a fraction of the deliveries."""

    def __init__(self, f, presence: float):
        super().__init__()
        self.f, self.presence = f, float(presence)

    def forward(self, s, a):
        return self.presence * self.f(s, a)


def _learn_person(sc, home, away, T: float, args):
    """A TDM from static contacts with the person at the bench, along the delivery (labels from
    the skin readout), as the modulation potential `presence x f_phi`."""
    import mujoco

    from skinsafe.core.experiments.scenes import STATE, static_contact_tdm
    from skinsafe.core.safety.potential import DangerPotential

    rng = np.random.default_rng(args.seed)
    n = args.samples
    Q = np.array([_delivery(t, T)[0] for t in rng.uniform(0, T, n)])
    Q[:, STATE] += rng.normal(0, 0.05, (n, len(STATE)))
    A = rng.uniform(-1, 1, (n, len(STATE)))
    D = np.zeros((n, sc.design.n_taxels), np.float32)
    m, d = sc.model, sc.data
    for i in tqdm(range(n), desc="contacts with the person", disable=args.no_progress, leave=False):
        mujoco.mj_resetData(m, d)
        d.qpos[sc.qadr] = Q[i]
        mujoco.mj_forward(m, d)
        D[i] = sc.readout.read(d) > 0
    return _Presence(DangerPotential(static_contact_tdm(Q[:, STATE], A, D, args)), args.presence)


def plot(res: dict):
    """Force on the person and the delivery (pan joint) over time per stack, and each event's
    transient and quasi-static force as a fraction of its limit."""
    import matplotlib.pyplot as plt

    fig, (a, p, b) = plt.subplots(1, 3, figsize=(14, 3.8))
    for stack, f in res["force_N"].items():
        t = np.arange(len(f)) * 0.01
        a.plot(t, f, label=stack, lw=1)
        pan = res["pan_rad"][stack]
        p.plot(np.arange(len(pan)) * 0.01, pan, label=f"{stack}: {res['runs'][stack]['task_time_s']:.2f} s", lw=1)
    for ax in (a, p):
        ax.axvspan(res["person_in_s"], res["person_out_s"], color="0.9", zorder=0)
        ax.set_xlabel("time (s)")
    hit = [e["start_s"] for e in res["contacts"]]
    a.set_xlim(min(hit, default=0) - 0.1, max(hit, default=1) + 0.6)
    a.set_ylabel("contact force on the person (N)")
    a.set_title("Fig. 15: the robot meets a person (grey: present)")
    a.legend(fontsize=7)
    p.set_ylabel("pan joint (rad)")
    p.set_title("the delivery; task time")
    p.legend(fontsize=7)
    xs, labels = [], []
    for i, e in enumerate(res["contacts"]):
        xs.append(i)
        labels.append(f"{e['stack']}\n{e['region']}")
        b.bar(i - 0.2, e["peak_N"] / max(e["limit_N"], 1e-9), 0.4, color="tab:red" if e["peak_N"] > e["limit_N"] else "tab:green")
        b.bar(i + 0.2, e["quasi_static_N"] / e["quasi_static_limit_N"], 0.4,
              color="tab:orange" if e["quasi_static_N"] > e["quasi_static_limit_N"] else "tab:olive")
    b.axhline(1, color="k", lw=0.8)
    b.set_xticks(xs, labels, fontsize=6, rotation=90)
    b.set_ylabel("force / ISO/TS 15066 limit")
    b.set_title("events: transient (left bar), quasi-static (right)")
    fig.tight_layout()
    return fig
