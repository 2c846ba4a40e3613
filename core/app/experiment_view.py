"""`skinsafe view --tracking RESULT.json` / `--collaboration RESULT.json`: an episode of the tracking
experiment (core/experiments/tracking_runs.py, paper Fig. 11) or of the collaboration experiment
(core/experiments/collaboration.py, Fig. 15) in the live view, as a record of the runtime's format
(core/runtime/sim_record.py).

The experiment's result holds its figures, not its ticks, so the episode is run again: the scene and noise
come from the seed, and a learning method's TDM is re-trained on the episodes before it as the experiment
did (vanilla needs none). Each control tick writes the measured q, the command sent (modulated), the plain
controller's plan, the taxel forces at the tick's end, the danger potential f the modulation saw, and a
`danger` flag on ticks with a taxel over its threshold; the balls go in as the view's obstacles. The
episode's contact ticks are compared with the result's figure (the same when the episode is the same).

A collaboration result's nominal episode of one scenario and stack is run again likewise (its config, its
skin `collaboration_skin.json` beside it, the nominal damping, attachment and timestep; a `full` stack's
TDM learned as the experiment did). Each control tick writes the measured q at the tick's end, the
command, the source's plan, the taxel forces (peak over the tick's physics steps), the modulation's f,
the retraction's pool, flags (the stack's, and the PFL cap's mode when not free) and the poses of the
person's parts, which move. Its contact events are compared with the result's rows of that stack.
"""
from __future__ import annotations

import json
from dataclasses import fields
from pathlib import Path

import mujoco
import numpy as np

from skinsafe.core.runtime.sim_record import SimRecord


class _Recorded:
    """The tracking env as `run_episode` uses it (reset, nominal, step, scene), each step written to `record`."""

    def __init__(self, env, record: SimRecord, layer):
        self.env, self.scene, self.record, self.layer = env, env.scene, record, layer
        m = self.scene.model
        names = self.record.rec.names
        self.qadr = np.array([m.jnt_qposadr[m.joint(n).id] for n in names])
        self.planned = None

    def reset(self, **kw):
        return self.env.reset(**kw)

    def nominal(self, obs):
        self.planned = self.env.nominal(obs)
        return self.planned

    def step(self, v):
        out = self.env.step(v)
        sc, info = self.scene, out[4]
        f = getattr(self.layer, "last_f", 0.0)
        self.record.tick(self.env.k * self.env.task.control_dt, sc.data.qpos[self.qadr], v, self.planned,
                         sc.readout.read(sc.data), f, flags=("danger",) if info["cost"] else ())
        return out


class _Tapped:
    """A modulation layer that keeps the danger potential f of its last call."""

    def __init__(self, layer):
        self.layer, self.last_f = layer, 0.0

    def __call__(self, s, v):
        out, self.last_f = self.layer(s, v)
        return out, self.last_f


def record_tracking(result: str | Path, out: str | Path, method: str = "vanilla", seed: int = 0,
                    episode: int = 0) -> dict:
    """Run episode `episode` of `method`/`seed` of a tracking result again into the record `out`."""
    from skinsafe.core.experiments.tracking_runs import Learner, RunConfig, run_episode
    from skinsafe.core.learn.tracking_env import TrackingEnv, TrackingScene, TrackingTask

    doc = json.loads(Path(result).read_text())
    rows = doc.get("runs", {}).get(method, {}).get(str(seed))
    if rows is None:
        raise ValueError(f"{result}: no {method} run with seed {seed}; it has "
                         + ", ".join(f"{m} seeds {sorted(r)}" for m, r in doc.get("runs", {}).items()))
    if not 0 <= episode < len(rows):
        raise ValueError(f"{result}: {method} seed {seed} has episodes 0..{len(rows) - 1}, not {episode}")
    cfg = RunConfig.from_dict(doc["config"])
    task = TrackingTask(**{f.name: getattr(cfg, f.name) for f in fields(TrackingTask)})
    scene = TrackingScene(task, seed)
    env = TrackingEnv(task, scene=scene)
    learner = None if method == "vanilla" else Learner(cfg, scene, method == "tdm2", seed)
    layer = None
    for e in range(episode if learner is not None else 0):  # the method's TDM as the experiment trained it
        layer, _ = learner.update(run_episode(env, layer, seed=1000 * seed + e))
    names = [scene.robot.model.joint(j).name for j in range(scene.robot.model.njnt)]
    balls = [{"kind": "sphere", "size": [task.ball_radius], "pos": [float(x) for x in c]} for c in scene.balls]
    record = SimRecord(out, scene.design, names, task.control_dt, "tracking", balls,
                       {"method": method, "seed": seed, "episode": episode, "result": str(Path(result).resolve())})
    tapped = _Tapped(layer) if layer is not None else None
    env_rec = _Recorded(env, record, tapped)
    ep = run_episode(env_rec, tapped, seed=1000 * seed + episode)
    rec = record.close()
    return {**rec, "map": str(record.map), "ticks": record.ticks, "contacts": ep.contacts,
            "contacts_in_result": int(rows[episode]["contacts"])}


def record_collaboration(result: str | Path, out: str | Path, scenario: str = "delivery",
                         stack: str = "full+pfl") -> dict:
    """Run the nominal `scenario`/`stack` episode of a collaboration result again into the record `out`;
    its contact events (`contacts`) beside the result's (`contacts_in_result`)."""
    import torch

    from skinsafe.core.experiments import collaboration_scenario as co
    from skinsafe.core.experiments.arm_scene import JOINTS
    from skinsafe.core.experiments.collaboration_person import learn_person
    from skinsafe.core.experiments.collaboration_result import contact_events
    from skinsafe.core.realtime import single_thread_blas
    from skinsafe.core.robot.kinematics import TaxelKinematics
    from skinsafe.core.robot.models import build_ur5
    from skinsafe.core.skin.taxel_map import load

    for name, value, known in (("scenario", scenario, co.SCENARIOS), ("stack", stack, co.STACKS)):
        if value not in known:
            raise ValueError(f"--{name} {value!r} is unknown; use one of {', '.join(known)}")
    try:
        doc = json.loads(Path(result).read_text())
    except json.JSONDecodeError as e:
        raise ValueError(f"{result}: not a JSON result ({e})") from None
    if not isinstance(doc, dict) or "nominal" not in doc or "config" not in doc:
        raise ValueError(f"{result}: not a collaboration result (no nominal runs); give the collaboration.json "
                         "that `skinsafe experiment collaboration` writes")
    if f"{scenario}/{stack}" not in doc.get("runs", {}):
        raise ValueError(f"{result}: no {scenario}/{stack} run (it has {', '.join(doc.get('runs', {})) or 'none'}); "
                         f"run `skinsafe experiment collaboration --stacks {stack}`")
    skin = Path(result).with_name("collaboration_skin.json")
    if not skin.is_file():
        raise ValueError(f"{result}: its skin {skin} is missing; put the taxel map the experiment ran on there")
    torch.set_num_threads(1)  # as the experiment's cells: the same TDM
    single_thread_blas()
    cfg, nominal, design = co.CollabConfig.from_json(doc["config"]), doc["nominal"], load(skin)
    lay = co.layout(scenario, TaxelKinematics(build_ur5().model, design), cfg)
    sc = co.build(lay, design, nominal["damping_ratio"], nominal["attachment_N_m"], nominal["dt_ms"], cfg)
    pot = learn_person(sc, lay, cfg) if stack.startswith("full") else None
    parts = [{"kind": p.kind, "size": list(p.size), "pos": [float(x) for x in at], "quat": list(p.quat),
              "name": p.region} for p, at in zip(lay.parts, lay.targets(0.0))]
    record = SimRecord(out, design, JOINTS, sc.control_dt, "collaboration", parts,
                       {"scenario": scenario, "stack": stack, **nominal, "result": str(Path(result).resolve())})

    def tick(t, source, force, v, st, cap):
        d = st.defensiveness
        retracting = d is not None and d.active
        flags = st.info.flags + ((f"pfl:{cap.last_mode}",) if cap is not None and cap.last_mode != "free" else ())
        record.tick(t + sc.control_dt, sc.q, v, source(t, sc.q), force, st.last_f, retracting,
                    d.pool if retracting else (), flags, person_poses(sc))

    run = co.episode(sc, lay, stack, pot, cfg, on_tick=tick)
    rec = record.close()
    names = [sc.model.body(b).name for b in range(sc.model.nbody)]
    events = contact_events(run["trace"], [p.region for p in lay.parts], sc.control_dt, run["acted"], names)
    rows = [e for e in doc.get("contacts", []) if (e["scenario"], e["stack"]) == (scenario, stack)]
    return {**rec, "map": str(record.map), "ticks": record.ticks, "contacts": events, "contacts_in_result": rows,
            "same": same_contacts(events, rows)}


def person_poses(sc) -> np.ndarray:
    """(P, 7) where the scene's person's parts are now: each geom's position and quaternion (w x y z)."""
    g = sc.human.geom
    quat = np.zeros((len(g), 4))
    for k, i in enumerate(g):
        mujoco.mju_mat2Quat(quat[k], sc.data.geom_xmat[i])
    return np.c_[sc.data.geom_xpos[g], quat]


def same_contacts(a, b) -> bool:
    """Two lists of contact events agree: region, kind and start, and their durations, peaks and ratios
    to 1e-6."""
    num = ("duration_s", "peak_N", "quasi_static_N", "peak_pressure_N_cm2", "ratio")
    return len(a) == len(b) and all((x["region"], x["kind"], x["start_s"]) == (y["region"], y["kind"], y["start_s"])
                                    and np.allclose([x[k] for k in num], [y[k] for k in num], rtol=1e-6, atol=1e-9)
                                    for x, y in zip(a, b))


def contact_summary(events) -> str:
    """Contact events as `region kind at start_s: peak N, ratio` (the worse of the transient and
    quasi-static peaks), or `none`."""
    return "; ".join(f"{e['region']} {e['kind']} at {e['start_s']:.3f} s: {max(e['peak_N'], e['quasi_static_N']):.1f} N, "
                     f"ratio {e['ratio']:.2f}" for e in events) or "none"
