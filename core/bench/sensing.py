"""`skinsafe bench sensing`: the vectorised skin readout against per-taxel MuJoCo touch sensors and
MuJoCo's native `tactile` sensor, collision-mesh simplification and the timestep, on the UR5 sample skin.

Scene: the UR5 held at home by its position servos, three mocap probes pressing 5 mm into the
tops of the upper arm, forearm and wrist and sliding along them (1 Hz, +-2 cm), a fixed box
beside the robot. Rows (one per setting):

- `sweep="taxels"`: `n_taxels`, `readout` ("vectorised" | "touch" | "tactile"), `steps_per_s`
  (physics plus readout), `overhead_vs_bare` (readout time / physics step of the skinned scene;
  the vectorised readout timed as a control loop runs it, `SkinReadout.update` into its own array;
  `read_copy_us` / `overhead_copy_vs_bare`: `read`, a new array per step, O(N) more),
  `overhead_vs_skinless` (skinned step + readout over the same scene with no skin, minus 1),
  `force_err`, `lit_recall` (against the touch sensors of the same simulation), `missed`.
  Accuracy against one ground truth (`Probes.truth`: the taxel cells each probe's contact patch
  covers, and their share of its force), every readout in its own scene over the same motion:
  `truth_lit_precision`, `truth_lit_recall`, `truth_lit_f1`, `truth_force_err` (the tactile
  sensor, not in newtons, after one least-squares gain). The tactile sensor's mesh has
  `tactile_points` vertices per taxel cell (1 = the taxels; more = hexagonal rings filling the
  cell); `speedup_vs_tactile` compares the added cost of the cheapest configuration that is at
  least as accurate (lit F1) as the readout, or of the most accurate one when none is
  (`tactile_points`, `tactile_lit_f1` say which).
- `sweep="collision"`: mesh UR5 (links as fine meshes), each `SceneOptions.collision` mode:
  collision faces, steps/s, force error against the full mesh.
- `sweep="timestep"`: a 0.5 kg box resting on the upper arm: force error against m g,
  penetration, steps/s and real-time factor.
"""
from __future__ import annotations

import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import mujoco
import numpy as np
from tqdm import tqdm

from skinsafe.core.design.sample import make_sample_design
from skinsafe.core.robot.models import build_ur5, mesh_ur5
from skinsafe.core.sim.probes import BASE_PITCH, Probes, design_for, probe_scene
from skinsafe.core.sim.readout import SkinReadout, TactileReadout, TouchReadout
from skinsafe.core.timing import interleaved_ms, median_ms


def _medians(fns: dict[str, Callable[[], object]], repeat: int) -> dict[str, float]:
    """Median ms of each named function, timed interleaved (`timing.interleaved_ms`)."""
    times = interleaved_ms(list(fns.values()), repeat=repeat)
    return {k: float(np.median(t)) for k, t in zip(fns, times)}

def add_arguments(p) -> None:
    p.add_argument("--sizes", default="256,1024,4096,16384", help="target taxel counts (comma separated)")
    p.add_argument("--steps", type=int, default=300, help="steps per agreement run and timing")
    p.add_argument("--tactile-points", default=",".join(map(str, TACTILE_POINTS)),
                   help="vertices per taxel cell of the native tactile sensor's mesh (1, 7, 19, 37; comma separated)")
    p.add_argument("--timesteps", default="0.0005,0.001,0.002,0.004,0.008", help="timesteps (s) to sweep")
    p.add_argument("--sweeps", default="taxels,collision,timestep", help="which sweeps to run")
    p.add_argument("--plot", default="out/bench_sensing.png", help="PNG to write ('' for none)")


def _stepper(model, data, probes):
    def step():
        probes.move(data, data.time)
        mujoco.mj_step(model, data)
    return step


TACTILE_POINTS = (1, 7, 19)  # vertices per taxel cell of the native tactile sensor's mesh


def taxel_rows(sizes, steps: int, tactile_points=TACTILE_POINTS) -> list[dict]:
    rows = []
    robot = build_ur5()
    for n_target in tqdm(sizes, desc="taxels sweep"):
        design = design_for(n_target)
        n = design.n_taxels
        probes = Probes(design, robot)
        m0, d0 = probe_scene(None, robot, probes.obstacles, probes.q)
        mb, db = probe_scene(design, robot, probes.obstacles, probes.q)
        mt, dt = probe_scene(design, robot, probes.obstacles, probes.q, touch_sensors=True)
        msites, dsites = probe_scene(design, robot, probes.obstacles, probes.q, taxel_sites=True)
        for _ in range(50):  # settle the contacts
            _stepper(mb, db, probes)()
        readers = {k: SkinReadout(mb, design, kernel=k) for k in ("linear", "nearest")}
        t_ms = _medians({"skinless": _stepper(m0, d0, probes), "bare": _stepper(mb, db, probes),
                              "sites": _stepper(msites, dsites, probes), "touch": _stepper(mt, dt, probes),
                              **{k: (lambda r=r: r.update(db)) for k, r in readers.items()},
                              "copy": lambda: readers["nearest"].read(db)}, repeat=max(steps // 5, 10) * 7)
        skinless, bare, sites, touch_step = t_ms["skinless"], t_ms["bare"], t_ms["sites"], t_ms["touch"]
        read_ms = {k: t_ms[k] for k in readers}
        agree = _agreement(mt, dt, design, probes, steps)
        truth = {k: _accuracy(design, robot, probes, steps, lambda m, d, k=k: SkinReadout(m, design, kernel=k).read)
                 for k in readers}
        truth["touch"] = _accuracy(design, robot, probes, steps, lambda m, d: TouchReadout(m, design).read,
                                   touch_sensors=True)
        common = dict(sweep="taxels", n_taxels=n, bare_step_us=bare * 1e3, skinless_step_us=skinless * 1e3,
                      sites_step_us=sites * 1e3)
        tactile = []
        for pts in tactile_points:
            mk, dk = probe_scene(design, robot, probes.obstacles, probes.q, tactile_sensors=True, tactile_points=pts)
            both = _medians({"skinless": _stepper(m0, d0, probes), "tactile": _stepper(mk, dk, probes)},
                                  repeat=max(steps // 5, 10) * 7)
            step_ms = both["tactile"] * skinless / both["skinless"]  # on the same skinless scale as the readout
            acc = _accuracy(design, robot, probes, steps, lambda m, d, p=pts: TactileReadout(m, d, design, p).read,
                            calibrate=True, tactile_sensors=True, tactile_points=pts)
            tactile.append(dict(common, readout="tactile", kernel=f"{pts} pt/taxel", tactile_points=pts,
                                steps_per_s=1e3 / step_ms, read_us=(step_ms - skinless) * 1e3, tactile_step_us=step_ms * 1e3,
                                overhead_vs_skinless=step_ms / skinless - 1, **acc))
        for kernel in ("linear", "nearest"):
            added = max(bare + read_ms[kernel] - skinless, 1e-9)
            ref = _equal_accuracy(tactile, truth[kernel]["truth_lit_f1"])
            rows.append(dict(common, readout="vectorised", kernel=kernel, steps_per_s=1e3 / (bare + read_ms[kernel]),
                             read_us=read_ms[kernel] * 1e3, overhead_vs_bare=read_ms[kernel] / bare,
                             read_copy_us=t_ms["copy"] * 1e3, overhead_copy_vs_bare=t_ms["copy"] / bare,
                             speedup_vs_touch=(touch_step - bare) / read_ms[kernel],
                             overhead_vs_skinless=(bare + read_ms[kernel]) / skinless - 1,
                             speedup_vs_tactile=(ref["tactile_step_us"] / 1e3 - skinless) / added,
                             tactile_points=ref["tactile_points"], tactile_lit_f1=ref["truth_lit_f1"],
                             tactile_step_us=ref["tactile_step_us"], **agree[kernel], **truth[kernel]))
        rows.append(dict(common, readout="touch", kernel="cell", steps_per_s=1e3 / touch_step,
                         read_us=(touch_step - bare) * 1e3, overhead_vs_bare=(touch_step - bare) / bare,
                         overhead_vs_skinless=touch_step / skinless - 1, force_err=0.0, lit_recall=1.0,
                         missed=agree["touch_missed"], speedup_vs_touch=1.0, **truth["touch"]))
        rows += tactile
    return rows


def _equal_accuracy(tactile: list[dict], f1: float) -> dict:
    """The cheapest tactile configuration that lights the pressed taxels at least as well (lit F1)
    as a readout with F1 `f1`; the most accurate one when none does."""
    good = [r for r in tactile if r["truth_lit_f1"] >= f1]
    if good:
        return min(good, key=lambda r: r["tactile_step_us"])
    return max(tactile, key=lambda r: r["truth_lit_f1"])


def _accuracy(design, robot, probes, steps: int, make_reader, calibrate: bool = False, **opts) -> dict:
    """One readout against the ground truth (`Probes.truth`: the taxel cells each probe's contact
    patch covers and their share of its force), in its own scene over the same probe motion.

    `truth_lit_precision`/`truth_lit_recall`/`truth_lit_f1` over all lit taxels of all steps;
    `truth_force_err` = sum |f - f_true| / sum f_true. `calibrate`: the readout is not in newtons
    (the tactile sensor's penetration pressure), so one least-squares gain over the run makes it newtons
    first (the best any calibration can do)."""
    model, data = probe_scene(design, robot, probes.obstacles, probes.q, **opts)
    read = make_reader(model, data)
    truth = probes.truth(model, design)
    step = _stepper(model, data, probes)
    tp = lit = pressed = 0
    got, want = [], []
    for k in range(steps + 50):
        step()
        if k < 50:  # the same settling as the timing runs
            continue
        f, ft = read(data), truth.read(model, data)
        a, b = f > 1e-9, ft > 0
        tp, lit, pressed = tp + int((a & b).sum()), lit + int(a.sum()), pressed + int(b.sum())
        got.append(f[a | b])
        want.append(ft[a | b])
    got, want = np.concatenate(got), np.concatenate(want)
    gain = float(got @ want / max(got @ got, 1e-300)) if calibrate else 1.0
    precision, recall = tp / max(lit, 1), tp / max(pressed, 1)
    return dict(truth_lit_precision=precision, truth_lit_recall=recall,
                truth_lit_f1=2 * precision * recall / max(precision + recall, 1e-12),
                truth_force_err=float(np.abs(gain * got - want).sum() / max(want.sum(), 1e-12)),
                truth_pressed_per_step=pressed / steps)


def _agreement(model, data, design, probes, steps: int) -> dict:
    """Vectorised readouts against the touch sensors of the same simulation, step by step."""
    touch = TouchReadout(model, design)
    readers = {k: SkinReadout(model, design, kernel=k) for k in ("linear", "nearest")}
    err = {k: [] for k in readers}
    recall = {k: [] for k in readers}
    missed = {k: 0 for k in readers}
    touch_missed = 0
    step = _stepper(model, data, probes)
    for _ in range(steps):
        step()
        ref = touch.read(data)
        lit_ref = ref > 1e-6
        if not lit_ref.any():
            touch_missed += 1
            continue
        for k, r in readers.items():
            f = r.read(data)
            err[k].append(np.abs(f - ref).sum() / ref.sum())
            recall[k].append((f[lit_ref] > 1e-6).mean())
            missed[k] += r.last_missed
    out = {k: dict(force_err=float(np.median(err[k])), lit_recall=float(np.mean(recall[k])), missed=missed[k])
           for k in readers}
    out["touch_missed"] = touch_missed
    return out


def collision_rows(steps: int) -> list[dict]:
    rows = []
    design = make_sample_design("ur5", pitch=BASE_PITCH)
    with tempfile.TemporaryDirectory() as tmp:
        robot = mesh_ur5(Path(tmp))
        probes = Probes(design, build_ur5())
        runs = {}
        for mode, faces in tqdm([("full", 0), ("decimate", 2000), ("decimate", 500), ("decimate", 100),
                                 ("hull", 0), ("primitive", 0)], desc="collision sweep"):
            model, data = probe_scene(design, robot, probes.obstacles, probes.q, collision=mode,
                                 target_faces=max(faces, 4))
            reader = SkinReadout(model, design)
            step = _stepper(model, data, probes)
            forces = []
            for _ in range(steps):
                step()
                forces.append(reader.read(data))
            ms = median_ms(step, repeat=steps)
            coll = [g for g in range(model.ngeom) if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH
                    and (model.geom_contype[g] or model.geom_conaffinity[g])]
            nfaces = int(sum(model.mesh_facenum[model.geom_dataid[g]] for g in coll))
            runs[(mode, faces)] = np.array(forces)
            ref = runs[("full", 0)]
            err = float(np.abs(runs[(mode, faces)] - ref).sum() / max(ref.sum(), 1e-12))
            rows.append(dict(sweep="collision", collision=mode, target_faces=faces or "", faces=nfaces,
                             steps_per_s=1e3 / ms, step_us=ms * 1e3, force_err=err))
    return rows


# --- timestep -------------------------------------------------------------------------------

REST_Q = np.array([0.0, 0.0, 0.0, -np.pi / 2, 0.0, 0.0])  # upper arm and forearm level


def resting_place(model, design, q) -> np.ndarray:
    """Where a load can rest on the skin at configuration q (world): on the link with the most
    up-facing taxels (normal within 8 degrees of up), the most upward of them nearest their middle.
    On the UR5 sample skin with the arm level, the top of the upper arm."""
    from skinsafe.core.robot.kinematics import TaxelKinematics

    pos, frames = TaxelKinematics(model, design).poses(q)
    up = np.flatnonzero(frames[:, 2, 2] > 0.99)
    if not len(up):
        raise ValueError("bench sensing: no taxel faces up at the rest pose; nothing to rest a load on")
    link = np.bincount(design.taxels.body[up]).argmax()
    on = up[design.taxels.body[up] == link]
    on = on[frames[on, 2, 2] >= frames[on, 2, 2].max() - 1e-3]
    return pos[on[np.argmin(np.linalg.norm(pos[on] - pos[on].mean(axis=0), axis=1))]]


def timestep_rows(timesteps=(0.0005, 0.001, 0.002, 0.004, 0.008), mass: float = 0.5) -> list[dict]:
    from skinsafe.core.sim.scene import Obstacle, SceneOptions, build_scene

    design = make_sample_design("ur5", pitch=BASE_PITCH)
    robot = build_ur5()
    rows = []
    top = resting_place(robot.model, design, REST_Q)
    box = Obstacle("load", "box", (0.04, 0.04, 0.01), pos=tuple(top + [0, 0, 0.011]), free=True, mass=mass)
    for ts in tqdm(timesteps, desc="timestep sweep"):
        model = build_scene(design, robot, [box], SceneOptions(timestep=ts)).compile()
        data = mujoco.MjData(model)
        data.qpos[:6] = REST_Q
        data.qpos[6:9] = box.pos
        data.qpos[9:13] = [1, 0, 0, 0]
        data.ctrl[:] = REST_Q
        reader = SkinReadout(model, design)
        settle, window = int(round(1.0 / ts)), int(round(0.2 / ts))
        load_geom = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "load")
        t0 = time.perf_counter()
        for _ in range(settle):
            mujoco.mj_step(model, data)
        wall = (time.perf_counter() - t0) / settle
        total, pen = [], []
        for _ in range(window):
            mujoco.mj_step(model, data)
            total.append(reader.read(data).sum())
            c = data.contact
            mine = (c.geom[:data.ncon] == load_geom).any(axis=1)
            pen.append(float(-c.dist[:data.ncon][mine].min()) if mine.any() else 0.0)
        weight = mass * float(-model.opt.gravity[2])
        rows.append(dict(sweep="timestep", timestep=ts, force_err=abs(float(np.mean(total)) - weight) / weight,
                         penetration_mm=float(np.mean(pen)) * 1e3, steps_per_s=1.0 / wall,
                         realtime_factor=ts / wall, on_arm=bool(data.qpos[8] > 0.05)))
    return rows


def plot(rows: list[dict], path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from skinsafe.core.skin.files import write_png

    present = [k for k in ("taxels", "collision", "timestep") if any(r["sweep"] == k for r in rows)]
    present[1:1] = ["accuracy"] if present[:1] == ["taxels"] else []
    if not present:
        return
    fig, axes = plt.subplots(1, len(present), figsize=(5.5 * len(present), 4.4), squeeze=False)
    ax = dict(zip(present, axes[0]))  # one panel per sweep that ran
    tx = [r for r in rows if r["sweep"] == "taxels"]
    styles = {("vectorised", "linear"): "o-", ("vectorised", "nearest"): "s--", ("touch", "cell"): "^-"}
    styles.update({("tactile", r["kernel"]): "x:" for r in tx if r["readout"] == "tactile"})
    for (readout, kernel), style in styles.items():
        pts = [(r["n_taxels"], r["steps_per_s"]) for r in tx if r["readout"] == readout and r["kernel"] == kernel]
        if pts:
            ax["taxels"].plot(*zip(*pts), style, label=f"{readout} ({kernel})")
    bare = sorted({(r["n_taxels"], 1e6 / r["skinless_step_us"]) for r in tx})
    if bare:
        ax["taxels"].plot(*zip(*bare), "k:", label="robot without skin")
        ax["taxels"].set(xscale="log", yscale="log", xlabel="taxels", ylabel="steps / s (physics + readout)",
                         title="UR5 + probes: what sensing costs")
        ax["taxels"].legend(fontsize=8)
        for (readout, kernel), style in styles.items():
            pts = [(r["n_taxels"], r["truth_lit_f1"]) for r in tx if r["readout"] == readout and r["kernel"] == kernel]
            if pts:
                ax["accuracy"].plot(*zip(*pts), style, label=f"{readout} ({kernel})")
        ax["accuracy"].set(xscale="log", ylim=(0, 1.02), xlabel="taxels", ylabel="lit F1 against the ground truth",
                           title="which taxels light: pressed cells vs lit (1 = exact)")
    co = [r for r in rows if r["sweep"] == "collision"]
    if co:
        a2 = ax["collision"].twinx()
        labels = [f"{r['collision']}{r['target_faces']}" for r in co]
        ax["collision"].bar(range(len(co)), [r["steps_per_s"] for r in co], color="C0")
        a2.plot(range(len(co)), [100 * r["force_err"] for r in co], "C3o-")
        ax["collision"].set_xticks(range(len(co)), labels, rotation=30, fontsize=8)
        ax["collision"].set(ylabel="steps / s (bars)", title="collision geometry")
        a2.set_ylabel("taxel force error vs full mesh, % (red)")
    ts = [r for r in rows if r["sweep"] == "timestep"]
    if ts:
        a3 = ax["timestep"].twinx()
        x = [r["timestep"] * 1e3 for r in ts]
        ax["timestep"].plot(x, [100 * r["force_err"] for r in ts], "C3o-", label="force error %")
        ax["timestep"].plot(x, [r["penetration_mm"] for r in ts], "C2s-", label="penetration mm")
        a3.plot(x, [r["realtime_factor"] for r in ts], "C0^--", label="real-time factor")
        ax["timestep"].set(xscale="log", xlabel="timestep, ms", title="0.5 kg box resting on the upper arm")
        a3.set_ylabel("real-time factor (blue)")
        ax["timestep"].legend(fontsize=8, loc="upper left")
    fig.tight_layout()
    write_png(fig, path)


def rows(args) -> list[dict]:
    sizes = [int(s) for s in str(args.sizes).split(",") if s]
    sweeps = set(str(args.sweeps).split(","))
    out = []
    if "taxels" in sweeps:
        out += taxel_rows(sizes, args.steps, [int(x) for x in str(getattr(args, "tactile_points", "1")).split(",") if x])
    if "collision" in sweeps:
        out += collision_rows(args.steps)
    if "timestep" in sweeps:
        out += timestep_rows([float(x) for x in str(args.timesteps).split(",") if x])
    if args.plot:
        plot(out, args.plot)
        print(f"wrote {Path(args.plot)}", file=sys.stderr)
    return out
