"""The one command limiter after the layers: what it returns is what the driver sends and the record holds.

All joints at once, from the last command sent: position (never toward a joint limit faster than the
arm can stop before it, |qd| <= sqrt(2 qdd_max d)), velocity, acceleration and, where the robot
states a jerk limit (the FR3), libfranka's `limitRate` rule with its margin. The runtime tells the
stack what was sent (its next tick's limits and no-push rows start from it), and a replay runs the
same limiter from the record's configuration. Both drivers get its output and send it unchanged; each
rate-limits only its own stop's ramp to zero (the same `rate_limit`, core/robot/rate_limit.py). A driver whose
`limits()` names position-dependent velocity bounds (`qd_bounds`: "fr3", libfranka's, see `fr3_velocity_bounds`) has
every joint kept inside them too, and the name goes into the record so a replay uses the same bounds. numpy only (hardware/ imports it).

It cannot emit a non-finite command: the rate limits run at the driver's command period (`period_s`: one command
goes out per period whatever the robot's clock says, libfranka's kDeltaT) or, without one, at the measured dt kept
within [DT_MIN, DT_MAX] (0, negative or non-finite: DT_MIN, the last command held); a non-finite layers' velocity
asks that joint for 0, and a joint whose measured position is not finite is brought to 0 (its bound is unknown).
"""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from skinsafe.core.robot.rate_limit import MARGIN, rate_limit

KEYS = ("q_min", "q_max", "qd_max", "qdd_max", "qddd_max")
DT_MIN, DT_MAX = 1e-5, 0.05  # s: the rate limits' step without a command period (the sim's shortest period / 20 and
# its longest)

# libfranka 0.21.3, include/franka/rate_limiting.h (Apache-2.0, Copyright (c) 2023 Franka Robotics GmbH),
# computeUpperLimitsJointVelocity / computeLowerLimitsJointVelocity (the FR3's, after
# https://frankarobotics.github.io/docs/control_parameters.html#limits-for-franka-research-3), per joint:
#   upper = min(v_max, max(0, -offset + sqrt(max(0, k * (q_upper - q))))) - kJointVelocityLimitsTolerance
#   lower = max(-v_max, min(0, offset - sqrt(max(0, k * (q - q_lower))))) + kJointVelocityLimitsTolerance
# with kJointVelocityLimitsTolerance = kLimitEps (1e-3; no packets lost on the FR3) and these constants:
_FR3_V_MAX = np.array([2.62, 2.62, 2.62, 2.62, 5.26, 4.18, 5.26])
_FR3_OFFSET = np.array([0.30, 0.20, 0.20, 0.30, 0.35, 0.35, 0.35])
_FR3_K = np.array([12.0, 5.17, 7.00, 8.00, 34.0, 11.0, 34.0])  # 2 x the joint's deceleration limit
_FR3_Q_UPPER = np.array([2.75010, 1.79180, 2.90650, -0.1458, 2.81010, 4.52050, 3.01960])
_FR3_Q_LOWER = np.array([-2.750100, -1.791800, -2.906500, -3.048100, -2.810100, 0.54092, -3.019600])


def fr3_velocity_bounds(q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """libfranka's position-dependent FR3 joint velocity limits at q (7,): (lower, upper), rad/s."""
    with np.errstate(over="ignore", invalid="ignore"):
        return _fr3_bounds(q)


def _fr3_bounds(q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    up = np.minimum(_FR3_V_MAX, np.maximum(0.0, -_FR3_OFFSET + np.sqrt(np.maximum(0.0, _FR3_K * (_FR3_Q_UPPER - q)))))
    lo = np.maximum(-_FR3_V_MAX, np.minimum(0.0, _FR3_OFFSET - np.sqrt(np.maximum(0.0, _FR3_K * (q - _FR3_Q_LOWER)))))
    return lo + MARGIN, up - MARGIN


BOUNDS = {"fr3": fr3_velocity_bounds}  # a driver's `qd_bounds` name -> its position-dependent velocity bounds


@dataclass(frozen=True, eq=False)
class JointLimits(Mapping):
    """A driver's joint limits, validated once where the runtime takes them (as ros2_control's joint_limits): q_min,
    q_max (rad; +-inf where a joint has none), qd_max, qdd_max (> 0, finite) and, where the robot states one,
    qddd_max; qd_bounds names position-dependent velocity bounds (BOUNDS). It reads like the driver's dict too
    (limits["qd_max"]), which the command sources and a record's configuration use."""

    q_min: np.ndarray
    q_max: np.ndarray
    qd_max: np.ndarray
    qdd_max: np.ndarray
    qddd_max: np.ndarray | None = None
    qd_bounds: str | None = None

    def __post_init__(self):
        n = None
        for k in KEYS:
            x = getattr(self, k)
            if x is None and k == "qddd_max":
                continue
            a = np.array(x, dtype=float).reshape(-1) if np.ndim(x) else np.array([x], float)
            n = len(a) if n is None else n
            if not len(a) or len(a) != n:
                raise ValueError(f"joint limits: {k} has {len(a)} values, q_min {n}; give one per joint")
            bad = np.flatnonzero(np.isnan(a) if k in ("q_min", "q_max") else ~(np.isfinite(a) & (a > 0)))
            if len(bad):
                raise ValueError(f"joint limits: {k}[{bad[0]}] is {a[bad[0]]}; give each joint's "
                                 + ("position limit (inf where it has none)" if k in ("q_min", "q_max") else
                                    "positive finite limit (the robot's data sheet)"))
            a.setflags(write=False)
            object.__setattr__(self, k, a)
        low = np.flatnonzero(~(self.q_min < self.q_max))
        if len(low):
            raise ValueError(f"joint limits: joint {low[0]}'s q_min {self.q_min[low[0]]} is not below its q_max "
                             f"{self.q_max[low[0]]}")
        if self.qd_bounds is not None and self.qd_bounds not in BOUNDS:
            raise ValueError(f"joint limits: qd_bounds {self.qd_bounds!r} is not one of {sorted(BOUNDS)}")

    @classmethod
    def of(cls, limits) -> JointLimits:
        """A driver's `limits()` (this record, or a dict with these keys), validated."""
        if isinstance(limits, JointLimits):
            return limits
        missing = [k for k in KEYS[:4] if limits.get(k) is None]
        if missing:
            raise ValueError(f"joint limits: {', '.join(missing)} missing; a driver's limits() gives "
                             f"{', '.join(KEYS[:4])} (and qddd_max, qd_bounds where it has them)")
        return cls(**{k: limits.get(k) for k in (*KEYS, "qd_bounds")})

    def __getitem__(self, key: str):
        if key not in (*KEYS, "qd_bounds") or getattr(self, key) is None:
            raise KeyError(key)
        return getattr(self, key)

    def __iter__(self):
        return iter(k for k in (*KEYS, "qd_bounds") if getattr(self, k) is not None)

    def __len__(self) -> int:
        return sum(1 for _ in self)

    @property
    def n(self) -> int:
        return len(self.qd_max)


def limits_config(limits: dict) -> dict:
    """A driver's limits as JSON (a record's configuration): lists, None for an unbounded value or a missing key."""
    out = {k: None if k not in limits else [None if not np.isfinite(x) else float(x) for x in limits[k]] for k in KEYS}
    return {**out, "qd_bounds": limits.get("qd_bounds")}


class Limiter:
    """The limiter for a driver's `limits()` (q_min, q_max, qd_max, qdd_max and optionally qddd_max, (n,) each; and
    optionally qd_bounds, a name in BOUNDS)."""

    def __init__(self, limits: dict, period_s: float | None = None):
        if period_s is not None and not (np.isfinite(period_s) and DT_MIN <= period_s <= DT_MAX):
            raise ValueError(f"limiter: command period {period_s} s; give {DT_MIN:g}..{DT_MAX:g} s")
        self.period_s = period_s
        get = {k: None if limits.get(k) is None else np.array([np.inf if x is None else x for x in limits[k]], float)
               for k in KEYS}
        self.q_min, self.q_max, self.qd_max, self.qdd_max, self.qddd_max = (get[k] for k in KEYS)
        name = limits.get("qd_bounds")
        if name is not None and name not in BOUNDS:
            raise ValueError(f"limits: qd_bounds {name!r} is not one of {sorted(BOUNDS)}; record it with this skinsafe")
        self.bounds = None if name is None else BOUNDS[name]
        self.last = np.zeros(len(self.qd_max))
        self.acc = np.zeros(len(self.qd_max))
        self.changed = 0  # ticks whose command it changed

    def __call__(self, v: np.ndarray, q: np.ndarray, dt: float) -> np.ndarray:
        """The command to send for the layers' `v` at measured q, dt s after the last one (always finite: module
        docstring)."""
        dt = self.step(dt)
        q = np.asarray(q, float)
        v = np.where(np.isfinite(v), v, 0.0)
        with np.errstate(invalid="ignore", over="ignore"):
            up, down = self.q_max - q, q - self.q_min  # NaN where q is not finite
            room = np.where(up > 0, np.sqrt(2 * self.qdd_max * np.where(up > 0, up, 0.0)), 0.0)
            back = np.where(down > 0, np.sqrt(2 * self.qdd_max * np.where(down > 0, down, 0.0)), 0.0)
        lo, hi = np.maximum(-self.qd_max, -back), np.minimum(self.qd_max, room)
        if self.bounds is not None:
            b_lo, b_hi = self.bounds(q)
            b_lo, b_hi = np.where(np.isfinite(b_lo), b_lo, 0.0), np.where(np.isfinite(b_hi), b_hi, 0.0)
            lo, hi = np.maximum(lo, b_lo), np.minimum(hi, b_hi)
        out = np.clip(v, lo, hi)
        if self.qddd_max is not None and self.bounds is None:
            out, self.acc = rate_limit(out, self.last, self.acc, dt, self.qd_max, self.qdd_max, self.qddd_max)
        elif self.qddd_max is not None:  # the bounds at q hold this tick even where braking to them needs more jerk
            out, _ = rate_limit(out, self.last, self.acc, dt, b_hi, self.qdd_max, self.qddd_max, qd_min=b_lo)
            out = np.clip(out, b_lo, b_hi)
            self.acc = (out - self.last) / dt
        else:
            out, self.acc = rate_limit(out, self.last, self.acc, dt, self.qd_max, self.qdd_max, None)
        if not np.isfinite(out).all() or not np.isfinite(self.acc).all():  # unreachable with finite limits: fail safe
            out, self.acc = np.where(np.isfinite(out), out, self.last), np.where(np.isfinite(self.acc), self.acc, 0.0)
        self.changed += bool(np.any(out != v))
        self.last = out
        return out.copy()

    def step(self, dt: float) -> float:
        """The rate limits' step: the command period, or the measured dt within [DT_MIN, DT_MAX] (module docstring)."""
        if self.period_s is not None:
            return self.period_s
        return min(max(dt, DT_MIN), DT_MAX) if np.isfinite(dt) and dt > 0 else DT_MIN
