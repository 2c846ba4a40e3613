"""`skinsafe bench jacobians`: batched taxel Jacobians vs one `mj_jac` per taxel, on the UR5."""
from __future__ import annotations

import numpy as np

from skinsafe.core.design.sample import design_with
from skinsafe.core.robot.kinematics import TaxelKinematics
from skinsafe.core.robot.models import build_ur5
from skinsafe.core.timing import median_ms


def add_arguments(p) -> None:
    p.add_argument("--sizes", default="256,1024,4096,16384", help="taxel counts (comma-separated)")
    p.add_argument("--repeat", type=int, default=50, help="timed repeats per size")


def rows(args) -> list[dict]:
    robot = build_ur5()
    rng = np.random.default_rng(0)
    out = []
    for n in (int(s) for s in args.sizes.split(",")):
        design, _ = design_with(n, robot)
        kin = TaxelKinematics(robot.model, design)
        q = robot.home + rng.normal(0, 0.3, robot.model.nq)
        fast = median_ms(lambda: kin.jacobians(q), repeat=args.repeat)
        loop = median_ms(lambda: kin.jacobians_loop(q), repeat=max(3, args.repeat // 10), warmup=1)
        err = float(np.abs(kin.jacobians(q)[0] - kin.jacobians_loop(q)).max())
        out.append({"n_taxels": n, "ms": round(fast, 4), "loop_ms": round(loop, 3),
                    "speedup_vs_loop": round(loop / fast, 1), "max_abs_diff": err})
    return out
