"""`skinsafe design ROBOT`: a skin on any robot (a built-in name, or a URDF, xacro or MJCF file)
from a layout spec, saved as a taxel map that `check`, `export`, `poke --map` and `trade` take.

The layout spec (JSON, every field optional; command-line flags override it):

    {"module": {"rows": 4, "cols": 4, "pitch": 0.012, "taxel_diameter": 0.007, "margin": 0.002,
                "min_bend_radius": 0.02},
     "bodies": ["panda_link2", "panda_link4"],   # default: every moving link with geometry
     "max_taxels": 4096, "board_capacity": 512, "force_threshold": 2.0}
"""
from __future__ import annotations

import json
import os
from dataclasses import fields
from pathlib import Path

from tqdm import tqdm

from skinsafe.core.skin.model import DesignError, Module, RobotRef

MODULE_KEYS = {"rows", "cols", "pitch", "taxel_diameter", "margin", "min_bend_radius", "template"}
SPEC_KEYS = {"module", "bodies", "max_taxels", "board_capacity", "force_threshold"}


def add_arguments(p) -> None:
    p.add_argument("robot", help="built-in name (ur5, panda) or a URDF / xacro / MJCF file")
    p.add_argument("--package-dir", action="append", default=[],
                   help="a ROS package folder (or a folder of packages) for package:// and $(find); repeatable")
    p.add_argument("--xacro-arg", action="append", default=[], metavar="NAME:=VALUE",
                   help="an argument for a xacro file (e.g. gazebo:=true); repeatable")
    p.add_argument("--layout", help="layout spec JSON (see `skinsafe design --help`)")
    p.add_argument("--bodies", help="comma separated links to skin (default: every moving link)")
    p.add_argument("--rows", type=int)
    p.add_argument("--cols", type=int)
    p.add_argument("--pitch", type=float, help="taxel pitch, m")
    p.add_argument("--max-taxels", type=int)
    p.add_argument("--out", default="out/skin.json", help="taxel map to write")


def robot_ref(robot: str, package_dirs, out: Path, xacro_args: dict | None = None) -> RobotRef:
    """A built-in name or a file, with paths stored relative to the taxel map's folder."""
    from skinsafe.core.robot.models import BUILTIN

    if robot in BUILTIN:
        return RobotRef("builtin", robot)
    path = Path(robot)
    if not path.is_file():
        raise DesignError(f"robot '{robot}' is neither a built-in ({', '.join(BUILTIN)}) nor a file; check the path")
    kind = "mjcf" if path.suffix == ".xml" and "<mujoco" in path.read_text()[:4000] else "urdf"
    rel = lambda p: os.path.relpath(Path(p).resolve(), out.parent.resolve())  # noqa: E731
    return RobotRef(kind, path.name.split(".")[0], rel(path), tuple(rel(d) for d in package_dirs), dict(xacro_args or {}))


def read_spec(path: str | None) -> dict:
    if not path:
        return {}
    try:
        spec = json.loads(Path(path).read_text())
    except FileNotFoundError:
        raise DesignError(f"layout spec '{path}': file not found; check the path") from None
    except json.JSONDecodeError as e:
        raise DesignError(f"layout spec '{path}': not valid JSON ({e})") from None
    if not isinstance(spec, dict):
        raise DesignError(f"layout spec '{path}': expected an object with {sorted(SPEC_KEYS)}")
    for key in spec:
        if key not in SPEC_KEYS:
            raise DesignError(f"layout spec '{path}': unknown field '{key}'; allowed: {sorted(SPEC_KEYS)}")
    for key in spec.get("module", {}):
        if key not in MODULE_KEYS:
            raise DesignError(f"layout spec '{path}': module field '{key}' is unknown; allowed: {sorted(MODULE_KEYS)}")
    return spec


def design_robot(robot, ref: RobotRef, spec: dict):
    """Tile the spec's module over the spec's bodies; returns (design, refusal messages)."""
    from skinsafe.core.bench.robot_import import skinnable_bodies
    from skinsafe.core.design.coverage import coverage_report
    from skinsafe.core.design.layout import tile_body, without_buried
    from skinsafe.core.design.placement import build_design
    from skinsafe.core.design.surface import cached_surfaces

    mod = {"rows": 4, "cols": 4, "pitch": 0.012, "margin": 0.002, "min_bend_radius": 0.02, **spec.get("module", {})}
    mod.setdefault("taxel_diameter", 0.6 * mod["pitch"])
    if not (0 < mod["pitch"] < 0.2) or mod["rows"] < 1 or mod["cols"] < 1:
        raise DesignError(f"layout: module {mod} needs rows, cols >= 1 and a pitch in (0, 0.2) m")
    template = Module(0, "tile", "", **{k: v for k, v in mod.items() if k in {f.name for f in fields(Module)}})
    bodies = spec.get("bodies") or skinnable_bodies(robot)
    unknown = [b for b in bodies if b not in robot.body_names]
    if unknown:
        raise DesignError(f"layout: body '{unknown[0]}' is not in robot {robot.name}; use one of "
                          f"{sorted(robot.body_names - {'world'})}")
    surfaces = cached_surfaces(robot.model, bodies)
    limit = spec.get("max_taxels")
    placed, refused = [], []
    for b in tqdm(bodies, desc="designing", unit="link"):
        left = None if limit is None else limit - sum(len(p) for p in placed)
        mine, why = tile_body(surfaces[b], robot.model, template, b, len(placed), left)
        placed += mine
        refused += why
    if not placed:
        raise DesignError(f"layout: no module fits on {bodies} ({len(refused)} refused; first: "
                          f"{refused[0] if refused else 'none'}); use smaller modules or a larger bend radius")
    design = build_design(ref, placed, int(spec.get("board_capacity", 512)), float(spec.get("force_threshold", 2.0)),
                          bodies=[b for b in bodies if any(p.module.body == b for p in placed)])
    design, dropped = without_buried(design, robot.model, robot.home)
    refused += [f"module {m}: buried inside another link at every sampled pose" for m in dropped]
    design.coverage = coverage_report(design, robot.model)
    return design, refused


def run(args) -> int:
    from skinsafe.core.design.coverage import format_report
    from skinsafe.core.robot.models import load_robot
    from skinsafe.core.skin.taxel_map import save

    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    spec = read_spec(args.layout)
    for key, value in (("rows", args.rows), ("cols", args.cols), ("pitch", args.pitch)):
        if value is not None:
            spec.setdefault("module", {})[key] = value
    if args.bodies:
        spec["bodies"] = [b for b in args.bodies.split(",") if b]
    if args.max_taxels is not None:
        spec["max_taxels"] = args.max_taxels
    bad = [a for a in args.xacro_arg if ":=" not in a]
    if bad:
        raise DesignError(f"--xacro-arg '{bad[0]}' is not NAME:=VALUE (e.g. gazebo:=true)")
    ref = robot_ref(args.robot, args.package_dir, out, dict(a.split(":=", 1) for a in args.xacro_arg))
    robot = load_robot(ref, base_dir=out.parent)
    design, refused = design_robot(robot, ref, spec)
    path = save(design, out)
    print(format_report(design.coverage))
    print(f"wrote {path} ({design.n_taxels} taxels, {len(design.modules)} modules on {len(design.bodies)} links, "
          f"{len(design.boards)} boards; {len(refused)} candidate placements refused)")
    return 0
