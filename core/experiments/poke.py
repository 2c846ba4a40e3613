"""`skinsafe poke`: scripted pokes on the UR5 sample skin (or any robot's map) in MuJoCo, retraction by the
defensiveness layer, plots and numbers (paper Fig. 8/12), and the multi-contact merge (Fig. 7) and the 3-D vs 6-D forms in kinematics.

The arm (the UR5 sample skin, or the robot of any taxel map) is gravity-compensated under its
position servos; the layer's joint velocity is integrated into the servo targets at 500 Hz (the UR
e-series rate). Probes are spheres on a spring (`PROBE_STIFFNESS`, a sprung mocap `Obstacle`) whose
holder jabs a taxel along its normal to a set depth and withdraws, so the force is about stiffness
x depth on any robot; a rigid probe driven to a depth would meet a force that scales with the
arm's effective mass at the taxel (1,200 kg near the Franka's shoulder axis: 60-300 kN at
0.6-2 mm). The skin is read with `SkinReadout(kernel="nearest")` (each contact goes to one taxel,
like a real FSR cell).

Outputs in `--out`: `poke_force_distance.png` (retraction distance vs peak force, linear fit),
`poke_displacement.png` (-z displacement vs time against eq. 10), `poke_multicontact.png`
(Fig. 7 numbers: the prioritised QP, and the closed-form merges for each epsilon) and `poke_results.json` with every number, plus the 3-D vs
6-D comparison (`compare_forms`, pure kinematics on every tenth taxel of the skin).
"""
from __future__ import annotations

import json
from dataclasses import dataclass, replace
from pathlib import Path

import mujoco
import numpy as np
from tqdm import tqdm

from skinsafe.core.design.sample import make_sample_design
from skinsafe.core.robot.kinematics import TaxelKinematics
from skinsafe.core.robot.models import Robot, build_ur5, load_robot
from skinsafe.core.safety.defensiveness import DefensivenessLayer
from skinsafe.core.safety.retraction import MERGES, RetractionParams, profile
from skinsafe.core.skin import taxel_map
from skinsafe.core.skin.files import atomic_write, write_png
from skinsafe.core.skin.model import SkinDesign

PROBE_RADIUS = 0.012  # m
PROBE_STIFFNESS = 20e3  # N/m: 20 N per mm of the holder's travel past the skin (a firm finger or a force gauge)
DT = 0.002  # s, control period
MAX_T = 10.0  # s: the longest retraction duration a poke simulates


@dataclass
class Poke:
    """A probe jab on taxel `taxel`: starts at `start` s, pushes `depth` m past the surface."""

    taxel: int
    depth: float
    start: float = 0.05
    gap: float = 0.01  # m between probe and skin at the start
    speed_in: float = 0.1  # m/s
    hold: float = 0.01  # s at full depth
    speed_out: float = 0.5  # m/s


def _probe_path(poke: Poke, t: float) -> float:
    """How far the probe centre has moved along -normal from its start at time t."""
    reach = poke.gap + poke.depth
    t_in = reach / poke.speed_in
    s = t - poke.start
    if s <= 0:
        return 0.0
    if s <= t_in:
        return s * poke.speed_in
    if s <= t_in + poke.hold:
        return reach
    return max(0.0, reach - (s - t_in - poke.hold) * poke.speed_out)


def poke_scene(design: SkinDesign, robot: Robot, pokes: list[Poke], stiffness: float = PROBE_STIFFNESS):
    """The robot at home with one sprung probe per poke, `gap` out along its taxel's normal: (compiled model,
    each probe's (start, normal)). A poke's depth and speeds only drive the probe, so pokes on the same taxels
    from the same gaps share one scene."""
    from skinsafe.core.sim.scene import Obstacle, SceneOptions, build_scene

    kin0 = TaxelKinematics(robot.model, design)
    pos0, frames0 = (a.copy() for a in kin0.poses(robot.home))
    starts = []
    obstacles = []
    for k, pk in enumerate(pokes):
        n = frames0[pk.taxel, :, 2]
        c = pos0[pk.taxel] + n * (PROBE_RADIUS + pk.gap)
        starts.append((c, n))
        obstacles.append(Obstacle(f"probe{k}", "sphere", (PROBE_RADIUS,), pos=tuple(c), quat=_quat_z_to(n),
                                  mocap=True, spring=stiffness))
    return build_scene(design, robot, obstacles, SceneOptions(timestep=DT)).compile(), starts


def simulate(design: SkinDesign, robot: Robot, pokes: list[Poke], params: RetractionParams, duration: float,
             stiffness: float = PROBE_STIFFNESS, scene=None) -> dict:
    """Run the pokes (in `scene`, a `poke_scene` of the same taxels and gaps, or a new one); returns per-tick
    times, joint positions, commands and the layer's record of every taxel it retracted (trigger time, peak force,
    normal, position at the trigger)."""
    from skinsafe.core.sim.readout import SkinReadout

    model, starts = scene or poke_scene(design, robot, pokes, stiffness)
    data = mujoco.MjData(model)
    nq = robot.model.nq  # the probes' spring joints come after the robot's
    data.qpos[:nq] = robot.home
    mujoco.mj_forward(model, data)
    kin = TaxelKinematics(robot.model, design)  # its own data: kinematics at the measured q
    readout = SkinReadout(model, design, kernel="nearest")
    layer = DefensivenessLayer(kin, design.taxels.thresholds, robot.vel_limits, robot.acc_limits, params, DT)
    target = robot.home.copy()
    steps = int(round(duration / DT))
    T, Q, F = np.zeros(steps), np.zeros((steps, nq)), np.zeros((steps, len(pokes)))
    record: dict[int, dict] = {}
    for k in range(steps):
        t = k * DT
        for j, (pk, (c, n)) in enumerate(zip(pokes, starts)):
            data.mocap_pos[j] = c - n * _probe_path(pk, t)
        data.qfrc_applied[:nq] = data.qfrc_bias[:nq]  # gravity (and Coriolis) compensation
        data.ctrl[:nq] = target
        mujoco.mj_step(model, data)
        force = readout.read(data)
        q = data.qpos[:nq].copy()
        qd = layer.tick(t, q, {"force": force}, None, DT)
        target = target + qd * DT
        for row in layer._state:
            i = int(row[0])
            rec = record.setdefault(i, {"tau": row[1], "p0": row[3:6].copy(), "z0": row[6:9].copy(), "f": 0.0})
            if row[1] != rec["tau"]:  # triggered again: keep the first retraction only
                continue
            rec["f"] = max(rec["f"], row[2] / params.alpha if params.alpha > 0 else 0.0)
        T[k], Q[k] = t, q
        F[k] = force[[pk.taxel for pk in pokes]]
    return {"t": T, "q": Q, "force": F, "record": record, "kin": TaxelKinematics(robot.model, design)}


def _quat_z_to(n: np.ndarray) -> tuple:
    """A MuJoCo quaternion (w, x, y, z) turning the z axis onto the unit vector n."""
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.align_vectors([n], [[0.0, 0.0, 1.0]])[0].as_quat()
    return (w, x, y, z)


def retracted_along(run: dict, taxel: int) -> tuple[np.ndarray, np.ndarray]:
    """(times since the trigger, displacement along -z(tau)) of a recorded taxel."""
    rec = run["record"][taxel]
    kin = run["kin"]
    sel = run["t"] >= rec["tau"]
    disp = np.array([(rec["p0"] - kin.poses(q)[0][taxel]) @ rec["z0"] for q in run["q"][sel]])
    return run["t"][sel] - rec["tau"], disp


def _levers(kin: TaxelKinematics, q: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """(k,) how fast each taxel can move along its normal per unit joint speed, ||J_p^T n|| (m/rad):
    small near a joint axis, where no retraction within the joint speed limits gets far."""
    J, _, frames = kin.jacobians_of(idx, q)
    return np.linalg.norm(np.einsum("kin,ki->kn", J[:, :3], frames[:, :, 2]), axis=1)


def pick_taxel(design: SkinDesign, robot: Robot, body: str) -> int:
    """A taxel in the middle of `body` whose normal points up at home (a probe can reach it),
    among those the arm can move well along their normal (lever >= 70% of the body's best)."""
    kin = TaxelKinematics(robot.model, design)
    pos, frames = kin.poses(robot.home)
    on = np.flatnonzero(design.taxels.body == design.bodies.index(body))
    lever = _levers(kin, robot.home, on)
    on = on[lever >= 0.7 * lever.max()]
    mid = np.linalg.norm(pos[on] - pos[on].mean(axis=0), axis=1)
    score = frames[on, 2, 2] - 2.0 * mid / max(mid.max(), 1e-9)
    return int(on[np.argmax(score)])


def poke_bodies(design: SkinDesign, robot: Robot) -> list[str]:
    """The links to poke, decided by the design's data on any robot (never by a link's name): the
    skinned links with at least 4 taxels, best lever first (a link the arm can pull back)."""
    kin = TaxelKinematics(robot.model, design)
    counts = np.bincount(design.taxels.body, minlength=len(design.bodies))
    bodies = [b for b, c in zip(design.bodies, counts) if c >= 4]
    best = {b: _levers(kin, robot.home, np.flatnonzero(design.taxels.body == design.bodies.index(b))).max()
            for b in bodies}
    return sorted(bodies, key=lambda b: -best[b])


def force_sweep(design, robot, params, depths, body: str | None = None, stiffness: float = PROBE_STIFFNESS) -> dict:
    """Fig. 8/12: one poke per depth on one taxel of `body` (default: the first of `poke_bodies`);
    distance achieved vs peak force."""
    body = body or poke_bodies(design, robot)[0]
    i = pick_taxel(design, robot, body)
    out = {"taxel": i, "body": body, "force": [], "distance": [], "desired": [], "curves": []}
    scene = poke_scene(design, robot, [Poke(i, 0.0)], stiffness)  # one taxel, one gap: the depths share one scene
    for depth in tqdm(depths, desc="pokes", leave=False):
        run = simulate(design, robot, [Poke(i, depth)], params, 0.05 + params.T + 0.25, stiffness, scene)
        rec = max(run["record"].items(), key=lambda kv: kv[1]["f"]) if run["record"] else None
        if rec is None:
            continue
        taxel, r = rec
        tt, disp = retracted_along(run, taxel)
        out["force"].append(r["f"])
        out["distance"].append(float(disp[-1]))
        out["desired"].append(min(params.alpha * r["f"], 12 * params.max_distance) / 12)
        out["curves"].append((tt, disp, r["f"]))
    f, d = np.array(out["force"]), np.array(out["distance"])
    slope, icpt = np.polyfit(f, d, 1) if len(f) > 1 else (np.nan, np.nan)
    resid = d - (slope * f + icpt)
    out["slope"], out["intercept"] = float(slope), float(icpt)
    out["r2"] = float(1 - resid @ resid / max(((d - d.mean()) ** 2).sum(), 1e-300)) if len(f) > 1 else float("nan")
    errs = []
    for tt, disp, fp in out["curves"]:
        ref = min(params.alpha * fp, 12 * params.max_distance) * profile(tt / params.T)
        errs.append(float(np.abs(disp - ref).max() / max(ref.max(), 1e-12)))
    out["profile_rel_err"] = errs
    return out


def retract_kinematic(kin: TaxelKinematics, layer: DefensivenessLayer, q: np.ndarray, force: np.ndarray,
                      duration: float, watch=None) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """Trigger with `force` at t=0 and integrate the layer's command perfectly (no physics).
    With `watch` (taxel indices): also the largest displacement of each toward its contact
    (along its normal at t=0, m) over the run."""
    q = q.copy()
    zero = np.zeros_like(force)
    if watch is not None:
        _, p0, fr0 = kin.jacobians_of(watch, q)
        worst = np.zeros(len(watch))
    for k in range(int(np.ceil(duration / DT))):
        q += layer.tick(k * DT, q, {"force": force if k == 0 else zero}, None, DT) * DT
        if watch is not None:
            worst = np.maximum(worst, np.einsum("ki,ki->k", kin.jacobians_of(watch, q)[1] - p0, fr0[:, :, 2]))
    return q if watch is None else (q, worst)


def multicontact(design, robot, params, bodies, forces, epsilons) -> list[dict]:
    """Fig. 7: simultaneous contacts on different links (kinematics: the merge alone, no probe
    pushing back); per merge and epsilon, the fraction of its own eq. 10 distance each contact
    achieved along its -z (first = dominant, the heaviest force) and how far any contacted taxel
    moved into its contact on the way (`into_contact_mm`). The prioritised QP (the default) does
    not use epsilon: it is run once."""
    taxels = [pick_taxel(design, robot, b) for b in bodies]
    kin = TaxelKinematics(robot.model, design)
    p0, fr = (a[taxels].copy() for a in kin.poses(robot.home))
    f = np.zeros(design.n_taxels)
    f[taxels] = forces
    rows = []
    for merge_kind in MERGES:
        for eps in epsilons if merge_kind != "qp" else epsilons[-1:]:
            p = replace(params, epsilon=eps, merge=merge_kind)
            layer = DefensivenessLayer(kin, design.taxels.thresholds, robot.vel_limits, robot.acc_limits, p, DT)
            q, worst = retract_kinematic(kin, layer, robot.home, f, p.T + 2 * DT, watch=np.asarray(taxels))
            along = np.einsum("ki,ki->k", p0 - kin.poses(q)[0][taxels], fr[:, :, 2])
            frac = along / (np.minimum(p.alpha * np.asarray(forces), 12 * p.max_distance) / 12)
            rows.append({"merge": merge_kind, "epsilon": eps, "contacts": len(taxels), "forces": list(forces),
                         "bodies": list(bodies), "dominant_fraction": round(float(frac[0]), 3),
                         "others_fraction": [round(float(x), 3) for x in frac[1:]],
                         "into_contact_mm": round(float(worst.max()) * 1e3, 3)})
    return rows


def compare_forms(design, robot, params, stride: int = 25, force: float = 40.0) -> dict:
    """3-D vs 6-D retraction, kinematics only: every `stride`-th taxel retracts alone from home
    with the layer; achieved distance along -z / commanded, and side drift / commanded."""
    kin = TaxelKinematics(robot.model, design)
    out = {}
    for form in ("3d", "6d"):
        p = replace(params, form=form)
        layer = DefensivenessLayer(kin, design.taxels.thresholds, robot.vel_limits, robot.acc_limits, p, DT)
        ratio, drift = [], []
        for i in tqdm(range(0, design.n_taxels, stride), desc=f"forms ({form})", leave=False):
            layer.reset()
            f = np.zeros(design.n_taxels)
            f[i] = force
            p0, fr = (a[i].copy() for a in kin.poses(robot.home))
            z = fr[:, 2].copy()
            q = retract_kinematic(kin, layer, robot.home, f, p.T + 2 * DT)
            disp = kin.poses(q)[0][i] - p0
            want = min(p.alpha * force, 12 * p.max_distance) / 12
            along = -disp @ z
            ratio.append(along / want)
            drift.append(np.linalg.norm(disp + along * z) / want)
        ratio, drift = np.array(ratio), np.array(drift)
        out[form] = {"taxels": len(ratio), "achieved_median": float(np.median(ratio)),
                     "achieved_p10": float(np.percentile(ratio, 10)),
                     "within_5pct": float(np.mean(np.abs(ratio - 1) < 0.05)),
                     "drift_median": float(np.median(drift)), "drift_p90": float(np.percentile(drift, 90))}
    return out


def plots(sweep: dict, multi: list[dict], params: RetractionParams, out: Path) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    paths = []
    f, d = np.array(sweep["force"]), np.array(sweep["distance"])
    fig, ax = plt.subplots(figsize=(5, 4))
    ax.plot(f, d * 100, "o", label="achieved (MuJoCo)")
    xs = np.linspace(0, f.max() * 1.05, 50)
    ax.plot(xs, (sweep["slope"] * xs + sweep["intercept"]) * 100, "-",
            label=f"fit: {sweep['slope'] * 100:.3f} cm/N, R$^2$={sweep['r2']:.4f}")
    ax.plot(xs, np.minimum(params.alpha * xs, 12 * params.max_distance) / 12 * 100, "--", label=r"$\alpha f/12$ (eq. 10)")
    ax.set_xlabel("peak force on the taxel [N]")
    ax.set_ylabel("retraction distance [cm]")
    ax.set_title("Retraction vs poke force (Fig. 8/12)")
    ax.legend()
    fig.tight_layout()
    paths.append(write_png(fig, out / "poke_force_distance.png"))

    fig, ax = plt.subplots(figsize=(5, 4))
    for tt, disp, fp in sweep["curves"]:
        line, = ax.plot(tt, disp * 100, label=f"{fp:.1f} N")
        ax.plot(tt, min(params.alpha * fp, 12 * params.max_distance) * profile(tt / params.T) * 100, ":",
                color=line.get_color())
    ax.set_xlabel(r"time since trigger $t-\tau$ [s]")
    ax.set_ylabel("displacement along -z [cm]")
    ax.set_title("Displacement vs eq. 10 (dotted)")
    ax.legend(fontsize=7)
    fig.tight_layout()
    paths.append(write_png(fig, out / "poke_displacement.png"))

    if not multi:  # a skin on one link: no multi-contact figure
        return paths
    fig, axes = plt.subplots(1, len(MERGES), figsize=(4.5 * len(MERGES), 4), sharey=True)
    for ax, kind in zip(axes, MERGES):
        rows = [r for r in multi if r["merge"] == kind]
        for c, n in enumerate(sorted({r["contacts"] for r in rows})):
            sub = [r for r in rows if r["contacts"] == n]
            x = np.arange(len(sub)) + 0.4 * c
            ax.bar(x - 0.1, [r["dominant_fraction"] for r in sub], 0.18, label=f"{n} contacts: dominant")
            ax.bar(x + 0.1, [np.mean(r["others_fraction"]) for r in sub], 0.18, label=f"{n} contacts: others (mean)")
            ax.set_xticks(np.arange(len(sub)) + 0.2,
                          ["prioritised QP" if kind == "qp" else f"eps={r['epsilon']}" for r in sub])
        ax.axhline(1.0, color="k", lw=0.5)
        worst = max(r["into_contact_mm"] for r in rows)
        ax.set_title(f"merge: {kind} (worst into contact {worst:.1f} mm)", fontsize=9)
        ax.set_ylabel("achieved / own retraction distance")
        ax.legend(fontsize=7)
    fig.tight_layout()
    paths.append(write_png(fig, out / "poke_multicontact.png"))
    return paths


def add_arguments(p) -> None:
    p.add_argument("--out", default="poke_out", help="folder for the PNG plots and poke_results.json")
    p.add_argument("--map", default=None, help="taxel map of a skin on any robot (default: the UR5 sample skin)")
    p.add_argument("--depths", default="0.0004,0.0008,0.0012,0.0016,0.002,0.0025,0.003",
                   help="probe depths past the skin in m, one poke each (comma-separated)")
    p.add_argument("--alpha", type=float, default=0.01, help="sensitivity alpha, m/N")
    p.add_argument("--T", type=float, default=0.5, help="retraction duration T, s")
    p.add_argument("--form", choices=("3d", "6d"), default="3d", help="retraction task form")
    p.add_argument("--epsilons", default="0,0.5,1", help="multi-contact tuning factors of the closed-form merges")
    p.add_argument("--forms-stride", type=int, default=25, help="3-D vs 6-D comparison on every k-th taxel")
    p.add_argument("--probe-stiffness", type=float, default=PROBE_STIFFNESS,
                   help="N/m of the probe's spring (force about stiffness x depth; default 20 N/mm)")


def run(args) -> int:
    try:
        depths = [float(s) for s in args.depths.split(",")]
        epsilons = [float(s) for s in args.epsilons.split(",")]
    except ValueError:
        raise SystemExit(f"skinsafe poke: --depths '{args.depths}' and --epsilons '{args.epsilons}' must be "
                         "comma-separated numbers (depths in m, e.g. 0.0005,0.001)") from None
    try:
        params = RetractionParams(alpha=args.alpha, T=args.T, form=args.form)
    except ValueError as e:
        raise SystemExit(f"skinsafe poke: {e}")
    if args.T > MAX_T:
        raise SystemExit(f"skinsafe poke: --T {args.T:g}: give a retraction duration up to {MAX_T:g} s (each poke "
                         "simulates it)")
    if not depths or min(depths) <= 0 or not all(np.isfinite(depths)):
        raise SystemExit("skinsafe poke: --depths must be positive distances in m")
    if not (np.isfinite(args.probe_stiffness) and args.probe_stiffness > 0) or args.forms_stride < 1:
        raise SystemExit("skinsafe poke: --probe-stiffness must be a positive N/m and --forms-stride at least 1")
    out = Path(args.out)
    if args.map:  # any robot: the one the map names (issue 18)
        robot = load_robot(taxel_map.load(args.map).robot, base_dir=Path(args.map).parent)
        design = taxel_map.load(args.map, robot.body_names)
    else:
        robot = build_ur5()
        design = make_sample_design("ur5", robot=robot)
    bodies = poke_bodies(design, robot)[:3]
    if not bodies:
        raise SystemExit(f"skinsafe poke: no link of {args.map or 'the sample skin'} carries 4 taxels or more; "
                         "design a skin with larger modules")
    sweep = force_sweep(design, robot, params, depths, body=bodies[0], stiffness=args.probe_stiffness)
    if len(sweep["force"]) < 2:
        raise SystemExit("skinsafe poke: fewer than two pokes triggered the skin; use deeper --depths")
    multi = multicontact(design, robot, params, bodies[:2], [30.0, 20.0], epsilons) if len(bodies) > 1 else []
    if len(bodies) > 2:
        multi += multicontact(design, robot, params, bodies[:3], [30.0, 20.0, 10.0], epsilons)
    forms = compare_forms(design, robot, params, stride=args.forms_stride)
    paths = plots(sweep, multi, params, out)
    result = {"params": {k: v for k, v in params.__dict__.items() if k != "stimulus_alpha"},
              "force_sweep": {k: v for k, v in sweep.items() if k != "curves"},
              "multicontact": multi, "forms": forms}
    paths.append(atomic_write(out / "poke_results.json", json.dumps(result, indent=1)))
    print(f"poke: taxel {sweep['taxel']} on {sweep['body']}: slope {sweep['slope'] * 100:.4f} cm/N "
          f"(alpha/12 = {params.alpha / 12 * 100:.4f}), R^2 {sweep['r2']:.5f}, "
          f"eq. 10 max error {max(sweep['profile_rel_err']) * 100:.1f}% of the distance")
    for r in multi:
        print(f"poke: {r['contacts']} contacts, merge {r['merge']}, eps {r['epsilon']}: forces {r['forces']} N, "
              f"dominant {r['dominant_fraction']}, others {r['others_fraction']}, "
              f"worst into contact {r['into_contact_mm']} mm")
    for form, r in forms.items():
        print(f"poke: form {form}: achieved median {r['achieved_median']:.3f} (p10 {r['achieved_p10']:.3f}), "
              f"within 5% {r['within_5pct'] * 100:.0f}%, drift median {r['drift_median']:.3f} p90 {r['drift_p90']:.3f}")
    for p in paths:
        print(f"wrote {p}")
    return 0
