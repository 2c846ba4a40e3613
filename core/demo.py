"""`skinsafe demo`: the product end to end on the bundled sample scene."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .coverage import format_report
from .kinematics import TaxelKinematics, retractability
from .robots import build_ur5
from .sample_skin import make_sample_design
from .taxel_map import save


def add_arguments(p) -> None:
    p.add_argument("--out", default="out", help="output folder (default: out)")


def run(args) -> int:
    out = Path(args.out)
    robot = build_ur5()
    design = make_sample_design("ur5", robot=robot)
    path = save(design, out / "ur5_skin.json", robot.body_names)
    print(format_report(design.coverage))
    kin = TaxelKinematics(robot.model, design)
    J, _, frames = kin.jacobians(robot.home)
    r = retractability(J, frames)
    print(f"retractability |J_p^T z| at home: min {r.min():.3f}, median {np.median(r):.3f}, max {r.max():.3f} m/s per rad/s")
    print(f"wrote {path}")
    return 0
