"""Tactile danger potential (eq. 4-5), its fast evaluator, and the n-step potential (eq. 8)."""
import numpy as np
import pytest
import torch
from scipy.special import expit

from skinsafe.core.safety.modulation import ModulationLayer
from skinsafe.core.safety.potential import (
    DangerPotential,
    EulerDynamics,
    FastPotential,
    NStepConfig,
    NStepPotential,
    UniformPolicy,
    distill_nstep,
    nstep_targets,
    potential_and_normal,
)
from skinsafe.core.safety.tdm import TactileDangerModel


def _tdm(n_taxels=40, seed=0, dtype=torch.float32):
    torch.manual_seed(seed)
    tdm = TactileDangerModel(3, 2, n_taxels, (16, 16)).to(dtype).eval()
    with torch.no_grad():
        tdm.head.bias.fill_(-5.0)
    return tdm


def test_potential_is_total_danger_and_gradient_matches_finite_differences():
    tdm = _tdm(dtype=torch.float64)
    pot = DangerPotential(tdm)
    rng = np.random.default_rng(0)
    s, a = rng.normal(size=(5, 3)), rng.normal(size=(5, 2))
    f, n = potential_and_normal(pot, s, a, dtype=torch.float64)
    with torch.no_grad():
        p = torch.sigmoid(tdm(torch.tensor(s), torch.tensor(a))).numpy()
    assert np.allclose(f, 1 - np.prod(1 - p, axis=1), rtol=1e-10)
    assert 0.05 < f.min() and f.max() < 0.95  # a non-trivial field
    h = 1e-6
    for j in range(3):
        e = np.zeros(3)
        e[j] = h
        fp, _ = potential_and_normal(pot, s + e, a, dtype=torch.float64)
        fm, _ = potential_and_normal(pot, s - e, a, dtype=torch.float64)
        assert np.allclose(n[:, j], (fp - fm) / (2 * h), rtol=1e-5, atol=1e-9)


def test_fast_potential_matches_autograd_for_tdm_and_nstep_net():
    rng = np.random.default_rng(1)
    s, a = rng.normal(size=(7, 3)), rng.normal(size=(7, 2))
    pot = DangerPotential(_tdm())
    net = NStepPotential(3, 2, hidden=8)
    net.mean.copy_(torch.tensor([0.1, -0.2, 0.3, 0.0, 0.5]))
    net.std.copy_(torch.tensor([1.0, 2.0, 0.5, 1.0, 3.0]))
    for p in (pot, net):
        f_ref, n_ref = potential_and_normal(p, s, a)
        f, n = FastPotential(p)(s, a)
        assert np.allclose(f, f_ref, rtol=1e-5)
        assert np.allclose(n, n_ref, rtol=1e-4, atol=1e-7)
        assert np.abs(n_ref).max() > 1e-3
    with pytest.raises(TypeError, match="potential_and_normal"):
        FastPotential(torch.nn.Linear(3, 1))


def test_huge_states_give_finite_potential_and_normal():
    pot = DangerPotential(_tdm())
    s = np.array([[1e6, -1e6, 1e7], [0.0, 0.0, 0.0]])
    a = np.array([[1e6, 1e6], [0.0, 0.0]])
    for f, n in (potential_and_normal(pot, s, a), FastPotential(pot)(s, a)):
        assert np.isfinite(f).all() and np.isfinite(n).all()
        assert ((0 <= f) & (f <= 1)).all()
    v, fv = ModulationLayer(pot)(s[0], np.ones(3), a[0])
    assert np.isfinite(v).all() and 0 <= fv <= 1


class Wall(torch.nn.Module):
    """A sharp 1-D danger: f(s) = sigmoid(k (s - 1)), independent of the action."""

    def forward(self, s, a):
        return torch.sigmoid(40.0 * (s[:, 0] - 1.0))


def test_nstep_targets_match_exact_expectation():
    pot, dyn, pol = Wall(), EulerDynamics(0.2), UniformPolicy([-1.0], [1.0])
    s0, a0 = np.array([[0.7], [0.9], [0.2]]), np.array([[1.0], [0.5], [-1.0]])
    f = lambda x: expit(40.0 * (x - 1.0))  # noqa: E731
    assert np.allclose(nstep_targets(pot, s0, a0, dyn, pol, NStepConfig(1, 0.9, 8)), f(s0[:, 0]), atol=1e-6)
    g = 0.8
    w = nstep_targets(pot, s0, a0, dyn, pol, NStepConfig(3, g, 4096), seed=3)
    s1 = s0[:, 0] + 0.2 * a0[:, 0]
    grid = np.linspace(-1, 1, 20001)
    e2 = f(s1[:, None] + 0.2 * grid[None]).mean(1)  # E over a1 ~ U[-1, 1] of f(s1 + dt a1)
    exact = np.minimum(f(s0[:, 0]) + g * f(s1) + g * g * e2, 1.0)
    assert np.allclose(w, exact, atol=0.01)
    # 0.7 heading toward the wall at 1.0: f is ~0 but w already sees the danger coming
    assert f(0.7) < 1e-5 and w[0] > 0.05


def test_distilled_nstep_potential_foresees_danger():
    pot, dyn, pol = Wall(), EulerDynamics(0.2), UniformPolicy([-1.0], [1.0])
    rng = np.random.default_rng(0)
    s = rng.uniform(0, 1.5, (400, 1))
    a = rng.uniform(-1, 1, (400, 1))
    net, info = distill_nstep(pot, s, a, dyn, pol, NStepConfig(4, 0.9, 32), state_noise=0.05, epochs=60, seed=0)
    assert info["rmse"] < 0.05
    probe_s, probe_a = np.array([[0.75]]), np.array([[1.0]])
    f, nf = potential_and_normal(pot, probe_s, probe_a)
    w, nw = FastPotential(net)(probe_s, probe_a)
    assert f[0] < 1e-3 and abs(nf[0, 0]) < 0.05  # the sharp potential is flat here
    assert w[0] > 0.05 and nw[0, 0] > 0.2  # the n-step one rises toward the wall
    layer = ModulationLayer(net)
    v, _ = layer(probe_s[0], np.array([1.0]), probe_a[0])
    assert v[0] < 1.0 - w[0] + 1e-6  # slowed before the boundary


def test_bad_configuration_is_refused():
    pot = Wall()
    with pytest.raises(ValueError, match="horizon"):
        nstep_targets(pot, [[0.0]], [[0.0]], EulerDynamics(0.1), UniformPolicy([-1.0], [1.0]), NStepConfig(0))
    with pytest.raises(ValueError, match="gamma"):
        NStepConfig(2, 1.5).check()
    with pytest.raises(ValueError, match="one action per state"):
        potential_and_normal(pot, np.zeros((3, 1)), np.zeros((2, 1)))
    with pytest.raises(ValueError, match="low <= high"):
        UniformPolicy([1.0], [0.0])
