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
  of `a_0 .. a_{j-1}`. eps = 1: full null-space projection, lower priorities cannot alter any
  higher taxel's retraction speed; eps = 0: the plain sum;
* safety guard: a component of a lower-priority motion that *opposes* a higher retraction
  (negative along the basis direction) is always removed in full, whatever eps. Along the
  dominant taxel's direction this is exact, so the dominant taxel never moves toward its
  contact (with opposite normals, e.g. a pinch, the lower-priority taxel may: a rigid link
  cannot retract from both sides).

Limits. The merged velocity is scaled uniformly (direction kept) to the joint velocity limits,
then the change from the previous command is scaled uniformly to the acceleration limits.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

FORMS = ("3d", "6d")


@dataclass
class RetractionParams:
    """Hyper-parameters of the retraction (paper: alpha sensitivity, T agility, eps merge)."""

    alpha: float = 0.05  # m per N: final distance alpha * f / 12
    T: float = 0.5  # s, duration of one retraction
    epsilon: float = 1.0  # 0: plain sum, 1: full null-space projection
    form: str = "3d"  # "3d" position only, "6d" the paper's zero rotational velocity
    damping: float = 0.05  # largest damping of the DLS inverse (at a singular value of 0)
    sv_threshold: float = 0.05  # singular values below this are damped
    max_distance: float = 0.25  # m, cap on the final distance alpha * f / 12
    stimulus_alpha: dict = field(default_factory=lambda: {"temperature": 0.002, "classifier": 0.12})
    rank_tol: float = 1e-3  # relative residual under which a direction adds no new constraint

    def __post_init__(self):
        checks = [
            ("alpha", self.alpha >= 0 and np.isfinite(self.alpha), "a finite number >= 0 (m/N)"),
            ("T", self.T > 0 and np.isfinite(self.T), "a positive duration in seconds"),
            ("epsilon", 0.0 <= self.epsilon <= 1.0, "in [0, 1]"),
            ("form", self.form in FORMS, f"one of {FORMS}"),
            ("damping", self.damping >= 0 and np.isfinite(self.damping), "a finite number >= 0"),
            ("sv_threshold", self.sv_threshold > 0 and np.isfinite(self.sv_threshold), "a positive number"),
            ("max_distance", self.max_distance > 0 and np.isfinite(self.max_distance), "a positive distance in m"),
            ("rank_tol", 0 < self.rank_tol < 1, "in (0, 1)"),
        ]
        for name, ok, want in checks:
            if not ok:
                raise ValueError(f"RetractionParams: '{name}' is {getattr(self, name)!r}; it must be {want}")
        for name, a in self.stimulus_alpha.items():
            if not (a >= 0 and np.isfinite(a)):
                raise ValueError(f"RetractionParams: stimulus_alpha['{name}'] is {a!r}; it must be a finite number >= 0")

    def alpha_of(self, stimulus: str) -> float:
        return self.alpha if stimulus == "force" else float(self.stimulus_alpha.get(stimulus, 0.0))


def profile(u: np.ndarray) -> np.ndarray:
    """s(u) of eq. 10 for u in [0, 1] (clipped): 0 at u=0, 1/12 at u=1."""
    u = np.clip(u, 0.0, 1.0)
    return u ** 4 / 4 - 2 * u ** 3 / 3 + u ** 2 / 2


def profile_rate(u: np.ndarray) -> np.ndarray:
    """ds/du = u (1-u)^2, zero at both ends, peak 4/27 at u = 1/3; 0 outside [0, 1]."""
    inside = (u >= 0) & (u <= 1)
    return np.where(inside, u * (1 - u) ** 2, 0.0)


def dls_pinv(J: np.ndarray, damping: float, sv_threshold: float) -> np.ndarray:
    """Numerically filtered damped least-squares inverses of a stack J (K,m,n) -> (K,n,m).

    `sigma / (sigma^2 + lam^2)` with `lam^2 = damping^2 (1 - (sigma/sv_threshold)^2)` under the
    threshold and 0 above: exact where well conditioned, bounded by 1/(2 damping)-ish near 0.
    """
    U, S, Vt = np.linalg.svd(J, full_matrices=False)
    lam2 = np.where(S < sv_threshold, damping ** 2 * (1 - (S / sv_threshold) ** 2), 0.0)
    den = S * S + lam2
    inv = np.divide(S, den, out=np.zeros_like(S), where=den > 1e-300)
    return np.einsum("kji,kj,klj->kil", Vt, inv, U)


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
    return np.einsum("kij,kj->ki", dls_pinv(Jt, params.damping, params.sv_threshold), rdot)


def constraint_rows(J: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """a_k (K,nv): taxel k's speed along its retraction direction is `a_k . qdot`."""
    return np.einsum("kij,ki->kj", J[:, :3, :], directions)


def merge(qdots: np.ndarray, A: np.ndarray, epsilon: float, rank_tol: float = 1e-3) -> np.ndarray:
    """Prioritised sum (module docstring) of joint velocities `qdots` (K,n), highest first,
    with constraint rows `A` (K,n). Vectorised: the basis only grows at most n times, so the
    tasks between two growths are projected as one batch."""
    K, n = qdots.shape
    out = np.zeros(n)
    if K == 0:
        return out
    out += qdots[0]
    U = np.zeros((n, 0))
    norms = np.linalg.norm(A, axis=1)
    scale = max(float(norms.max()), 1e-300)
    start = 0  # A[start] is the next candidate direction; tasks > start are not yet summed
    while start < K:
        # residual of every remaining direction against the current basis
        rest = A[start:]
        res = rest - (rest @ U) @ U.T if U.shape[1] else rest
        rn = np.linalg.norm(res, axis=1)
        new = (rn > rank_tol * norms[start:]) & (norms[start:] > 1e-9 * scale) if U.shape[1] < n else np.zeros(len(rn), bool)
        hit = np.flatnonzero(new)
        stop = start + (int(hit[0]) if len(hit) else K - start)  # A[stop] grows the basis
        # tasks start+1 .. stop are projected with the basis of A[0 .. start] (A[start] included
        # once it is added below); here the basis spans A[0 .. start-1] and A[start] adds nothing
        # new unless start == stop.
        if stop == start:
            u = res[0] / rn[0]
            u -= U @ (U.T @ u)  # re-orthogonalise (twice is enough)
            U = np.column_stack([U, u / np.linalg.norm(u)])
            _add_projected(out, qdots[start + 1:start + 2], U, epsilon)
            start += 1
            continue
        _add_projected(out, qdots[start + 1:stop + 1], U, epsilon)
        start = stop
    return out


def _add_projected(out: np.ndarray, Q: np.ndarray, U: np.ndarray, epsilon: float) -> None:
    """out += sum of rows of Q, each minus eps (helping) or all (opposing) of its part along U."""
    if len(Q) == 0:
        return
    total = Q.sum(axis=0)
    if U.shape[1]:
        C = Q @ U  # (b, m) components
        gamma = np.where(C >= 0, epsilon, 1.0)
        total -= U @ (gamma * C).sum(axis=0)
    out += total


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


def limit(qdot: np.ndarray, prev: np.ndarray, vel_limits: np.ndarray, acc_limits: np.ndarray, dt: float) -> np.ndarray:
    """Scale qdot uniformly into the velocity limits, then the step from `prev` into the
    acceleration limits (direction of the step kept). Non-finite input gives `prev` held."""
    if not np.all(np.isfinite(qdot)):
        qdot = prev.copy()
    peak = np.max(np.abs(qdot) / vel_limits)
    if peak > 1:
        qdot = qdot / peak
    step = qdot - prev
    over = np.max(np.abs(step) / (acc_limits * dt))
    return prev + step / over if over > 1 else qdot
