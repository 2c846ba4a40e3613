"""Eq. 1-3 of the strategy layer against brute force, in log space, and at the edges."""
import itertools

import numpy as np
import pytest
import torch

from skinsafe.core.safety import danger
from skinsafe.core.safety.danger import PolicyFilter
from skinsafe.core.safety.tdm import TactileDangerModel


def sigmoid(x):
    return 1 / (1 + np.exp(-x))


def test_total_danger_matches_union_by_enumeration():
    rng = np.random.default_rng(0)
    logits = rng.normal(size=5) * 2
    p = sigmoid(logits)
    # P(union) by inclusion over all 2^5 outcomes of independent events.
    p_none = 0.0
    for outcome in itertools.product([0, 1], repeat=5):
        pr = np.prod([pi if o else 1 - pi for pi, o in zip(p, outcome)])
        if not any(outcome):
            p_none += pr
    assert danger.total_danger(logits) == pytest.approx(1 - p_none, rel=1e-12)
    assert danger.total_danger_probs(p) == pytest.approx(1 - p_none, rel=1e-12)
    assert float(danger.total_danger(torch.tensor(logits))) == pytest.approx(1 - p_none, rel=1e-12)


def test_log_space_equals_naive_product_where_it_does_not_underflow():
    rng = np.random.default_rng(1)
    logits = rng.normal(-3, 1, size=(4, 300))
    naive = np.prod(1 - sigmoid(logits), axis=1)
    assert naive.min() > 1e-200
    np.testing.assert_allclose(np.exp(danger.log_total_safety(logits)), naive, rtol=1e-10)
    np.testing.assert_allclose(danger.total_danger(logits), 1 - naive, rtol=1e-10)


def test_log_space_is_finite_and_exact_where_the_product_underflows():
    # 10,000 taxels each at p = 0.5: prod(1-p) = 0.5**10000 = 10**-3010 underflows to 0.
    logits = np.zeros(10000)
    assert np.prod(1 - sigmoid(logits)) == 0.0
    ls = danger.log_total_safety(logits)
    assert np.isfinite(ls) and ls == pytest.approx(10000 * np.log(0.5), rel=1e-12)
    assert danger.total_danger(logits) == 1.0
    # Tiny dangers keep their precision: 10,000 taxels at p = 1e-12 -> p(D) = 1e-8 (naive 1 - prod loses it).
    tiny = np.full(10000, np.log(1e-12))
    assert danger.total_danger(tiny) == pytest.approx(1e-8, rel=1e-6)
    t = danger.log_total_safety(torch.full((2, 10000), 50.0))
    assert torch.isfinite(t).all() and float(t[0]) == pytest.approx(-10000 * 50.0, rel=1e-6)


def test_marginal_danger_discrete_and_importance_sampling_agree():
    rng = np.random.default_rng(2)
    d = np.array([0.9, 0.05, 0.3, 0.6])  # p(D|s,a) for 4 actions
    policy = np.array([0.1, 0.6, 0.2, 0.1])
    exact = danger.marginal_danger_discrete(d)  # uniform U(a|s)
    assert exact == pytest.approx(d.mean())
    a = rng.choice(4, size=200000, p=policy)
    est = danger.marginal_danger(d[a], np.log(policy[a]), np.log(np.full(a.size, 0.25)))
    assert est.value == pytest.approx(exact, abs=0.01)
    assert est.weight_mean == pytest.approx(1.0, abs=0.02)  # E_p[U/p] = 1
    # weights 2.5, 0.417, 1.25, 2.5 under p: variance sum p (w-1)^2
    w = 0.25 / policy
    assert est.weight_var == pytest.approx(np.sum(policy * (w - 1) ** 2), rel=0.05)
    assert est.clipped == 0 and est.reliable


def test_importance_weights_stay_finite_when_policy_probability_vanishes():
    log_p = np.array([np.log(0.5), np.log(0.5), np.log(1e-300), -np.inf])
    est = danger.marginal_danger([0.2, 0.4, 0.3, 0.1], log_p, np.log([0.25] * 4))
    assert np.isfinite([est.value, est.weight_mean, est.weight_var, est.ess]).all()
    assert est.clipped == 2  # the two exploding weights hit max_weight = sqrt(4) = 2
    assert est.value == pytest.approx((0.2 * 0.5 + 0.4 * 0.5 + 0.3 * 2 + 0.1 * 2) / 4)
    assert 1 <= est.ess <= 4
    with pytest.raises(ValueError, match="one per sample"):
        danger.marginal_danger([0.1], [0.0, 0.0])


def brute_force_filter(policy, p_danger):
    joint = policy * (1 - p_danger)
    return joint / joint.sum()


@pytest.mark.parametrize("case", ["all_safe", "mixed", "all_dangerous", "all_certain"])
def test_filter_is_a_distribution_and_bayes_exact(case):
    policy = np.array([0.4, 0.3, 0.2, 0.1])
    n_taxels = 50
    per_taxel = {"all_safe": np.full((4, n_taxels), -30.0),
                 "mixed": np.array([[5.0] * n_taxels, [-8.0] * n_taxels, [-2.0] * n_taxels, [0.0] * n_taxels]),
                 "all_dangerous": np.array([[30.0 + k] * n_taxels for k in range(4)]),
                 "all_certain": np.full((4, n_taxels), np.inf)}[case]
    ls = danger.log_total_safety(per_taxel)
    out = danger.filter_probs(policy, ls)
    assert np.all(out >= 0) and out.sum() == pytest.approx(1.0, abs=1e-12)
    if case in ("all_safe", "mixed"):
        np.testing.assert_allclose(out, brute_force_filter(policy, danger.total_danger(per_taxel)), atol=1e-12)
    if case == "all_safe":
        np.testing.assert_allclose(out, policy, atol=1e-10)
    if case == "mixed":
        assert out[0] < 1e-100 and out[1] > policy[1]
    if case == "all_dangerous":
        # p(not D) underflows for every action, yet the least dangerous (action 0, -50*30 nats vs -50*31...) wins.
        assert out[0] == pytest.approx(1.0) and np.isfinite(out).all()
    if case == "all_certain":
        np.testing.assert_allclose(out, policy)  # nothing distinguishes the actions: the policy is kept
    t = danger.filter_log_probs(torch.log(torch.tensor(policy)), torch.tensor(ls))
    np.testing.assert_allclose(t.exp().numpy(), out, atol=1e-12)


def test_continuous_filter_by_sampling_matches_the_bayes_posterior():
    rng = np.random.default_rng(3)
    # p(a|s) = N(0, 1); p(D|s,a) = sigmoid(4 a): the filtered policy leans to negative actions.
    picks = []
    for _ in range(3000):
        a = rng.normal(size=64)
        k, log_z = danger.filter_samples(danger.log_total_safety(4 * a[:, None]), rng)
        picks.append(a[k])
    grid = np.linspace(-6, 6, 4001)
    post = np.exp(-grid ** 2 / 2) * (1 - sigmoid(4 * grid))
    mean_exact = (grid * post).sum() / post.sum()
    assert np.mean(picks) == pytest.approx(mean_exact, abs=0.05)
    assert mean_exact < -0.5
    k, log_z = danger.filter_samples(np.full(5, -np.inf), rng)
    assert 0 <= k < 5 and log_z == -np.inf


class _FixedPolicy:
    def __init__(self, probs):
        self.probs = np.asarray(probs)

    def action_probs(self, states):
        return np.tile(self.probs, (len(np.atleast_2d(states)), 1))


def test_policy_filter_wraps_any_policy_and_composes():
    torch.manual_seed(0)
    model = TactileDangerModel(3, 4, 20, hidden=(16,))
    pf = PolicyFilter(_FixedPolicy([0.25, 0.25, 0.25, 0.25]), model, 4)
    s = np.random.default_rng(0).normal(size=(5, 3))
    out = pf.action_probs(s)
    with torch.no_grad():
        ls = np.stack([danger.log_total_safety(model(torch.tensor(s, dtype=torch.float32),
                                                     torch.eye(4)[[k] * 5]).double().numpy()) for k in range(4)], 1)
    np.testing.assert_allclose(out, np.exp(ls) / np.exp(ls).sum(1, keepdims=True), rtol=1e-6)
    twice = PolicyFilter(pf, model, 4).action_probs(s)  # filtering twice squares the safety factor
    np.testing.assert_allclose(twice, np.exp(2 * ls) / np.exp(2 * ls).sum(1, keepdims=True), rtol=1e-5)
    assert 0 <= pf.act(s[0], np.random.default_rng(0)) < 4
    with pytest.raises(TypeError, match="action_probs"):
        PolicyFilter(object(), model, 4)


def test_eq2_estimate_from_few_samples_is_marked_unreliable():
    """A proposal with little mass where the danger is: with 10 samples the estimate is far off
    and must say so (ESS under MIN_ESS); with 200,000 it is close and reliable."""
    from scipy.special import expit
    from scipy.stats import norm

    rng = np.random.default_rng(3)
    for k, ok in ((10, False), (200_000, True)):
        a = rng.normal(0.5, 0.7, k)
        est = danger.marginal_danger(expit(4 * (a - 1.5)), norm.logpdf(a, 0.5, 0.7),
                                     np.where(np.abs(a) <= 3, -np.log(6.0), -np.inf))
        assert est.reliable is ok and (est.ess < danger.MIN_ESS) is not ok
    assert est.value == pytest.approx(0.2501, abs=0.01)
