"""The prioritised QP (qp.py) against the closed-form recursion, the J_i qd_(i-1) correction,
priority-preserving saturation and the no-push constraints, on random small problems."""
from pathlib import Path

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from skinsafe.core.safety.qp import _svd, prioritised, recursive_qdot
from skinsafe.core.safety.retraction import merge, single_qdots

FAST = settings(max_examples=60, deadline=None)
BIG = np.full(7, 1e3)


def solve(J, r, A=None, b=None, lo=None, hi=None, n=None):
    n = J.shape[2]
    A = np.zeros((0, n)) if A is None else A
    b = np.zeros(len(A)) if b is None else b
    lo = -BIG[:n] if lo is None else lo
    hi = BIG[:n] if hi is None else hi
    return prioritised(J, r, A, b, lo, hi, np.maximum(np.abs(lo), np.abs(hi)), 0.05, 0.05)


@FAST
@given(seed=st.integers(0, 2 ** 32 - 1), K=st.integers(1, 8), n=st.sampled_from([6, 7]))
def test_equals_the_recursion_when_nothing_binds(seed, K, n):
    rng = np.random.default_rng(seed)
    J, r = rng.normal(size=(K, 3, n)), rng.normal(size=(K, 3)) * 0.1
    sol = solve(J, r)
    assert np.allclose(sol.qd, recursive_qdot(J, r, 0.05, 0.05), atol=1e-5)
    assert not (sol.limited or sol.blocked or sol.infeasible)


@FAST
@given(seed=st.integers(0, 2 ** 32 - 1))
def test_lower_task_exact_where_dofs_allow_unlike_the_old_merge(seed):
    """Two 3-D tasks on 6 joints: the recursion with the J_2 qd_1 correction meets both exactly;
    the closed-form joint-space merge (no correction) misses the second."""
    rng = np.random.default_rng(seed)
    J, d, sp = rng.normal(size=(2, 6, 6)), rng.normal(size=(2, 3)), rng.uniform(0.05, 0.2, 2)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    r = d * sp[:, None]
    N1 = np.eye(6) - np.linalg.pinv(J[0, :3]) @ J[0, :3]
    assume(min(np.linalg.svd(J[0, :3])[1].min(), np.linalg.svd(J[1, :3] @ N1)[1][:3].min()) > 0.1)  # undamped
    qd = solve(J[:, :3], r).qd
    for k in range(2):
        assert np.allclose(J[k, :3] @ qd, r[k], atol=1e-6)
    old = merge(single_qdots(J, d, sp, _params()), np.einsum("kij,ki->kj", J[:, :3], d), 1.0)
    assert np.linalg.norm(J[1, :3] @ old - r[1]) > 1e-3 * np.linalg.norm(r[1])


def _params():
    from skinsafe.core.safety.retraction import RetractionParams

    return RetractionParams(merge="joint")


@FAST
@given(seed=st.integers(0, 2 ** 32 - 1), scale=st.sampled_from([3.0, 30.0, 1e4]))
def test_saturation_spares_the_dominant_task(seed, scale):
    """A lower task asking for far more than the limits allow is saturated first: the dominant
    task stays exact as long as it fits in the box on its own (Flacco et al. 2012)."""
    rng = np.random.default_rng(seed)
    J = rng.normal(size=(2, 3, 6))
    r = np.vstack([rng.normal(size=3) * 0.05, rng.normal(size=3) * scale])
    lim = np.full(6, 1.0)
    alone = solve(J[:1], r[:1], lo=-lim, hi=lim)
    both = solve(J, r, lo=-lim, hi=lim)
    assert np.all(np.abs(both.qd) <= lim + 1e-12)
    if not alone.limited:
        assert np.allclose(J[0] @ both.qd, r[0], atol=1e-6)
        assert both.dominant_residual < 1e-6


@FAST
@given(seed=st.integers(0, 2 ** 32 - 1), K=st.integers(2, 64), kind=st.sampled_from(["random", "same", "opposite"]))
def test_no_push_rows_hold_and_pinches_are_flagged(seed, K, kind):
    rng = np.random.default_rng(seed)
    J = rng.normal(size=(K, 3, 6))
    if kind != "random":  # every contact on one point of one link: identical or opposite normals
        J[:] = J[0]
    d = rng.normal(size=(K, 3))
    if kind == "same":
        d[:] = d[0]
    if kind == "opposite":
        d[1::2] = -d[0]
        d[0::2] = d[0]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    r = d * rng.uniform(0.01, 0.3, (K, 1))
    A = np.einsum("kij,ki->kj", J, d)
    sol = solve(J, r, A, lo=-np.full(6, 3.0), hi=np.full(6, 3.0))
    assert np.all(np.isfinite(sol.qd))
    assert np.all(A @ sol.qd >= -1e-6 * (1 + np.abs(A).max()))
    if kind == "opposite":  # a pinch: the dominant taxel cannot retract without pushing the other in
        assert sol.blocked and sol.dominant_residual > 0.99
        assert np.allclose(sol.qd, 0, atol=1e-5)  # DAQP primal tolerance 1e-6 per row


def test_infeasible_box_keeps_limits_least_violation_and_says_so():
    """Moving into a contact faster than one tick's deceleration allows: the limits hold, the
    command brakes as hard as they allow (the least violation), flagged infeasible."""
    J = np.zeros((1, 3, 6))
    J[0, 0, 0] = 1.0
    r = np.array([[0.1, 0.0, 0.0]])
    A = np.array([[1.0, 0, 0, 0, 0, 0]])  # joint 0 positive = away from the contact
    prev = np.array([-1.0, 0, 0, 0, 0, 0])  # moving into it at 1 rad/s
    lo, hi = prev - 0.03, prev + 0.03
    sol = prioritised(J, r, A, np.zeros(1), lo, hi, np.full(6, 3.0), 0.05, 0.05)
    assert sol.infeasible and sol.qd[0] == pytest.approx(-0.97)
    pushing = prioritised(J, r, A, np.array([0.02]), -np.full(6, 3.0), np.full(6, 3.0), np.full(6, 3.0), 0.05, 0.05)
    assert not pushing.infeasible and pushing.qd[0] >= 0.02 - 1e-9


@FAST
@given(st.integers(0, 10 ** 6), st.sampled_from([3, 6]), st.integers(1, 7), st.sampled_from(["full", "dup", "rank1", "zero"]))
def test_compiled_svd_matches_lapack(seed, m, d, kind):
    """qp._svd (Jacobi, no LAPACK) against np.linalg.svd on the level blocks J_k Z, incl. rank
    deficient and zero ones: same singular values, M = U S V^T, orthonormal U and full V."""
    rng = np.random.default_rng(seed)
    M = rng.normal(size=(m, d))
    if kind == "dup" and d > 1:
        M[:, 1] = 2 * M[:, 0]
    elif kind == "rank1":
        M = np.outer(rng.normal(size=m), rng.normal(size=d))
    elif kind == "zero":
        M[:] = 0.0
    S, U, Vt = _svd(M)
    S0 = np.linalg.svd(M, compute_uv=False)
    scale = max(S0[0], 1.0)
    k = min(m, d)
    assert S.shape == (k,) and U.shape == (m, k) and Vt.shape == (d, d)
    np.testing.assert_allclose(S, S0, atol=1e-12 * scale)
    np.testing.assert_allclose(U @ np.diag(S) @ Vt[:k], M, atol=1e-12 * scale)
    np.testing.assert_allclose(U.T @ U, np.eye(k), atol=1e-12)
    np.testing.assert_allclose(Vt @ Vt.T, np.eye(d), atol=1e-12)
    assert np.all(np.diff(S) <= 1e-12 * scale)  # descending


def test_a_level_daqp_calls_infeasible_is_retried_and_solved():
    """A level problem recorded in the audit (Panda, 8 contacts, case 14): H's condition 2.9e8, its
    region strictly feasible (margin 2e-5 by linear programming), yet DAQP alone stops cycling."""
    import daqp

    from skinsafe.core.safety import qp

    p = np.load(Path(__file__).parent / "data" / "daqp_cycling_level.npz")
    H, f, C, lower, upper = (np.ascontiguousarray(p[k]) for k in ("H", "f", "C", "lower", "upper"))
    assert daqp.solve(H, f, C, upper, lower, np.zeros(len(lower), np.int32), primal_tol=1e-9)[2] < 1
    x, ok, _ = qp.solve(H, f, C, lower, upper)
    cx = C @ x
    assert ok and np.all(cx >= lower - 1e-7) and np.all(cx <= upper + 1e-7)


@pytest.mark.parametrize("case", ["ur5_post", "panda_patch"])
def test_a_least_violation_sliver_is_solved_not_called_a_solver_failure(case):
    """Contacts met at speed (recorded: the UR5 sample's post at 0.23 rad/s of the shoulder pan, the runtime bench's
    contact; a Panda patch of five taxels): no command in the acceleration box keeps every contact, the rows are
    relaxed to the least violation, and that region is a sliver DAQP called infeasible with H's condition near 6e8.
    With the rows lowered by at most `WIDEN[-1]` x `MARGIN` it solves: the command is in the box, meets every relaxed
    row to that margin, and is no solver failure (that latched every sim contact at speed as a protective stop)."""
    from skinsafe.core.safety import qp

    p = np.load(Path(__file__).parent / "data" / "least_violation_slivers.npz")
    J, r, A, b, lo, hi, vel = (p[f"{case}_{k}"] for k in ("J", "r", "A", "b", "lo", "hi", "vel"))
    damping, sv, rank_tol = p[f"{case}_params"]
    assert qp.unreachable(A, b, lo, hi)  # the contact cannot be kept this tick
    sol = prioritised(J, r, A, b, lo, hi, vel, damping, sv, rank_tol)
    assert sol.infeasible and not sol.solver_failed
    assert np.all(sol.qd >= lo - 1e-9) and np.all(sol.qd <= hi + 1e-9)
    relaxed = qp.relaxed_bounds(A, b, lo, hi)
    assert np.all(A @ sol.qd >= relaxed - qp.WIDEN[-1] * qp._margin(A) - 1e-7)
    assert np.linalg.norm(sol.qd) > 0.2  # the arm is not simply stopped: it brakes from its speed at its limit


def test_a_qp_without_a_solution_sends_zero_within_the_box_and_says_so(monkeypatch):
    from skinsafe.core.safety import qp

    rng = np.random.default_rng(3)
    J, r = rng.normal(size=(2, 3, 6)), rng.normal(size=(2, 3))
    A, b = rng.normal(size=(2, 6)), np.zeros(2)
    lo, hi = np.full(6, 0.1), np.full(6, 0.5)  # zero is outside: the command is clipped into the box
    monkeypatch.setattr(qp, "solve", lambda H, f, C, lower, upper: (np.zeros(len(H)), False, np.zeros(len(lower))))
    sol = prioritised(J, r, A, b, lo, hi, np.full(6, 3.0), 0.05, 0.05)
    assert sol.solver_failed and np.allclose(sol.qd, 0.1)


def _relaxed_by_qp(A, b, lo, hi):
    """The QP-only answer (no shortcut): the feasibility QP, else the least-violation QP."""
    from skinsafe.core.safety import qp

    n, K = A.shape[1], len(A)
    b0 = np.minimum(b, 0.0)
    _, ok, _ = qp.solve(np.eye(n), np.zeros(n), np.vstack([np.eye(n), A]), np.r_[lo, b0], np.r_[hi, np.full(K, qp.BIG)])
    if ok:
        return b0
    H = np.diag(np.r_[np.full(n, 1e-9), np.ones(K)])
    C = np.zeros((n + 2 * K, n + K))
    C[:n, :n], C[n:n + K, :n], C[n:n + K, n:], C[n + K:, n:] = np.eye(n), A, np.eye(K), np.eye(K)
    xs, ok, _ = qp.solve(H, np.zeros(n + K), C, np.r_[lo, b0, np.zeros(K)], np.r_[hi, np.full(2 * K, qp.BIG)])
    assert ok
    return b0 - xs[n:] - qp._margin(A)


@settings(max_examples=300, deadline=None)
@given(seed=st.integers(0, 2 ** 32 - 1), K=st.integers(1, 6), n=st.sampled_from([6, 7]),
       box=st.sampled_from(["around0", "away", "thin"]))
def test_relaxed_bounds_shortcuts_give_the_qps_answer(seed, K, n, box):
    """The certificate (the box's point nearest 0), the one-row infeasibility test and the one-row closed form give
    what the QPs give, to solver tolerance; a repeated call with other rows or box is never served the last answer."""
    from skinsafe.core.safety import qp

    rng = np.random.default_rng(seed)
    A = rng.normal(size=(K, n))
    b = rng.normal(scale=2.0, size=K)
    centre = {"around0": 0.0, "away": rng.normal(scale=3.0), "thin": rng.normal()}[box]
    half = 1e-3 if box == "thin" else rng.uniform(0.1, 2.0)
    lo, hi = centre + rng.uniform(-1, 0, n) * half - half, centre + rng.uniform(0, 1, n) * half + half
    got = qp.relaxed_bounds(A, b, lo, hi)
    want = _relaxed_by_qp(A, b, lo, hi)
    assert np.allclose(got, want, atol=1e-6, rtol=1e-6)
    assert (got <= np.minimum(b, 0.0) + 1e-12).all()
    _, ok, _ = qp.solve(np.eye(n), np.zeros(n), np.vstack([np.eye(n), A]), np.r_[lo, got], np.r_[hi, np.full(K, qp.BIG)])
    assert ok  # the relaxed rows meet the box
    other = b + 1.0
    assert np.allclose(qp.relaxed_bounds(A, other, lo, hi), _relaxed_by_qp(A, other, lo, hi), atol=1e-6, rtol=1e-6)
    assert np.array_equal(qp.relaxed_bounds(A, b, lo, hi), got)  # the same inputs again: the same answer
