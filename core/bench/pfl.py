"""`skinsafe bench pfl`: one tick of the ISO/TS 15066 speed cap (`PFLCap`) on the UR5.

Rows: `layer` = "pfl", `n_taxels` (the sample skin repeated up to n), `ms` (median of one tick:
normal rows, mass matrix and `mj_solveM` for every taxel, the cap), `ms_worst` (the slowest
tick), `ms_ref` against a simple loop reference in the same run (per taxel `mj_jac`, `J_p^T z`,
`mj_solveM`, v_max and the ratio), `speedup_vs_ref` and `max_abs_diff` between the two commands.
"""
from __future__ import annotations

import time

import mujoco
import numpy as np

from skinsafe.core.safety.pfl import PFLCap, region
from skinsafe.core.timing import median_ms


def add_arguments(p) -> None:
    p.add_argument("--taxels", type=int, nargs="+", default=[4096, 16384])
    p.add_argument("--repeat", type=int, default=200)
    p.add_argument("--regions", nargs="+", default=["hand", "lower_arm"])


def loop_cap(kin, regions, q, v) -> np.ndarray:
    """Reference: the cap taxel by taxel."""
    m, d = kin.model, kin.data
    pos, frames = kin.poses(q)
    mujoco.mj_crb(m, d)
    mujoco.mj_factorM(m, d)
    regs = [region(r) for r in regions]
    jp = np.zeros((3, m.nv))
    x = np.zeros((1, m.nv))
    scale = 1.0
    for i in range(kin.n):
        mujoco.mj_jac(m, d, jp, None, pos[i], int(kin.body_id[i]))
        a = jp.T @ frames[i, :, 2]
        mujoco.mj_solveM(m, d, x, a[None])
        inv = float(a @ x[0])
        vm = min(r.transient_limit() / np.sqrt(r.k_N_per_m) * np.sqrt(1 / r.mass_kg + inv) for r in regs)
        vn = float(a @ v)
        if vn > vm:
            scale = min(scale, vm / vn)
    return v * scale


def rows(args) -> list[dict]:
    from skinsafe.core.design.sample import make_sample_design
    from skinsafe.core.robot.kinematics import TaxelKinematics
    from skinsafe.core.robot.models import build_ur5

    robot = build_ur5()
    base = make_sample_design("ur5", robot=robot)
    rng = np.random.default_rng(0)
    out = []
    for n in args.taxels:
        t = base.taxels.subset(np.resize(np.arange(base.n_taxels), n))
        t.ids = np.arange(n, dtype=np.int64)
        kin = TaxelKinematics(robot.model, base.with_taxels(t))
        cap = PFLCap(kin, args.regions)
        q = robot.home + rng.uniform(-0.5, 0.5, 6)
        v = rng.uniform(-3, 3, 6)
        diff = float(np.abs(cap(q, v) - loop_cap(kin, args.regions, q, v)).max())
        times = []

        def tick():
            t0 = time.perf_counter()
            cap(q, v)
            times.append(time.perf_counter() - t0)

        ms = median_ms(tick, args.repeat)
        ms_ref = median_ms(lambda: loop_cap(kin, args.regions, q, v), 3, warmup=1)
        out.append({"layer": "pfl", "n_taxels": n, "ms": ms, "ms_worst": 1e3 * max(times), "ms_ref": ms_ref,
                    "speedup_vs_ref": ms_ref / ms, "max_abs_diff": diff})
    return out
