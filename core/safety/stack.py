"""The three safety layers as one filter for any command source (paper Fig. 2).

A command source is anything callable as `source(t, q) -> qdot_planned (nv,)`: a planner
(`TrajectorySource`, joint-space tracking of q_d(t)) or a teleoperation stream
(`TeleopStream`, a recorded leader-arm trajectory replayed with its latency). Every tick,
`SafetyStack.tick(t, q, readings, command, dt)`:

1. strategy (III-A): the planned velocity is one of a few candidates (the command and slower
   versions of it, down to stop) with a prior p(a|s) that prefers the command; eq. 3 re-weights
   them by the TDM's p(not D | s, a) and the most probable candidate (MAP) is kept - the argmax
   of `log p(a|s) + log p(not D|s,a)`, as eq. 3's denominator does not depend on a;
2. tactile defensiveness (III-C): a retraction, when active, outranks the plan;
3. modulation (III-B): whatever comes out - plan or retraction - is modulated by the danger
   potential (`ModulationLayer`; a retraction leaving danger keeps its speed, one heading into
   danger, e.g. toward a desk, is slowed), then (optional `pfl`) capped so no taxel approaches
   faster than ISO/TS 15066 allows (`pfl.PFLCap`), then scaled into the joint velocity limits.

Each layer is optional. The potential and the TDM see the state `s = q[joints]` and the action
`a = qdot[joints]` (`joints` default: all).
"""
from __future__ import annotations

from typing import Callable

import numpy as np

from skinsafe.core.safety.modulation import ModulationLayer

CommandSource = Callable[[float, np.ndarray], np.ndarray]

SCALES = (1.0, 0.5, 0.0)
PRIOR = (0.9, 0.07, 0.03)


class TrajectorySource:
    """A planner: track q_d(t) with `qd_d(t) + gain * clip(q_d - q, +-max_error)`."""

    def __init__(self, desired: Callable[[float], tuple[np.ndarray, np.ndarray]], gain: float = 3.0,
                 max_error: float = 0.15):
        self.desired, self.gain, self.max_error = desired, float(gain), float(max_error)

    def __call__(self, t: float, q: np.ndarray) -> np.ndarray:
        qd, vd = self.desired(t)
        return vd + self.gain * np.clip(qd - q, -self.max_error, self.max_error)


class TeleopStream:
    """A teleoperation stream: leader joint targets recorded at `times` (s), replayed `latency`
    seconds late and tracked like a planner (linear interpolation, finite-difference rate)."""

    def __init__(self, times, targets, latency: float = 0.0, gain: float = 3.0, max_error: float = 0.15):
        self.times = np.asarray(times, dtype=float)
        self.targets = np.asarray(targets, dtype=float)
        if self.times.ndim != 1 or len(self.times) < 2 or self.targets.shape[0] != len(self.times):
            raise ValueError(f"TeleopStream: got {self.times.shape} times and {self.targets.shape} targets; "
                             "give at least two samples, one target row per time")
        if np.any(np.diff(self.times) <= 0):
            raise ValueError("TeleopStream: times must increase strictly (sort the recording)")
        self.rates = np.gradient(self.targets, self.times, axis=0)
        self.latency = float(latency)
        self.track = TrajectorySource(self._at, gain, max_error)

    def _at(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        t = float(np.clip(t - self.latency, self.times[0], self.times[-1]))
        q = np.array([np.interp(t, self.times, c) for c in self.targets.T])
        i = min(int(np.searchsorted(self.times, t)), len(self.times) - 1)
        return q, self.rates[i]

    def __call__(self, t: float, q: np.ndarray) -> np.ndarray:
        return self.track(t, q)


class StrategyFilter:
    """Eq. 3 over the candidates `scale * command` (SCALES) with a prior favouring the command."""

    def __init__(self, tdm, scales=SCALES, prior=PRIOR):
        from skinsafe.core.safety.potential import DangerPotential, FastPotential

        self.fast = FastPotential(DangerPotential(tdm))
        self.scales = np.asarray(scales, dtype=float)
        prior = np.asarray(prior, dtype=float)
        if prior.shape != self.scales.shape or (prior <= 0).any():
            raise ValueError(f"StrategyFilter: give one positive prior weight per scale ({len(self.scales)})")
        self.log_prior = np.log(prior / prior.sum())
        self.order = np.argsort(-self.log_prior, kind="stable")

    def __call__(self, s: np.ndarray, a: np.ndarray) -> np.ndarray:
        """The MAP candidate. The candidate with the highest prior is scored first; the others
        only when one of them could still beat it (log p(not D) <= 0 can only lower a score), all
        in one batch: the same argmax, usually from one TDM evaluation. A NaN safety counts as
        certain danger; ties go to the higher prior."""
        first, rest = self.order[0], self.order[1:]
        best = self.scales[first] * a
        score = self._scores(s, best[None], self.log_prior[first:first + 1])[0]
        if len(rest) == 0 or score >= self.log_prior[rest].max():
            return best
        cand = self.scales[rest, None] * a
        scores = self._scores(s, cand, self.log_prior[rest])
        k = int(np.argmax(scores))
        return cand[k] if scores[k] > score else best

    def _scores(self, s, cand, log_prior):
        log_safe = self.fast.log_safety(np.broadcast_to(s, (len(cand), len(s))), cand)
        return log_prior + np.where(np.isnan(log_safe), -np.inf, log_safe)


class SafetyStack:
    """Strategy filter -> defensiveness -> modulation -> limits, for one robot and its skin."""

    def __init__(self, vel_limits, defensiveness=None, modulation: ModulationLayer | None = None,
                 strategy: StrategyFilter | None = None, joints=None, pfl=None):
        self.vel_limits = np.asarray(vel_limits, dtype=float)
        self.pfl = pfl  # optional ISO/TS 15066 speed cap `pfl(q, qdot) -> qdot` (pfl.PFLCap), after modulation
        self.defensiveness, self.modulation, self.strategy = defensiveness, modulation, strategy
        self.joints = np.arange(len(self.vel_limits)) if joints is None else np.asarray(joints)
        self.last_f = 0.0

    def tick(self, t: float, q: np.ndarray, readings: dict[str, np.ndarray] | None, command: np.ndarray,
             dt: float) -> np.ndarray:
        """The joint velocity to send now."""
        j = self.joints
        v = np.array(command, dtype=float)
        if not np.all(np.isfinite(v)):
            v = np.zeros_like(v)  # a broken command source never moves the robot
        s = q[j]
        if self.strategy is not None:
            v[j] = self.strategy(s, v[j])
        if self.defensiveness is not None:
            v = self.defensiveness.tick(t, q, readings or {}, v, dt)
        if self.modulation is not None:
            v[j], self.last_f = self.modulation(s, v[j])
        if self.pfl is not None:
            v = self.pfl(q, v)
        peak = float(np.max(np.abs(v) / self.vel_limits))
        return v / peak if peak > 1 else v

    def run(self, source: CommandSource, t: float, q: np.ndarray, readings, dt: float) -> np.ndarray:
        """One tick for a command source (planner or teleoperation stream)."""
        return self.tick(t, q, readings, source(t, q), dt)
