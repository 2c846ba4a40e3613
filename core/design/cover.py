"""Coverage fill: cover a link with copies of one module at a pitch, as densely as the surface allows.

`cover_link` tries a module centred on each point of an even sample of the link's surface (about
one per pitch), in raster order along the link's principal axis (band by band, around the axis
within a band), rows first along that axis, then across it; from each module it places, the
neighbours that continue its taxel grid are tried next (a quilt), and then copies trimmed to fewer
rows/columns fill what is left (`trimmed`). A module is kept where `place_module` accepts it (on
the surface, within the FPC's bend radius and in-plane strain), the independent wrap of its flat
pattern (`roundtrip.disagreement`) puts every pad within 1 mm of the placement's, its outline does not
overhang the link, none of its
taxels is hidden (more than `audit.BURIED_TOL` inside another link at the home pose, or
`audit.enclosed` by its own link's mesh), and none of its cells meets a same-facing module already
placed on this link or on any other link at home (links that coincide share one skin, never two
on top of each other). Points where a module laid flat would clearly meet one already placed are
not tried.

`cover_design` covers a robot's arm (or the named links) and `cover_report` says, per link, how
much is covered, where it is bare (`coverage.gaps`), and whether any cells overlap or any taxel
is buried (both 0 for a fill).
"""
from __future__ import annotations

from collections import deque
from dataclasses import replace

import mujoco
import numpy as np
from scipy.spatial import cKDTree

from skinsafe.core.design.audit import SURFACE_TOL, buried_points, enclosed, outline_overhang
from skinsafe.core.design.placement import (
    PlacedModule,
    PlacementError,
    _march,
    _steps,
    build_design,
    clearance,
    place_module,
    placed_from_design,
    placement_record,
    template_grid,
)
from skinsafe.core.design.roundtrip import TOL as ROUNDTRIP_TOL
from skinsafe.core.design.roundtrip import disagreement
from skinsafe.core.design.surface import Surface, cached_surfaces, surface_bodies
from skinsafe.core.skin.model import DesignError, Module, RobotRef, SkinDesign, frames_from_normals

COVER_MODULE = Module(0, "cover", "", rows=3, cols=3, pitch=0.01, taxel_diameter=0.006, margin=0.001,
                      min_bend_radius=0.01)  # 3x3 cells of 1 cm; the FPC bends to 1 cm


def surface_samples(surface: Surface, spacing: float, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Points (k,3) and their normals spread evenly over a surface, about one per `spacing`
    square: area-weighted random points thinned to one per voxel of side `spacing`."""
    pts = surface.random_points(int(min(200_000, max(100, 8 * surface.area / spacing ** 2))), seed)
    _, first = np.unique(np.floor(pts / spacing).astype(np.int64), axis=0, return_index=True)
    pts = pts[np.sort(first)]
    return surface.closest(pts)[:2]


def principal_axis(surface: Surface) -> np.ndarray:
    """The direction along which the link's surface extends most (unit, body frame)."""
    centred = surface.vertices - surface.vertices.mean(axis=0)
    return np.linalg.svd(centred, full_matrices=False)[2][0]


def raster_order(points: np.ndarray, axis: np.ndarray, band: float) -> np.ndarray:
    """Indices of `points` band by band along `axis` (bands `band` wide), around the axis within a band."""
    centre = points.mean(axis=0)
    rel = points - centre
    along = rel @ axis
    u = np.cross(axis, [1.0, 0, 0] if abs(axis[0]) < 0.9 else [0, 1.0, 0])
    u /= np.linalg.norm(u)
    angle = np.arctan2(rel @ np.cross(axis, u), rel @ u)
    return np.lexsort((angle, np.floor((along - along.min()) / band)))


class _Home:
    """Taxels placed so far, in the world frame at the home pose, for the overlap test across links."""

    def __init__(self, model: mujoco.MjModel, home: np.ndarray):
        self.model, self.data = model, mujoco.MjData(model)
        self.data.qpos[:] = home
        mujoco.mj_kinematics(model, self.data)
        self.surfaces = cached_surfaces(model, surface_bodies(model))
        self.points, self.normals = np.zeros((0, 3)), np.zeros((0, 3))
        self.tree = None

    def world(self, body: str, local: np.ndarray) -> np.ndarray:
        b = self.model.body(body).id
        return local @ self.data.xmat[b].reshape(3, 3).T + self.data.xpos[b]

    def hidden(self, body: str, local: np.ndarray, normals: np.ndarray) -> np.ndarray:
        """(N,) True where a point of `body` (body frame) is buried in another link at home or
        enclosed by its own (`audit.enclosed`): no skin can go there."""
        w = self.world(body, local)
        out = buried_points(self.model, self.data, self.surfaces, w, self.model.body(body).id)
        rest = np.flatnonzero(~out)
        R = self.data.xmat[self.model.body(body).id].reshape(3, 3)
        out[rest] = enclosed(self.model, self.data, body, w[rest], normals[rest] @ R.T)
        return out

    def meets(self, world: np.ndarray, normals: np.ndarray, limit: float) -> bool:
        """Whether a placed taxel facing the same way (within 60 degrees) lies within `limit` of one
        of the points `world` (n,3) with their `normals` (facing surfaces across a gap do not meet)."""
        return bool(self.meets_each(world[None], np.broadcast_to(normals, world.shape)[None], limit)[0])

    def meets_each(self, world: np.ndarray, normals: np.ndarray, limit: float) -> np.ndarray:
        """`meets` for k modules at once: world (k,n,3), normals (k,n,3) -> (k,) bool."""
        k, n = world.shape[:2]
        if self.tree is None:
            return np.zeros(k, bool)
        d, j = self.tree.query(world.reshape(-1, 3), k=min(8, len(self.points)), distance_upper_bound=limit)
        d, j = d.reshape(k * n, -1), j.reshape(k * n, -1)
        near = np.isfinite(d)
        rows = np.nonzero(near)[0]
        same = np.sum(self.normals[j[near]] * normals.reshape(-1, 3)[rows], axis=1) > 0.5
        return np.bincount(rows[same] // n, minlength=k) > 0

    def exposed(self, body: str, surface: Surface, n: int = 4000) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """`n` area-uniform points of the link's surface (seed fixed), their normals and whether skin can
        go there (not `hidden`): their mean is the exposed share, +-0.8% at 4,000."""
        q, nrm = surface.closest(surface.random_points(n, seed=1))[:2]
        return q, nrm, ~self.hidden(body, q, nrm)

    def add(self, world: np.ndarray, normals: np.ndarray) -> None:
        self.points, self.normals = np.concatenate([self.points, world]), np.concatenate([self.normals, normals])
        self.tree = cKDTree(self.points)


def neighbour_anchors(surface: Surface, p: PlacedModule) -> list[tuple[np.ndarray, np.ndarray]]:
    """Where the four modules that continue `p`'s taxel grid would be centred (a module width along
    its rows both ways, a module height across them), walked on the surface: (anchor, normal, row
    direction) each."""
    m = p.module
    x, y, z = p.origin_frame[:, 0], p.origin_frame[:, 1], p.origin_frame[:, 2]
    hs, idx = _steps(np.array([m.cols * m.pitch, m.rows * m.pitch]), 0.005)
    start = np.repeat(p.origin[None], 4, 0)
    P, N, X, fail = _march(surface, start, np.repeat(z[None], 4, 0), np.stack([x, -x, y, -y]),
                           np.repeat(x[None], 4, 0), hs)
    reach = idx[[0, 0, 1, 1]]
    return [(P[reach[k], k], N[reach[k], k], X[reach[k], k]) for k in range(4) if fail[k] < 0 or fail[k] > reach[k]]


def trimmed(template: Module, smallest: int = 2) -> list[Module]:
    """The template, then copies of it cut down to fewer rows and/or columns (at least `smallest`
    taxels), largest first: they fill what is left where a whole module does not fit (the FPC cut
    to the local surface, as the paper's modules are)."""
    r0, c0 = template.rows, template.cols
    # rows <= cols: the fill tries each module both ways round, so r x c and c x r are one size
    sizes = {(min(r, c), max(r, c)) for r in range(1, r0 + 1) for c in range(1, c0 + 1) if r * c >= smallest}
    sizes.discard((min(r0, c0), max(r0, c0)))
    order = sorted(sizes, key=lambda rc: (-rc[0] * rc[1], -rc[1]))
    return [template] + [replace(template, rows=r, cols=c) for r, c in order]


def cover_link(surface: Surface, home: _Home, template: Module, body: str, first_id: int = 0,
               limit: int | None = None) -> tuple[list[PlacedModule], dict]:
    """Copies of `template` (then trimmed ones, `trimmed`) filling one link (see the module
    docstring). Returns the placed modules and the count of refused attempts by reason."""
    gap = max(2 * clearance(template), 0.75 * template.pitch)  # closest two modules' taxels may come
    pts, nrm = surface_samples(surface, template.pitch)
    open_ = ~home.hidden(body, pts, nrm)
    axis = principal_axis(surface)
    order = raster_order(pts, axis, template.pitch)
    R = home.data.xmat[home.model.body(body).id].reshape(3, 3)  # body to world at home
    placed: list[PlacedModule] = []
    refused = {"placement": 0, "strain": 0, "overhang": 0, "buried": 0, "overlap": 0, "roundtrip": 0}

    def flat(uv, anchor, frames):
        """A module's taxels laid flat in the tangent plane (k anchors, k frames) -> (k, n, 3) world."""
        local = anchor[:, None] + uv[None, :, :1] * frames[:, None, :, 0] + uv[None, :, 1:] * frames[:, None, :, 1]
        return home.world(body, local.reshape(-1, 3)).reshape(local.shape)

    def attempt(m, anchor, direction) -> PlacedModule | None:
        mod = replace(m, id=first_id + len(placed), name=f"{body}_m{len(placed)}", body=body)
        try:
            p = place_module(surface, mod, anchor, direction)
        except PlacementError as e:
            refused["strain" if e.kind == "strain" else "placement"] += 1
            return None
        w, wn = home.world(body, p.positions), p.frames[:, :, 2] @ R.T
        reason = ("overlap" if home.meets(w, wn, gap) else
                  "overhang" if outline_overhang(surface, p.positions, p.frames, m.pitch / 2,
                                                 m.min_bend_radius).max() > SURFACE_TOL else
                  "buried" if home.hidden(body, p.positions, p.frames[:, :, 2]).any() else
                  "roundtrip" if disagreement(surface, p) > ROUNDTRIP_TOL else None)
        if reason:
            refused[reason] += 1
            return None
        p.module = replace(mod, placement=placement_record(p.origin, p.origin_frame[:, 0], "geodesic"))
        home.add(w, wn)
        placed.append(p)
        return p

    # each size in turn, rows along the axis first, then around it; from each seed the quilt of
    # whole modules grows module by module (a try is skipped where the module laid flat clearly
    # meets a placed one)
    for m in trimmed(template):
        uv = template_grid(m)[0]
        for direction in (np.broadcast_to(axis, pts.shape), np.cross(nrm, axis)):
            seeds = flat(uv, pts, frames_from_normals(nrm, direction))
            seed_n = np.broadcast_to((nrm @ R.T)[:, None], seeds.shape)
            free = open_ & ~home.meets_each(seeds, seed_n, 0.8 * gap)  # before this pass, all at once
            for i in order[free[order]]:
                if home.meets(seeds[i], seed_n[i], 0.8 * gap):
                    continue
                front = deque([(pts[i], None, direction[i])])  # the seed is checked already
                while front:
                    anchor, normal, d = front.popleft()
                    if normal is not None and home.meets(
                            flat(uv, anchor[None], frames_from_normals(normal[None], d[None]))[0], normal @ R.T,
                            0.8 * gap):
                        continue
                    if limit is not None and sum(len(p) for p in placed) + m.rows * m.cols > limit:
                        return placed, refused
                    p = attempt(m, anchor, d)
                    if p is not None and m is template:
                        front.extend(neighbour_anchors(surface, p))
    return placed, refused


def cover_design(robot, ref: RobotRef, bodies: list[str] | None = None, template: Module = COVER_MODULE,
                 pitch: float | None = None, board_capacity: int = 512, force_threshold: float = 2.0,
                 limit: int | None = None, progress=None, keep: SkinDesign | None = None,
                 surfaces: dict[str, Surface] | None = None, first_id: int = 0) -> tuple[SkinDesign, dict]:
    """A skin covering `bodies` (default: every moving link with a real surface, the whole arm) of
    `robot` with copies of `template` (at `pitch` if given, the taxel diameter and margin scaled
    with it), around the modules of `keep` (kept, numbered first, never overlapped), on
    `surfaces` (default: the links' design surfaces, `cached_surfaces`). New modules take ids from `first_id` on,
    above every id `keep` has used (its retired ones too: an id never comes back meaning another module). Returns
    the design and, per link, the refused attempts by reason."""
    if template.template not in ("rect", "strip"):
        raise DesignError(f"cover: a '{template.template}' module cannot be tiled; use rect or strip")
    if pitch is not None:
        if not 0 < pitch < 0.2:
            raise DesignError(f"cover: pitch {pitch} m is outside (0, 0.2); use e.g. 0.01")
        scale = pitch / template.pitch
        template = replace(template, pitch=pitch, taxel_diameter=template.taxel_diameter * scale,
                           margin=template.margin * scale)
    bodies = list(bodies or surface_bodies(robot.model, moving=True))
    unknown = [b for b in bodies if b not in robot.body_names]
    if unknown:
        raise DesignError(f"cover: body '{unknown[0]}' is not in robot {robot.name}; use one of "
                          f"{sorted(robot.body_names - {'world'})}")
    surfaces = {**cached_surfaces(robot.model, [b for b in bodies if b not in (surfaces or {})]), **(surfaces or {})}
    home = _Home(robot.model, robot.home)
    kept = [placed_from_design(keep, m.id) for m in keep.modules] if keep is not None else []
    if kept:
        rot = lambda b: home.data.xmat[robot.model.body(b).id].reshape(3, 3)  # noqa: E731
        home.add(np.concatenate([home.world(p.module.body, p.positions) for p in kept]),
                 np.concatenate([p.frames[:, :, 2] @ rot(p.module.body).T for p in kept]))
    first = max(first_id, 1 + max([p.module.id for p in kept] + list(keep.retired_modules if keep else ()), default=-1))
    placed, refused = [], {}
    for b in bodies:
        left = None if limit is None else limit - sum(len(p) for p in kept + placed)
        mine, refused[b] = cover_link(surfaces[b], home, template, b, first + len(placed), left)
        placed += mine
        if progress is not None:
            progress.update(1)
    if not placed:
        raise DesignError(f"cover: no {template.rows}x{template.cols} module at {template.pitch * 1e3:g} mm pitch fits on "
                          f"{bodies} (refused: {refused}); use a smaller module, a finer pitch or a smaller bend radius")
    order = list(keep.bodies) if keep is not None else []
    order += [b for b in bodies if b not in order and any(p.module.body == b for p in placed)]
    design = build_design(ref, kept + placed, board_capacity, force_threshold, bodies=order)
    return replace(design, retired_modules=keep.retired_modules if keep else ()), refused


def cover_report(design: SkinDesign, model: mujoco.MjModel, home: np.ndarray) -> dict:
    """Per skinned link: `covered` (the share of the link's exposed surface, what does not lie inside
    another link at home or its own housing, that the cells cover: `coverage.covered_points`, each
    point once), `covered_of_link` (the cells' area over its whole surface), `exposed` (the exposed share of the surface), `bare_fraction` and
    `largest_gap_mm` (`coverage.gaps`), `overlaps` (taxels whose cell meets another module's facing
    the same way, on this link or another at home) and `buried` (taxels more than `BURIED_TOL` inside another link
    at home, or enclosed by their own: `audit.enclosed`)."""
    from skinsafe.core.design.coverage import coverage_report, covered_points

    t = design.taxels
    cov = coverage_report(design, model)
    data = mujoco.MjData(model)
    data.qpos[:] = home
    mujoco.mj_kinematics(model, data)
    bid = np.array([model.body(b).id for b in design.bodies])[t.body]
    world = np.einsum("nij,nj->ni", data.xmat[bid].reshape(-1, 3, 3), t.positions) + data.xpos[bid]
    mods = {m.id: m for m in design.modules}
    gap = np.array([max(2 * clearance(mods[int(k)]), 0.75 * mods[int(k)].pitch) for k in t.module])
    pairs = cKDTree(world).query_pairs(float(gap.max()) if len(gap) else 0.0, output_type="ndarray")
    normals = np.einsum("nij,nj->ni", data.xmat[bid].reshape(-1, 3, 3), t.frames[:, :, 2])
    a, b = pairs[:, 0], pairs[:, 1]
    pairs = pairs[(t.module[a] != t.module[b]) & (np.sum(normals[a] * normals[b], axis=1) > 0.5)
                  & (np.linalg.norm(world[a] - world[b], axis=1) < np.minimum(gap[a], gap[b]))]
    overlapping = np.zeros(len(t), bool)
    overlapping[pairs.ravel()] = True
    at_home = _Home(model, home)
    buried = np.zeros(len(t), bool)
    for i, name in enumerate(design.bodies):
        on = np.flatnonzero(t.body == i)
        buried[on] = at_home.hidden(name, t.positions[on], t.frames[on, :, 2])
    out = {}
    for i, name in enumerate(design.bodies):
        on = t.body == i
        c = cov[name]
        q, nrm, open_ = at_home.exposed(name, cached_surfaces(model, [name])[name])
        covered = covered_points(design, i, q, nrm)
        exposed = float(open_.mean())
        out[name] = {"covered": float((covered & open_).sum() / max(open_.sum(), 1)), "covered_of_link": c["fraction"],
                     "exposed": exposed, "bare_fraction": c["bare_fraction"], "largest_gap_mm": c["largest_gap_mm"],
                     "taxels": c["taxels"], "modules": c["modules"], "overlaps": int(overlapping[on].sum()),
                     "buried": int(buried[on].sum())}
    return out


def format_cover_report(report: dict) -> str:
    """The cover report as an aligned text table."""
    lines = [f"{'link':<20}{'covered':>9}{'of link':>9}{'exposed':>9}{'bare':>7}{'gap mm':>8}{'taxels':>8}{'modules':>9}{'overlaps':>10}{'buried':>8}"]
    for name, r in report.items():
        lines.append(f"{name:<20}{r['covered'] * 100:>8.1f}%{r['covered_of_link'] * 100:>8.1f}%{r['exposed'] * 100:>8.1f}%"
                     f"{r['bare_fraction'] * 100:>6.0f}%{r['largest_gap_mm']:>8.0f}"
                     f"{r['taxels']:>8}{r['modules']:>9}{r['overlaps']:>10}{r['buried']:>8}")
    return "\n".join(lines)
