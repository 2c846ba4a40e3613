"""The tactile defensiveness layer (paper III-C): readings -> danger events -> active pool ->
the joint velocity to command, which outranks any planned motion.

Each tick: taxels whose stimulus exceeds its threshold (`events.danger_events`) and that are not
already retracting join the pool with their trigger time, position and normal; a retraction
lasts T and then leaves the pool (a taxel still in danger then triggers again). While a taxel
retracts, its severity is the peak `alpha_s * reading_s` seen so far (the sensed force still
rises for a few ms after the threshold is crossed). Only the pool's Jacobians are computed.
The maths is in `retraction.py`.
"""
from __future__ import annotations

import numba
import numpy as np

from skinsafe.core.robot.kinematics import TaxelKinematics
from skinsafe.core.safety.events import danger_events
from skinsafe.core.safety.retraction import RetractionParams, limit, merge_paper, profile, profile_rate, retract_qdot


class DefensivenessLayer:
    """Reflexive retraction from tactile danger events, for one robot and its skin."""

    def __init__(self, kin: TaxelKinematics, thresholds: dict[str, np.ndarray], vel_limits, acc_limits,
                 params: RetractionParams | None = None):
        self.kin = kin
        self.params = params or RetractionParams()
        nv = kin.model.nv
        self.vel_limits = _positive(vel_limits, nv, "vel_limits")
        self.acc_limits = _positive(acc_limits, nv, "acc_limits")
        if not thresholds:
            raise ValueError("DefensivenessLayer: 'thresholds' is empty; pass the taxel map's thresholds "
                             "(design.taxels.thresholds), at least 'force'")
        self.thresholds = {}
        for name, th in thresholds.items():
            th = np.asarray(th, dtype=float)
            if th.shape != (kin.n,):
                raise ValueError(f"DefensivenessLayer: thresholds['{name}'] has shape {th.shape}, the skin has "
                                 f"{kin.n} taxels; pass one threshold per taxel")
            self.thresholds[name] = th
        self.reset()

    def reset(self) -> None:
        """Forget every retraction and the last command."""
        self._in_pool = np.zeros(self.kin.n, bool)
        # one row per retracting taxel: index, tau, peak severity alpha*f (m), p(tau) (3), z(tau) (3)
        self._state = np.zeros((0, 9))
        self.priorities = np.zeros(0)  # eq. 12, aligned with `pool`
        self.retracted = np.zeros(0)  # distance retracted so far along -z(tau), aligned with `pool`
        self.last = np.zeros(self.kin.model.nv)

    @property
    def active(self) -> bool:
        """True while any taxel is retracting."""
        return len(self._state) > 0

    @property
    def pool(self) -> np.ndarray:
        """Indices of the retracting taxels, highest priority first (as of the last tick)."""
        return self._state[:, 0].astype(np.intp)

    def tick(self, t: float, q: np.ndarray, readings: dict[str, np.ndarray], qdot_planned: np.ndarray | None = None,
             dt: float = 0.002) -> np.ndarray:
        """The joint velocity to command now: the merged retraction while any retraction is active
        (it outranks the plan), else the plan (zero without one); always within the velocity and
        acceleration limits (from the last command, `dt` seconds ago)."""
        p = self.params
        for name, value in readings.items():
            if np.shape(value) != (self.kin.n,):
                raise ValueError(f"DefensivenessLayer.tick: readings['{name}'] has shape {np.shape(value)}; "
                                 f"pass one (N,) array per stimulus with N = {self.kin.n}")
        events = danger_events(readings, self.thresholds)
        st = self._state
        over = t - st[:, 1] > p.T  # retractions that are over leave the pool
        if over.any():
            self._in_pool[st[over, 0].astype(np.intp)] = False
            st = st[~over]
        new = np.flatnonzero(events & ~self._in_pool)
        if len(st) + len(new) == 0:
            self._state, self.priorities, self.retracted = st, np.zeros(0), np.zeros(0)
            plan = np.zeros_like(self.last) if qdot_planned is None else np.asarray(qdot_planned, float)
            self.last = limit(plan, self.last, self.vel_limits, self.acc_limits, dt)
            return self.last.copy()
        idx = np.concatenate([st[:, 0].astype(np.intp), new])
        J, pos, frames = self._jacobians(idx, q)
        if len(new):
            self._in_pool[new] = True
            rows = np.empty((len(new), 9))
            rows[:, 0], rows[:, 1], rows[:, 2] = new, t, 0.0
            rows[:, 3:6], rows[:, 6:9] = pos[len(st):], frames[len(st):, :, 2]
            st = np.concatenate([st, rows])
        order, w, done, speed = _rank(st, pos, self._severity_now(readings, idx), t, p.T, p.max_distance)
        self._state, self.priorities, self.retracted = st[order], w, done
        qdot = self._merged(J[order], -self._state[:, 6:9], speed)
        self.last = limit(qdot, self.last, self.vel_limits, self.acc_limits, dt)
        return self.last.copy()

    def desired_distance(self) -> np.ndarray:
        """(K,) eq. 10's final distance `min(alpha f, 12 max_distance) / 12` of the pool's taxels."""
        return np.minimum(self._state[:, 2], 12 * self.params.max_distance) / 12

    def desired_displacement(self, t: float) -> np.ndarray:
        """(K,) eq. 10's displacement along -z at time t for the pool's taxels."""
        return 12 * self.desired_distance() * profile((t - self._state[:, 1]) / self.params.T)

    def _jacobians(self, idx: np.ndarray, q: np.ndarray):
        return self.kin.jacobians_of(idx, q)

    def _merged(self, J: np.ndarray, back: np.ndarray, speed: np.ndarray) -> np.ndarray:
        """Eq. 11 per taxel, then the prioritised merge (rows highest priority first)."""
        p = self.params
        if p.merge == "paper":
            return merge_paper(J, back, speed, p)
        return retract_qdot(J, back, speed, p)

    def _severity_now(self, readings: dict[str, np.ndarray], idx: np.ndarray) -> np.ndarray:
        out = np.zeros(len(idx))
        for name, value in readings.items():
            if name in self.thresholds:
                a = self.params.alpha_of(name)
                if a > 0:
                    out = np.fmax(out, a * np.asarray(value, float)[idx])
        return out  # fmax skips NaN readings; an infinite one is capped by max_distance


def _positive(x, n: int, name: str) -> np.ndarray:
    x = np.broadcast_to(np.asarray(x, dtype=float), (n,)).copy()
    if not np.all((x > 0) & np.isfinite(x)):
        raise ValueError(f"DefensivenessLayer: '{name}' must be {n} positive finite numbers (one per joint), got {x}")
    return x


@numba.njit(cache=True, nogil=True)
def _rank(st, pos, severity, t, T, max_distance):
    """Eq. 12 for the pool rows `st` (updated in place: peak severity): the priority order
    (stable, highest first) and, in that order, priorities, distances retracted and speeds."""
    K = st.shape[0]
    D, w, done = np.empty(K), np.empty(K), np.empty(K)
    for k in range(K):
        if severity[k] > st[k, 2]:
            st[k, 2] = severity[k]
        D[k] = min(st[k, 2], 12 * max_distance)
        done[k] = -((pos[k, 0] - st[k, 3]) * st[k, 6] + (pos[k, 1] - st[k, 4]) * st[k, 7]
                    + (pos[k, 2] - st[k, 5]) * st[k, 8])  # along -z(tau)
        w[k] = D[k] / 12 - done[k]
    order = np.argsort(-w, kind="mergesort")
    speed = np.empty(K)
    for i in range(K):
        k = order[i]
        speed[i] = D[k] * profile_rate((t - st[k, 1]) / T) / T
    return order, w[order], done[order], speed
