"""The three safety layers as one filter for any command source (paper Fig. 2).

A command source is anything callable as `source(t, q) -> qdot_planned (nv,)`: a planner
(`TrajectorySource`, joint-space tracking of q_d(t)) or a teleoperation stream
(`TeleopStream`, a recorded leader-arm trajectory replayed with its latency). Every tick,
`SafetyStack.tick(t, q, readings, command, dt)`:

1. strategy (III-A): the planned velocity is one of a few candidates (the command and slower
   versions of it, down to stop) with a prior p(a|s) that prefers the command; eq. 3 re-weights
   them by the TDM's p(not D | s, a) and the most probable candidate (MAP) is kept - the argmax
   of `log p(a|s) + log p(not D|s,a)`, as eq. 3's denominator does not depend on a;
2. tactile defensiveness (III-C): a retraction, when active, outranks the plan (the layer runs
   first, and the strategy filter only on ticks without a retraction, whose plan is used);
3. modulation (III-B): whatever comes out - plan or retraction - is modulated by the danger
   potential (`ModulationLayer`; a retraction leaving danger keeps its speed, one heading into
   danger, e.g. toward a desk, is slowed). With the modulation's `stop` level, a retraction never
   carries the arm into an obstacle the potential knows: while the potential's rise along the
   brake from this command (`S n.v`, S the braking horizon of `viability.braking_horizon`) would
   pass `stop - f`, the retraction is scaled down as a whole (direction kept), so the arm stops
   before the potential reaches `stop` rather than sliding along a level set. With a strategy
   filter over the same TDM, both share one evaluator (`FastPotential`): scoring the candidates
   is one forward pass over the TDM's head that keeps its sigmoids, and the modulation of the
   chosen one needs only the backward pass (the planned command unlimited until step 4); a
   retraction's modulation is one fused pass;
4. limits (`limits.final_command`) on the final command: velocity and acceleration limits from
   the last command sent; while taxels are retracting, also their no-push and viability rows
   (the modulated command is projected, so modulation can never push a contacted taxel into its
   contact, the acceleration limit never makes one move into it, and the arm can always brake
   without pushing one: `viability.py`).

Measured velocity: `tick(..., qdot=measured)` takes the robot's measured joint velocity, distinct
from the planned command. The acceleration limits (and the brake) start from the last command sent,
as ros2_control's joint limits and libfranka's `limitRate` do: started from the measured velocity,
a servo that lags the command by tau lets the arm gain only acc * dt / tau (the sim's UR5 servo, 60 ms:
0.5 of its 15 rad/s^2). The measured velocity is checked (non-finite: the brake), sets the braking
horizon where it is the faster (step 3), goes to the PFL cap (an arm faster than its command, its servo
lagging a braking one, brakes from its own speed: `pfl.PFLCap`), and while taxels retract a measured
motion that carries one of them into its contact (`a_k . qdot < 0`) is flagged `pushing`.

Fail safe: a tick with a non-finite clock, q, dt, measured velocity, planned command, reading, TDM output or
potential sends the safe command (`limits.brake`) or, where its own inputs are finite, the
ongoing retraction (unmodulated when the potential is the bad input), never the plan, and counts
the input in `flags`; `info` says what happened. A clock that goes backwards resets the layers.
Missing readings (no readings, a stimulus the skin reports left out, an array that is not one
value per taxel) are a fault of the same kind where the stack has a defensiveness layer (flag
`missing`): never "no contact".

dt: the stack is built for a control period (`dt`, required, equal to its defensiveness layer's)
and every tick passes its own measured dt, which the acceleration limits and the brake use.

Each layer is optional. The potential and the TDM see the state `s = q[joints]` and the action
`a = qdot[joints]` (`joints` default: all).
"""
from __future__ import annotations

from collections import Counter
from typing import Callable

import numpy as np

from skinsafe.core.safety.defensiveness import TickInfo
from skinsafe.core.safety.limits import JointLimits, brake, final_command, finite
from skinsafe.core.safety.modulation import ModulationLayer
from skinsafe.core.safety.viability import braking_horizon

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

        self.tdm = tdm
        self.fast = FastPotential(DangerPotential(tdm))
        self.scales = np.asarray(scales, dtype=float)
        prior = np.asarray(prior, dtype=float)
        if prior.shape != self.scales.shape or (prior <= 0).any():
            raise ValueError(f"StrategyFilter: give one positive prior weight per scale ({len(self.scales)})")
        self.log_prior = np.log(prior / prior.sum())
        self.order = np.argsort(-self.log_prior, kind="stable")
        rest = self.order[1:]
        self._rest = (self.scales[rest, None], self.log_prior[rest], self.log_prior[rest].max() if len(rest) else 0.0)
        self.nonfinite = False  # the last call met a non-finite TDM output (and chose to stop)

    def __call__(self, s: np.ndarray, a: np.ndarray) -> np.ndarray:
        """The MAP candidate. The candidate with the highest prior is scored first; the others
        only when one of them could still beat it (log p(not D) <= 0 can only lower a score), all
        in one batch: the same argmax, usually from one TDM evaluation; ties go to the higher
        prior. A non-finite TDM output (NaN or infinite log-safety) for any scored candidate
        returns a stop (zeros) and sets `nonfinite`."""
        self.nonfinite = False
        first = self.order[0]
        rest_scales, rest_prior, rest_max = self._rest
        best = self.scales[first] * a
        score = self._scores(s, best[None], self.log_prior[first:first + 1])[0]
        if self.nonfinite:
            return np.zeros_like(a)
        if len(rest_prior) == 0 or score >= rest_max:
            return best
        cand = rest_scales * a
        scores = self._scores(s, cand, rest_prior)
        if self.nonfinite:
            return np.zeros_like(a)
        k = int(np.argmax(scores))
        return cand[k] if scores[k] > score else best

    def _scores(self, s, cand, log_prior):
        log_safe = np.asarray(self.fast.log_safety(np.asarray(s, dtype=float)[None], cand), dtype=float)  # one state, all candidates
        if not finite(log_safe):
            self.nonfinite = True
        return log_prior + log_safe


class SafetyStack:
    """Strategy filter -> defensiveness -> modulation -> limits, for one robot and its skin.

    `dt` is the control period the stack ticks at (s): required, never assumed, and equal to the
    defensiveness layer's. `acc_limits` default to the defensiveness layer's (no acceleration
    limit without one); `vel_limits` are the robot's."""

    def __init__(self, vel_limits, defensiveness=None, modulation: ModulationLayer | None = None,
                 strategy: StrategyFilter | None = None, joints=None, acc_limits=None, dt: float | None = None,
                 pfl=None, faults=None):
        """`faults`: a run's fault plan (core/runtime/fault_plan.py), for tests and the fault bench: from its
        `stack-nan` on, the command returned is non-finite (what the stack keeps as sent is not)."""
        vel = np.asarray(vel_limits, dtype=float)
        self.faults = faults
        d = defensiveness
        if dt is None:
            raise ValueError("SafetyStack: give dt, the control period (s) the stack ticks at (the scene's or the "
                             "robot's control rate); it is never assumed")
        if d is not None and not np.isclose(dt, d.limits.dt, rtol=1e-9, atol=0.0):
            raise ValueError(f"SafetyStack: dt is {dt} s but the defensiveness layer was built for {d.limits.dt} s; "
                             "build both for the period the scene runs at")
        acc = (d.limits.acc if d is not None else np.inf) if acc_limits is None else acc_limits
        self.limits = JointLimits(vel, np.broadcast_to(np.asarray(acc, dtype=float), vel.shape), dt)
        if d is not None and d.kin.model.nv != len(vel):
            raise ValueError(f"SafetyStack: 'vel_limits' has {len(vel)} values, the defensiveness layer's robot "
                             f"{d.kin.model.nv} joints; give one limit per joint")
        self.defensiveness, self.modulation, self.strategy = defensiveness, modulation, strategy
        self.pfl = pfl  # optional ISO/TS 15066 speed cap `pfl(q, v, measured qdot or None) -> v` (pfl.PFLCap)
        if strategy is not None and modulation is not None:
            from skinsafe.core.safety.potential import FastPotential

            if isinstance(modulation._eval, FastPotential) and getattr(modulation.potential, "tdm", None) is strategy.tdm:
                strategy.fast = modulation._eval  # one evaluator: the modulation reads the chosen candidate's normal
        self.joints = np.arange(len(vel)) if joints is None else np.asarray(joints)
        self.flags: Counter = Counter()
        self.reset()

    @property
    def vel_limits(self) -> np.ndarray:
        return self.limits.vel

    def reset(self) -> None:
        """Forget the last command, the clock and every layer's state."""
        self.last = np.zeros(len(self.limits.vel))
        self.last_f = 0.0
        self._t = -np.inf
        self.info = TickInfo()
        if self.defensiveness is not None:
            self.defensiveness.reset()

    def tick(self, t: float, q: np.ndarray, readings: dict[str, np.ndarray] | None, command: np.ndarray,
             dt: float, qdot: np.ndarray | None = None) -> np.ndarray:
        """The joint velocity to send now (module docstring), `dt` seconds (measured) after the last
        tick. `qdot`: the robot's measured joint velocity, if known: checked and watched for pushing (module
        docstring); the limits start from the last command sent either way."""
        j, d, prev = self.joints, self.defensiveness, self.last
        q = np.asarray(q, dtype=float)
        v = np.array(command, dtype=float)
        checks = [("clock", t), ("q", q), ("dt", dt if finite(dt) and dt > 0 else np.nan), ("command", v)]
        if qdot is not None:
            qdot = np.asarray(qdot, dtype=float)
            if qdot.shape != prev.shape:
                raise ValueError(f"SafetyStack.tick: qdot has shape {qdot.shape}; pass the robot's {len(prev)} "
                                 "measured joint velocities (or None)")
            checks.append(("qdot", qdot))
        bad = [n for n, x in checks if not finite(x)]
        bad += [f"readings:{n}" for n, x in (readings or {}).items() if not finite(x)]
        if "clock" not in bad and t < self._t:  # the clock went backwards: start again
            self.reset()
            self.last = prev
            self.flags["clock_reset"] += 1
        if {"clock", "q", "dt", "qdot"} & set(bad):
            return self._send(brake(prev, self.limits, None if "dt" in bad else dt),
                              TickInfo(nonfinite=tuple(bad), safe=True))
        self._t = t
        plan_ok = not bad
        s = q[j]
        info = TickInfo(nonfinite=tuple(bad))
        if d is not None:
            vd = d.tick(t, q, readings, None, dt, prev=prev)
            info = d.info
            info.nonfinite = tuple(bad + [n for n in info.nonfinite if n not in bad])
            if info.safe:
                return self._send(vd, info)
        retracting = d is not None and d.active
        if retracting:  # the retraction outranks the plan: no strategy filter needed this tick
            v = vd
        else:
            if self.strategy is not None and plan_ok:
                v[j] = self.strategy(s, v[j])
                if self.strategy.nonfinite:
                    bad.append("tdm")
                    info.nonfinite = info.nonfinite + ("tdm",)
                    plan_ok = False
            if not plan_ok:
                return self._send(brake(prev, self.limits, dt), TickInfo(nonfinite=info.nonfinite, safe=True))
        if self.modulation is not None:
            w = v.copy()
            w[j], f = self.modulation(s, v[j])
            self.last_f = f
            if not (self.modulation.finite and finite(w)):
                info.nonfinite = info.nonfinite + ("potential",)
                if not retracting:
                    return self._send(brake(prev, self.limits, dt), TickInfo(nonfinite=info.nonfinite, safe=True))
            else:
                v = w
                if retracting and self.modulation.stop is not None:
                    faster = prev if qdot is None else np.where(np.abs(qdot) > np.abs(prev), qdot, prev)
                    v = self._stop_short(v, faster, f, dt)
        if self.pfl is not None:
            v = self.pfl(q, v, qdot)
        A, b = d.rows if retracting else (None, None)
        proj = final_command(v, prev, self.limits, A, b, dt=dt)
        info.infeasible = info.infeasible or proj.infeasible
        if qdot is not None and retracting:  # the robot is moving a contacted taxel into its contact now
            into = -(d.A @ qdot)
            info.push_speed = float(into.max()) if len(into) and into.max() > 0 else 0.0
            info.pushing = info.push_speed > 1e-9
        return self._send(proj.v, info)

    def _stop_short(self, v: np.ndarray, prev: np.ndarray, f: float, dt: float) -> np.ndarray:
        """The retraction `v`, scaled down as a whole so that the potential's rise along the brake
        from it, `S n.v`, stays within `stop - f` (module docstring, step 3)."""
        rise = float(np.asarray(self.modulation.normal, dtype=float).reshape(-1) @ v[self.joints])
        room = max(self.modulation.stop - float(f), 0.0)
        S = braking_horizon(prev, self.limits.acc, dt)
        return v * (room / (rise * S)) if rise * S > room else v

    def _send(self, v: np.ndarray, info: TickInfo) -> np.ndarray:
        flags = [f"nonfinite:{n}" for n in info.nonfinite] + (["nonfinite"] if info.nonfinite else [])
        flags += [f"missing:{n}" for n in info.missing] + (["missing"] if info.missing else [])
        flags += [n for n in ("safe", "infeasible", "pushing") if getattr(info, n)]
        if flags:
            self.flags.update(flags)
        info.flags = tuple(flags)
        self.info, self.last = info, v
        if self.faults is not None and self.faults.due("stack-nan"):
            return np.full_like(v, np.nan)
        return v.copy()

    def run(self, source: CommandSource, t: float, q: np.ndarray, readings, dt: float,
            qdot: np.ndarray | None = None) -> np.ndarray:
        """One tick for a command source (planner or teleoperation stream)."""
        return self.tick(t, q, readings, source(t, q), dt, qdot)
