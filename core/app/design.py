"""`skinsafe design ROBOT`: a skin on any robot (a built-in name, or a URDF, xacro or MJCF file)
from a layout spec, saved as a taxel map that `check`, `export`, `poke --map` and `trade` take.

The layout spec (JSON, every field optional; command-line flags override it):

    {"module": {"rows": 4, "cols": 4, "pitch": 0.012, "taxel_diameter": 0.007, "margin": 0.002,
                "min_bend_radius": 0.02},
     "bodies": ["panda_link2", "panda_link4"],   # default: every moving link with geometry
     "cover": ["panda_link2"],                    # or "all": fill these links (see below)
     "max_taxels": 4096, "board_capacity": 512, "force_threshold": 2.0}

Without `cover`, modules are tiled over each link (`layout.tile_body`). With `cover` (or
`--cover LINK[,LINK...]|all`), the named links are filled as densely as their surface allows
(`cover.cover_design`: whole modules, then trimmed ones; nothing on hidden surface, nothing
overlapping across links) with the spec's module, by default 3 x 3 taxels at 1 cm
(`--module RxC|rect|strip`, `--pitch P`), and the command prints per link how much is covered,
the gaps, overlaps and buried taxels.
"""
from __future__ import annotations

import json
import os
from dataclasses import fields
from pathlib import Path

from tqdm import tqdm

from skinsafe.core.skin.model import DesignError, Module, RobotRef

MODULE_KEYS = {"rows", "cols", "pitch", "taxel_diameter", "margin", "min_bend_radius", "max_strain", "template"}
SPEC_KEYS = {"module", "bodies", "cover", "max_taxels", "board_capacity", "force_threshold"}


def add_arguments(p) -> None:
    p.add_argument("robot", help="built-in name (ur5, panda) or a URDF / xacro / MJCF file")
    p.add_argument("--package-dir", action="append", default=[],
                   help="a ROS package folder (or a folder of packages) for package:// and $(find); repeatable")
    p.add_argument("--xacro-arg", action="append", default=[], metavar="NAME:=VALUE",
                   help="an argument for a xacro file (e.g. gazebo:=true); repeatable")
    p.add_argument("--layout", help="layout spec JSON (see `skinsafe design --help`)")
    p.add_argument("--bodies", help="comma separated links to skin (default: every moving link)")
    p.add_argument("--cover", metavar="LINK[,LINK...]|all",
                   help="fill these links (or every moving link) as densely as their surface allows")
    p.add_argument("--module", metavar="RxC|rect|strip",
                   help="the module: RxC taxels (e.g. 3x3), or a template with --rows/--cols")
    p.add_argument("--rows", type=int)
    p.add_argument("--cols", type=int)
    p.add_argument("--pitch", type=float, help="taxel pitch, m")
    p.add_argument("--max-taxels", type=int)
    p.add_argument("--out", default="out/skin.json", help="taxel map to write")
    p.add_argument("--report", metavar="JSON", help="with --cover: write the per-link cover report as JSON rows")


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


def module_spec(spec: dict) -> dict:
    """The spec's module with its defaults: 4 x 4 taxels at 12 mm for tiling, the cover module
    (3 x 3 at 1 cm) for a cover; taxel diameter and margin follow the pitch unless given."""
    from skinsafe.core.design.cover import COVER_MODULE

    given = spec.get("module", {})
    if "cover" in spec:
        base = {k: getattr(COVER_MODULE, k) for k in ("rows", "cols", "pitch", "min_bend_radius")}
        scale = given.get("pitch", COVER_MODULE.pitch) / COVER_MODULE.pitch
        base |= {"taxel_diameter": COVER_MODULE.taxel_diameter * scale, "margin": COVER_MODULE.margin * scale}
    else:
        base = {"rows": 4, "cols": 4, "pitch": 0.012, "margin": 0.002, "min_bend_radius": 0.02}
    mod = {**base, **given}
    if "taxel_diameter" not in given and "cover" not in spec:
        mod["taxel_diameter"] = 0.6 * mod["pitch"]
    if mod.get("template", "rect") == "strip":
        mod["rows"] = 1
    if not (0 < mod["pitch"] < 0.2) or mod["rows"] < 1 or mod["cols"] < 1:
        raise DesignError(f"layout: module {mod} needs rows, cols >= 1 and a pitch in (0, 0.2) m")
    if mod.get("template", "rect") not in ("rect", "strip"):
        raise DesignError(f"layout: module template '{mod['template']}' cannot be tiled or cover a link; use rect or strip")
    return mod


def design_robot(robot, ref: RobotRef, spec: dict):
    """Tile (or with `cover`, fill) the spec's module over the spec's bodies; returns (design,
    refusal messages: one per refused module when tiling, per link and reason when covering)."""
    from skinsafe.core.bench.robot_import import skinnable_bodies
    from skinsafe.core.design.cover import cover_design
    from skinsafe.core.design.coverage import coverage_report
    from skinsafe.core.design.layout import tile_body, without_buried
    from skinsafe.core.design.placement import build_design
    from skinsafe.core.design.surface import cached_surfaces

    mod = module_spec(spec)
    template = Module(0, "tile", "", **{k: v for k, v in mod.items() if k in {f.name for f in fields(Module)}})
    cover = spec.get("cover")
    bodies = (skinnable_bodies(robot) if cover == "all" else cover) if cover else \
        (spec.get("bodies") or skinnable_bodies(robot))
    if not isinstance(bodies, list) or not all(isinstance(b, str) for b in bodies):
        raise DesignError(f"layout: cover is {cover!r}; give a list of link names or \"all\"")
    unknown = [b for b in bodies if b not in robot.body_names]
    if unknown:
        raise DesignError(f"layout: body '{unknown[0]}' is not in robot {robot.name}; use one of "
                          f"{sorted(robot.body_names - {'world'})}")
    limit = spec.get("max_taxels")
    capacity, threshold = int(spec.get("board_capacity", 512)), float(spec.get("force_threshold", 2.0))
    if cover:
        with tqdm(total=len(bodies), desc="covering", unit="link") as bar:
            design, why = cover_design(robot, ref, bodies, template, board_capacity=capacity,
                                       force_threshold=threshold, limit=limit, progress=bar)
        refused = [f"{b}: {n} tries refused ({reason})" for b, r in why.items() for reason, n in r.items() if n]
        design.coverage = coverage_report(design, robot.model)
        return design, refused
    surfaces = cached_surfaces(robot.model, bodies)
    placed, refused = [], []
    for b in tqdm(bodies, desc="designing", unit="link"):
        left = None if limit is None else limit - sum(len(p) for p in placed)
        mine, why = tile_body(surfaces[b], robot.model, template, b, len(placed), left)
        placed += mine
        refused += why
    if not placed:
        raise DesignError(f"layout: no module fits on {bodies} ({len(refused)} refused; first: "
                          f"{refused[0] if refused else 'none'}); use smaller modules or a larger bend radius")
    design = build_design(ref, placed, capacity, threshold,
                          bodies=[b for b in bodies if any(p.module.body == b for p in placed)])
    design, dropped = without_buried(design, robot.model, robot.home)
    refused += [f"module {m}: buried inside another link at every sampled pose" for m in dropped]
    design.coverage = coverage_report(design, robot.model)
    return design, refused


def parse_module(text: str) -> dict:
    """`--module`: 'RxC' (a rect of R rows, C columns) or a template name."""
    if text in ("rect", "strip"):
        return {"template": text}
    rows, x, cols = text.partition("x")
    if not (x and rows.isdigit() and cols.isdigit() and int(rows) > 0 and int(cols) > 0):
        raise DesignError(f"--module '{text}' is not RxC (e.g. 3x3), rect or strip")
    return {"template": "rect", "rows": int(rows), "cols": int(cols)}


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
    if args.module:
        spec.setdefault("module", {}).update(parse_module(args.module))
    if args.bodies:
        spec["bodies"] = [b for b in args.bodies.split(",") if b]
    if args.cover:
        spec["cover"] = "all" if args.cover == "all" else [b for b in args.cover.split(",") if b]
    if args.max_taxels is not None:
        spec["max_taxels"] = args.max_taxels
    bad = [a for a in args.xacro_arg if ":=" not in a]
    if bad:
        raise DesignError(f"--xacro-arg '{bad[0]}' is not NAME:=VALUE (e.g. gazebo:=true)")
    ref = robot_ref(args.robot, args.package_dir, out, dict(a.split(":=", 1) for a in args.xacro_arg))
    robot = load_robot(ref, base_dir=out.parent)
    design, refused = design_robot(robot, ref, spec)
    path = save(design, out)
    if spec.get("cover"):
        from skinsafe.core.design.cover import cover_report, format_cover_report
        from skinsafe.core.skin.files import atomic_write

        report = cover_report(design, robot.model, robot.home)
        print(format_cover_report(report))
        if args.report:
            mod = module_spec(spec)
            rows = [{"robot": robot.name, "link": link, "module": f"{mod['rows']}x{mod['cols']}", "pitch": mod["pitch"],
                     **r} for link, r in report.items()]
            atomic_write(args.report, json.dumps(rows, indent=1) + "\n")
    else:
        print(format_report(design.coverage))
    tail = "coverage per link above" if spec.get("cover") else f"{len(refused)} candidate placements refused"
    print(f"wrote {path} ({design.n_taxels} taxels, {len(design.modules)} modules on {len(design.bodies)} links, "
          f"{len(design.boards)} boards; {tail})")
    return 0
