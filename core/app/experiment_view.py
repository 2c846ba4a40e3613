"""`skinsafe view --tracking RESULT.json`: an episode of the tracking experiment (core/experiments/tracking.py,
paper Fig. 11) in the live view, as a record of the runtime's format (core/runtime/sim_record.py).

The experiment's result holds its figures, not its ticks, so the episode is run again: the scene and noise
come from the seed, and a learning method's TDM is re-trained on the episodes before it as the experiment
did (vanilla needs none). Each control tick writes the measured q, the command sent (modulated), the plain
controller's plan, the taxel forces at the tick's end, the danger potential f the modulation saw, and a
`danger` flag on ticks with a taxel over its threshold; the balls go in as the view's obstacles. The
episode's contact ticks are compared with the result's figure (the same when the episode is the same).
"""
from __future__ import annotations

import json
from dataclasses import fields
from pathlib import Path

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
    from skinsafe.core.experiments.tracking import Learner, TrackingConfig, run_episode
    from skinsafe.core.learn.tracking_env import TrackingEnv, TrackingScene, TrackingTask

    doc = json.loads(Path(result).read_text())
    rows = doc.get("runs", {}).get(method, {}).get(str(seed))
    if rows is None:
        raise ValueError(f"{result}: no {method} run with seed {seed}; it has "
                         + ", ".join(f"{m} seeds {sorted(r)}" for m, r in doc.get("runs", {}).items()))
    if not 0 <= episode < len(rows):
        raise ValueError(f"{result}: {method} seed {seed} has episodes 0..{len(rows) - 1}, not {episode}")
    cfg = TrackingConfig(**{k: tuple(v) if isinstance(v, list) else v for k, v in doc["config"].items()})
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
