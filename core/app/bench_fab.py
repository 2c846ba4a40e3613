"""`skinsafe bench fab`: a skin that can be built, on robots' own descriptions (in app: it writes the
fabrication files through exporters). Per robot, a cover of its whole arm with a module that a doubly curved link cannot take whole (default 6 x 6 at 1 cm):
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

import json
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree
from tqdm import tqdm

ROBOTS = "ur5e,gen3,xarm7"


def add_arguments(p) -> None:
    p.add_argument("--robots", default=ROBOTS, help="bundled descriptions to cover (comma list)")
    p.add_argument("--module", default="6x6", metavar="RxC", help="the cover's module")
    p.add_argument("--pitch", type=float, default=0.01, help="taxel pitch, m")
    p.add_argument("--pictures", metavar="DIR", help="also draw the docs' pictures into DIR (results/design)")


def pad_overlaps(design) -> int:
    """Pairs of pads (any two taxels on one link, facing the same way within 60 degrees: not the two
    faces of a thin flange) closer than a pad's diameter: discs that overlap."""
    t = design.taxels
    diameter = {m.id: m.taxel_diameter for m in design.modules}
    d = np.array([diameter[int(m)] for m in t.module])
    count = 0
    for b in range(len(design.bodies)):
        on = np.flatnonzero(t.body == b)
        if len(on) < 2:
            continue
        pairs = cKDTree(t.positions[on]).query_pairs(float(d[on].max()), output_type="ndarray")
        a, b = on[pairs[:, 0]], on[pairs[:, 1]]
        gap = np.linalg.norm(t.positions[a] - t.positions[b], axis=1)
        facing = np.sum(t.frames[a, :, 2] * t.frames[b, :, 2], axis=1) > 0.5
        count += int((facing & (gap < np.minimum(d[a], d[b]) - 1e-9)).sum())
    return count


def robot_row(name: str, rows: int, cols: int, pitch: float) -> dict:
    from skinsafe.core.design.audit import module_strains
    from skinsafe.core.design.cover import COVER_MODULE, cover_design, cover_report
    from skinsafe.core.design.coverage import body_area
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
    area = {b: body_area(robot.model, b) for b in report}
    covered = sum(r["covered"] * r["exposed"] * area[b] for b, r in report.items())
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
    if args.pictures:
        pictures(args.pictures)
    return out + [place_row()]


def pictures(out: str, robot_name: str = "ur5e", body: str = "wrist_1_link", seed: int = 3) -> list[str]:
    """The docs' pictures of a buildable skin, into `out`: a stretched grid refused on a doubly curved link
    beside the cut that fits there (`strain_refused.png`), a module's flat pattern and the KiCad board of it as
    kiutils reads the file back (`flat_and_board.png`), and the round trip's pad errors (`roundtrip.png`)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from skinsafe.core.design.cover import COVER_MODULE, cover_design
    from skinsafe.core.design.placement import PlacementError, largest_fit, place_module, template_grid
    from skinsafe.core.design.roundtrip import roundtrip
    from skinsafe.core.design.strain import module_strain
    from skinsafe.core.design.surface import cached_surfaces
    from skinsafe.core.robot.catalog import description
    from skinsafe.core.robot.models import load_robot

    Path(out).mkdir(parents=True, exist_ok=True)
    ref = description(robot_name)
    robot = load_robot(ref)
    surface = cached_surfaces(robot.model, [body])[body]
    asked = replace(COVER_MODULE, rows=8, cols=8, max_strain=1e9)  # the walk as it was: nothing refused
    rng = np.random.default_rng(seed)
    for anchor in surface.random_points(400, seed=seed):  # a spot where 8 x 8 stretches and a cut fits
        direction = rng.normal(size=3)
        try:
            wide = place_module(surface, asked, anchor, direction)
        except PlacementError:
            continue
        uv, row, col = template_grid(asked)
        strain = module_strain(uv, row, col, wide.positions, wide.frames[:, :, 2])
        fit = largest_fit(surface, replace(asked, max_strain=0.01), anchor, direction, strain, row, col) \
            if 0.03 < strain.max < 0.3 else (0, 0)
        if 0.03 < strain.max < 0.3 and fit[0] * fit[1] >= 9:
            break
    cut = place_module(surface, replace(asked, rows=fit[0], cols=fit[1], max_strain=0.01), anchor, direction)
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    fig = plt.figure(figsize=(10, 4.4))
    tri = surface.vertices[surface.triangles]
    near = tri[(np.linalg.norm(tri.mean(axis=1) - anchor, axis=1) < 0.06)]
    shade = 0.55 + 0.4 * np.abs(surface.face_normals[(np.linalg.norm(tri.mean(axis=1) - anchor, axis=1) < 0.06)]
                                @ np.array([0.3, -0.5, 0.8]))
    for k, (p, title) in enumerate([(wide, f"8 x 8 asked: {strain.max * 100:.1f}% in-plane strain, refused"),
                                    (cut, f"what fits there: {fit[0]} x {fit[1]}, {cut.strain * 100:.2f}%")]):
        ax = fig.add_subplot(1, 2, k + 1, projection="3d")
        ax.add_collection3d(Poly3DCollection(near, facecolors=np.repeat(np.clip(shade, 0, 1)[:, None], 3, 1),
                                             edgecolor="none", alpha=0.6))
        m = p.module
        g = template_grid(m)
        s = module_strain(*g, p.positions, p.frames[:, :, 2]).per_pad(len(p))
        lift = p.positions + 0.002 * p.frames[:, :, 2]  # just above the surface, to be seen
        sc = ax.scatter(*lift.T, c=s * 100, cmap="inferno_r", vmin=0, vmax=max(3.0, strain.max * 100), s=30,
                        depthshade=False)
        ax.set_title(title, fontsize=9)
        ax.set_axis_off()
        lo, hi = near.reshape(-1, 3).min(axis=0), near.reshape(-1, 3).max(axis=0)
        ax.set(xlim=(lo[0], hi[0]), ylim=(lo[1], hi[1]), zlim=(lo[2], hi[2]))
        ax.set_box_aspect(hi - lo)
        z = p.frames[len(p) // 2, :, 2]
        ax.view_init(elev=float(np.degrees(np.arcsin(np.clip(z[2], -1, 1)))), azim=float(np.degrees(np.arctan2(z[1], z[0]))))
    fig.colorbar(sc, ax=fig.axes, shrink=0.6, label="largest strain of the pad's neighbour pairs, %")
    fig.savefig(Path(out) / "strain_refused.png", dpi=110, bbox_inches="tight")
    plt.close(fig)
    paths = [str(Path(out) / "strain_refused.png")]
    design, _ = cover_design(robot, ref, bodies=[body], template=replace(COVER_MODULE, rows=4, cols=4))
    paths.append(_flat_and_board(design, Path(out) / "flat_and_board.png", plt))
    fig, ax = plt.subplots(figsize=(6, 3.2))
    for name in ROBOTS.split(","):
        ref = description(name)
        robot = load_robot(ref)
        design, _ = cover_design(robot, ref, template=replace(COVER_MODULE, rows=4, cols=4))
        errors = np.concatenate([r.error for r in roundtrip(design, robot.model)]) * 1e3
        ax.hist(np.maximum(errors, 1e-4), bins=np.logspace(-4, 0.5, 40), histtype="step", label=f"{name} ({len(errors)} pads)")
    ax.axvline(1.0, color="k", ls="--", lw=1)
    ax.set(xscale="log", xlabel="pad: map vs independent wrap, mm", ylabel="pads")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(Path(out) / "roundtrip.png", dpi=110)
    plt.close(fig)
    return paths + [str(Path(out) / "roundtrip.png")]


def _flat_and_board(design, path, plt) -> str:
    """A module's flat pattern (left) and its KiCad board as kiutils reads the written file back (right)."""
    from kiutils.board import Board

    from skinsafe.exporters.fab import flat_pattern, write_fab

    m = max(design.modules, key=lambda m: (len(flat_pattern(design, m).bends), m.rows * m.cols))
    p = flat_pattern(design, m)
    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 4.6))
    for loop in p.loops:
        a.fill(*(np.vstack([loop, loop[:1]]) * 1e3).T, fc="#f4d9a0", ec="k", lw=0.8)
    for (u, v), tid in zip(p.uv * 1e3, p.ids):
        a.add_patch(plt.Circle((u, v), m.taxel_diameter * 500, fc="#c8772b", ec="none"))
        a.text(u, v, str(int(tid) & 0xFFFF), ha="center", va="center", fontsize=5)
    for bend in p.bends:
        xs = [bend.at * 1e3] * 2 if bend.axis == "u" else [s * 1e3 for s in bend.span]
        ys = [s * 1e3 for s in bend.span] if bend.axis == "u" else [bend.at * 1e3] * 2
        a.plot(xs, ys, "b--", lw=1)
        a.text(xs[1], ys[1], f"{bend.angle_deg:.0f} deg", color="b", fontsize=7)
    a.set(aspect="equal", title=f"flat pattern of '{m.name}' ({len(p.uv)} pads, mm)")
    with tempfile.TemporaryDirectory() as tmp:
        index = json.loads((write_fab(design, tmp) / "fab.json").read_text())
        entry = next(e for e in index["modules"] if e["id"] == m.id)
        board = Board.from_file(str(Path(tmp) / "fab" / entry["files"]["kicad_pcb"]))
    for item in board.graphicItems:
        if getattr(item, "layer", "") == "Edge.Cuts" and hasattr(item, "start"):
            b.plot([item.start.X, item.end.X], [item.start.Y, item.end.Y], "k", lw=0.8)
    for fp in board.footprints:
        for pad in fp.pads:
            x, y = fp.position.X + pad.position.X, fp.position.Y + pad.position.Y
            if pad.shape == "circle":
                b.add_patch(plt.Circle((x, y), pad.size.X / 2, fc="#c8772b"))
            else:
                b.add_patch(plt.Rectangle((x - pad.size.X / 2, y - pad.size.Y / 2), pad.size.X, pad.size.Y, fc="#c8772b"))
    b.set(aspect="equal", title=f"{len(board.footprints)} footprints, {len(board.nets) - 1} nets (KiCad, y down)")
    b.invert_yaxis()
    b.autoscale()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return str(path)
