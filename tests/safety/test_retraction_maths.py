"""Retraction maths (eq. 10-13): profile, filtered DLS inverse, the closed-form merges."""
import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from skinsafe.core.safety.retraction import (
    RetractionParams,
    dls_pinv,
    dls_solve,
    merge,
    merge_loop,
    merge_paper,
    ordered_basis,
    profile,
    profile_rate,
    single_qdots,
)

FAST = settings(max_examples=60, deadline=None)


def test_profile_is_eq10():
    u = np.linspace(0, 1, 1001)
    s = profile(u)
    assert s[0] == 0 and s[-1] == pytest.approx(1 / 12, abs=1e-15)
    assert np.all(np.diff(s) >= 0)  # monotone: never back toward the contact
    rate = profile_rate(u)
    assert rate[0] == 0 and rate[-1] == 0
    assert np.allclose(np.gradient(s, u)[1:-1], rate[1:-1], atol=1e-6)
    assert rate.max() == pytest.approx(4 / 27, abs=1e-6) and u[rate.argmax()] == pytest.approx(1 / 3, abs=1e-3)
    assert profile_rate(np.array([-0.5, 1.5])).tolist() == [0.0, 0.0]


def _random_jacobian(rng, K, m, n, rank):
    return rng.normal(size=(K, m, rank)) @ rng.normal(size=(K, rank, n))


@FAST
@given(seed=st.integers(0, 2 ** 32 - 1), m=st.sampled_from([3, 6]), rank=st.integers(0, 6),
       scale=st.sampled_from([1e-8, 1e-3, 1.0, 1e3]), still=st.integers(0, 5))
def test_dls_exact_when_well_conditioned_and_bounded_at_singularities(seed, m, rank, scale, still):
    """3-D and 6-D task blocks of any rank, with `still` joints that do not move the taxel (zero
    columns, as for a taxel on the upper arm); the compiled Jacobi solve against LAPACK's SVD."""
    rng = np.random.default_rng(seed)
    J = _random_jacobian(rng, 4, m, 6, min(rank, m)) * scale
    J[:, :, 6 - still:] = 0.0
    damping, th = 0.05, 0.1
    P = dls_pinv(J, damping, th)
    assert np.all(np.isfinite(P))
    S = np.linalg.svd(J, compute_uv=False)
    a = 1 - damping ** 2 / th ** 2
    bound = max(1 / th, 1 / (2 * damping * np.sqrt(a)))
    assert np.linalg.svd(P, compute_uv=False).max() <= bound * (1 + 1e-9)
    well = S.min(axis=1) >= th
    if well.any():
        assert np.allclose(P[well], np.linalg.pinv(J[well]), atol=1e-9 * max(1, 1 / scale))
    rhs = rng.normal(size=(4, m))
    want = np.einsum("kij,kj->ki", P, rhs)
    noise = 1e-13 * np.abs(J).max() / damping ** 2  # rounding of a zero singular value, damped
    assert np.abs(dls_solve(J, rhs, damping, th) - want).max() <= 1e-10 * np.abs(want).max() + noise
    # the achieved task velocity never points against the requested one
    assert np.all(np.einsum("ki,kij,kjl,kl->k", rhs, J, P, rhs) >= -1e-12)


def _constraint_set(rng, K, n, kind):
    """Rows with the degeneracies of real skins: identical, opposite, collinear, zero."""
    base = rng.normal(size=(max(1, min(K, n - 1)), n))
    A = base[rng.integers(0, len(base), K)] * rng.choice([-1.0, 1.0, 2.5, 1e-6], size=(K, 1))
    if kind == "identical":
        A[:] = A[0]
    elif kind == "opposite":
        A[1::2] = -A[0]
        A[0::2] = A[0]
    elif kind == "generic":
        A = rng.normal(size=(K, n))
    A[rng.random(K) < 0.1] = 0.0
    return A


@FAST
@given(seed=st.integers(0, 2 ** 32 - 1), K=st.integers(1, 40), eps=st.sampled_from([0.0, 0.5, 1.0]),
       kind=st.sampled_from(["mixed", "identical", "opposite", "generic"]))
@example(seed=3107382, K=14, eps=1.0, kind="generic")  # row 7 within rank_tol of rows 0-6: a 0.003 leak, bounded
def test_merge_matches_loop_and_keeps_priorities(seed, K, eps, kind):
    rng = np.random.default_rng(seed)
    n = 6
    A = _constraint_set(rng, K, n, kind)
    qdots = rng.normal(size=(K, n))
    out = merge(qdots, A, eps)
    assert np.all(np.isfinite(out))
    assert np.allclose(out, merge_loop(qdots, A, eps), atol=1e-10)
    U, first = ordered_basis(A)
    assert np.allclose(U.T @ U, np.eye(U.shape[1]), atol=1e-9)
    assert U.shape[1] <= np.linalg.matrix_rank(A) and (kind != "identical" or U.shape[1] <= 1)
    # the dominant task never loses speed along its own direction, whatever eps
    assert A[0] @ out >= A[0] @ qdots[0] - 1e-9 * (1 + np.abs(qdots).sum())
    if eps == 1.0:  # full projection: lower priorities change a higher one's speed only along its residual
        for k in range(K):
            contrib = out - merge(qdots[:k + 1], A[:k + 1], eps)  # what the tasks below k add
            above = U[:, first < k]
            residual = A[k] - above @ (above.T @ A[k])  # a_k's part outside the rows above it
            rounding = 1e-8 * (1 + np.abs(qdots).sum() * np.abs(A[k]).sum())
            # a row that added a column keeps its speed exactly; a row within rank_tol of the rows above
            # (treated as dependent) leaks exactly its residual's share, at most rank_tol * |a_k| * |contrib|
            assert abs(A[k] @ contrib - (residual @ contrib if k not in first else 0.0)) <= rounding
            if k not in first:
                assert np.linalg.norm(residual) <= 1e-3 * np.linalg.norm(A[k]) * (1 + 1e-9) + 1e-12
            assert abs(A[k] @ contrib) <= 1e-3 * np.linalg.norm(A[k]) * np.linalg.norm(contrib) + rounding


def test_merge_eps0_is_plain_sum_without_conflict():
    rng = np.random.default_rng(3)
    A = rng.normal(size=(5, 6))
    qdots = np.abs(rng.normal(size=(5, 6)))
    qdots = np.repeat(qdots[:1], 5, axis=0)  # identical motions: every component helps
    A = np.repeat(qdots[:1], 5, axis=0) + 0.01 * A
    assert np.allclose(merge(qdots, A, 0.0), qdots.sum(axis=0))
    half = merge(qdots, A, 0.5)
    assert A[0] @ qdots.sum(0) > A[0] @ half > A[0] @ merge(qdots, A, 1.0)


def test_merge_removes_opposing_part_even_at_eps0():
    a = np.array([[1.0, 0, 0, 0, 0, 0], [1.0, 0, 0, 0, 0, 0]])
    qd = np.array([[1.0, 0, 0, 0, 0, 0], [-3.0, 1.0, 0, 0, 0, 0]])  # the second pushes the first back
    out = merge(qd, a, 0.0)
    assert np.allclose(out, [1.0, 1.0, 0, 0, 0, 0])


def test_merge_paper_literal_eq13():
    rng = np.random.default_rng(0)
    J = rng.normal(size=(2, 6, 6))
    d = np.array([[0, 0, -1.0], [0, -1.0, 0]])
    p = RetractionParams(form="3d", epsilon=1.0)
    sp = np.array([1.0, 2.0])
    one = merge_paper(J[:1], d[:1], sp[:1], p)
    assert np.allclose(one, single_qdots(J[:1], d[:1], sp[:1], p)[0])
    Jt = J[:, :3]
    P = [np.linalg.pinv(Jt[i]) for i in range(2)]
    r0, r1 = Jt[0] @ P[0] @ (d[0] * sp[0]), Jt[0] @ P[1] @ (d[1] * sp[1])
    want = P[0] @ (r0 + (np.eye(3) - np.outer(r0, r0) / (r0 @ r0)) @ r1)
    assert np.allclose(merge_paper(J, d, sp, p), want, atol=1e-9)


def test_params_errors_name_the_field():
    with pytest.raises(ValueError, match="'epsilon'.*\\[0, 1\\]"):
        RetractionParams(epsilon=1.5)
    with pytest.raises(ValueError, match="'form'"):
        RetractionParams(form="4d")
    with pytest.raises(ValueError, match="'T'"):
        RetractionParams(T=0.0)
