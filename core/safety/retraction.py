"""Retraction maths of the tactile defensiveness layer (paper III-C, eq. 10-13), on arrays.

Single taxel (eq. 10-11). A taxel triggered at time tau retracts along `-z_i(tau)` by
`D_i * s(u)`, `u = (t - tau) / T`, `s(u) = u^4/4 - 2u^3/3 + u^2/2`, so the final distance is
`D_i / 12` with `D_i = alpha * f_i` (capped at `12 * max_distance` so that no force, however
large, asks for an absurd motion) and the speed `D_i * u (1-u)^2 / T` is zero at both ends.
Joint velocities come from a damped least-squares inverse with numerical filtering
(`dls_pinv`: only singular values under `sv_threshold` are damped, smoothly, so the inverse is
exact away from singularities and bounded at them). Two task forms:

* `"6d"` (the paper): `r_dot = [p_dot, 0]`, the taxel must also keep its orientation;
* `"3d"`: position only, `r_dot = p_dot`; the remaining DoFs are left free (minimum norm).

Which form retracts better is measured by `compare_forms` (achieved distance along -z vs
commanded, side drift; see `skinsafe poke`). The default is the one that measured better, 3-D:
on the UR5 a taxel on the upper arm rides on two joints only, and "do not rotate" then fights
"move along -z" (6-D least squares can only split the difference).

Multi-contact (eq. 12-13). The priority is `w_i = D_i/12 - d_i` with `d_i` the distance already
retracted (eq. 12); the pool is re-sorted by it every tick. Eq. 13 as printed maps every
trajectory into the dominant taxel's task space (`J_0 J_i^-1 r_i`) and inverts with `J_0^-1`
at the end; that keeps only the part of each motion that the dominant taxel's Jacobian can
see (a wrist taxel's own retraction vanishes when the dominant taxel sits on the upper arm),
and its product of rank-one projectors is not a projector onto the common null space when the
directions are not orthogonal. We implement the stated intent instead (`merge`; the literal
formula is kept as `merge_paper` for comparison):

* the common frame is joint space: each taxel's own joint velocity `qd_j = J_j^# r_j`;
* taxel k's retraction is the scalar `a_k . qd` with `a_k = -J_p,k^T z_k(tau_k)` (its speed
  along its retraction axis); lower priorities must not change the higher ones' speeds;
* `qd = qd_0 + sum_j P_j qd_j`, `P_j = I - eps * U_j U_j^T` where `U_j` is an orthonormal basis
  (Gram-Schmidt, rank-safe: directions with a relative residual under `rank_tol` add nothing)
  of `a_0 .. a_{j-1}`. eps = 1: full null-space projection, lower priorities cannot alter the
  retraction speed of a higher taxel whose row added a column; a row within `rank_tol` of the rows
  above it counts as dependent, and lower priorities may change its speed by its residual's share,
  at most `rank_tol * |a_k| * |their motion|` (tested over random sets); eps = 0: the plain sum;
* safety guard: a component of a lower-priority motion that *opposes* a higher retraction
  (negative along the basis direction) is always removed in full, whatever eps. Along the
  dominant taxel's direction this is exact, so the dominant taxel never moves toward its
  contact (with opposite normals, e.g. a pinch, the lower-priority taxel may: a rigid link
  cannot retract from both sides).

The default merge is neither: `merge="qp"` solves the priorities as a sequence of small QPs with
the `J_i q_dot_(i-1)` correction of recursive task-priority control and the hard no-push
constraints `-z_i^T J_i q_dot >= 0` (`qp.py`); `"joint"` and `"paper"` are kept as the closed-form
references it is compared with (Fig. 7, `skinsafe bench safety`). Limits: `limits.py`.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from types import MappingProxyType

import numba
import numpy as np

from skinsafe.core.safety.jacobi import orthogonalise_columns

FORMS = ("3d", "6d")
MERGES = ("qp", "joint", "paper")  # prioritised QP (default); closed forms: eq. 13 intent in joint space, as printed


@dataclass(frozen=True)
class RetractionParams:
    """Hyper-parameters of the retraction (paper: alpha sensitivity, T agility, eps merge),
    validated at construction and immutable (change one with `dataclasses.replace`)."""

    alpha: float = 0.05  # m per N: final distance alpha * f / 12
    T: float = 0.5  # s, duration of one retraction
    epsilon: float = 1.0  # 0: plain sum, 1: full null-space projection
    form: str = "3d"  # "3d" position only, "6d" the paper's zero rotational velocity
    damping: float = 0.05  # largest damping of the DLS inverse (at a singular value of 0)
    sv_threshold: float = 0.05  # singular values below this are damped
    max_distance: float = 0.25  # m, cap on the final distance alpha * f / 12
    stimulus_alpha: dict = field(default_factory=lambda: {"temperature": 0.002, "classifier": 0.12})
    rank_tol: float = 1e-3  # relative residual under which a direction adds no new constraint
    merge: str = "qp"  # "qp" (default), or the closed forms "joint" and "paper" (module docstring)
    recovery_gain: float = 20.0  # 1/s: a contacted taxel that drifted toward its contact must move back this fast

    def __post_init__(self):
        checks = [
            ("alpha", self.alpha >= 0 and np.isfinite(self.alpha), "a finite number >= 0 (m/N); 0 disables force retraction"),
            ("T", self.T > 0 and np.isfinite(self.T), "a positive duration in seconds"),
            ("epsilon", 0.0 <= self.epsilon <= 1.0, "in [0, 1] (0 plain sum, 1 full null-space projection)"),
            ("form", self.form in FORMS, f"one of {FORMS}"),
            ("damping", self.damping >= 0 and np.isfinite(self.damping), "a finite number >= 0"),
            ("sv_threshold", self.sv_threshold > 0 and np.isfinite(self.sv_threshold), "a positive number"),
            ("max_distance", self.max_distance > 0 and np.isfinite(self.max_distance), "a positive distance in m"),
            ("rank_tol", 0 < self.rank_tol < 1, "in (0, 1)"),
            ("merge", self.merge in MERGES, f"one of {MERGES}"),
            ("recovery_gain", self.recovery_gain >= 0 and np.isfinite(self.recovery_gain), "a finite number >= 0 (1/s)"),
        ]
        for name, ok, want in checks:
            if not ok:
                raise ValueError(f"RetractionParams: '{name}' is {getattr(self, name)!r}; it must be {want}")
        for name, a in self.stimulus_alpha.items():
            if not (a >= 0 and np.isfinite(a)):
                raise ValueError(f"RetractionParams: stimulus_alpha['{name}'] is {a!r}; it must be a finite number >= 0")
        object.__setattr__(self, "stimulus_alpha", MappingProxyType(dict(self.stimulus_alpha)))

    def alpha_of(self, stimulus: str) -> float:
        return self.alpha if stimulus == "force" else float(self.stimulus_alpha.get(stimulus, 0.0))


def profile(u: np.ndarray) -> np.ndarray:
    """s(u) of eq. 10 for u in [0, 1] (clipped): 0 at u=0, 1/12 at u=1."""
    u = np.clip(u, 0.0, 1.0)
    return u ** 4 / 4 - 2 * u ** 3 / 3 + u ** 2 / 2


@numba.njit(cache=True, nogil=True)
def profile_rate(u):
    """ds/du = u (1-u)^2, zero at both ends, peak 4/27 at u = 1/3; 0 outside [0, 1] (a scalar or an
    array; also callable from compiled code). Compiled on first use, not at import: `skinsafe run`'s
    warm-up (and `skinsafe precompile`) reach it through the defensiveness kernel."""
    u = np.minimum(np.maximum(u, 0.0), 1.0)
    return u * (1 - u) ** 2


def _filtered_svd(J: np.ndarray, damping: float, sv_threshold: float):
    U, S, Vt = np.linalg.svd(J, full_matrices=False)
    lam2 = np.where(S < sv_threshold, damping ** 2 * (1 - (S / sv_threshold) ** 2), 0.0)
    den = S * S + lam2
    return U, np.divide(S, den, out=np.zeros_like(S), where=den > 1e-300), Vt


def dls_pinv(J: np.ndarray, damping: float, sv_threshold: float) -> np.ndarray:
    """Numerically filtered damped least-squares inverses of a stack J (K,m,n) -> (K,n,m).

    `sigma / (sigma^2 + lam^2)` with `lam^2 = damping^2 (1 - (sigma/sv_threshold)^2)` under the
    threshold and 0 above: exact where well conditioned, at most `1 / (2 damping)` near 0.
    """
    U, inv, Vt = _filtered_svd(J, damping, sv_threshold)
    return (Vt.transpose(0, 2, 1) * inv[:, None, :]) @ U.transpose(0, 2, 1)


def dls_solve(J: np.ndarray, rhs: np.ndarray, damping: float, sv_threshold: float) -> np.ndarray:
    """`dls_pinv(J) @ rhs` for a stack, (K,m,n) and (K,m) -> (K,n), without forming the inverses
    (compiled, no LAPACK call: see `_dls_solve`)."""
    return _dls_solve(np.ascontiguousarray(J, dtype=np.float64), np.ascontiguousarray(rhs, dtype=np.float64),
                      float(damping), float(sv_threshold))


@numba.njit(cache=True, nogil=True)
def _dls_solve(J, rhs, damping, sv_threshold):
    """One-sided (Hestenes) Jacobi SVD of each small J: rotate the columns of `A = J^T` pairwise
    until orthogonal, `A W = B`, so `J = W B^T` with `U = W` and `B` = V diag(sigma) (sigma the
    column norms). Then `J^# r = sum_i (u_i . r) b_i / (sigma_i^2 + lam_i^2)`, no division by
    sigma. Accurate to the last digits for the 3x6 and 6x6 blocks here, and ~10x cheaper than a
    LAPACK call with its workspace queries at this size."""
    K, m, n = J.shape
    out = np.zeros((K, n))
    A = np.empty((n, m))
    W = np.empty((m, m))
    for k in range(K):
        A[:] = J[k].T
        W[:] = 0.0
        for i in range(m):
            W[i, i] = 1.0
        orthogonalise_columns(A, W)
        for i in range(m):
            s2 = 0.0
            for j in range(n):
                s2 += A[j, i] * A[j, i]
            sigma = np.sqrt(s2)
            lam2 = damping ** 2 * (1.0 - (sigma / sv_threshold) ** 2) if sigma < sv_threshold else 0.0
            den = s2 + lam2
            if den <= 1e-300:
                continue
            c = 0.0
            for j in range(m):
                c += W[j, i] * rhs[k, j]
            c /= den
            for j in range(n):
                out[k, j] += A[j, i] * c
    return out


def task_jacobians(J: np.ndarray, form: str) -> np.ndarray:
    """The rows of J (K,6,n) a form controls: all 6, or the 3 linear ones."""
    return J if form == "6d" else J[:, :3, :]


def task_velocities(directions: np.ndarray, speed: np.ndarray, form: str) -> np.ndarray:
    """r_dot (K,6) or (K,3): `speed` along `directions` (K,3), zero angular velocity in 6-D."""
    lin = directions * speed[:, None]
    return np.concatenate([lin, np.zeros_like(lin)], axis=1) if form == "6d" else lin


def single_qdots(J: np.ndarray, directions: np.ndarray, speed: np.ndarray, params: RetractionParams) -> np.ndarray:
    """Eq. 11 for every active taxel at once: (K,nv) joint velocities of their own retractions."""
    Jt = task_jacobians(J, params.form)
    rdot = task_velocities(directions, speed, params.form)
    return dls_solve(Jt, rdot, params.damping, params.sv_threshold)


def ordered_basis(A: np.ndarray, rank_tol: float = 1e-3) -> tuple[np.ndarray, np.ndarray]:
    """Gram-Schmidt of the rows of A (K,n) in order: an orthonormal basis U (n,m) of their span
    and `first` (m,), the row that added each column. A row adds a column when its residual
    against the rows before it exceeds `rank_tol` times its norm (rank-safe); each column is
    oriented along its row's residual. Compiled: one pass over the rows, at most n columns."""
    U, first, m = _ordered_basis(np.ascontiguousarray(A, dtype=np.float64), rank_tol)
    return U[:, :m], first[:m]


@numba.njit(cache=True, nogil=True)
def _ordered_basis(A, rank_tol):
    K, n = A.shape
    cols = min(n, K)
    U = np.zeros((n, cols))
    first = np.zeros(cols, np.intp)
    scale = 0.0
    for i in range(K):
        scale = max(scale, np.sqrt(np.dot(A[i], A[i])))
    m = 0
    r = np.empty(n)
    for i in range(K):
        if m == cols:
            break
        na = np.sqrt(np.dot(A[i], A[i]))
        if na <= 1e-9 * max(scale, 1e-300):
            continue
        r[:] = A[i] / na
        for _ in range(2):  # modified Gram-Schmidt, twice for orthogonality
            for c in range(m):
                d = 0.0
                for j in range(n):
                    d += U[j, c] * r[j]
                for j in range(n):
                    r[j] -= d * U[j, c]
        nr = np.sqrt(np.dot(r, r))
        if nr > rank_tol:
            U[:, m] = r / nr
            first[m] = i
            m += 1
    return U, first, m


def merge(qdots: np.ndarray, A: np.ndarray, epsilon: float, rank_tol: float = 1e-3) -> np.ndarray:
    """Prioritised sum (module docstring) of joint velocities `qdots` (K,n), highest first,
    with constraint rows `A` (K,n): task j is projected by the basis columns that rows before
    it added, `qd_j - sum_c gamma_jc (u_c . qd_j) u_c`, gamma = eps (helping) or 1 (opposing)."""
    return _merge(np.ascontiguousarray(qdots, dtype=np.float64), np.ascontiguousarray(A, dtype=np.float64),
                  float(epsilon), float(rank_tol))


@numba.njit(cache=True, nogil=True)
def _merge(qdots, A, epsilon, rank_tol):
    K, n = qdots.shape
    out = np.zeros(n)
    for k in range(K):
        out += qdots[k]
    if K < 2:
        return out
    U, first, m = _ordered_basis(A, rank_tol)
    for c in range(m):
        g = 0.0
        for k in range(first[c] + 1, K):
            d = 0.0
            for j in range(n):
                d += U[j, c] * qdots[k, j]
            g += (epsilon if d >= 0 else 1.0) * d
        for j in range(n):
            out[j] -= g * U[j, c]
    return out


def retract_qdot(J: np.ndarray, directions: np.ndarray, speed: np.ndarray, params: RetractionParams) -> np.ndarray:
    """The merged joint velocity of a pool (rows highest priority first): eq. 11 per taxel
    (`single_qdots`), then `merge` with the constraint rows `a_k = J_p,k^T d_k`; one compiled call."""
    return _retract(np.ascontiguousarray(J, dtype=np.float64), np.ascontiguousarray(directions, dtype=np.float64),
                    np.ascontiguousarray(speed, dtype=np.float64), params.form == "6d", float(params.damping),
                    float(params.sv_threshold), float(params.epsilon), float(params.rank_tol))


@numba.njit(cache=True, nogil=True)
def _retract(J, directions, speed, six, damping, sv_threshold, epsilon, rank_tol):
    K, _, n = J.shape
    m = 6 if six else 3
    Jt = np.ascontiguousarray(J[:, :m, :])
    rdot = np.zeros((K, m))
    A = np.zeros((K, n))
    for k in range(K):
        for i in range(3):
            rdot[k, i] = directions[k, i] * speed[k]
            for j in range(n):
                A[k, j] += J[k, i, j] * directions[k, i]
    return _merge(_dls_solve(Jt, rdot, damping, sv_threshold), A, epsilon, rank_tol)


def merge_loop(qdots: np.ndarray, A: np.ndarray, epsilon: float, rank_tol: float = 1e-3) -> np.ndarray:
    """Reference for `merge`: one task at a time, Gram-Schmidt after each."""
    K, n = qdots.shape
    out = np.zeros(n)
    basis: list[np.ndarray] = []
    scale = max(float(np.linalg.norm(A, axis=1).max()), 1e-300) if K else 1.0
    for j in range(K):
        x = qdots[j].copy()
        for u in basis:
            c = float(u @ qdots[j])
            x -= (epsilon if c >= 0 else 1.0) * c * u
        out += x
        a = A[j]
        na = float(np.linalg.norm(a))
        r = a.copy()
        for u in basis:
            r -= (u @ a) * u
        if len(basis) < n and na > 1e-9 * scale and np.linalg.norm(r) > rank_tol * na:
            for u in basis:
                r -= (u @ r) * u
            basis.append(r / np.linalg.norm(r))
    return out


def merge_paper(J: np.ndarray, directions: np.ndarray, speed: np.ndarray, params: RetractionParams) -> np.ndarray:
    """Eq. 13 as printed, for comparison: trajectories mapped to the dominant taxel's task space
    (`r_i0 = J_0 J_i^# r_i`), projected by the product of `(I - eps r_k0 r_k0^T / |r_k0|^2)` of all
    higher priorities, summed and inverted with `J_0^#`. Rows are highest priority first."""
    Jt = task_jacobians(J, params.form)
    rdot = task_velocities(directions, speed, params.form)
    pinv = dls_pinv(Jt, params.damping, params.sv_threshold)
    mapped = np.einsum("ij,kjl,kl->ki", Jt[0], pinv, rdot)  # (K, m) in the dominant frame
    total = mapped[0].copy()
    P = np.eye(mapped.shape[1])
    for j in range(1, len(mapped)):
        r = mapped[j - 1]
        nr = float(r @ r)
        if nr > 1e-300:
            P = P @ (np.eye(len(r)) - params.epsilon * np.outer(r, r) / nr)
        total += P @ mapped[j]
    return pinv[0] @ total
