"""A simulated run (an experiment's episode) written as a runtime record: the same MCAP topics and
metadata as `skinsafe run --record` (core/runtime/record.py), so `skinsafe view FILE.mcap` and Blender's
live link show an experiment as they show a run.

`SimRecord(path, design, joint_names, period_s, ...)` saves the design as the record's taxel map
(`FILE.skin.json` beside it), then `tick(...)` once per control tick and `close()`. The runtime's
Recorder writes it, waiting for its writer instead of dropping ticks (no loop to keep here). Its
metadata says `"source": "experiment"` (a replay refuses it: the experiment's controller is not the
runtime's stack) and carries the scene's obstacles for the view (`{"kind": a MuJoCo primitive, "size": its
MuJoCo size, "pos", "quat" (w x y z; default unturned)}`); obstacles that move (a person) get poses every tick.
"""
from __future__ import annotations

import hashlib
import time
from pathlib import Path

import numpy as np

from skinsafe.core.runtime.record import Recorder
from skinsafe.core.runtime.tick import Tick

PRIMITIVES = ("sphere", "capsule", "ellipsoid", "cylinder", "box")  # the obstacle kinds the views draw


def obstacle_mesh(ob: dict) -> tuple[np.ndarray, np.ndarray] | None:
    """(vertices (V, 3), triangles (T, 3)) of an obstacle in its own frame (MuJoCo's tessellation of the
    primitive, 5 mm from the true surface at most); None for a kind the views do not draw."""
    if ob.get("kind") not in PRIMITIVES:
        return None
    import mujoco

    from skinsafe.core.design.surface import tessellate_geom

    gtype = getattr(mujoco.mjtGeom, f"mjGEOM_{ob['kind'].upper()}")
    v, tri, _ = tessellate_geom(gtype, np.asarray(ob["size"], float), tol=5e-4, max_edge=0.02)
    return v, tri


class SimRecord:
    def __init__(self, path: str | Path, design, joint_names, period_s: float, experiment: str = "",
                 obstacles: list[dict] = (), meta: dict | None = None):
        from skinsafe.core.skin.taxel_map import save

        self.path = Path(path)
        self.map = save(design, self.path.with_suffix(".skin.json")).resolve()
        config = {"source": "experiment", "experiment": experiment, "map": str(self.map),
                  "map_sha256": hashlib.sha256(self.map.read_bytes()).hexdigest(), "joint_names": list(joint_names),
                  "period_s": float(period_s), "obstacles": list(obstacles),
                  "threshold_N": float(np.max(design.taxels.thresholds.get("force", [np.inf]))), **(meta or {})}
        self.rec = Recorder(self.path, list(joint_names), config)
        self.n = design.n_taxels
        self.t0_ns, self.ticks, self.prev = time.time_ns(), 0, None

    def tick(self, t: float, q, command, planned=None, force=None, potential: float = 0.0, retracting: bool = False,
             pool_taxels=(), flags=(), obstacles=None) -> None:
        """One control tick at time t (s): measured q, the command sent, the controller's plan (None: the
        command), the taxel forces (N, design order), the layers' states, the obstacles' poses ((P, 7):
        position, quaternion w x y z; None: where the metadata puts them)."""
        q, command = np.asarray(q, float), np.asarray(command, float)
        planned = command if planned is None else np.asarray(planned, float)
        dt = t - self.prev[0] if self.prev else 0.0
        qd = (q - self.prev[1]) / dt if self.prev and dt > 0 else np.zeros_like(q)
        norm = float(np.linalg.norm(planned))
        factor = float(np.linalg.norm(command)) / norm if norm > 1e-12 else 1.0
        pool = np.asarray(pool_taxels, float)
        self.ticks += 1
        self.rec.put(Tick(t=float(t), q=q, qd=qd, dt=dt, command=command, planned=planned,
                          force=None if force is None else np.asarray(force, float), force_new=force is not None,
                          reading_seq=float(self.ticks), retracting=bool(retracting), pool=len(pool), pool_taxels=pool,
                          flags=tuple(flags), potential=float(potential), speed_factor=factor, board_age_s={},
                          index=self.ticks, ns=self.t0_ns + int(t * 1e9),
                          obstacles=None if obstacles is None else np.array(obstacles, float)), wait=True)
        self.prev = (t, q)

    def close(self, reason: str = "the episode ended") -> dict:
        t = self.prev[0] if self.prev else 0.0
        return self.rec.close({"reason": reason, "kind": "end", "t": t, "ns": self.t0_ns + int(t * 1e9),
                               "ticks": self.ticks, "dropped": self.rec.dropped})
