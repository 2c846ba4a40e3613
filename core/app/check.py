"""`skinsafe check MAP`: validate a taxel map against its robot, audit where its taxels sit
(on the link's surface, outlines not overhanging, anchors on the link, none buried inside another
link at every sampled pose) and print the coverage summary. Exit code 1 when the audit fails."""
from __future__ import annotations

import math
import sys
from pathlib import Path

from skinsafe.core.design.audit import audit
from skinsafe.core.design.coverage import coverage_report, format_report
from skinsafe.core.robot.models import load_robot
from skinsafe.core.skin.model import DesignError
from skinsafe.core.skin.taxel_map import load


def add_arguments(p) -> None:
    p.add_argument("map", help="taxel map JSON")
    p.add_argument("--poses", type=int, default=16, help="sampled poses for the buried-taxel check (home first)")
    p.add_argument("--tol", type=float, default=0.002, help="m a taxel may sit off its link's surface")


MAX_POSES = 10_000


def run(args) -> int:
    if not 1 <= args.poses <= MAX_POSES:
        raise DesignError(f"--poses {args.poses}: give 1..{MAX_POSES} (the home pose and sampled ones)")
    if not (math.isfinite(args.tol) and args.tol >= 0):
        raise DesignError(f"--tol {args.tol}: give a finite distance >= 0 in m, e.g. 0.002")
    path = Path(args.map)
    design = load(path)
    robot = load_robot(design.robot, base_dir=path.parent)
    design.validate(str(path), robot.body_names)
    print(f"{path}: robot {robot.name} ({robot.model.nv} dof), {design.n_taxels} taxels, "
          f"{len(design.modules)} modules, {len(design.boards)} boards")
    problems = audit(design, robot.model, robot.home, args.poses, args.tol)
    print(format_report(coverage_report(design, robot.model)))
    for line in problems:
        print(f"{path}: refused: {line}", file=sys.stderr)
    print(f"{path}: {'valid' if not problems else f'{len(problems)} problems'}")
    return 1 if problems else 0
