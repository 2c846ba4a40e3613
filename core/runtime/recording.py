"""A record (`skinsafe run --record`, or an experiment's: core/runtime/sim_record.py) as arrays for a viewer:
each tick's time, q, command, forces, layers' states and (an experiment's moving person) obstacle poses,
any tick in the view stream's frame format, the next contact after a time. Used by `skinsafe view
DIR` and Blender's live link; every record version read by core/runtime/record_read.py (no mujoco)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from skinsafe.core.runtime.record_read import NO_LAYERS, ReplayError, read_record
from skinsafe.core.runtime.tick import Tick
from skinsafe.core.runtime.view_stream import frame_header


class Recording:
    """A record's ticks as arrays (time on the robot's clock) and the view-stream frame of any tick."""

    def __init__(self, path: str | Path):
        self.config, ticks = read_record(path)
        t, q, cmd, planned, force_at, layers, poses, diag, forces = [], [], [], [], [], [], [], [], []
        for k in ticks:
            if k.force is not None:
                forces.append(k.force.astype(np.float32))
            t.append(k.t)
            q.append(k.q)
            cmd.append(k.command)
            planned.append(k.planned)
            force_at.append(len(forces) - 1)
            layers.append(k.layers or NO_LAYERS)
            poses.append(k.obstacles)
            if k.status:
                diag.append((k.t, k.status))
        if not t or q[0] is None:
            raise ReplayError(f"{path}: no tick recorded (the robot never moved)")
        self.t = np.asarray(t)
        self.q, self.command = np.array(q), np.array(cmd)
        self.planned = planned
        self.forces = np.array(forces) if forces else np.zeros((1, 0), np.float32)
        self.force_at = np.asarray(force_at)
        self.layers = layers
        self.potential = np.array([x.potential for x in layers])
        self.speed_factor = np.array([x.speed_factor for x in layers])
        self.retracting = np.array([float(x.retracting) for x in layers])
        # (ticks, P, 7) poses of the metadata's obstacles, or None: they stand still (runs, older records)
        self.obstacles = np.array(poses) if all(p is not None for p in poses) else None
        ticked = [d for d in diag if "skinsafe/layers" in d[1]]  # the ticks' diagnostics (not the stop's)
        self.diag_t = np.array([d[0] for d in ticked])
        self.diag = [d[1] for d in ticked]
        self.stop = next((d["skinsafe/watchdog"]["message"] for _, d in diag[::-1] if "skinsafe/watchdog" in d), "")
        peak = np.array([np.nanmax(f) if f.size else 0.0 for f in self.forces])
        self.peak = np.where(self.force_at >= 0, peak[np.maximum(self.force_at, 0)], 0.0)
        # a contact: a retraction (a run), or a taxel over the threshold (an experiment: no retraction layer)
        self.active = (self.peak > self.config["threshold_N"] if self.config.get("source") == "experiment"
                       else self.retracting > 0).astype(float)

    def index(self, t: float) -> int:
        """The tick nearest to time t."""
        i = int(np.clip(np.searchsorted(self.t, t), 1, max(1, len(self.t) - 1)))
        return i - 1 if len(self.t) < 2 or t - self.t[i - 1] <= self.t[i] - t else i

    def tick(self, i: int) -> Tick:
        """Tick i as the loop made it (forces: the newest reading by then, NaN before the first)."""
        k = self.force_at[i]
        force = self.forces[k].astype(float) if k >= 0 else np.full(self.forces.shape[1], np.nan)
        lay = self.layers[i]
        d = self.diag[max(0, int(np.searchsorted(self.diag_t, self.t[i], side="right")) - 1)] if self.diag else {}
        layers = d.get("skinsafe/layers", {}).get("values", {})
        skin = d.get("skinsafe/skin", {}).get("values", {})
        ages = {int(k.split()[1], 16): float(v) / 1e3 for k, v in skin.items() if k.startswith("board ")}
        pool = np.asarray(lay.pool, int)
        return Tick(t=float(self.t[i]), q=self.q[i], command=self.command[i], planned=self.planned[i], force=force,
                    retracting=lay.retracting, pool=len(pool), pool_taxels=pool, potential=float(lay.potential),
                    speed_factor=float(lay.speed_factor), flags=tuple(f for f in layers.get("flags", "").split(",") if f),
                    stop=self.stop if i == len(self.t) - 1 else "", board_age_s=ages,
                    frames_lost=int(skin.get("frames_lost", 0)), index=i + 1,
                    obstacles=None if self.obstacles is None else self.obstacles[i])

    def frame(self, i: int) -> tuple[dict, np.ndarray]:
        """Tick i in the view stream's frame format (header, forces)."""
        k = self.tick(i)
        h = frame_header(i + 1, k)
        if k.obstacles is not None:
            h["obstacles"] = k.obstacles.tolist()
        return h, k.force

    def next_contact(self, t: float) -> float | None:
        """The time of the largest reading of the next contact (`active`) after `t` (None: no more)."""
        i = self.index(t)
        on = np.flatnonzero((self.active[i + 1:] > 0) & (self.active[i:-1] == 0)) + i + 1 if i + 1 < len(
            self.t) else np.zeros(0, int)
        if not len(on):
            return None
        start = int(on[0])
        end = start + int(np.argmax(self.active[start:] == 0)) if (self.active[start:] == 0).any() else len(self.t)
        return float(self.t[start + int(np.argmax(self.peak[start:end]))])

