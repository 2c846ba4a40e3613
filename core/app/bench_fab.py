"""`skinsafe bench fab` (in app: it writes the fabrication files through exporters): a skin that can be built, on robots' own descriptions. Per robot, a cover
of its whole arm with a module that a doubly curved link cannot take whole (default 6 x 6 at 1 cm):
what was placed (`modules`, `taxels`), how much the FPCs are asked to stretch (`strain_max`,
`strain_p99`, within each module's `max_strain`), the placements refused as unbuildable
(`modules_refused`: over the strain tolerance or failing the round trip), the independent round
trip's worst pad (`roundtrip_err_mm_max`), pads of any two modules overlapping (`pad_overlaps`), the
honest coverage of the arm's exposed surface (`coverage_exposed`, and the links below 60%), the
cover's time (`cover_s`) and the fabrication files' (`fab_export_s`). A last row times placing 10,240
taxels (`place_s`, the design bench's tiling of the UR5's links) against the same tiling without the
strain check (`place_unchecked_s`), in the same run.
"""
from __future__ import annotations

import tempfile
import time
from dataclasses import replace

import numpy as np
from scipy.spatial import cKDTree
from tqdm import tqdm

ROBOTS = "ur5e,gen3,xarm7"


def add_arguments(p) -> None:
    p.add_argument("--robots", default=ROBOTS, help="bundled descriptions to cover (comma list)")
    p.add_argument("--module", default="6x6", metavar="RxC", help="the cover's module")
    p.add_argument("--pitch", type=float, default=0.01, help="taxel pitch, m")


def pad_overlaps(design) -> int:
    """Pairs of pads (any two taxels on one link) closer than a pad's diameter: discs that overlap."""
    t = design.taxels
    diameter = {m.id: m.taxel_diameter for m in design.modules}
    d = np.array([diameter[int(m)] for m in t.module])
    count = 0
    for b in range(len(design.bodies)):
        on = np.flatnonzero(t.body == b)
        if len(on) < 2:
            continue
        pairs = cKDTree(t.positions[on]).query_pairs(float(d[on].max()), output_type="ndarray")
        gap = np.linalg.norm(t.positions[on][pairs[:, 0]] - t.positions[on][pairs[:, 1]], axis=1)
        count += int((gap < np.minimum(d[on][pairs[:, 0]], d[on][pairs[:, 1]]) - 1e-9).sum())
    return count


def robot_row(name: str, rows: int, cols: int, pitch: float) -> dict:
    from skinsafe.core.design.audit import module_strains
    from skinsafe.core.design.cover import COVER_MODULE, cover_design, cover_report
    from skinsafe.core.design.roundtrip import roundtrip
    from skinsafe.core.robot.catalog import description
    from skinsafe.core.robot.models import load_robot
    from skinsafe.exporters.fab import write_fab

    ref = description(name)
    robot = load_robot(ref)
    template = replace(COVER_MODULE, rows=rows, cols=cols)
    t0 = time.perf_counter()
    design, refused = cover_design(robot, ref, template=template, pitch=pitch)
    cover_s = time.perf_counter() - t0
    strains = np.array([v[0] for v in module_strains(design).values() if v is not None])
    errors = np.concatenate([r.error for r in roundtrip(design, robot.model)])
    report = cover_report(design, robot.model, robot.home)
    from skinsafe.core.design.coverage import body_area

    area = {b: body_area(robot.model, b) for b in report}
    covered = sum(r["covered_of_link"] * area[b] for b, r in report.items())
    exposed = sum(r["exposed"] * area[b] for b, r in report.items())
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        write_fab(design, tmp)
        fab_s = time.perf_counter() - t0
    return {"robot": name, "module": f"{rows}x{cols}", "pitch_mm": pitch * 1e3, "modules": len(design.modules),
            "taxels": design.n_taxels, "strain_max": float(strains.max()), "strain_p99": float(np.percentile(strains, 99)),
            "max_strain": template.max_strain,
            "modules_refused": int(sum(r["strain"] + r["roundtrip"] for r in refused.values())),
            "refused_strain": int(sum(r["strain"] for r in refused.values())),
            "refused_roundtrip": int(sum(r["roundtrip"] for r in refused.values())),
            "roundtrip_err_mm_max": float(errors.max() * 1e3), "roundtrip_err_mm_p99": float(np.percentile(errors, 99) * 1e3),
            "pad_overlaps": pad_overlaps(design), "cell_overlaps": int(sum(r["overlaps"] for r in report.values())),
            "coverage_exposed": covered / exposed,
            "links_below_0_6": ",".join(b for b, r in report.items() if r["covered"] < 0.6),
            "cover_s": cover_s, "fab_export_s": fab_s}


def place_row() -> dict:
    """Placing 10,240 taxels (16 x 16 modules at 4 mm on the UR5's links, the design bench's tiling) with
    the strain check, and the same placements with the check turned off (`max_strain` 1e9), in one run."""
    from skinsafe.core.bench.design import TEMPLATE
    from skinsafe.core.design.placement import tile_bodies
    from skinsafe.core.design.sample import sample_bodies
    from skinsafe.core.design.surface import body_surfaces
    from skinsafe.core.robot.models import build_ur5
    from skinsafe.core.timing import median_ms

    robot = build_ur5()
    bodies = sample_bodies(robot.model)
    surfaces = body_surfaces(robot.model, bodies)
    run = lambda t: tile_bodies(surfaces, robot.model, t, bodies, limit=10240)  # noqa: E731
    placed, _ = run(TEMPLATE)
    checked = median_ms(lambda: run(TEMPLATE), repeat=3, warmup=1) / 1e3
    unchecked = median_ms(lambda: run(replace(TEMPLATE, max_strain=1e9)), repeat=3, warmup=0) / 1e3
    return {"robot": "ur5", "taxels": sum(len(p) for p in placed), "place_s": checked, "place_unchecked_s": unchecked,
            "strain_max": float(max(p.strain for p in placed))}


def rows(args) -> list[dict]:
    r, c = (int(x) for x in args.module.lower().split("x"))
    out = [robot_row(name, r, c, args.pitch) for name in tqdm(args.robots.split(","), desc="bench fab", unit="robot")]
    return out + [place_row()]
