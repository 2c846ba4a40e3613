"""Joint velocity and acceleration limits on the final command, and the safe command.

`JointLimits` is validated once and immutable. Within one control period `dt` a command may
change by at most `acc * dt` per joint and never exceed `vel`: the box `box(prev)`. The final
command of the safety stack goes through `final_command`:

* no contact active: the command is scaled uniformly into the box (direction kept, so a planned
  path keeps its shape);
* contacts active: the command is projected onto the box and the no-push half-spaces
  `a_k . qd >= b_k` (a small QP, `qp.solve`): the acceleration limit never makes a contacted
  taxel move into its contact where any command within the limits avoids it. Where the box and
  the half-spaces do not meet (a contact arrived while the arm was moving into it faster than
  one tick can undo, or a pinch), the limits stay hard, the least-violating command is taken
  (`qp.relaxed_bounds`) and the result says so (`infeasible`).

`brake(prev)` is the safe command for a tick whose inputs cannot be trusted: every joint slows
toward zero at its acceleration limit (zero at once when it is within one tick of zero), never
the planned command.

`dt` is never assumed: `JointLimits` needs the control period it is built for, and `brake`,
`scale_into` and `final_command` take the tick's own (measured) dt where it is known.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

from skinsafe.core.safety import qp


@dataclass(frozen=True)
class JointLimits:
    """Per-joint velocity (rad/s or m/s) and acceleration limits, and the control period dt (s)
    they are applied at (no default: a wrong dt scales every acceleration limit). `acc` may be
    +inf (no acceleration limit); everything else must be positive and finite."""

    vel: np.ndarray
    acc: np.ndarray
    dt: float

    def __post_init__(self):
        vel = np.array(self.vel, dtype=float, ndmin=1)
        acc = np.array(np.broadcast_to(np.asarray(self.acc, dtype=float), vel.shape) if np.ndim(self.acc) == 0
                       else self.acc, dtype=float, ndmin=1)
        if vel.ndim != 1 or acc.shape != vel.shape:
            raise ValueError(f"JointLimits: 'vel' has shape {vel.shape} and 'acc' {acc.shape}; give one value per "
                             "joint for both (a scalar acc applies to every joint)")
        if not np.all((vel > 0) & np.isfinite(vel)):
            raise ValueError(f"JointLimits: 'vel' must be positive finite numbers, one per joint; got {vel}")
        if not np.all((acc > 0) & ~np.isnan(acc)):
            raise ValueError(f"JointLimits: 'acc' must be positive (inf for none), one per joint; got {acc}")
        if not (isinstance(self.dt, (int, float, np.floating)) and np.isfinite(self.dt) and self.dt > 0):
            raise ValueError(f"JointLimits: 'dt' is {self.dt!r}; it must be the positive control period in s")
        vel.flags.writeable = acc.flags.writeable = False
        object.__setattr__(self, "vel", vel)
        object.__setattr__(self, "acc", acc)
        object.__setattr__(self, "dt", float(self.dt))

    @property
    def nv(self) -> int:
        return len(self.vel)

    def box(self, prev: np.ndarray, dt: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(lo, hi): the commands reachable from `prev` within one tick and the velocity limits."""
        step = self.acc * (self.dt if dt is None else dt)
        return np.maximum(-self.vel, prev - step), np.minimum(self.vel, prev + step)

    def violations(self, v: np.ndarray, prev: np.ndarray, tol: float = 1e-9) -> tuple[bool, bool]:
        """(velocity limit exceeded, acceleration limit exceeded) by `v` after `prev`."""
        vel = bool(np.any(np.abs(v) > self.vel * (1 + tol)))
        acc = bool(np.any(np.abs(v - prev) > self.acc * self.dt * (1 + tol) + tol))
        return vel, acc


def finite(x) -> bool:
    """True when x (a number or an array of numbers) holds no NaN or infinity; cheap for both
    (a control tick checks a dozen inputs)."""
    if isinstance(x, (float, int)):
        return math.isfinite(x)
    x = np.asarray(x, dtype=np.float64)
    return _all_finite(x.reshape(-1)) if x.flags.c_contiguous else bool(np.isfinite(x).all())


@numba.njit(cache=True, nogil=True, fastmath={"reassoc"})
def _all_finite(x):
    """x - x is 0 for every finite x and NaN for NaN or +-inf; the NaN survives the sum (only
    its order is relaxed, so the loop vectorises: 16,384 readings in about 2 us)."""
    s = 0.0
    for i in range(x.shape[0]):
        s += x[i] - x[i]
    return s == 0.0


def brake(prev: np.ndarray, limits: JointLimits, dt: float | None = None) -> np.ndarray:
    """The safe command: each joint's speed reduced toward 0 by at most its acc * dt (`dt`: this
    tick's, where known and valid; else the limits' control period)."""
    step = limits.acc * (limits.dt if dt is None else dt)
    return np.where(np.isfinite(prev), prev - np.clip(prev, -step, step), 0.0)


def scale_into(v: np.ndarray, prev: np.ndarray, limits: JointLimits, dt: float | None = None) -> np.ndarray:
    """Scale v uniformly into the velocity limits, then the step from `prev` uniformly into the
    acceleration limits (direction of the step kept). For commands with no contact active."""
    return _scale_into(np.asarray(v, dtype=float), np.asarray(prev, dtype=float), limits.vel, limits.acc,
                       float(limits.dt if dt is None else dt))


@numba.njit(cache=True, nogil=True)
def _scale_into(qdot, prev, vel, acc, dt):
    n = qdot.shape[0]
    peak = 0.0
    for i in range(n):
        peak = max(peak, abs(qdot[i]) / vel[i])
    q = qdot / peak if peak > 1 else qdot.copy()
    over = 0.0
    for i in range(n):
        over = max(over, abs(q[i] - prev[i]) / (acc[i] * dt))
    if over > 1:
        for i in range(n):
            q[i] = prev[i] + (q[i] - prev[i]) / over
    return q


@dataclass
class Projection:
    """The limited command and what happened: `changed` (v was outside the feasible set),
    `infeasible` (no command within the limits met every no-push row: the least-violating one)."""

    v: np.ndarray
    changed: bool = False
    infeasible: bool = False


def final_command(v: np.ndarray, prev: np.ndarray, limits: JointLimits, A: np.ndarray | None = None,
                  b: np.ndarray | None = None, tol: float = 1e-9, dt: float | None = None) -> Projection:
    """The command to send: `v` limited (module docstring), `dt` seconds after `prev` (default: the
    limits' control period). `A` (K, nv) and `b` (K,) are the no-push (and viability) constraints
    `A qd >= b` of the contacted taxels (None or K = 0: none)."""
    dt = limits.dt if dt is None else float(dt)
    if A is None or len(A) == 0:
        out = scale_into(v, prev, limits, dt)
        return Projection(out, changed=not np.array_equal(out, v))
    v = np.asarray(v, dtype=np.float64)
    inside, lo, hi, C, lower, upper = _projection(v, np.asarray(prev, dtype=np.float64), limits.vel, limits.acc,
                                                  dt, np.ascontiguousarray(A, dtype=np.float64),
                                                  np.ascontiguousarray(b, dtype=np.float64), tol)
    if inside:
        return Projection(np.minimum(np.maximum(v, lo), hi))
    n = len(v)
    H, f = _EYE[n] if n < len(_EYE) else np.eye(n), -v
    x, ok, _ = (None, False, None) if qp.unreachable(A, b, lo, hi) else qp.solve(H, f, C, lower, upper)
    bb = b
    if not ok:
        bb = qp.relaxed_bounds(A, b, lo, hi)
        lower[n:] = bb
        # v meets the relaxed rows (the retraction's command, limited by the same rows): it is its own projection
        x, ok, _ = (v, True, None) if qp.meets(C, v, lower, upper) else qp.solve(H, f, C, lower, upper)
    if not ok:  # cannot happen for bounds from relaxed_bounds; stay safe anyway
        return Projection(brake(prev, limits, dt), True, True)
    return Projection(np.minimum(np.maximum(x, lo), hi), True, bool((bb < 0).any()))


_EYE = [np.eye(n) for n in range(16)]


@numba.njit(cache=True, nogil=True)
def _projection(v, prev, vel, acc, dt, A, b, tol):
    """The box (`JointLimits.box`), whether v already meets it and every no-push row (to tol),
    and the projection QP's rows: `lower <= [I; A] x <= upper`."""
    n, K = len(v), len(b)
    lo, hi = np.empty(n), np.empty(n)
    inside = True
    for i in range(n):
        lo[i] = max(-vel[i], prev[i] - acc[i] * dt)
        hi[i] = min(vel[i], prev[i] + acc[i] * dt)
        if v[i] < lo[i] - tol or v[i] > hi[i] + tol:
            inside = False
    C = np.zeros((n + K, n))
    lower, upper = np.empty(n + K), np.empty(n + K)
    for i in range(n):
        C[i, i] = 1.0
        lower[i], upper[i] = max(lo[i], -qp.BIG), min(hi[i], qp.BIG)
    for k in range(K):
        s = 0.0
        for i in range(n):
            C[n + k, i] = A[k, i]
            s += A[k, i] * v[i]
        if s < b[k] - tol:
            inside = False
        lower[n + k], upper[n + k] = b[k], qp.BIG
    return inside, lo, hi, C, lower, upper
