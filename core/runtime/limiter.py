"""The one command limiter after the layers: what it returns is what the driver sends and the record holds.

All joints at once, from the last command sent: position (never toward a joint limit faster than the
arm can stop before it, |qd| <= sqrt(2 qdd_max d)), velocity, acceleration and, where the robot
states a jerk limit (the FR3), libfranka's `limitRate` rule with its margin. The runtime tells the
stack what was sent (its next tick's limits and no-push rows start from it), and a replay runs the
same limiter from the record's configuration. Both drivers get its output: the FR3 driver then sends
it unchanged and rate-limits only its own ramp to zero. The FR3's velocity limits are its published
constants, not libfranka's position-dependent ones. numpy only (hardware/ imports it).
"""
from __future__ import annotations

import numpy as np

MARGIN = 1e-3  # libfranka's kLimitEps: stay this fraction inside each limit (with a jerk limit)
KEYS = ("q_min", "q_max", "qd_max", "qdd_max", "qddd_max")


def rate_limit(qd_cmd: np.ndarray, qd_last: np.ndarray, qdd_last: np.ndarray, dt: float, qd_max: np.ndarray,
               qdd_max: np.ndarray, qddd_max: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """libfranka's `limitRate` for joint velocities: the command reached from the last one with bounded jerk and
    acceleration, inside the velocity limit. Returns (velocity, acceleration)."""
    qd_max, qdd_max, qddd_max = (x * (1 - MARGIN) for x in (qd_max, qdd_max, qddd_max))
    jerk = np.clip(((qd_cmd - qd_last) / dt - qdd_last) / dt, -qddd_max, qddd_max)
    acc = qdd_last + jerk * dt
    hi = np.minimum(qddd_max / qdd_max * (qd_max - qd_last), qdd_max)
    lo = np.maximum(qddd_max / qdd_max * (-qd_max - qd_last), -qdd_max)
    acc = np.clip(acc, lo, hi)
    return qd_last + acc * dt, acc


def limits_config(limits: dict) -> dict:
    """A driver's limits as JSON (a record's configuration): lists, None for an unbounded value or a missing key."""
    return {k: None if k not in limits else [None if not np.isfinite(x) else float(x) for x in limits[k]]
            for k in KEYS}


class Limiter:
    """The limiter for a driver's `limits()` (q_min, q_max, qd_max, qdd_max and optionally qddd_max, (n,) each)."""

    def __init__(self, limits: dict):
        get = {k: None if limits.get(k) is None else np.array([np.inf if x is None else x for x in limits[k]], float)
               for k in KEYS}
        self.q_min, self.q_max, self.qd_max, self.qdd_max, self.qddd_max = (get[k] for k in KEYS)
        self.last = np.zeros(len(self.qd_max))
        self.acc = np.zeros(len(self.qd_max))
        self.changed = 0  # ticks whose command it changed

    def __call__(self, v: np.ndarray, q: np.ndarray, dt: float) -> np.ndarray:
        """The command to send for the layers' `v` at measured q, dt s after the last one."""
        room = np.sqrt(2 * self.qdd_max * np.maximum(self.q_max - q, 0.0))
        back = np.sqrt(2 * self.qdd_max * np.maximum(q - self.q_min, 0.0))
        out = np.clip(v, np.maximum(-self.qd_max, -back), np.minimum(self.qd_max, room))
        if self.qddd_max is not None:
            out, self.acc = rate_limit(out, self.last, self.acc, dt, self.qd_max, self.qdd_max, self.qddd_max)
        else:
            out = np.clip(out, self.last - self.qdd_max * dt, self.last + self.qdd_max * dt)
            self.acc = (out - self.last) / dt
        self.changed += bool(np.any(out != v))
        self.last = out
        return out.copy()
