"""`skinsafe check MAP`: validate a taxel map against its robot and print the coverage summary."""
from __future__ import annotations

from pathlib import Path

from skinsafe.core.design.coverage import coverage_report, format_report
from skinsafe.core.robot.models import load_robot
from skinsafe.core.skin.taxel_map import load


def add_arguments(p) -> None:
    p.add_argument("map", help="taxel map JSON")


def run(args) -> int:
    path = Path(args.map)
    design = load(path)
    robot = load_robot(design.robot, base_dir=path.parent)
    design.validate(str(path), robot.body_names)
    print(f"{path}: valid, robot {robot.name} ({robot.model.nv} dof), {design.n_taxels} taxels, "
          f"{len(design.modules)} modules, {len(design.boards)} boards")
    print(format_report(coverage_report(design, robot.model)))
    return 0
