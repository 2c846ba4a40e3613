"""Velocity modulation (eq. 6-7): the matrix, the decisions at the edges, and the safety property."""
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from skinsafe.core.safety.modulation import EPS_GRAD, modulate, modulation_matrix


def _unit(x):
    return x / np.linalg.norm(x)


@pytest.mark.parametrize("d", [2, 3, 6, 7])
def test_matrix_symmetric_with_paper_eigenvalues(d):
    rng = np.random.default_rng(d)
    for f in (0.0, 0.3, 0.9, 1.0):
        n = rng.normal(size=d)
        M = modulation_matrix(f, n)[0]
        assert np.allclose(M, M.T)
        w, V = np.linalg.eigh(M)
        assert w[0] == pytest.approx(1 - f, abs=1e-12)
        assert np.allclose(w[1:], 1 + f)
        if f > 0:  # the (1-f) eigenvector is the normal
            assert abs(V[:, 0] @ _unit(n)) == pytest.approx(1.0, abs=1e-9)


def test_modulate_equals_M_v_and_scales_normal_component():
    rng = np.random.default_rng(1)
    n = rng.normal(size=(50, 6))
    v = rng.normal(size=(50, 6))
    f = rng.uniform(0, 1, 50)
    M = modulation_matrix(f, n)
    paper = modulate(v, f, n, keep_away=False)
    assert np.allclose(paper, np.einsum("bij,bj->bi", M, v))
    u = n / np.linalg.norm(n, axis=1, keepdims=True)
    vn = np.sum(u * v, 1)
    assert np.allclose(np.sum(u * paper, 1), (1 - f) * vn)
    # tangential part amplified by (1+f)
    assert np.allclose(paper - np.sum(u * paper, 1)[:, None] * u, (1 + f)[:, None] * (v - vn[:, None] * u))
    kept = modulate(v, f, n)  # default keep_away: leaving motions keep their normal component
    toward = vn >= 0
    assert np.allclose(kept[toward], paper[toward])
    assert np.allclose(np.sum(u * kept, 1)[~toward], vn[~toward])


def test_keep_away_is_continuous_across_the_tangent_plane():
    n = np.array([1.0, 0, 0])
    for f in (0.2, 1.0):
        a = modulate(np.array([1e-9, 1.0, 0]), f, n)
        b = modulate(np.array([-1e-9, 1.0, 0]), f, n)
        assert np.allclose(a, b, atol=1e-8)
        assert np.allclose(a, [0, 1 + f, 0], atol=1e-8)


def test_f_zero_is_identity_and_f_one_stops_the_normal_component():
    rng = np.random.default_rng(2)
    v, n = rng.normal(size=6), rng.normal(size=6)
    assert np.allclose(modulate(v, 0.0, n), v)
    out = modulate(v * np.sign(v @ n), 1.0, n)  # toward danger
    assert np.isfinite(out).all() and abs(out @ _unit(n)) < 1e-12
    assert np.linalg.norm(out) > 0  # the tangential part survives (x2)


def test_tiny_gradient_blends_to_isotropic_slowdown():
    v = np.array([0.3, -0.2, 0.5])
    f = 0.6
    # |n| -> 0: direction undefined, uniform (1-f) slowdown whatever the (noise) direction
    for n in (np.zeros(3), 1e-12 * np.array([1.0, 2, -1]), 1e-12 * np.array([-3.0, 0, 1])):
        assert np.allclose(modulate(v, f, n), (1 - f) * v)
        assert np.allclose(modulation_matrix(f, n)[0], (1 - f) * np.eye(3))
    # |n| = eps/2: normal eigenvalue still 1-f, tangential 1 - f + 2 f b^2 with b = 1/2
    n = np.array([0.0, 0.0, EPS_GRAD / 2])
    w = np.sort(np.linalg.eigvalsh(modulation_matrix(f, n)[0]))
    assert np.allclose(w, [1 - f, 1 - f + 2 * f * 0.25, 1 - f + 2 * f * 0.25])
    # continuous at |n| = eps
    a = modulation_matrix(f, np.array([0, 0, EPS_GRAD * (1 - 1e-9)]))
    b = modulation_matrix(f, np.array([0, 0, EPS_GRAD * (1 + 1e-9)]))
    assert np.allclose(a, b, atol=1e-6)


def test_non_finite_and_huge_inputs():
    v = np.array([1.0, 2.0, -1.0])
    assert np.allclose(modulate(v, np.nan, np.array([1.0, 0, 0])), 0.0)  # unknown danger: stop
    assert np.allclose(modulate(v, 0.5, np.array([np.inf, 0, 0])), 0.5 * v)  # no direction
    huge = modulate(v, 0.5, np.array([1e300, 1e300, 0]))
    assert np.isfinite(huge).all()
    assert np.allclose(huge, modulate(v, 0.5, np.array([1.0, 1.0, 0])))
    assert np.allclose(modulate(v, 7.0, np.array([1.0, 0, 0])), modulate(v, 1.0, np.array([1.0, 0, 0])))  # clipped


@settings(max_examples=300, deadline=None)
@given(f=st.floats(0, 1), n=st.lists(st.floats(-1e6, 1e6), min_size=4, max_size=4),
       v=st.lists(st.floats(-1e3, 1e3), min_size=4, max_size=4), keep=st.booleans())
def test_never_gains_toward_higher_potential(f, n, v, keep):
    n, v = np.array(n), np.array(v)
    out = modulate(v, f, n, keep_away=keep)
    assert np.isfinite(out).all()
    norm = np.linalg.norm(n)
    if norm < EPS_GRAD:
        b2 = (norm / EPS_GRAD) ** 2
        assert np.linalg.norm(out) <= ((1 - f) + 2 * f * b2) * np.linalg.norm(v) + 1e-9
        return
    u = n / norm
    vn, on = v @ u, out @ u
    tol = 1e-9 * (1 + np.abs(v).max())
    if vn >= 0:
        assert on <= (1 - f) * vn + tol
    else:
        assert on <= tol  # still moving away


def test_tangent_gain_zero_never_speeds_up():
    rng = np.random.default_rng(5)
    v, n, f = rng.normal(size=(40, 5)), rng.normal(size=(40, 5)), rng.uniform(0, 1, 40)
    out = modulate(v, f, n, tangent_gain=0.0)
    assert (np.linalg.norm(out, axis=1) <= np.linalg.norm(v, axis=1) + 1e-12).all()
    w = np.linalg.eigvalsh(modulation_matrix(0.4, n[0], tangent_gain=0.0)[0])
    assert np.allclose(np.sort(w), [0.6, 1, 1, 1, 1])


def test_bench_modulation_rows_fast_path_matches_reference():
    import argparse

    from skinsafe.core.bench.modulation import rows

    out = rows(argparse.Namespace(taxels=[256], active=[8], hidden=32, repeat=3, nstep=False, no_full=False))
    assert [(r["layer"], r["n_taxels"]) for r in out] == [("modulation", 256), ("full", 256)]
    full = out[1]
    assert full["active"] == 8 and full["ms"] > 0 and full["ms_worst"] > 0 and full["ms_ref"] > 0
    # ms_worst: the median of the costlier tick kind; the jitter beside it, never folded in
    assert full["ms_worst"] == max(full["ms"], full["ms_all_candidates"])
    assert full["ms_max"] >= full["ms_p99"] >= min(full["ms_best"], full["ms_all_candidates_best"])
    assert full["ms_max"] >= full["ms_worst"]
    assert full["max_abs_diff"] < 1e-4  # the fast potential, modulation and retraction give the same command
