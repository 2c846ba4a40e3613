"""Velocity modulation by a tactile danger potential (paper eq. 6-7).

With equal tangential eigenvalues and an orthonormal E, `M = E D E^-1` is
`M = (1+f) I - 2 f n n^T` (n the unit normal): no tangent basis, any dimension. Decisions where
the paper is silent (all tested in tests/test_modulation_*.py):

- **|df/ds| tiny** (flat potential, e.g. a saturated plateau): the direction is undefined. Below
  `eps_grad` the matrix blends continuously to the isotropic `(1-f) I` ("danger, but no escape
  direction: slow down uniformly"): `M = [(1-f) + 2f b^2] I - 2f n n^T / eps^2` with
  `b = |n| / eps_grad`. The eigenvalue along n stays `1-f`; across n it rises from `1-f` to `1+f`.
- **Velocity already pointing away** (n . v < 0): by default its normal component is not slowed
  (`keep_away=True`), so the robot can always leave danger (e.g. retract from a contact); the
  paper's M (which also slows leaving motions) is `keep_away=False`. Both are continuous in v.
- **Tangential gain**: the paper's tangential eigenvalue is `1 + f`; `tangent_gain` g makes it
  `1 + g f` (g = 1 the paper, g = 0 never speeds a motion up: with a learned, imperfect normal,
  amplifying "tangential" motion can drive the robot into danger faster - seen in the desk scene).
- **f outside [0, 1]** is clipped; a **non-finite f** counts as f = 1 with no direction (stop);
  a non-finite normal counts as no direction.
- **A retraction and the obstacles the potential knows** (`stop`, used by `SafetyStack`): the
  paper's M only slows the normal component, and a learned potential's level sets do not follow
  an obstacle's surface exactly, so a retraction (which outranks the plan) could slide along a
  level set into the obstacle. With `stop` set, a retraction is slowed as a whole (direction
  kept) so that the arm can brake, within its acceleration limits, before the potential rises
  to `stop`: the danger level where the potential knows the obstacle (module `stack`).
"""
from __future__ import annotations

import numba
import numpy as np

from skinsafe.core.safety.limits import finite

EPS_GRAD = 1e-3
"""Default gradient norm (potential units per state unit) below which the normal is blended out."""


def _prepare(f, n, eps_grad: float):
    """Clipped f (B,), unit normals (B, d) and blend weights b (B,) in [0, 1] (module docstring)."""
    n = np.asarray(n, dtype=float)
    if n.ndim == 1:
        n = n[None]
    f = np.asarray(f, dtype=float).reshape(-1)
    if f.shape[0] != n.shape[0]:
        f = np.broadcast_to(f, (n.shape[0],))
    return _unit(np.ascontiguousarray(f), np.ascontiguousarray(n), float(eps_grad))


@numba.njit(cache=True, nogil=True)
def _unit(f, n, eps_grad):
    B, d = n.shape
    fc, u, b = np.empty(B), np.zeros((B, d)), np.zeros(B)
    for r in range(B):
        fr = f[r]
        direction = np.isfinite(fr)
        if not direction:
            fr = 1.0  # unknown danger: stop, no direction
        scale = 0.0
        for j in range(d):
            if not np.isfinite(n[r, j]):
                direction = False
            scale = max(scale, abs(n[r, j]))
        fc[r] = min(max(fr, 0.0), 1.0)
        if not direction or scale == 0.0:
            continue
        norm = 0.0
        for j in range(d):  # scaled before squaring: huge gradients stay finite
            norm += (n[r, j] / scale) ** 2
        norm = np.sqrt(norm) * scale
        for j in range(d):
            u[r, j] = n[r, j] / norm
        b[r] = min(norm / eps_grad, 1.0) if eps_grad > 0 else 1.0
    return fc, u, b


def modulation_matrix(f, n, eps_grad: float = EPS_GRAD, tangent_gain: float = 1.0) -> np.ndarray:
    """M (B, d, d) for potentials f (B,) and gradients n (B, d) (eq. 7, toward-danger form)."""
    f, u, b = _prepare(f, n, eps_grad)
    d = u.shape[1]
    lam_t = (1.0 - f) + (1.0 + tangent_gain) * f * b * b
    return lam_t[:, None, None] * np.eye(d) - (lam_t - (1.0 - f))[:, None, None] * np.einsum("bi,bj->bij", u, u)


def modulate(v, f, n, eps_grad: float = EPS_GRAD, keep_away: bool = True, tangent_gain: float = 1.0) -> np.ndarray:
    """Modulated velocities `M v` (B, d) for velocities v (B, d) or (d,), f (B,), n (B, d).

    Computed without forming M: `lam_t v + (lam_n - lam_t) u (u . v)`.
    """
    v = np.asarray(v, dtype=float)
    single = v.ndim == 1
    f, u, b = _prepare(f, n, eps_grad)
    v2 = v[None] if single else v
    if len(v2) != len(u):  # one velocity for many states, or the reverse
        rows = max(len(u), len(v2))
        v2, f, u, b = (np.ascontiguousarray(np.broadcast_to(x, (rows,) + x.shape[1:])) for x in (v2, f, u, b))
    out = _apply(np.ascontiguousarray(v2), f, u, b, bool(keep_away), float(tangent_gain))
    return out[0] if single else out


@numba.njit(cache=True, nogil=True)
def _apply(v, f, u, b, keep_away, tangent_gain):
    B, d = v.shape
    out = np.empty((B, d))
    for r in range(B):
        b2 = b[r] * b[r]
        lam_t = (1.0 - f[r]) + (1.0 + tangent_gain) * f[r] * b2
        vn = 0.0
        for j in range(d):
            vn += u[r, j] * v[r, j]
        # leaving danger (keep_away): the normal component is kept, blended toward (1-f) where the normal fades
        lam_n = 1.0 - f[r] * (1.0 - b2) if keep_away and vn < 0 else 1.0 - f[r]
        for j in range(d):
            out[r, j] = lam_t * v[r, j] + (lam_n - lam_t) * vn * u[r, j]
    return out


class ModulationLayer:
    """The modulation layer: a potential (f_phi or a distilled w_phi) applied to velocities.

    `layer(s, v, a=None)` -> (modulated v, f) for one state (d,) or a batch (B, d); the action
    passed to the potential defaults to the velocity itself (velocity-command actions). Networks
    of Linear/ReLU/Tanh layers are evaluated by `FastPotential` (call `set_potential` again after
    training), others by autograd. `stop`: the danger level a retraction may not carry the arm
    past (module docstring; None: the paper's modulation alone).
    """

    def __init__(self, potential, eps_grad: float = EPS_GRAD, keep_away: bool = True, tangent_gain: float = 1.0,
                 stop: float | None = None):
        self.eps_grad, self.keep_away, self.tangent_gain = float(eps_grad), bool(keep_away), float(tangent_gain)
        if stop is not None and not 0.0 < stop <= 1.0:
            raise ValueError(f"ModulationLayer: 'stop' is {stop!r}; give the danger level in (0, 1] a retraction may "
                             "not carry the arm past (or None)")
        self.stop = None if stop is None else float(stop)
        self.finite = True
        self.normal = np.zeros(0)  # n = df/ds of the last call
        self.set_potential(potential)

    def set_potential(self, potential) -> None:
        from skinsafe.core.safety.potential import FastPotential, potential_and_normal

        self.potential = potential
        try:
            self._eval = FastPotential(potential)
        except TypeError:
            self._eval = lambda s, a: potential_and_normal(potential, s, a)

    def __call__(self, s, v, a=None) -> tuple[np.ndarray, np.ndarray | float]:
        """Also sets `finite`: False when the potential or its gradient was not finite (the
        modulation then stops the motion; the safety stack counts it and sends its safe command)."""
        single = np.ndim(v) == 1
        a = v if a is None else a
        f, n = self._eval(s, a)
        self.finite = finite(f) and finite(n)
        self.normal = n
        out = modulate(v, f, n, self.eps_grad, self.keep_away, self.tangent_gain)
        return (out, float(f[0])) if single else (out, f)
