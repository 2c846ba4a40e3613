"""`skinsafe bench modulation`: one modulation tick and one full three-layer tick.

Rows: `layer` ("modulation": potential + gradient + M v for one UR5 state; "full": the safety
stack's strategy filter + modulation + defensiveness with `active` contacts), `n_taxels`,
`active`, `ms` (median, one thread) and `ms_ref`/`speedup_vs_ref` against the simple reference
in the same run (autograd for the normal, the layers one after another without the fast paths).
Full rows: `ms` is the median tick with `active` contacts retracting; `ms_all_candidates` the
median of the other costly kind of tick, no contact and a flat prior, so that the strategy
filter must score every candidate. `ms_worst` is the median of the costlier kind (the larger of
the two medians: the worst case of work a tick does, deterministic); the jitter is reported
beside it, not folded in: `ms_p99` the 99th percentile and `ms_max` the largest single tick over
both kinds (on a shared machine mostly the load of other processes), `ms_best` /
`ms_all_candidates_best` the fastest tick of each kind (on a loaded machine the closest to its
unloaded cost). `ms_ref_worst`, `worst_speedup_vs_ref` the same for the reference. The four are
timed interleaved in blocks of 20 ticks (`timing.interleaved_ms`), so that the load of a shared
machine falls on all alike; `max_abs_diff` is the largest difference between the commands of the
two paths over every timed tick (each fast stack ticks in step with its reference).
With `--nstep`, rows `layer` = "nstep" add the Monte Carlo trade of eq. 8 on a sharp potential:
horizon and samples vs the RMS error of w against 1,024 rollouts, the time for 256 states, and
`reach` (how much danger w already shows 0.1 before the edge, where f is about 0.02).
"""
from __future__ import annotations

import numpy as np
import torch

from skinsafe.core.realtime import single_thread_blas
from skinsafe.core.safety.modulation import ModulationLayer, modulate
from skinsafe.core.safety.potential import (
    DangerPotential,
    EulerDynamics,
    NStepConfig,
    UniformPolicy,
    nstep_targets,
    nstep_trade,
    potential_and_normal,
)
from skinsafe.core.safety.stack import PRIOR, SafetyStack, StrategyFilter
from skinsafe.core.safety.tdm import TactileDangerModel
from skinsafe.core.timing import interleaved_ms, median_ms

DT = 0.002  # s: the control period of the benched ticks (a 500 Hz robot)


def add_arguments(p) -> None:
    p.add_argument("--taxels", type=int, nargs="+", default=[1024, 4096, 16384], help="TDM output sizes")
    p.add_argument("--active", type=int, nargs="+", default=[8], help="active contacts for the full tick")
    p.add_argument("--hidden", type=int, default=128, help="TDM hidden width (two layers)")
    p.add_argument("--repeat", type=int, default=200)
    p.add_argument("--nstep", action="store_true", help="also measure the n-step Monte Carlo trade")
    p.add_argument("--no-full", action="store_true", help="skip the full three-layer rows")


def _tdm(n_taxels: int, hidden: int, seed: int = 0) -> TactileDangerModel:
    torch.manual_seed(seed)
    tdm = TactileDangerModel(6, 6, n_taxels, (hidden, hidden)).eval()
    with torch.no_grad():  # a trained-looking field: most taxels far from danger, f well inside (0, 1)
        tdm.head.bias.fill_(-4.6 - np.log(n_taxels / 8))
    return tdm


def modulation_rows(taxels, hidden: int, repeat: int) -> list[dict]:
    rows = []
    rng = np.random.default_rng(0)
    for n in taxels:
        pot = DangerPotential(_tdm(n, hidden))
        layer = ModulationLayer(pot)
        s, v = rng.uniform(-1, 1, 6), rng.uniform(-1, 1, 6)
        ms = median_ms(lambda: layer(s, v), repeat)
        ms_ref = median_ms(lambda: modulate(v, *potential_and_normal(pot, s, v)), repeat)
        rows.append({"layer": "modulation", "n_taxels": n, "active": 0, "ms": ms, "ms_ref": ms_ref,
                     "speedup_vs_ref": ms_ref / ms, "f": layer(s, v)[1]})
    return rows


class SharpBall(torch.nn.Module):
    """A step-like potential (a TDM's sharp edge, Fig. 5): f = sigmoid(40 (0.5 - |s|)), 6-D."""

    def forward(self, s, a):
        return torch.sigmoid(40.0 * (0.5 - s.norm(dim=1)))


def nstep_rows() -> list[dict]:
    """Eq. 8's Monte Carlo on a sharp potential: error vs samples and horizon, and the time for
    256 states; `reach` is the mean w at states 0.1 outside the edge moving toward it (f ~ 0.02)."""
    rng = np.random.default_rng(1)
    s = rng.normal(size=(256, 6))
    s *= (rng.uniform(0.3, 0.9, 256) / np.linalg.norm(s, axis=1))[:, None]
    a = rng.uniform(-1, 1, (256, 6))
    dyn, pol = EulerDynamics(0.1), UniformPolicy(-np.ones(6), np.ones(6))
    rows = nstep_trade(SharpBall(), s, a, dyn, pol, horizons=(1, 2, 4, 8), samples=(1, 4, 16, 64))
    probe = rng.normal(size=(256, 6))
    probe *= (0.6 / np.linalg.norm(probe, axis=1))[:, None]
    toward = -probe / 0.6  # unit speed toward the centre
    for r in rows:
        w = nstep_targets(SharpBall(), probe, toward, dyn, pol, NStepConfig(r["horizon"], 0.9, 64))
        r["reach"] = float(w.mean())
    return [{"layer": "nstep", "n_taxels": 0, "active": 0, **r} for r in rows]


def full_tick_rows(taxels, actives, hidden: int, repeat: int) -> list[dict]:
    """Bench rows for the full three-layer tick on the UR5 with `a` active contacts out of `n`
    taxels (module docstring), fast and reference paths interleaved."""
    from skinsafe.core.design.sample import make_sample_design
    from skinsafe.core.robot.kinematics import TaxelKinematics
    from skinsafe.core.robot.models import build_ur5
    from skinsafe.core.safety.defensiveness import DefensivenessLayer
    from skinsafe.core.safety.potential import DangerPotential

    robot = build_ur5()
    base = make_sample_design("ur5", robot=robot)
    rows = []
    rng = np.random.default_rng(0)
    for n in taxels:
        idx = np.resize(np.arange(base.n_taxels), n)  # repeat the sample skin's taxels up to n
        t = base.taxels.subset(idx)
        t.ids = np.arange(n, dtype=np.int64)
        design = base.with_taxels(t)
        kin = TaxelKinematics(robot.model, design)
        tdm = _tdm(n, hidden)
        for a in actives:
            force = np.zeros(n)
            force[rng.choice(n, a, replace=False)] = 10.0
            q = robot.home.copy()
            cmd = rng.uniform(-0.5, 0.5, 6)

            def make(fast: bool, readings, prior=PRIOR, out=None):
                d = DefensivenessLayer(kin, design.taxels.thresholds, robot.vel_limits, robot.acc_limits, dt=DT)
                mod = ModulationLayer(DangerPotential(tdm))
                if not fast:
                    from skinsafe.core.safety.potential import potential_and_normal
                    mod._eval = lambda s, a_: potential_and_normal(mod.potential, s, a_)
                stack = SafetyStack(robot.vel_limits, d, mod, StrategyFilter(tdm, prior=prior), dt=DT)
                clock = iter(np.arange(10 ** 6) * DT)
                if out is None:
                    return lambda: stack.tick(next(clock), q, readings, cmd, DT)
                return lambda: out.append(stack.tick(next(clock), q, readings, cmd, DT))

            torch.set_num_threads(1)
            touch, free, flat = {"force": force}, {"force": np.zeros(n)}, np.ones(len(PRIOR))
            cmds = [[], [], [], []]  # the commands of each stack, tick by tick
            # the second kind: no contact and a flat prior (the strategy filter scores every candidate)
            ms, ms_all, ms_ref, ms_all_ref = interleaved_ms([make(True, touch, out=cmds[0]), make(True, free, flat, cmds[1]),
                                                             make(False, touch, out=cmds[2]),
                                                             make(False, free, flat, cmds[3])], repeat)
            diff = max(float(np.abs(np.array(cmds[k]) - np.array(cmds[k + 2])).max()) for k in (0, 1))
            med = [float(np.median(x)) for x in (ms, ms_all, ms_ref, ms_all_ref)]
            both = np.r_[ms, ms_all]
            rows.append({"layer": "full", "n_taxels": n, "active": a, "ms": med[0], "ms_all_candidates": med[1],
                         "ms_worst": max(med[:2]), "ms_p99": float(np.percentile(both, 99)), "ms_max": float(both.max()),
                         "ms_best": float(ms.min()), "ms_all_candidates_best": float(ms_all.min()),
                         "ms_ref": med[2], "ms_ref_worst": max(med[2:]), "speedup_vs_ref": med[2] / med[0],
                         "worst_speedup_vs_ref": max(med[2:]) / max(med[:2]), "max_abs_diff": diff})
    return rows


def rows(args) -> list[dict]:
    torch.set_num_threads(1)
    single_thread_blas()
    out = modulation_rows(args.taxels, args.hidden, args.repeat)
    if not args.no_full:
        out += full_tick_rows(args.taxels, args.active, args.hidden, args.repeat)
    if args.nstep:
        out += nstep_rows()
    return out
