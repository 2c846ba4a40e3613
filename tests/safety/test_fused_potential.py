"""The compiled few-row TDM potential (`FastPotential`'s forward, backward and fused passes over
the blocked head) and the evaluator the strategy filter and the modulation share."""
import numpy as np
import pytest
import torch

from skinsafe.core.design.sample import make_sample_design
from skinsafe.core.robot.kinematics import TaxelKinematics
from skinsafe.core.robot.models import build_ur5
from skinsafe.core.safety.defensiveness import DefensivenessLayer
from skinsafe.core.safety.modulation import ModulationLayer
from skinsafe.core.safety.potential import FUSED_ROWS, DangerPotential, FastPotential, potential_and_normal
from skinsafe.core.safety.stack import PRIOR, SafetyStack, StrategyFilter
from skinsafe.core.safety.tdm import TactileDangerModel


def _tdm(n, seed=0):
    torch.manual_seed(seed)
    tdm = TactileDangerModel(6, 6, n, (32, 32)).eval()
    with torch.no_grad():
        tdm.head.bias.uniform_(-14.0, 0.5)  # logits on both sides of 0, and some far below
    return tdm


@pytest.mark.parametrize("n", [1, 100, 640])  # a partial last block, and whole blocks
def test_few_rows_agree_with_blas_and_autograd(n):
    pot = DangerPotential(_tdm(n))
    fp = FastPotential(pot)
    rng = np.random.default_rng(n)
    s, a = rng.normal(size=(3, 6)), rng.normal(size=(3, 6))
    f, g = fp(s, a)  # compiled passes
    many_s, many_a = np.repeat(s, 4, 0), np.repeat(a, 4, 0)
    assert len(many_s) > FUSED_ROWS
    f_blas, g_blas = fp(many_s, many_a)  # BLAS path
    f_ref, g_ref = potential_and_normal(pot, s, a)
    assert np.allclose(f, f_blas[::4], rtol=1e-5, atol=1e-12) and np.allclose(f, f_ref, rtol=1e-5)
    assert np.allclose(g, g_blas[::4], rtol=1e-4, atol=1e-7) and np.allclose(g, g_ref, rtol=1e-4, atol=1e-7)
    assert np.allclose(fp.log_safety(s, a), fp.log_safety(many_s, many_a)[::4], rtol=1e-5)


def test_scored_candidates_give_the_same_normal_without_a_second_forward_pass():
    fp, fresh = FastPotential(DangerPotential(_tdm(300))), FastPotential(DangerPotential(_tdm(300)))
    rng = np.random.default_rng(1)
    s, a = rng.normal(size=6), rng.normal(size=6)
    cand = np.array([1.0, 0.5, 0.0])[:, None] * a
    fp.log_safety(np.broadcast_to(s, (3, 6)), cand)
    for k in range(3):
        assert fp._recall(s, cand[k]) == (0, k)
        f, g = fp(s, cand[k])
        f2, g2 = fresh(s, cand[k])
        assert np.allclose(f, f2, rtol=1e-12) and np.allclose(g, g2, rtol=1e-6, atol=1e-12)
    assert fp._recall(s, 0.25 * a) == (-1, -1) and fp._recall(s + 1e-12, cand[0]) == (-1, -1)


def test_stack_reads_the_head_once_per_tick_where_the_first_candidate_wins_or_it_retracts():
    robot = build_ur5()
    design = make_sample_design("ur5", robot=robot)
    kin = TaxelKinematics(robot.model, design)
    n = design.n_taxels
    tdm = _tdm(n)
    with torch.no_grad():
        tdm.head.bias.fill_(-12.0)  # little danger: the commanded candidate wins
    calls = []
    for prior in (PRIOR, np.ones(3)):
        d = DefensivenessLayer(kin, design.taxels.thresholds, robot.vel_limits, robot.acc_limits, dt=0.002)
        stack = SafetyStack(robot.vel_limits, d, ModulationLayer(DangerPotential(tdm)), StrategyFilter(tdm, prior=prior),
                            dt=0.002)
        fp = stack.strategy.fast
        assert fp is stack.modulation._eval
        count = {"rows": 0, "backward": 0, "fused": 0}
        fwd, bwd, fused = fp._forward, fp._normal, fp._fused
        fp._forward = lambda s, a: (count.__setitem__("rows", count["rows"] + np.atleast_2d(a).shape[0]), fwd(s, a))[1]
        fp._normal = lambda *x: (count.__setitem__("backward", count["backward"] + 1), bwd(*x))[1]
        fp._fused = lambda *x: (count.__setitem__("fused", count["fused"] + 1), fused(*x))[1]
        cmd = np.array([0.3, -0.2, 0.1, 0.2, 0.1, -0.1])
        for i in range(20):
            stack.tick(i * 0.002, robot.home, {"force": np.zeros(n)}, cmd, 0.002)
        calls.append(dict(count))
        force = np.zeros(n)
        force[np.argmax(kin.body_id)] = 40.0  # a contact: retraction, the strategy filter is not asked
        count["rows"] = count["backward"] = count["fused"] = 0
        for i in range(20, 30):
            stack.tick(i * 0.002, robot.home, {"force": force}, cmd, 0.002)
            assert d.active
        calls.append(dict(count))
    assert calls[0] == {"rows": 20, "backward": 20, "fused": 0}  # one forward row + the backward per tick
    assert calls[1] == {"rows": 0, "backward": 0, "fused": 10}  # retracting: the modulation's own pass, one read
    assert calls[2] == {"rows": 60, "backward": 20, "fused": 0}  # flat prior: every candidate scored, one backward


def test_a_caller_reusing_its_arrays_gets_fresh_values():
    fp, fresh = FastPotential(DangerPotential(_tdm(200))), FastPotential(DangerPotential(_tdm(200)))
    rng = np.random.default_rng(2)
    s, a = rng.normal(size=(1, 6)), rng.normal(size=(1, 6))
    fp.log_safety(s, a)
    a *= 3.0  # in place: the kept candidate must not follow
    assert fp._recall(s[0], a[0]) == (-1, -1)
    assert np.allclose(fp(s[0], a[0])[1], fresh(s[0], a[0])[1], rtol=1e-6, atol=1e-12)


def test_bench_sized_head_agrees_with_autograd_at_16384_taxels():
    """The bench's TDM (hidden 128, 16,384 taxels): the one-read pass (`_fused`), and the scored
    candidates' forward plus backward, against autograd in float64; the skipped hidden units (0
    after the trunk's ReLU) are really there."""
    from skinsafe.core.bench.modulation import _tdm as bench_tdm

    pot = DangerPotential(bench_tdm(16384, 128).double())
    fp = FastPotential(pot)
    rng = np.random.default_rng(7)
    s, a = rng.uniform(-1, 1, (3, 6)), rng.uniform(-1, 1, (3, 6))
    h = fp._trunk(s, a)[-1]
    assert 0.2 < (h == 0).mean() < 0.8
    f_ref, n_ref = potential_and_normal(pot, s, a, dtype=torch.float64)
    fp.log_safety(s, a)
    for k in range(3):
        log_safe, n_fused = fp._fused(s[k:k + 1], a[k:k + 1])
        assert fp._recall(s[k], a[k]) == (0, k)  # the scored row: the backward pass
        for f, n in (fp(s[k], a[k]), (-np.expm1(log_safe), n_fused)):
            assert abs(f[0] - f_ref[k]) <= 1e-5 * f_ref[k]
            assert np.abs(n - n_ref[k]).max() <= 1e-4 * np.abs(n_ref[k]).max()


def test_bench_full_tick_commands_match_the_reference_at_16384_taxels():
    import argparse

    from skinsafe.core.bench.modulation import rows

    out = rows(argparse.Namespace(taxels=[16384], active=[8], hidden=128, repeat=20, nstep=False, no_full=False))
    full = out[1]
    assert full["n_taxels"] == 16384 and full["layer"] == "full"
    assert full["max_abs_diff"] < 1e-6  # every timed tick of both kinds, fast vs the autograd reference
