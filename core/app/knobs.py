"""The knobs `skinsafe trade` sweeps: for each, its values (reference first), the task that
measures one point (speed and what it computed) and the error of a point against the reference.
See `skinsafe.core.app.trade` for what each knob trades.

Every point runs on the UR5 sample skin, or with `where` (a taxel map path) on that map's robot
and skin (`skin_of`): `density`, `timestep`, `collision` and `sensing` work on any robot; `nstep`
does not depend on one; `damping` sweeps the UR5's elbow singularity and runs on the UR5 only."""
from __future__ import annotations

import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from skinsafe.core.app.knob_skins import map_pitch, map_probe_points, retiled, skin_of

PROBE_R, PROBE_DEPTH = 0.01, 0.003  # m, density knob probes
SAMPLE_DT = 0.008  # s between force samples of the timestep knob (every swept timestep divides it)


@dataclass(frozen=True)
class Knob:
    """One knob: its values (full and quick sweeps, reference first), the task computing one
    point and the error of a point's output against the reference's output."""

    name: str
    values: tuple
    quick: tuple
    point: Callable[[object, bool, str | None], dict]  # (value, quick, where) -> {"ms", "unit", "out", extras...}
    error: Callable[[object, object], float]  # (out, reference out) -> error >= 0
    error_metric: str
    cost: str = "ms"  # the column minimised with the error on the Pareto front
    any_robot: bool = True  # False: the UR5 only
    on_map: Callable[[bool, str], tuple] | None = None  # (quick, where) -> values on a map's skin

    def sweep(self, quick: bool, where: str | None = None) -> tuple:
        if where is not None and self.on_map is not None:
            return self.on_map(quick, where)
        return self.quick if quick else self.values


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
    upper arm, forearm and wrist and sliding 1 Hz, +-2 cm) with `SceneOptions(**opts)`:
    (model, data, step), `step()` moves the probes and steps the physics."""
    import mujoco

    from skinsafe.core.sim.probes import Probes
    from skinsafe.core.sim.scene import SceneOptions, build_scene

    probes = Probes(design, robot)
    model = build_scene(design, robot, probes.obstacles, SceneOptions(**opts)).compile()
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

def probe_points(robot, per_body: int, seed: int = 0, cell: float = 0.03) -> tuple[np.ndarray, np.ndarray]:
    """Probe contact points and outward normals (world, at home) on the sample-skin links of the
    UR5, where the coarsest swept skin (pitch `cell`) has cells: random points in random cells, the
    same points whatever the skin's pitch."""
    from skinsafe.core.design.sample import make_sample_design
    from skinsafe.core.robot.kinematics import TaxelKinematics

    coarse = make_sample_design("ur5", pitch=cell, robot=robot)
    pos, frames = TaxelKinematics(robot.model, coarse).poses(robot.home)
    rng = np.random.default_rng(seed)
    pts, normals = [], []
    for bi, name in enumerate(coarse.bodies):
        idx = rng.choice(np.flatnonzero(coarse.taxels.body == bi), per_body)
        r = float(robot.model.geom_size[robot.model.body(name).geomadr[0]][0])
        u, v = rng.uniform(-0.5, 0.5, (2, per_body)) * cell
        a = u / r  # around the axis (x), an arc on the cylinder
        x, y, z = frames[idx, :, 0], frames[idx, :, 1], frames[idx, :, 2]
        pts.append(pos[idx] + v[:, None] * y + (r * np.sin(a))[:, None] * x - (r * (1 - np.cos(a)))[:, None] * z)
        normals.append(np.cos(a)[:, None] * z + np.sin(a)[:, None] * x)
    return np.concatenate(pts), np.concatenate(normals)


def density_point(pitch: float, quick: bool, where: str | None = None) -> dict:
    """Press a sphere 3 mm into each probe point (`mj_forward`, arm at rest at home); the skin's
    estimate is the force-weighted centroid of the lit taxels. Speed: the readout plus all
    taxels' Jacobians, once per control tick."""
    import mujoco

    from skinsafe.core.robot.kinematics import TaxelKinematics
    from skinsafe.core.sim.readout import SkinReadout
    from skinsafe.core.sim.scene import Obstacle, SceneOptions, build_scene
    from skinsafe.core.timing import median_ms

    if where is None:
        robot, design = skin_of(None, pitch)
        pts, normals = probe_points(robot, 2 if quick else 6)
    else:
        robot, design = retiled(where, pitch)
        pts, normals = map_probe_points(where, 6 if quick else 12)
    probe = Obstacle("probe", "sphere", (PROBE_R,), pos=(0, 0, -5), mocap=True)
    model = build_scene(design, robot, [probe], SceneOptions(taxel_sites=False)).compile()
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

def timestep_point(dt: float, quick: bool, where: str | None = None) -> dict:
    """The sliding-probe scene for a fixed simulated time; taxel forces every SAMPLE_DT."""
    from skinsafe.core.sim.readout import SkinReadout

    robot, design = skin_of(where, 0.02 if quick else 0.01)
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


def collision_point(value: str, quick: bool, where: str | None = None) -> dict:
    """The sliding-probe scene on a UR5 whose links are fine meshes (or a map's robot with its
    own meshes), collision geometry as asked."""
    import mujoco

    from skinsafe.core.robot.models import mesh_ur5
    from skinsafe.core.sim.readout import SkinReadout

    mode = value.rstrip("0123456789")
    faces = int(value[len(mode):] or 500)
    design = skin_of(where, 0.02 if quick else 0.01)[1]
    steps = 100 if quick else 300
    with tempfile.TemporaryDirectory() as tmp:
        robot = mesh_ur5(Path(tmp), sections=32 if quick else 64) if where is None else skin_of(where)[0]
        model, data, step = _probe_scene(design, robot, collision=mode, target_faces=faces, taxel_sites=False)
        readout = SkinReadout(model, design)
        ms, forces = _timed_run(step, lambda: readout.read(data), steps, every=2)
        coll = [g for g in range(model.ngeom) if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH
                and (model.geom_contype[g] or model.geom_conaffinity[g])]
        nfaces = int(sum(model.mesh_facenum[model.geom_dataid[g]] for g in coll))
    return {"ms": ms, "unit": "physics step", "out": forces, "collision_faces": nfaces}


# --- knob: sensing model ----------------------------------------------------------------------

SENSING_VALUES = ("touch", "linear R=2p", "linear R=1p", "linear R=0.5p", "nearest R=1p")


def sensing_point(value: str, quick: bool, where: str | None = None) -> dict:
    """Per-taxel MuJoCo touch sensors (the reference) or the vectorised readout with a kernel and
    footprint radius in units of the pitch p, on the same sliding-probe simulation."""
    from skinsafe.core.sim.readout import SkinReadout, TouchReadout
    from skinsafe.core.timing import median_ms

    robot, design = skin_of(where, 0.02 if quick else 0.01)
    pitch = map_pitch(where) if where is not None else (0.02 if quick else 0.01)
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

def nstep_point(samples: int, quick: bool, where: str | None = None) -> dict:
    """w of eq. 8 (horizon 4, gamma 0.9, uniform policy, Euler rollouts of 0.15 s) for a batch of
    UR5 joint states and velocity actions, through the danger potential of a fixed-seed TDM
    over 64 taxels (6-D state and action, as in `experiment tracking`; head weights scaled so
    the field has contrast). `w_spread`: the standard deviation of w over the states."""
    import torch

    from skinsafe.core.safety.potential import DangerPotential, EulerDynamics, NStepConfig, UniformPolicy, nstep_targets
    from skinsafe.core.safety.tdm import TactileDangerModel
    from skinsafe.core.timing import median_ms

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


def damping_point(damping: float, quick: bool, where: str | None = None) -> dict:
    """A 20 N poke on the wrist_1 taxel whose retraction stretches the UR5 arm (elbow 0.6 rad from
    straight) into its elbow singularity; the defensiveness layer (default 3-D form) with the
    given DLS damping, integrated kinematically at 500 Hz with the joint limits lifted, so the
    peak joint speed is what the inverse asks for."""
    from skinsafe.core.design.sample import make_sample_design
    from skinsafe.core.robot.kinematics import TaxelKinematics
    from skinsafe.core.robot.models import build_ur5
    from skinsafe.core.safety.defensiveness import DefensivenessLayer
    from skinsafe.core.safety.retraction import RetractionParams, profile

    robot = build_ur5()
    design = make_sample_design("ur5", pitch=0.02, robot=robot)
    kin = TaxelKinematics(robot.model, design)
    q = robot.home.copy()
    q[2] = ELBOW
    i = stretching_taxel(kin, design, q)
    params = RetractionParams(damping=float(damping))
    dt = 0.002
    layer = DefensivenessLayer(kin, design.taxels.thresholds, 1e6, 1e9, params, dt)
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
    """The taxel whose retraction direction -z points most outward along the arm (from the origin
    of the skin's most proximal link to the middle of the taxel's own link): retracting it
    stretches the arm toward its elbow singularity. On the UR5 sample skin, one on wrist_1_link."""
    import mujoco

    pos, frames = kin.poses(q)
    ids = [mujoco.mj_name2id(kin.model, mujoco.mjtObj.mjOBJ_BODY, b) for b in design.bodies]
    shoulder = kin.data.xpos[min(ids)]  # bodies come in tree order: a parent before its children
    best, score = 0, -np.inf
    for bi in range(len(design.bodies)):
        on = np.flatnonzero(design.taxels.body == bi)
        if not len(on):
            continue
        out = pos[on].mean(axis=0) - shoulder
        s = -frames[on, :, 2] @ (out / max(np.linalg.norm(out), 1e-12))
        if s.max() > score:
            best, score = int(on[np.argmax(s)]), float(s.max())
    return best


def path_error(path: np.ndarray, ref: np.ndarray) -> float:
    return float(np.linalg.norm(path - ref, axis=1).max() * 1e3)


def _map_pitches(quick: bool, where: str) -> tuple:
    p = map_pitch(where)
    return tuple(round(p * s, 5) for s in ((1.0, 1.5, 2.5) if quick else (0.75, 1.0, 1.5, 2.0, 2.5)))


def _map_collisions(quick: bool, where: str) -> tuple:
    return ("skin", "full", "primitive") if quick else ("skin", "full", "decimate500", "decimate100", "hull", "primitive")


KNOBS = {k.name: k for k in (
    Knob("density", (0.005, 0.0075, 0.01, 0.015, 0.02, 0.03), (0.01, 0.02, 0.03), density_point, density_error,
         "mean |centroid - centroid at densest| (mm)", on_map=_map_pitches),
    Knob("timestep", (0.00025, 0.0005, 0.001, 0.002, 0.004, 0.008), (0.0005, 0.002, 0.008), timestep_point,
         _median_l1, "taxel force rel. L1 vs smallest dt (median)"),
    Knob("collision", COLLISION_VALUES, ("full", "decimate100", "primitive"), collision_point, _total_l1,
         "taxel force rel. L1 vs the first (full mesh; on a map the skin-fitted model)", on_map=_map_collisions),
    Knob("sensing", SENSING_VALUES, ("touch", "linear R=1p", "nearest R=1p"), sensing_point, _median_l1,
         "taxel force rel. L1 vs touch sensors (median)"),
    Knob("nstep", (1024, 1, 2, 4, 8, 16, 64, 256), (256, 1, 4, 16), nstep_point, rms_error,
         "RMS |w - w(most samples)|"),
    Knob("damping", (0.0, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2), (0.0, 0.01, 0.05, 0.2), damping_point, path_error,
         "max |taxel path - undamped path| (mm)", cost="peak_qdot", any_robot=False),
)}
