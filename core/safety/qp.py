"""Prioritised retraction as a sequence of small QPs (lexicographic task priority with
inequalities), solved by DAQP.

Why DAQP: the per-tick problem is tiny and dense (nv = 6 or 7 variables, up to nv + 64
constraint rows, many of them duplicates when contacts share a link and normal). Measured here
on 2,000 such problems with duplicated, opposite and near-zero rows: DAQP (dual active set,
made for this size) solved all of them in about 13 us per call; quadprog failed on 9% (it needs
linearly independent active constraints) and took twice as long; OSQP and proxsuite are built
for larger sparse problems (setup cost per call). See `skinsafe bench retraction`.

The problem (paper eq. 10-13 as recursive task-priority control, Siciliano-Slotine):
tasks k = 1..K in priority order want `J_k qd = r_k` (the eq. 10 retraction velocity of taxel
k along -z_k(tau)); hard constraints hold at every level: the box `lo <= qd <= hi` (velocity
and acceleration limits) and the no-push rows `A qd >= b` (`a_k = J_p,k^T d_k`, d_k = -z_k(tau):
no contacted taxel moves into its contact). Level k solves

    min_z |J_k (x + Z z) - r_k|^2_filtered + reg |z|^2   s.t. the hard constraints at x + Z z,

where x is the solution so far and Z an orthonormal basis of the directions that keep every
higher task's achieved velocity (`J_j qd` fixed for j < k): exactly the recursion
`qd_k = qd_(k-1) + (J_k N_(k-1))^# (r_k - J_k qd_(k-1))` when no inequality binds, and
priority-preserving saturation (Flacco et al. 2012) when one does - a lower task can only use
what the limits leave after the higher ones. The least-squares term uses the numerically
filtered damping of `retraction.dls_pinv` (singular values under `sv_threshold` damped), so the
QP and the closed form agree to solver tolerance away from active constraints
(`recursive_qdot` is that closed form, the reference).

Infeasible level 1 (the box excludes every command that meets A qd >= b: a contact arrived
while the arm was moving into it faster than one tick's deceleration can undo, or push-back
terms b > 0 of opposing contacts): b is first lowered to 0; if that is still infeasible the
limits stay hard and the no-push rows take the least-violating motion (`least_violation`:
minimum sum of squared violations inside the box), and the result says so (`recovery_dropped`,
`infeasible`). A region feasible only to within DAQP's tolerance gets the rows lowered by `MARGIN`
as well, widened step by step (`WIDEN`, at most 1e-5 m/s per unit row norm); should DAQP still find
no solution, the smallest command meeting every constraint is taken and `solver_failed` says so
(zero within the box if even that fails). Never a silent push.
"""
from __future__ import annotations

from dataclasses import dataclass

import daqp
import numba
import numpy as np

from skinsafe.core.safety.jacobi import orthogonalise_columns

BIG = 1e30  # DAQP's "no bound"
# A failed DAQP solve is retried once with this added to H's diagonal. In 60 Panda 8-contact sets
# (`skinsafe bench safety --robots panda --contacts 8 --cases 60`) DAQP called 35 level problems
# infeasible or cycling whose region linear programming (HiGHS) finds strictly feasible (margin
# 2e-7 to 2e-5; H's condition 2.9e8); with 1e-8 to 1e-4 added, every one solved.
RETRY_REG = 1e-6
MARGIN = 1e-9  # m/s per unit row norm: how far relaxed no-push rows are lowered below what is just feasible
# A least-violation region is a sliver around one point; with H's condition near 6e8 DAQP needs it wider than its
# tolerance: the rows are lowered by MARGIN x each of these in turn until it solves (the UR5's post met at 0.23 rad/s
# solved at 10x, a Panda patch at 1,000x; 1e4 x MARGIN is 10 um/s into a contact, 0.02 um in a 2 ms tick).
WIDEN = (1.0, 1e1, 1e2, 1e3, 1e4)
_SENSE = np.zeros(256, dtype=np.int32)  # every row an inequality (read-only use)


def solve(H, f, C, lower, upper):
    """min 1/2 x'Hx + f'x s.t. lower <= C x <= upper (+-1e30 for none), all float64
    C-contiguous. Returns (x, ok, lam), lam the rows' multipliers (0 where inactive); ok is
    checked against the rows (primal tolerance 1e-9, rows met to 1e-7), not only DAQP's exit flag
    (a failed solve is retried once with `RETRY_REG` more regularisation)."""
    sense = _SENSE[:len(lower)] if len(lower) <= len(_SENSE) else np.zeros(len(lower), dtype=np.int32)
    x, _, flag, info = daqp.solve(H, f, C, upper, lower, sense, primal_tol=1e-9)
    if flag < 1:  # H's condition reaches 1e9 near singularities: retried with a little more regularisation
        x, _, flag, info = daqp.solve(H + RETRY_REG * np.eye(len(H)), f, C, upper, lower, sense, primal_tol=1e-9)
    x = np.asarray(x)
    return x, flag >= 1 and meets(C, x, lower, upper), info["lam"]


@numba.njit(cache=True, nogil=True)
def meets(C, x, lower, upper):
    """x finite and `lower <= C x <= upper` to the tolerance `solve` accepts."""
    for i in range(x.shape[0]):
        if not np.isfinite(x[i]):
            return False
    cx = C @ x
    for i in range(len(cx)):
        if cx[i] < lower[i] - 1e-7 * (1 + abs(lower[i])) or cx[i] > upper[i] + 1e-7 * (1 + abs(upper[i])):
            return False
    return True


@dataclass
class Prioritised:
    """One tick's solution. `limited`: a box row (velocity/acceleration limit) was active at the
    dominant level; `blocked`: a no-push row was (another contact stops the dominant one's
    retraction: an opposing pinch); `infeasible`: no command within the limits met every no-push
    row (the least-violating one was taken); `dominant_residual`: |J_1 qd - r_1| / |r_1|;
    `solver_failed`: DAQP found no solution to the first level's QP even with relaxed no-push rows;
    the smallest command meeting every constraint was sent instead (zero within the box if even that
    failed)."""

    qd: np.ndarray
    levels: int = 0
    limited: bool = False
    blocked: bool = False
    infeasible: bool = False
    recovery_dropped: bool = False
    damped: bool = False
    dominant_residual: float = 0.0
    solver_failed: bool = False


@numba.njit(cache=True, nogil=True)
def _filtered(S, damping, sv_threshold):
    out = S * S
    for i in range(len(S)):
        if S[i] < sv_threshold:
            out[i] += damping ** 2 * (1 - (S[i] / sv_threshold) ** 2)
    return out


@numba.njit(cache=True, nogil=True)
def _svd(M):
    """`np.linalg.svd(M)` of a small (m, d) block as (S, U[:, :p], Vt), p = min(m, d), S
    descending, Vt (d, d) full: one-sided (Hestenes) Jacobi on the columns of M (rotate pairs
    until orthogonal, `M W = B`; V = W, sigma_i = |B_i|, U_i = B_i / sigma_i). No LAPACK call:
    about 1 us for the 3 x 6 blocks here where a `gesdd` call with its workspace takes 15 us
    (`jacobi.orthogonalise_columns`, shared with `retraction._dls_solve`). Columns of U for zero singular values
    complete an orthonormal basis (as LAPACK's do)."""
    m, d = M.shape
    B = np.ascontiguousarray(M).copy()
    W = np.eye(d)
    orthogonalise_columns(B, W)
    norms = np.empty(d)
    for j in range(d):
        norms[j] = np.sqrt(np.sum(B[:, j] * B[:, j]))
    order = np.argsort(-norms, kind="mergesort")
    k = min(m, d)
    S = norms[order[:k]]
    Vt = np.ascontiguousarray(W[:, order].T)
    U = np.zeros((m, k))
    v = np.empty(m)
    for j in range(k):
        if S[j] > 1e-150 * max(S[0], 1e-300):  # B_j / sigma_j, re-orthogonalised
            v[:] = B[:, order[j]] / S[j]
            nv = _orthogonalise(v, U, j)
        else:
            nv = 0.0
        if nv < 0.5:  # zero sigma (or lost to rounding): the unit vector that best completes the basis
            best = -1.0
            for i in range(m):
                w = np.zeros(m)
                w[i] = 1.0
                nw = _orthogonalise(w, U, j)
                if nw > best:
                    best, v[:] = nw, w
            nv = best
        U[:, j] = v / nv
    return S, U, Vt


@numba.njit(cache=True, nogil=True)
def _orthogonalise(v, U, j):
    """v minus its projection on U's first j (orthonormal) columns, twice (in place); its norm."""
    for _ in range(2):
        for c in range(j):
            dot = 0.0
            for i in range(len(v)):
                dot += U[i, c] * v[i]
            for i in range(len(v)):
                v[i] -= dot * U[i, c]
    return np.sqrt(np.sum(v * v))


@numba.njit(cache=True, nogil=True)
def _level(Jk, Z, x, rk, A, b, lo, hi, damping, sv_threshold, rank_tol, reg):
    """One level's QP data (H, f, C, lower, upper), the rank of J_k Z and the SVD's V^T; rank 0:
    the task has nothing left to move. Rank is relative to the task's own scale |J_k|. Written as
    loops over these few-row blocks (no BLAS call, few temporaries: about half the time of the
    same products as array expressions here)."""
    m, n = Jk.shape
    d, K = Z.shape[1], A.shape[0]
    M = np.zeros((m, d))
    res = rk.copy()  # r_k - J_k x
    for i in range(m):
        for l in range(n):
            res[i] -= Jk[i, l] * x[l]
            for j in range(d):
                M[i, j] += Jk[i, l] * Z[l, j]
    S, U, Vt = _svd(M)
    p = len(S)
    tol = rank_tol * max(np.sqrt(np.sum(Jk * Jk)), 1e-12)
    rank = 0
    for i in range(p):
        if S[i] > tol:
            rank += 1
    g = _filtered(S, damping, sv_threshold)
    e = np.zeros(p)
    total = 0.0
    for i in range(p):
        for r in range(m):
            e[i] += U[r, i] * res[r]
        total += abs(e[i])
    H = np.zeros((d, d))
    f, free = np.zeros(d), np.zeros(d)
    for i in range(p):
        se = S[i] * e[i]
        step = se / (g[i] + reg)  # the unconstrained minimiser (filtered DLS step)
        for j in range(d):
            f[j] -= Vt[i, j] * se
            free[j] += Vt[i, j] * step
            for c in range(d):
                H[j, c] += g[i] * Vt[i, j] * Vt[i, c]
    for j in range(d):
        H[j, j] += reg
    C = np.zeros((n + K, d))
    lower, upper = np.empty(n + K), np.empty(n + K)
    for l in range(n):
        for j in range(d):
            C[l, j] = Z[l, j]
        lower[l], upper[l] = max(lo[l] - x[l], -BIG), min(hi[l] - x[l], BIG)
    for k in range(K):
        ax = 0.0
        for l in range(n):
            ax += A[k, l] * x[l]
            for j in range(d):
                C[n + k, j] += A[k, l] * Z[l, j]
        lower[n + k], upper[n + k] = max(b[k] - ax, -BIG), BIG
    damped = False
    for i in range(p):
        if S[i] < sv_threshold and abs(e[i]) > 1e-3 * max(total, 1e-300):
            damped = True
    free_ok = True
    for r in range(n + K):
        cz = 0.0
        for j in range(d):
            cz += C[r, j] * free[j]
        if cz < lower[r] or cz > upper[r]:
            free_ok = False
    null = np.empty((d, d - rank))
    for j in range(d):
        for c in range(d - rank):
            null[j, c] = Vt[rank + c, j]
    return H, f, C, lower, upper, rank, null, damped, free, free_ok


@numba.njit(cache=True, nogil=True)
def _levels(J, r, A, b, lo, hi, damping, sv_threshold, rank_tol, reg, x, Z, k, levels, first, z, null, lam):
    """The recursion from level k. A level whose unconstrained (closed-form) step meets every
    constraint takes it (that is its QP's optimum); at the first level that needs a QP, return
    its data. `z`, `null`, `lam` (non-empty z): the QP solution of level k - 1 to apply first.
    `first` [damped, dominant_residual, limited, blocked] is written while no level has been
    accepted yet. Returns (k, x, Z, levels, H, f, C, lower, upper, null); k == K: done, x clipped."""
    K, n = J.shape[0], J.shape[2]
    if len(z):
        x = x + Z @ z
        if levels == 0:
            _first_level(J[k - 1], r[k - 1], x, lam, n, first)
        levels += 1
        Z = np.ascontiguousarray(Z @ null)
    d0 = Z.shape[1]
    while k < K and Z.shape[1] > 0:
        H, f, C, lower, upper, rank, null, damped, free, free_ok = _level(J[k], Z, x, r[k], A, b, lo, hi, damping,
                                                                          sv_threshold, rank_tol, reg)
        if rank == 0:
            k += 1
            continue
        if levels == 0:
            first[0] = 1.0 if damped else 0.0
        if not free_ok:
            return k, x, Z, levels, H, f, C, lower, upper, null
        x = x + Z @ free
        if levels == 0:
            _first_level(J[k], r[k], x, np.zeros(0), n, first)
        levels += 1
        Z = np.ascontiguousarray(Z @ null)
        k += 1
    none = np.empty((0, 0))
    return K, np.minimum(np.maximum(x, lo), hi), Z, levels, none, np.empty(0), np.empty((0, d0)), np.empty(0), \
        np.empty(0), none


@numba.njit(cache=True, nogil=True)
def _first_level(Jk, rk, x, lam, n, first):
    """The dominant level's record: residual |J_1 qd - r_1| / |r_1|, and whether a box row
    (limited) or a no-push row (blocked) was active (multipliers lam; none: nothing bound)."""
    e = Jk @ x - rk
    nr = np.sqrt(np.sum(rk * rk))
    first[1] = np.sqrt(np.sum(e * e)) / nr if nr > 0 else 0.0
    first[2] = first[3] = 0.0
    for i in range(len(lam)):
        if abs(lam[i]) > 1e-9:
            first[2 if i < n else 3] = 1.0


def prioritised(J, r, A, b, lo, hi, limits_vel, damping: float, sv_threshold: float, rank_tol: float = 1e-3,
                reg: float = 1e-9) -> Prioritised:
    """The prioritised command (module docstring). J (K, m, nv) task Jacobians and r (K, m)
    task velocities, highest priority first; A (K, nv), b (K,) no-push rows; lo, hi the box;
    `limits_vel` the velocity limits (the box left when the acceleration limit must yield).

    One compiled call runs the levels whose closed-form step meets every constraint; DAQP is
    called only for the levels where a constraint binds, then the next compiled call goes on
    (none when that level left no freedom or no task) (cold solves: a primal warm start made DAQP report feasible levels infeasible, and a cold
    solve takes about 6 us here)."""
    J, r, A, b = (np.ascontiguousarray(a, dtype=np.float64) for a in (J, r, A, b))
    lo, hi = np.ascontiguousarray(lo, dtype=np.float64), np.ascontiguousarray(hi, dtype=np.float64)
    K, n = J.shape[0], J.shape[2]
    x, Z, k, levels, first = np.zeros(n), np.eye(n), 0, 0, np.zeros(4)
    z, null, lam = _NONE, _NONE2, _NONE
    out = Prioritised(x)
    while True:
        k, x, Z, levels, H, f, C, lower, upper, null = _levels(J, r, A, b, lo, hi, damping, sv_threshold, rank_tol,
                                                               reg, x, Z, k, levels, first, z, null, lam)
        if k >= K:
            break
        doomed = levels == 0 and unreachable(A, b, lo, hi)  # x = 0, Z = I: the level's rows are A's and the box
        z, ok, lam = (_NONE, False, _NONE) if doomed else solve(H, f, C, lower, upper)
        if not ok and levels == 0:  # fallback chain (module docstring); x = 0 here
            pushing = bool(np.any(b > 0))
            b = relaxed_bounds(A, b, lo, hi)
            out.recovery_dropped, out.infeasible = pushing, bool(np.any(b < 0))
            lower = lower.copy()
            lower[n:] = b
            z, ok, lam = solve(H, f, C, lower, upper)
            relaxed = b
            for widen in WIDEN:  # feasible only to within DAQP's tolerance: lower the rows by a margin as well
                if ok:
                    break
                b = relaxed - widen * _margin(A)
                lower[n:] = b
                z, ok, lam = solve(H, f, C, lower, upper)
            if not ok:  # DAQP gives up on this H (condition ~5e8): the smallest command meeting every row
                out.solver_failed = True
                z, ok, lam = solve(np.eye(len(H)), np.zeros(len(H)), C, lower, upper)
        k += 1
        if not ok:  # z = 0 is feasible here (x met every constraint at the level before): keep x
            z = _NONE
        elif k >= K or null.shape[1] == 0:  # no level left to run: apply z here (what the next call would do)
            x = x + Z @ z
            if levels == 0:
                _first_level(J[k - 1], r[k - 1], x, lam, n, first)
            x, levels = np.minimum(np.maximum(x, lo), hi), levels + 1
            break
    out.qd, out.levels = x, levels
    out.damped, out.dominant_residual, out.limited, out.blocked = bool(first[0]), float(first[1]), bool(first[2]), \
        bool(first[3])
    return out


_NONE, _NONE2 = np.zeros(0), np.zeros((0, 0))


def relaxed_bounds(A, b, lo, hi) -> np.ndarray:
    """The largest lower bounds b' <= b such that `A qd >= b'` meets the box: b' = min(b, 0)
    where that is feasible, else the least violation: `b' = min(b, 0) - s` with s >= 0 the
    slack of `min |s|^2 s.t. A qd + s >= min(b, 0), lo <= qd <= hi` (a tiny margin keeps the
    next solve feasible).

    A tick asks twice with the same rows and box (the retraction's first level, then the final
    command's projection): the last answer is kept and given again for identical inputs. Feasibility
    needs no QP where a point shows it (the box's point nearest 0 meets every row) or one row shows
    the opposite (its largest value over the box is below its bound); one row has the slack in
    closed form (s = its bound minus that largest value)."""
    global _last_relaxed
    A, b, lo, hi = (np.ascontiguousarray(a, dtype=np.float64) for a in (A, b, lo, hi))
    key = (A.shape, A.tobytes(), b.tobytes(), lo.tobytes(), hi.tobytes())
    if _last_relaxed[0] == key:
        return _last_relaxed[1].copy()
    out = _relaxed(A, b, lo, hi)
    _last_relaxed = (key, out)
    return out.copy()


def _relaxed(A, b, lo, hi) -> np.ndarray:
    n, K = A.shape[1], len(A)
    b0 = np.minimum(b, 0.0)
    reach = _box_max(A, lo, hi)
    alone = bool((reach >= b0).all())  # every row can be met on its own
    if alone and (K == 1 or (A @ np.clip(0.0, lo, hi) >= b0).all()):
        return b0
    if not alone and K == 1:
        return reach - _margin(A)  # b0 - s with s = b0 - reach
    if alone:
        C = np.zeros((n + K, n))
        C[:n] = np.eye(n)
        C[n:] = A
        _, ok, _ = solve(np.eye(n), np.zeros(n), C, np.concatenate([lo, b0]), np.concatenate([hi, np.full(K, BIG)]))
        if ok:
            return b0
    H = np.diag(np.concatenate([np.full(n, 1e-9), np.ones(K)]))
    C = np.zeros((n + 2 * K, n + K))
    C[:n, :n] = np.eye(n)
    C[n:n + K, :n], C[n:n + K, n:] = A, np.eye(K)
    C[n + K:, n:] = np.eye(K)
    xs, ok, _ = solve(H, np.zeros(n + K), C, np.concatenate([lo, b0, np.zeros(K)]),
                      np.concatenate([hi, np.full(2 * K, BIG)]))
    s = xs[n:] if ok else np.maximum(b0 - A @ np.clip(0.0, lo, hi), 0.0)  # the box's point nearest 0
    return b0 - s - _margin(A)


_last_relaxed: tuple = (None, None)  # (inputs, answer) of the last `relaxed_bounds`


@numba.njit(cache=True, nogil=True)
def _box_max(A, lo, hi):
    """(K,) the largest value of each row `a_k . qd` over the box lo <= qd <= hi."""
    K, n = A.shape
    out = np.zeros(K)
    for k in range(K):
        for j in range(n):
            out[k] += max(A[k, j] * lo[j], A[k, j] * hi[j])
    return out


def unreachable(A, b, lo, hi) -> bool:
    """True when some row `a_k . qd >= b_k` cannot be met anywhere in the box, not even to `solve`'s
    tolerance (so a QP over the rows and the box could only fail)."""
    return bool(len(b)) and bool((_box_max(A, lo, hi) < b - 1e-7 * (1 + np.abs(b))).any())


def _margin(A) -> np.ndarray:
    """How far relaxed no-push rows are lowered below just feasible: `MARGIN` x (1 + the row's 1-norm)."""
    return MARGIN * (1 + np.abs(A).sum(axis=1))


def recursive_qdot(J, r, damping: float, sv_threshold: float, rank_tol: float = 1e-3) -> np.ndarray:
    """The closed-form reference: `qd_k = qd_(k-1) + (J_k N_(k-1))^# (r_k - J_k qd_(k-1))` with the
    filtered DLS inverse and `N_k` the projector onto the null space of tasks 1..k (no limits,
    no inequalities)."""
    K, _, n = J.shape
    x, N = np.zeros(n), np.eye(n)
    for k in range(K):
        M = J[k] @ N
        U, S, Vt = np.linalg.svd(M, full_matrices=False)
        keep = S > rank_tol * max(np.linalg.norm(J[k]), 1e-12)
        if not keep.any():
            continue
        inv = np.where(keep, S / _filtered(S, damping, sv_threshold), 0.0)
        x = x + Vt.T @ (inv * (U.T @ (r[k] - J[k] @ x)))
        V = Vt[keep]
        N = N - V.T @ V
    return x
