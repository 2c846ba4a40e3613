"""`skinsafe bench modulation`: one modulation tick and one full three-layer tick.

Rows: `layer` ("modulation": potential + gradient + M v for one UR5 state; "full": the safety
stack's strategy filter + modulation + defensiveness with `active` contacts), `n_taxels`,
`active`, `ms` (median, one thread) and `ms_ref`/`speedup_vs_ref` against the simple reference
in the same run (autograd for the normal, the layers one after another without the fast paths).
With `--nstep`, rows `layer` = "nstep" add the Monte Carlo trade of eq. 8: horizon and samples
vs the RMS error of w against 1,024 rollouts and the time for 256 states.
"""
from __future__ import annotations

import numpy as np
import torch

from .modulation import ModulationLayer, modulate
from .potential import (DangerPotential, EulerDynamics, UniformPolicy, nstep_trade, potential_and_normal,
                        single_thread_blas)
from .tdm import TactileDangerModel
from .timing import median_ms


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


def nstep_rows(hidden: int) -> list[dict]:
    pot = DangerPotential(_tdm(1024, hidden))
    rng = np.random.default_rng(1)
    s = rng.uniform(-1, 1, (256, 6))
    a = rng.uniform(-1, 1, (256, 6))
    rows = nstep_trade(pot, s, a, EulerDynamics(0.1), UniformPolicy(-np.ones(6), np.ones(6)),
                       horizons=(1, 2, 4, 8), samples=(1, 4, 16, 64))
    return [{"layer": "nstep", "n_taxels": 1024, "active": 0, **r} for r in rows]


def rows(args) -> list[dict]:
    torch.set_num_threads(1)
    single_thread_blas()
    out = modulation_rows(args.taxels, args.hidden, args.repeat)
    if not args.no_full:
        from .safety_stack import full_tick_rows

        out += full_tick_rows(args.taxels, args.active, args.hidden, args.repeat)
    if args.nstep:
        out += nstep_rows(args.hidden)
    return out
