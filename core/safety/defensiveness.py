"""The tactile defensiveness layer (paper III-C): readings -> danger events -> active pool ->
the joint velocity to command, which outranks any planned motion.

Each tick: taxels whose stimulus exceeds its threshold (`events.danger_events`) and that are not
already retracting join the pool with their trigger time, position and normal; a retraction
lasts T and then leaves the pool (a taxel still in danger then triggers again). While a taxel
retracts, its severity is the peak `alpha_s * reading_s` over the stimuli above their thresholds
(the sensed force still rises for a few ms after the threshold is crossed). Only the pool's
Jacobians are computed. The maths is in `retraction.py` (eq. 10-13) and `qp.py` (the
prioritised QP with the no-push constraints); the limits in `limits.py`.

Viability (`viability.py`): besides the no-push rows at this tick's q, every command must leave
the arm able to brake, within its acceleration limits, without moving a contacted taxel into its
contact: the QP's hard rows (`rows`) are the no-push rows `A`, `b` and the viability rows `V`,
`c`, those that some command within the tick's limits could break.

Fail safe. A tick whose clock, q, planned command or dt is not finite gets the safe command
(`limits.brake`: every joint slows to zero at its acceleration limit) and a counted flag
(`flags`), never the plan; a non-finite reading is ignored for new events and blocks the plan
(the ongoing retraction goes on, its own inputs being finite; otherwise the safe command).
Missing data is a fault, never "no contact": a stimulus the skin reports (a key of `thresholds`)
that is absent from the readings (an empty dict, a missing key) or whose array is not one value
per taxel (a board's block cut off) is flagged `missing` and treated like a non-finite reading.
Nothing latches: the next finite tick starts from the safe command as its previous command. A
clock that goes backwards resets the pool. Every tick's outcome is in `info` (`TickInfo`).
"""
from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field

import numba
import numpy as np

from skinsafe.core.robot.kinematics import TaxelKinematics
from skinsafe.core.safety.limits import JointLimits, brake, finite, scale_into
from skinsafe.core.safety.qp import prioritised
from skinsafe.core.safety.retraction import (
    RetractionParams,
    merge_paper,
    profile,
    profile_rate,
    retract_qdot,
)
from skinsafe.core.safety.viability import check_joints, hard_rows

MAX_TASKS = 64
"""At most this many of the highest-priority contacts are retraction tasks (a 6- or 7-DoF arm has
no freedom left for more); every contacted taxel of the pool is still a no-push constraint."""


@dataclass
class TickInfo:
    """What one tick did. `nonfinite`: the inputs that were not finite; `missing`: the stimuli the
    skin reports that the readings lacked (absent, or not one value per taxel); `safe`: the safe command
    (brake) was sent; `limited`/`blocked`: a joint limit / another contact's no-push constraint
    held the dominant retraction back (`blocked` is the opposing-pinch case: the dominant taxel
    retracts less rather than push another one into its contact); `infeasible`: no command within
    the velocity and acceleration limits kept every contacted taxel out of its contact (the
    least-violating one was sent); `recovery_dropped`: a drifted
    taxel could not be pushed back this tick; `damped`: the dominant task is near a singularity;
    `pushing`: the measured joint velocity (`SafetyStack.tick(qdot=...)`) moved a contacted taxel
    into its contact (`push_speed`: the fastest, m/s along its normal); `solver_failed`: the retraction QP's
    solver gave up on the dominant level (the smallest command meeting every constraint was sent)."""

    nonfinite: tuple = ()
    missing: tuple = ()
    safe: bool = False
    clock_reset: bool = False
    retracting: bool = False
    limited: bool = False
    blocked: bool = False
    infeasible: bool = False
    recovery_dropped: bool = False
    damped: bool = False
    pushing: bool = False
    push_speed: float = 0.0
    solver_failed: bool = False
    dominant_residual: float = 0.0
    flags: tuple = field(default=())


class DefensivenessLayer:
    """Reflexive retraction from tactile danger events, for one robot and its skin."""

    def __init__(self, kin: TaxelKinematics, thresholds: dict[str, np.ndarray], vel_limits, acc_limits,
                 params: RetractionParams | None = None, dt: float | None = None, faults=None):
        """`dt`: the control period (s) the layer ticks at; required (the acceleration limits and
        the braking horizon scale with it; a tick may pass its own measured dt). `faults`: a run's fault plan
        (core/runtime/fault_plan.py): from its `stack-qp-fail` on, a retraction tick's solve reports failure."""
        self.kin = kin
        self.faults = faults
        self.params = params or RetractionParams()
        nv = kin.model.nv
        if dt is None:
            raise ValueError("DefensivenessLayer: give dt, the control period (s) the layer ticks at (the scene's "
                             "or the robot's control rate); it is never assumed")
        check_joints(kin.model)
        try:
            self.limits = JointLimits(np.broadcast_to(np.asarray(vel_limits, dtype=float), (nv,)),
                                      np.broadcast_to(np.asarray(acc_limits, dtype=float), (nv,)), dt)
        except ValueError as e:
            raise ValueError(f"DefensivenessLayer: {e} (the robot has {nv} joints)") from None
        if self.params.T < 10 * dt:
            raise ValueError(f"DefensivenessLayer: T = {self.params.T} s is under 10 control periods (dt = {dt} s): "
                             "eq. 10 cannot be followed in so few ticks; use T >= 10 dt (the paper: 0.5 s)")
        if not thresholds:
            raise ValueError("DefensivenessLayer: 'thresholds' is empty; pass the taxel map's thresholds "
                             "(design.taxels.thresholds), at least 'force'")
        self.thresholds = {}
        for name, th in thresholds.items():
            th = np.array(th, dtype=float)
            if th.shape != (kin.n,):
                raise ValueError(f"DefensivenessLayer: thresholds['{name}'] has shape {th.shape}, the skin has "
                                 f"{kin.n} taxels; pass one threshold per taxel")
            if not np.all(np.isfinite(th)):
                raise ValueError(f"DefensivenessLayer: thresholds['{name}'] has non-finite values; give finite "
                                 "thresholds (a taxel that must never trigger: a very large finite value)")
            th.flags.writeable = False
            self.thresholds[name] = th
        self.flags: Counter = Counter()
        self.reset()

    @property
    def vel_limits(self) -> np.ndarray:
        return self.limits.vel

    @property
    def acc_limits(self) -> np.ndarray:
        return self.limits.acc

    def reset(self) -> None:
        """Forget every retraction, the clock and the last command."""
        self._in_pool = np.zeros(self.kin.n, bool)
        # one row per retracting taxel: index, tau, peak severity alpha*f (m), p(tau) (3), z(tau) (3)
        self._state = np.zeros((0, 9))
        self.priorities = np.zeros(0)  # eq. 12, aligned with `pool`
        self.retracted = np.zeros(0)  # distance retracted so far along -z(tau), aligned with `pool`
        nv = self.kin.model.nv
        self.A, self.b = np.zeros((0, nv)), np.zeros(0)  # no-push rows A qd >= b of the pool, this tick
        self.V, self.c = self.A, self.b  # viability rows V qd >= c that can bind, this tick
        self.rows = (self.A, self.b)  # the hard rows that can bind this tick: no-push rows, then V, c
        self.last = np.zeros(nv)
        self._t = -np.inf
        self.info = TickInfo()

    @property
    def active(self) -> bool:
        """True while any taxel is retracting."""
        return len(self._state) > 0

    @property
    def pool(self) -> np.ndarray:
        """Indices of the retracting taxels, highest priority first (as of the last tick)."""
        return self._state[:, 0].astype(np.intp)

    def tick(self, t: float, q: np.ndarray, readings: dict[str, np.ndarray], qdot_planned: np.ndarray | None = None,
             dt: float | None = None, prev: np.ndarray | None = None) -> np.ndarray:
        """The joint velocity to command now: the prioritised retraction while any retraction is
        active (it outranks the plan), else the plan (zero without one); always within the
        velocity and acceleration limits from `prev` (default: this layer's last command), `dt`
        seconds ago (default: the construction's dt). Fail-safe rules: module docstring."""
        p, nv = self.params, self.kin.model.nv
        prev = self.last if prev is None else np.asarray(prev, dtype=float)
        prev = prev if finite(prev) else np.where(np.isfinite(prev), prev, 0.0)
        dt = self.limits.dt if dt is None else float(dt)
        q = np.asarray(q, dtype=float)
        if q.shape != (self.kin.model.nq,):
            raise ValueError(f"DefensivenessLayer.tick: q has shape {q.shape}; pass the robot's {self.kin.model.nq} "
                             "joint positions")
        bad, clean, missing = [], {}, []
        readings = {} if readings is None else readings
        for name in self.thresholds:
            value = readings.get(name)
            value = None if value is None else np.asarray(value, dtype=float)
            if value is None or value.shape != (self.kin.n,):  # a silent board: a fault, never "no contact"
                missing.append(name)
                continue
            if not finite(value):
                bad.append(f"readings:{name}")
                value = np.where(np.isfinite(value), value, -np.inf)  # a non-finite reading never triggers
            clean[name] = value
        bad += [f"readings:{name}" for name, value in readings.items()
                if name not in self.thresholds and not finite(value)]
        plan = None if qdot_planned is None else np.asarray(qdot_planned, dtype=float)
        if plan is not None and not finite(plan):
            bad.append("command")
        fatal = [n for n, ok in (("clock", finite(t)), ("q", finite(q)), ("dt", finite(dt) and dt > 0)) if not ok]
        clock_reset = not fatal and t < self._t
        if clock_reset:
            last = prev
            self.reset()
            prev = last
            self.flags["clock_reset"] += 1
        if fatal:
            return self._finish(brake(prev, self.limits), TickInfo(nonfinite=tuple(fatal + bad), missing=tuple(missing),
                                                                   safe=True), prev)
        self._t = t
        st = self._state
        if len(st):
            over = t - st[:, 1] > p.T  # retractions that are over leave the pool
            if over.any():
                self._in_pool[st[over, 0].astype(np.intp)] = False
                st = st[~over]
        events = np.zeros(self.kin.n, bool)  # above a threshold and not retracting already
        for name, value in clean.items():
            if name in self.thresholds:
                _mark_over(value, self.thresholds[name], self._in_pool, len(st) > 0, events)
        new = np.flatnonzero(events)
        faulty = bool(bad or missing)
        if len(st) + len(new) == 0:
            self._state, self.priorities, self.retracted = st, np.zeros(0), np.zeros(0)
            self.A, self.b = np.zeros((0, nv)), np.zeros(0)
            self.V, self.c = self.A, self.b
            self.rows = (self.A, self.b)
            info = TickInfo(nonfinite=tuple(bad), missing=tuple(missing), safe=faulty, clock_reset=clock_reset)
            if faulty:
                return self._finish(brake(prev, self.limits, dt), info, prev)
            return self._finish(scale_into(np.zeros(nv) if plan is None else plan, prev, self.limits, dt),
                                info, prev)
        idx = np.concatenate([st[:, 0].astype(np.intp), new])
        J, pos, frames = self._jacobians(idx, q)
        if len(new):
            self._in_pool[new] = True
            rows = np.empty((len(new), 9))
            rows[:, 0], rows[:, 1], rows[:, 2] = new, t, 0.0
            rows[:, 3:6], rows[:, 6:9] = pos[len(st):], frames[len(st):, :, 2]
            st = np.concatenate([st, rows])
        six = p.form == "6d"
        order, w, done, speed, self.A, self.b, Jt, rt = _rank(st, pos, self._severity_now(clean, idx), t, p.T,
                                                              p.max_distance, J, six, p.recovery_gain, MAX_TASKS)
        self._state, self.priorities, self.retracted = st[order], w, done
        info = TickInfo(nonfinite=tuple(bad), missing=tuple(missing), clock_reset=clock_reset, retracting=True)
        if p.merge != "qp":  # the closed-form references, limited as before (uniform scaling)
            self.V, self.c = self.A[:0], self.b[:0]
            self.rows = (self.A, self.b)
            return self._finish(scale_into(self._merged(J[order], -self._state[:, 6:9], speed), prev, self.limits, dt),
                                info, prev)
        lo, hi = self.limits.box(prev, dt)
        A, b, n_push = hard_rows(J, order, self._state, self.A, self.b, prev, lo, hi, self.limits.acc, dt)
        self.rows, self.V, self.c = (A, b), A[n_push:], b[n_push:]
        A, b = _distinct_rows(A, b) if len(A) > MAX_TASKS else (A, b)
        sol = prioritised(Jt, rt, A, b, lo, hi, self.limits.vel, p.damping, p.sv_threshold, p.rank_tol)
        if self.faults is not None and self.faults.due("stack-qp-fail"):
            sol.solver_failed = True
        for name in ("limited", "blocked", "infeasible", "recovery_dropped", "damped", "dominant_residual",
                     "solver_failed"):
            setattr(info, name, getattr(sol, name))
        return self._finish(sol.qd, info, prev)

    def _finish(self, out: np.ndarray, info: TickInfo, prev: np.ndarray) -> np.ndarray:
        flags = [f"nonfinite:{n}" for n in info.nonfinite] + (["nonfinite"] if info.nonfinite else [])
        flags += [f"missing:{n}" for n in info.missing] + (["missing"] if info.missing else [])
        flags += [n for n in ("safe", "infeasible", "recovery_dropped", "blocked", "solver_failed") if getattr(info, n)]
        if flags:
            self.flags.update(flags)
        info.flags = tuple(flags)
        self.info, self.last = info, out
        return out.copy()

    def desired_distance(self) -> np.ndarray:
        """(K,) eq. 10's final distance `min(alpha f, 12 max_distance) / 12` of the pool's taxels."""
        return np.minimum(self._state[:, 2], 12 * self.params.max_distance) / 12

    def desired_displacement(self, t: float) -> np.ndarray:
        """(K,) eq. 10's displacement along -z at time t for the pool's taxels."""
        return 12 * self.desired_distance() * profile((t - self._state[:, 1]) / self.params.T)

    def _jacobians(self, idx: np.ndarray, q: np.ndarray):
        return self.kin.jacobians_of(idx, q)

    def _merged(self, J: np.ndarray, back: np.ndarray, speed: np.ndarray) -> np.ndarray:
        """The closed-form references: eq. 11 per taxel, then the merge (rows highest priority first)."""
        p = self.params
        if p.merge == "paper":
            return merge_paper(J, back, speed, p)
        return retract_qdot(J, back, speed, p)

    def _severity_now(self, readings: dict[str, np.ndarray], idx: np.ndarray) -> np.ndarray:
        """Per pool taxel, max over the stimuli above their thresholds of alpha_s * reading_s."""
        out = np.zeros(len(idx))
        for name, value in readings.items():
            a = self.params.alpha_of(name)
            if name in self.thresholds and a > 0:
                v = value[idx]
                out = np.maximum(out, np.where(v > self.thresholds[name][idx], a * v, 0.0))
        return out


def _distinct_rows(A: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The no-push rows of a large pool without near-duplicates (same direction to 1e-9 after
    normalising; the largest b kept): the same feasible set, far fewer QP rows."""
    scale = np.linalg.norm(A, axis=1)
    use = scale > 0
    A, b, scale = A[use], b[use], scale[use]
    key = np.round(A / scale[:, None], 9)
    _, inv = np.unique(key, axis=0, return_inverse=True)
    inv = inv.ravel()
    first = np.full(inv.max() + 1 if len(inv) else 0, -1)
    first[inv[::-1]] = np.arange(len(inv))[::-1]
    bmax = np.zeros(len(first))
    np.maximum.at(bmax, inv, b / scale)
    return A[first], bmax * scale[first]


@numba.njit(cache=True, nogil=True)
def _mark_over(value, threshold, in_pool, skip_pool, events):
    """`events |= (value > threshold) & ~in_pool` (`in_pool` only with `skip_pool`), in place:
    one pass over the skin, no temporaries."""
    for i in range(value.shape[0]):
        if value[i] > threshold[i] and not (skip_pool and in_pool[i]):
            events[i] = True


@numba.njit(cache=True, nogil=True)
def _rank(st, pos, severity, t, T, max_distance, J, six, recovery_gain, max_tasks):
    """Eq. 12 for the pool rows `st` (updated in place: peak severity): the priority order
    (stable, highest first) and, in that order, priorities, distances retracted and speeds; then
    the no-push rows `A qd >= b` (a_k = J_p,k^T d_k, d_k = -z_k(tau): speed along the retraction
    axis; b pushes back what drifted in) and the tasks of the first `max_tasks` (task Jacobians
    (m, 3 or 6, nv) and their eq. 10 velocities along d_k, zero rotation in 6-D)."""
    K, nv = st.shape[0], J.shape[2]
    D, w, done = np.empty(K), np.empty(K), np.empty(K)
    for k in range(K):
        if severity[k] > st[k, 2]:
            st[k, 2] = severity[k]
        D[k] = min(st[k, 2], 12 * max_distance)
        done[k] = -((pos[k, 0] - st[k, 3]) * st[k, 6] + (pos[k, 1] - st[k, 4]) * st[k, 7]
                    + (pos[k, 2] - st[k, 5]) * st[k, 8])  # along -z(tau)
        w[k] = D[k] / 12 - done[k]
    order = np.argsort(-w, kind="mergesort")
    m, rows = min(K, max_tasks), 6 if six else 3
    speed, A, b = np.empty(K), np.zeros((K, nv)), np.empty(K)
    Jt, rt = np.zeros((m, rows, nv)), np.zeros((m, rows))
    for i in range(K):
        k = order[i]
        speed[i] = D[k] * profile_rate((t - st[k, 1]) / T) / T
        b[i] = min(recovery_gain * max(-done[k], 0.0), 0.05)  # push back what drifted in
        for c in range(3):
            for j in range(nv):
                A[i, j] -= J[k, c, j] * st[k, 6 + c]
        if i < m:
            for c in range(3):
                rt[i, c] = -st[k, 6 + c] * speed[i]
            for c in range(rows):
                for j in range(nv):
                    Jt[i, c, j] = J[k, c, j]
    return order, w[order], done[order], speed, A, b, Jt, rt
