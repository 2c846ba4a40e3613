"""A joint velocity command stepped toward a target at a robot's limits (numpy only): libfranka's `limitRate` rule
with a jerk limit, the acceleration limit alone without one. The runtime's limiter (core/runtime/limiter.py), the FR3
driver's own rate limit and both drivers' stop ramps (hardware/franka.py, core/sim/robot_driver.py) step with it."""
from __future__ import annotations

import numpy as np

MARGIN = 1e-3  # libfranka's kLimitEps: stay this fraction inside each limit (with a jerk limit)


def rate_limit(qd_cmd: np.ndarray, qd_last: np.ndarray, qdd_last: np.ndarray, dt: float, qd_max: np.ndarray,
               qdd_max: np.ndarray, qddd_max: np.ndarray | None, qd_min: np.ndarray | None = None
               ) -> tuple[np.ndarray, np.ndarray]:
    """The command reached from the last one in `dt` s, inside the velocity limits [-qd_max, qd_max] (or [qd_min,
    qd_max] as given: position-dependent bounds, which carry their own tolerance). With a jerk limit `qddd_max`:
    libfranka's `limitRate`, bounded jerk and acceleration, each limit kept MARGIN inside; without one (None): at most
    `qdd_max` x dt from the last command, exactly. Returns (velocity, acceleration)."""
    if qddd_max is None:
        out = np.clip(np.clip(qd_cmd, qd_last - qdd_max * dt, qd_last + qdd_max * dt),
                      -qd_max if qd_min is None else qd_min, qd_max)
        return out, (out - qd_last) / dt
    qdd_max, qddd_max = qdd_max * (1 - MARGIN), qddd_max * (1 - MARGIN)
    if qd_min is None:
        qd_max = qd_max * (1 - MARGIN)
        qd_min = -qd_max
    jerk = np.clip(((qd_cmd - qd_last) / dt - qdd_last) / dt, -qddd_max, qddd_max)
    acc = qdd_last + jerk * dt
    hi = np.minimum(qddd_max / qdd_max * (qd_max - qd_last), qdd_max)
    lo = np.maximum(qddd_max / qdd_max * (qd_min - qd_last), -qdd_max)
    acc = np.clip(acc, lo, hi)
    return qd_last + acc * dt, acc
