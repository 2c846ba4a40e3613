"""`skinsafe trade`: speed against accuracy for the knobs users turn, swept in parallel with Ray.

Each knob is swept over a few values; every point is one Ray task that measures its speed
(median wall time of its unit of work) and returns what it computed. The error of a point is
measured against the knob's most accurate setting (the reference, error 0, speedup 1):

- `density`, the sample skin's pitch (m): readout + all taxels' Jacobians per control tick;
  contact localisation (force-weighted centroid of the lit taxels) vs the densest skin, mm.
- `timestep`, MuJoCo's timestep (s): wall ms per simulated second; taxel forces vs the
  smallest timestep (relative L1, median over samples).
- `collision`, `ExportOptions.collision` (+ target faces): physics step; taxel forces vs the
  full mesh (relative L1).
- `sensing`, the readout model: physics step + readout; taxel forces vs per-taxel MuJoCo
  touch sensors (relative L1, median).
- `nstep`, Monte Carlo rollouts per (s, a) of eq. 8: the targets of a batch of states; RMS of
  w vs the most samples.
- `damping`, the DLS damping: one defensiveness tick; the taxel path vs the undamped inverse,
  max mm.

For `damping` the trade is accuracy against the peak joint speed the retraction asks for near
the UR5 elbow singularity (compute time hardly changes): its Pareto front uses `peak_qdot`.
Every other knob's front uses `ms`. Outputs in `--out`: `trade.png` (one panel per knob, error
against speedup or peak joint speed, Pareto points filled), `trade.md` and `trade.json`.

Ray: `--address` joins an existing cluster (`auto` for one started with `ray start` on this
machine; every node needs skinsafe installed); without it a new local Ray starts by itself and
stops at the end.
"""
from __future__ import annotations

import io
import json
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from .files import atomic_write

PROBE_R, PROBE_DEPTH = 0.01, 0.003  # m, density knob probes
SAMPLE_DT = 0.008  # s between force samples of the timestep knob (every swept timestep divides it)


@dataclass(frozen=True)
class Knob:
    """One knob: its values (full and quick sweeps, reference first), the task computing one
    point and the error of a point's output against the reference's output."""

    name: str
    values: tuple
    quick: tuple
    point: Callable[[object, bool], dict]  # (value, quick) -> {"ms", "unit", "out", extras...}
    error: Callable[[object, object], float]  # (out, reference out) -> error >= 0
    error_metric: str
    cost: str = "ms"  # the column minimised with the error on the Pareto front

    def sweep(self, quick: bool) -> tuple:
        return self.quick if quick else self.values


# --- Pareto front ---------------------------------------------------------------------------

def pareto_front(cost, error) -> np.ndarray:
    """(K,) True where no other point is at least as good in both (lower cost, lower error) and
    strictly better in one. Equal points are all on the front."""
    c, e = np.asarray(cost, float), np.asarray(error, float)
    if c.shape != e.shape or c.ndim != 1:
        raise ValueError(f"pareto_front: cost {c.shape} and error {e.shape} must be 1-D of the same length")
    le = (c[None, :] <= c[:, None]) & (e[None, :] <= e[:, None])
    lt = (c[None, :] < c[:, None]) | (e[None, :] < e[:, None])
    return ~(le & lt).any(axis=1)


# --- shared helpers -------------------------------------------------------------------------

def _relative_l1(f: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """Per sample sum |f - ref| / sum ref (samples where the reference senses nothing dropped)."""
    total = ref.sum(axis=1)
    keep = total > 1e-9
    return np.abs(f[keep] - ref[keep]).sum(axis=1) / total[keep]


def _median_l1(out, ref) -> float:
    err = _relative_l1(out, ref)
    return float(np.median(err)) if len(err) else 0.0


def _total_l1(out, ref) -> float:
    return float(np.abs(out - ref).sum() / max(ref.sum(), 1e-12))


def _probe_scene(design, robot, **opts):
    """The sliding-probe scene of `skinsafe bench sensing` (three probes pressing 5 mm into the
    upper arm, forearm and wrist and sliding 1 Hz, +-2 cm) with `ExportOptions(**opts)`:
    (model, data, step), `step()` moves the probes and steps the physics."""
    import mujoco

    from ..exporters.mjcf import ExportOptions, build_scene
    from .bench_sensing import Probes

    probes = Probes(design, robot)
    model = build_scene(design, robot, probes.obstacles, ExportOptions(**opts)).compile()
    data = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, data, 0)
    data.ctrl[:] = robot.home
    data.qpos[: len(probes.q)] = probes.q

    def step():
        probes.move(data, data.time)
        mujoco.mj_step(model, data)
    return model, data, step


def _timed_run(step, read, steps: int, every: int = 1):
    """Run `steps` steps timing each; `read()` after every `every`-th step. -> (median step ms, (S, N))."""
    times, out = np.empty(steps), []
    for k in range(steps):
        t0 = time.perf_counter()
        step()
        times[k] = time.perf_counter() - t0
        if (k + 1) % every == 0:
            out.append(read())
    return float(np.median(times) * 1e3), np.array(out)


# --- knob: taxel density --------------------------------------------------------------------

def probe_points(robot, per_body: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Probe contact points and outward normals (world, at home) on the cylindrical middle of the
    sample-skin links of the UR5: the same points whatever the skin's pitch."""
    import mujoco

    from .sample_skin import SAMPLE_BODIES

    model = robot.model
    data = mujoco.MjData(model)
    data.qpos[:] = robot.home
    mujoco.mj_kinematics(model, data)
    rng = np.random.default_rng(seed)
    pts, normals = [], []
    for name in SAMPLE_BODIES["ur5"]:
        bid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, name)
        g = int(np.flatnonzero(model.geom_bodyid == bid)[0])
        r, half = model.geom_size[g][:2]
        phi = rng.uniform(0, 2 * np.pi, per_body)
        z = rng.uniform(-0.5, 0.5, per_body) * half
        radial = np.stack([np.cos(phi), np.sin(phi), np.zeros(per_body)], 1)
        local = r * radial + z[:, None] * [0.0, 0.0, 1.0]
        R = data.geom_xmat[g].reshape(3, 3)
        pts.append(local @ R.T + data.geom_xpos[g])
        normals.append(radial @ R.T)
    return np.concatenate(pts), np.concatenate(normals)


def density_point(pitch: float, quick: bool) -> dict:
    """Press a sphere 3 mm into each probe point (`mj_forward`, arm at rest at home); the skin's
    estimate is the force-weighted centroid of the lit taxels. Speed: the readout plus all
    taxels' Jacobians, once per control tick."""
    import mujoco

    from ..exporters.mjcf import ExportOptions, Obstacle, build_scene
    from .kinematics import TaxelKinematics
    from .robots import build_ur5
    from .sample_skin import make_sample_design
    from .sensing import SkinReadout
    from .timing import median_ms

    robot = build_ur5()
    design = make_sample_design("ur5", pitch=float(pitch), robot=robot)
    pts, normals = probe_points(robot, 2 if quick else 6)
    probe = Obstacle("probe", "sphere", (PROBE_R,), pos=(0, 0, -5), mocap=True)
    model = build_scene(design, robot, [probe], ExportOptions(taxel_sites=False)).compile()
    model.opt.gravity[:] = 0  # the arm at rest at home: every probe contact pushes back
    data = mujoco.MjData(model)
    data.qpos[: robot.model.nq] = robot.home
    data.ctrl[:] = robot.home
    kin = TaxelKinematics(model, design)
    taxel_pos = kin.poses(robot.home)[0].copy()
    readout = SkinReadout(model, design)
    probe_geom = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "probe")
    est, truth = np.full((len(pts), 3), np.nan), np.full((len(pts), 3), np.nan)
    for k, (p, n) in enumerate(zip(pts, normals)):
        data.mocap_pos[0] = p + n * (PROBE_R - PROBE_DEPTH)
        mujoco.mj_forward(model, data)
        f = readout.read(data)
        mine = (data.contact.geom[: data.ncon] == probe_geom).any(axis=1)
        if mine.any():
            truth[k] = data.contact.pos[: data.ncon][mine].mean(axis=0)
        if f.sum() > 0:
            est[k] = f @ taxel_pos / f.sum()
    tick = median_ms(lambda: (readout.read(data), kin.jacobians(robot.home)), repeat=20,
                     min_time_s=0.2 if quick else 1.0)
    sensed = ~np.isnan(est[:, 0]) & ~np.isnan(truth[:, 0])
    return {"ms": tick, "unit": "control tick", "out": est, "n_taxels": design.n_taxels,
            "missed": int(np.isnan(est[:, 0]).sum()),
            "truth_err_mm": float(np.linalg.norm(est[sensed] - truth[sensed], axis=1).mean() * 1e3)}


def density_error(est: np.ndarray, ref: np.ndarray) -> float:
    both = ~np.isnan(est[:, 0]) & ~np.isnan(ref[:, 0])
    return float(np.linalg.norm(est[both] - ref[both], axis=1).mean() * 1e3) if both.any() else float("inf")


# --- knob: physics timestep -----------------------------------------------------------------

def timestep_point(dt: float, quick: bool) -> dict:
    """The sliding-probe scene for a fixed simulated time; taxel forces every SAMPLE_DT."""
    from .robots import build_ur5
    from .sample_skin import make_sample_design
    from .sensing import SkinReadout

    robot = build_ur5()
    design = make_sample_design("ur5", pitch=0.02 if quick else 0.01, robot=robot)
    duration = 0.25 if quick else 0.5
    steps = int(round(duration / dt))
    every = int(round(SAMPLE_DT / dt))
    if abs(every * dt - SAMPLE_DT) > 1e-12 or every < 1:
        raise ValueError(f"timestep knob: {dt} s does not divide the sample interval {SAMPLE_DT} s")
    model, data, step = _probe_scene(design, robot, timestep=float(dt), taxel_sites=False)
    readout = SkinReadout(model, design)
    ms, forces = _timed_run(step, lambda: readout.read(data), steps, every)
    per_sim_s = ms / dt
    return {"ms": per_sim_s, "unit": "simulated second", "out": forces, "n_taxels": design.n_taxels,
            "realtime_factor": 1e3 / per_sim_s, "stable": bool(np.isfinite(data.qpos).all())}


# --- knob: collision mesh resolution ----------------------------------------------------------

COLLISION_VALUES = ("full", "decimate2000", "decimate500", "decimate100", "hull", "primitive")


def collision_point(value: str, quick: bool) -> dict:
    """The sliding-probe scene on a UR5 whose links are fine meshes, collision geometry as asked."""
    import mujoco

    from .bench_sensing import mesh_ur5
    from .sample_skin import make_sample_design
    from .sensing import SkinReadout

    mode = value.rstrip("0123456789")
    faces = int(value[len(mode):] or 500)
    design = make_sample_design("ur5", pitch=0.02 if quick else 0.01)
    steps = 100 if quick else 300
    with tempfile.TemporaryDirectory() as tmp:
        robot = mesh_ur5(Path(tmp), sections=32 if quick else 64)
        model, data, step = _probe_scene(design, robot, collision=mode, target_faces=faces, taxel_sites=False)
        readout = SkinReadout(model, design)
        ms, forces = _timed_run(step, lambda: readout.read(data), steps, every=2)
        coll = [g for g in range(model.ngeom) if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH
                and (model.geom_contype[g] or model.geom_conaffinity[g])]
        nfaces = int(sum(model.mesh_facenum[model.geom_dataid[g]] for g in coll))
    return {"ms": ms, "unit": "physics step", "out": forces, "collision_faces": nfaces}


# --- knob: sensing model ----------------------------------------------------------------------

SENSING_VALUES = ("touch", "linear R=2p", "linear R=1p", "linear R=0.5p", "nearest R=1p")


def sensing_point(value: str, quick: bool) -> dict:
    """Per-taxel MuJoCo touch sensors (the reference) or the vectorised readout with a kernel and
    footprint radius in units of the pitch p, on the same sliding-probe simulation."""
    from .robots import build_ur5
    from .sample_skin import make_sample_design
    from .sensing import SkinReadout, TouchReadout
    from .timing import median_ms

    robot = build_ur5()
    pitch = 0.02 if quick else 0.01
    design = make_sample_design("ur5", pitch=pitch, robot=robot)
    steps = 100 if quick else 300
    touch = value == "touch"
    model, data, step = _probe_scene(design, robot, touch_sensors=touch)
    if touch:
        reader = TouchReadout(model, design)
        ms, forces = _timed_run(step, lambda: reader.read(data), steps)
        return {"ms": ms, "unit": "physics step + readout", "out": forces, "n_taxels": design.n_taxels}
    kernel, radius = value.split(" R=")
    reader = SkinReadout(model, design, footprint_radius=float(radius[:-1]) * pitch, kernel=kernel)
    step_ms, forces = _timed_run(step, lambda: reader.read(data), steps)
    read_ms = median_ms(lambda: reader.read(data), repeat=steps)
    return {"ms": step_ms + read_ms, "unit": "physics step + readout", "out": forces, "n_taxels": design.n_taxels,
            "read_us": read_ms * 1e3}


# --- knob: n-step Monte Carlo samples -------------------------------------------------------

def nstep_point(samples: int, quick: bool) -> dict:
    """w of eq. 8 (horizon 4, gamma 0.9, uniform policy, Euler rollouts of 0.15 s) for a batch of
    UR5 joint states and velocity actions, through the danger potential of a fixed-seed TDM
    over 64 taxels (6-D state and action, as in `experiment tracking`; head weights scaled so
    the field has contrast). `w_spread`: the standard deviation of w over the states."""
    import torch

    from .potential import DangerPotential, EulerDynamics, NStepConfig, UniformPolicy, nstep_targets
    from .tdm import TactileDangerModel
    from .timing import median_ms

    torch.set_num_threads(1)
    torch.manual_seed(0)
    tdm = TactileDangerModel(6, 6, 64, (64, 64)).eval()
    with torch.no_grad():
        tdm.head.weight.mul_(10.0)  # contrast: f from about 0.25 to 0.55 over the states
        tdm.head.bias.fill_(float(np.log(0.2 / 64)))
    pot = DangerPotential(tdm)
    rng = np.random.default_rng(0)
    batch = 128 if quick else 256
    s = rng.uniform(-np.pi, np.pi, (batch, 6))
    a = rng.uniform(-1.0, 1.0, (batch, 6))
    args = (pot, s, a, EulerDynamics(0.15), UniformPolicy(-np.ones(6), np.ones(6)), NStepConfig(4, 0.9, int(samples)))
    w = nstep_targets(*args, seed=1)
    ms = median_ms(lambda: nstep_targets(*args, seed=1), repeat=3 if quick else 5, warmup=1,
                   min_time_s=0.2 if quick else 1.0)
    return {"ms": ms, "unit": f"{batch} states", "out": w, "w_spread": float(w.std())}


def rms_error(w: np.ndarray, ref: np.ndarray) -> float:
    return float(np.sqrt(np.mean((w - ref) ** 2)))


# --- knob: DLS damping ------------------------------------------------------------------------

ELBOW = 0.6  # rad from straight: the retraction (8.3 cm) needs more than the arm's remaining reach (about 4 cm)


def damping_point(damping: float, quick: bool) -> dict:
    """A 20 N poke on the wrist_1 taxel whose retraction stretches the UR5 arm (elbow 0.6 rad from
    straight) into its elbow singularity; the defensiveness layer (default 3-D form) with the
    given DLS damping, integrated kinematically at 500 Hz with the joint limits lifted, so the
    peak joint speed is what the inverse asks for."""
    from .defensiveness import DefensivenessLayer
    from .kinematics import TaxelKinematics
    from .retraction import RetractionParams, profile
    from .robots import build_ur5
    from .sample_skin import make_sample_design

    robot = build_ur5()
    design = make_sample_design("ur5", pitch=0.02, robot=robot)
    kin = TaxelKinematics(robot.model, design)
    q = robot.home.copy()
    q[2] = ELBOW
    i = stretching_taxel(kin, design, q)
    params = RetractionParams(damping=float(damping))
    layer = DefensivenessLayer(kin, design.taxels.thresholds, 1e6, 1e9, params)
    dt = 0.002
    force = np.zeros(design.n_taxels)
    force[i] = 20.0
    zero = np.zeros_like(force)
    p0, z0 = (a[i].copy() for a in kin.poses(q))
    z0 = z0[:, 2]
    ticks = int(np.ceil((params.T + 2 * dt) / dt))
    path, times, peak, track = np.zeros((ticks, 3)), np.zeros(ticks), 0.0, 0.0
    want = min(params.alpha * 20.0, 12 * params.max_distance)
    for k in range(ticks):
        t0 = time.perf_counter()
        qd = layer.tick(k * dt, q, {"force": force if k == 0 else zero}, None, dt)
        times[k] = time.perf_counter() - t0
        q = q + qd * dt
        peak = max(peak, float(np.abs(qd).max()))
        path[k] = kin.poses(q)[0][i]
        desired = p0 - z0 * want * profile((k + 1) * dt / params.T)
        track = max(track, float(np.linalg.norm(path[k] - desired)))
    return {"ms": float(np.median(times) * 1e3), "unit": "defensiveness tick", "out": path,
            "peak_qdot": peak, "tracking_err_mm": track * 1e3, "taxel": int(i)}


def stretching_taxel(kin, design, q) -> int:
    """The wrist_1 taxel whose retraction direction -z points most outward along the arm (from
    the shoulder to the wrist): retracting it stretches the arm toward its elbow singularity."""
    import mujoco

    on = np.flatnonzero(design.taxels.body == design.bodies.index("wrist_1_link"))
    pos, frames = kin.poses(q)
    shoulder = kin.data.xpos[mujoco.mj_name2id(kin.model, mujoco.mjtObj.mjOBJ_BODY, "upper_arm_link")]
    out = pos[on].mean(axis=0) - shoulder
    return int(on[np.argmax(-frames[on, :, 2] @ (out / np.linalg.norm(out)))])


def path_error(path: np.ndarray, ref: np.ndarray) -> float:
    return float(np.linalg.norm(path - ref, axis=1).max() * 1e3)


KNOBS = {k.name: k for k in (
    Knob("density", (0.005, 0.0075, 0.01, 0.015, 0.02, 0.03), (0.01, 0.02, 0.03), density_point, density_error,
         "mean |centroid - centroid at densest| (mm)"),
    Knob("timestep", (0.00025, 0.0005, 0.001, 0.002, 0.004, 0.008), (0.0005, 0.002, 0.008), timestep_point,
         _median_l1, "taxel force rel. L1 vs smallest dt (median)"),
    Knob("collision", COLLISION_VALUES, ("full", "decimate100", "primitive"), collision_point, _total_l1,
         "taxel force rel. L1 vs full mesh"),
    Knob("sensing", SENSING_VALUES, ("touch", "linear R=1p", "nearest R=1p"), sensing_point, _median_l1,
         "taxel force rel. L1 vs touch sensors (median)"),
    Knob("nstep", (1024, 1, 2, 4, 8, 16, 64, 256), (256, 1, 4, 16), nstep_point, rms_error,
         "RMS |w - w(most samples)|"),
    Knob("damping", (0.0, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2), (0.0, 0.01, 0.05, 0.2), damping_point, path_error,
         "max |taxel path - undamped path| (mm)", cost="peak_qdot"),
)}


# --- the sweep --------------------------------------------------------------------------------

def _task(knob: str, value, quick: bool) -> dict:
    """One sweep point (runs in a Ray worker)."""
    return KNOBS[knob].point(value, quick)


def parse_knobs(text: str | list | tuple) -> list[str]:
    names = [k.strip() for k in text.split(",")] if isinstance(text, str) else list(text)
    names = [k for k in names if k]
    bad = [k for k in names if k not in KNOBS]
    if bad or not names:
        raise ValueError(f"knobs {bad or '(none)'} unknown; choose from {', '.join(KNOBS)} (comma-separated)")
    return list(dict.fromkeys(names))


def rows_from_results(results: dict[tuple[str, object], dict], knobs: list[str], quick: bool) -> list[dict]:
    """Flat rows (one per point, knob by knob in sweep order) with errors, speedups and Pareto flags."""
    rows = []
    for name in knobs:
        knob = KNOBS[name]
        values = knob.sweep(quick)
        ref = results[(name, values[0])]
        mine = []
        for v in values:
            r = results[(name, v)]
            extras = {k: x for k, x in r.items() if k not in ("ms", "unit", "out")}
            mine.append({"knob": name, "value": v, "ms": r["ms"], "unit": r["unit"],
                         "speedup_vs_reference": ref["ms"] / r["ms"],
                         "error": 0.0 if v == values[0] else knob.error(r["out"], ref["out"]),
                         "error_metric": knob.error_metric, "pareto": False, **extras})
        flags = pareto_front([r[knob.cost] for r in mine], [r["error"] for r in mine])
        for r, f in zip(mine, flags):
            r["pareto"] = bool(f)
        rows += mine
    return rows


def run_sweep(knobs=tuple(KNOBS), quick: bool = False, address: str | None = None, out: str | Path | None = "out/trade",
              progress: bool = True) -> list[dict]:
    """Sweep the knobs as Ray tasks (one per point) and return the rows; with `out`, also write
    `trade.png`, `trade.md` and `trade.json` there. Joins the cluster at `address`, else starts a
    local Ray (and stops it at the end) unless one is already initialised in this process."""
    import ray
    from tqdm import tqdm

    names = parse_knobs(knobs)
    started = not ray.is_initialized()
    if started:
        if address:
            ray.init(address=address, log_to_driver=False)
        else:
            # "local": a new Ray of our own, even where `ray start` left a cluster on this machine
            ray.init(address="local", include_dashboard=False, log_to_driver=False,
                     object_store_memory=256 * 2 ** 20)
    try:
        task = ray.remote(num_cpus=1)(_task)
        points = [(n, v) for n in names for v in KNOBS[n].sweep(quick)]
        refs = {task.remote(n, v, quick): (n, v) for n, v in points}
        results: dict = {}
        pending = list(refs)
        with tqdm(total=len(pending), desc="trade sweep", disable=not progress, file=sys.stderr) as bar:
            while pending:
                done, pending = ray.wait(pending, num_returns=1)
                for ref in done:
                    key = refs[ref]
                    results[key] = ray.get(ref)
                    bar.set_postfix_str(f"{key[0]}={key[1]}")
                    bar.update()
    finally:
        if started:
            ray.shutdown()
    rows = rows_from_results(results, names, quick)
    if out is not None:
        write_outputs(rows, Path(out))
    return rows


# --- outputs ----------------------------------------------------------------------------------

CORE = ("knob", "value", "ms", "unit", "speedup_vs_reference", "error", "error_metric", "pareto")


def markdown(rows: list[dict]) -> str:
    """The rows as a markdown table; per-knob extra columns go into `details`."""
    def fmt(v):
        return f"{v:.4g}" if isinstance(v, float) else str(v)

    lines = ["| " + " | ".join(CORE) + " | details |", "|" + " --- |" * (len(CORE) + 1)]
    for r in rows:
        details = ", ".join(f"{k}={fmt(v)}" for k, v in r.items() if k not in CORE)
        lines.append("| " + " | ".join(fmt(r[k]) for k in CORE) + f" | {details} |")
    return "\n".join(lines) + "\n"


def plot(rows: list[dict], path: Path) -> Path:
    """One panel per knob: error against speedup (or peak joint speed), Pareto points filled."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import ScalarFormatter

    knobs = list(dict.fromkeys(r["knob"] for r in rows))
    cols = min(3, len(knobs))
    nrows = int(np.ceil(len(knobs) / cols))
    fig, axes = plt.subplots(nrows, cols, figsize=(5 * cols, 4 * nrows), squeeze=False)
    for ax, name in zip(axes.ravel(), knobs):
        mine = [r for r in rows if r["knob"] == name]
        peak = KNOBS[name].cost == "peak_qdot"
        x = np.array([r["peak_qdot"] if peak else r["speedup_vs_reference"] for r in mine])
        y = np.array([r["error"] for r in mine])
        front = np.array([r["pareto"] for r in mine])
        ax.plot(x[~front], y[~front], "o", mfc="none", color="C0", label="dominated")
        order = np.argsort(x[front])
        ax.plot(x[front][order], y[front][order], "o-", color="C3", label="Pareto-optimal")
        for xi, yi, r in zip(x, y, mine):
            ax.annotate(str(r["value"]), (xi, yi), fontsize=7, xytext=(3, 3), textcoords="offset points")
        if x.max() / x.min() > 5:
            ax.set_xscale("log")
            ax.xaxis.set_major_formatter(ScalarFormatter())
        ax.set_xlabel("peak joint speed asked [rad/s] (lower is safer)" if peak else
                      f"speedup vs reference ({mine[0]['unit']})")
        ax.set_ylabel(mine[0]["error_metric"], fontsize=8)
        ax.set_title(f"{name} (reference {mine[0]['value']})")
        ax.legend(fontsize=7)
    for ax in axes.ravel()[len(knobs):]:
        ax.axis("off")
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    plt.close(fig)
    return atomic_write(path, buf.getvalue())


def write_outputs(rows: list[dict], out: Path) -> list[Path]:
    return [plot(rows, out / "trade.png"), atomic_write(out / "trade.md", markdown(rows)),
            atomic_write(out / "trade.json", json.dumps(rows, indent=1))]


# --- CLI ----------------------------------------------------------------------------------------

def add_arguments(p) -> None:
    p.add_argument("--knobs", default=",".join(KNOBS), help=f"comma-separated, from: {', '.join(KNOBS)}")
    p.add_argument("--quick", action="store_true", help="a reduced sweep (a few points per knob, smaller scenes)")
    p.add_argument("--address", default=None, help="an existing Ray cluster (host:6379, ray://host:10001, or auto "
                   "for one started with `ray start` here); default: start a local Ray")
    p.add_argument("--out", default="out/trade", help="folder for trade.png, trade.md, trade.json")
    p.add_argument("--json", action="store_true", help="print the rows as one JSON list")


def run(args) -> int:
    from .cli import print_rows

    try:
        knobs = parse_knobs(args.knobs)
    except ValueError as e:
        raise SystemExit(f"skinsafe trade: --knobs: {e}")
    rows = run_sweep(knobs, quick=args.quick, address=args.address, out=args.out)
    print_rows(rows, args.json)
    for name in ("trade.png", "trade.md", "trade.json"):
        print(f"wrote {Path(args.out) / name}", file=sys.stderr)
    return 0
