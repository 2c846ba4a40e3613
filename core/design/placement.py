"""Conformal placement of FPC skin modules on a body surface.

A module template is a grid of taxel centres (u, v) in the flat FPC, u along the rows (the
taxel x axis), v across them. `geodesic` layout walks the surface from the picked anchor: first
along x for u (the spine), then from each spine point along the surface's y = z cross x for v,
re-projecting every small step onto the surface and carrying the direction in the tangent plane.
On a developable link (cylinder, cone, plane) that is the FPC's own isometric wrap: taxel
spacing measured on the surface equals the pitch. `projection` lays the flat grid in the anchor's
tangent plane and drops each taxel to the closest surface point (spacing shrinks on curves).

A flexible circuit bends but never stretches: every placement's in-plane strain is measured
(`strain.module_strain`: surface length between neighbouring pads against the flat pattern, rows,
columns and diagonals) and a module over its `max_strain` is refused, naming the pad pair, the
strain and the largest centred cut of the module that fits there.

Refusals (`PlacementError`, a `DesignError` carrying `where`): taxels falling off the surface,
a bend radius below the module's minimum, in-plane strain over the module's tolerance, and
overlap with another module.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial import cKDTree

from skinsafe.core.design.strain import Strain, module_strain, surface_length
from skinsafe.core.design.surface import Surface
from skinsafe.core.skin.boards import assign_boards, number_channels
from skinsafe.core.skin.ids import stable_ids
from skinsafe.core.skin.model import DesignError, Module, RobotRef, SkinDesign, Taxels, frames_from_normals

TEMPLATES = ("rect", "strip", "curve")
METHODS = ("geodesic", "projection")


FAR_ANCHOR = 0.02  # m: an anchor farther than this from its link's surface is refused, not snapped


class PlacementError(DesignError):
    """The FPC cannot be placed as asked; `where` holds (row, col, body-frame position) or None."""

    def __init__(self, message: str, kind: str, where: tuple | None = None):
        super().__init__(message)
        self.kind = kind  # "off_surface", "bend_radius", "strain", "overlap", "template", "far_anchor"
        self.where = where


@dataclass
class PlacedModule:
    """One module's taxels on its body, in the body frame, in template order."""

    module: Module
    positions: np.ndarray  # (n, 3)
    frames: np.ndarray  # (n, 3, 3) columns x (along rows), y, z (outward normal)
    row: np.ndarray  # (n,) int
    col: np.ndarray  # (n,) int
    min_bend_radius: float  # the tightest bend the placement asks of the FPC, m
    origin: np.ndarray | None = None  # (3,) the anchor on the surface
    origin_frame: np.ndarray | None = None  # (3,3) the module frame there (x along rows, z out)
    strain: float = 0.0  # the largest in-plane strain the wrap asks of the FPC (`strain.module_strain`)

    def __len__(self) -> int:
        return len(self.positions)


def template_grid(module: Module, outline: np.ndarray | None = None):
    """Taxel grid of a module template: (u, v) in m (n,2), row (n,), col (n,).

    rect: rows x cols; strip: one row of cols taxels; curve: the cells of the rows x cols grid
    whose centres lie inside `outline` (a closed polygon (k,2) in m, module-centred).
    """
    m = module
    if m.template not in TEMPLATES:
        raise PlacementError(f"module {m.id} '{m.name}': template '{m.template}' is unknown; use one of "
                             f"{', '.join(TEMPLATES)}", "template")
    if m.rows < 1 or m.cols < 1 or not (m.pitch > 0) or not (0 < m.taxel_diameter <= m.pitch):
        raise PlacementError(f"module {m.id} '{m.name}': rows {m.rows}, cols {m.cols}, pitch {m.pitch}, taxel diameter "
                             f"{m.taxel_diameter} are not a valid grid; use rows, cols >= 1 and 0 < diameter <= pitch",
                             "template")
    if m.template == "strip" and m.rows != 1:
        raise PlacementError(f"module {m.id} '{m.name}': a strip has one row, not {m.rows}; set rows = 1 "
                             "or use the 'rect' template", "template")
    row, col = np.meshgrid(np.arange(m.rows), np.arange(m.cols), indexing="ij")
    row, col = row.ravel(), col.ravel()
    uv = np.stack([(col - (m.cols - 1) / 2) * m.pitch, (row - (m.rows - 1) / 2) * m.pitch], axis=1)
    if m.template == "curve":
        if outline is None or len(outline) < 3:
            raise PlacementError(f"module {m.id} '{m.name}': the 'curve' template needs an outline of >= 3 points; "
                                 "pick a closed curve", "template")
        inside = points_in_polygon(uv, np.asarray(outline, dtype=float))
        if not inside.any():
            raise PlacementError(f"module {m.id} '{m.name}': no taxel centre of the {m.rows}x{m.cols} grid lies inside "
                                 "the outline; enlarge the outline or the grid", "template")
        uv, row, col = uv[inside], row[inside], col[inside]
    return uv, row, col


def points_in_polygon(p: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """Even-odd rule: which points (n,2) lie inside the closed polygon (k,2)."""
    x, y = p[:, 0:1], p[:, 1:2]
    x0, y0 = poly[:, 0], poly[:, 1]
    x1, y1 = np.roll(x0, -1), np.roll(y0, -1)
    crosses = (y0 > y) != (y1 > y)
    with np.errstate(divide="ignore", invalid="ignore"):
        xi = x0 + (y - y0) * (x1 - x0) / (y1 - y0)
    return (np.sum(crosses & (x < xi), axis=1) % 2) == 1


def _fmt(p) -> str:
    return "(" + ", ".join(f"{c:.4f}" for c in p) + ") m"


def _march(surface: Surface, p, n, t, carry, hs: np.ndarray):
    """Walk points p (m,3) with normals n along tangents t in steps of surface lengths hs,
    carrying the tangent `carry` (m,3) along. Each step goes h' along the tangent and back onto
    the surface, h' stretched by the curvature seen on the previous step (tan(kh)/k) so the arc,
    not the chord, is h. Returns per-step arrays (steps+1, m, ...) and each walker's first failing
    step (-1 for none)."""
    f = lambda a: np.ascontiguousarray(a, dtype=float)  # noqa: E731
    from skinsafe.core.design.surface_kernels import march

    return march(f(p), f(n), f(t), f(carry), f(hs), *surface.kernel)


def place_module(surface: Surface, module: Module, anchor, direction, method: str = "geodesic",
                 outline: np.ndarray | None = None, others: list[PlacedModule] = (),
                 max_step: float = 0.005) -> PlacedModule:
    """Wrap `module` onto `surface` (its body) centred at `anchor` (body frame) with rows along
    `direction` (projected onto the tangent plane). Raises PlacementError when the FPC would
    fall off the surface, bend tighter than `module.min_bend_radius`, or overlap `others`."""
    if method not in METHODS:
        raise PlacementError(f"module {module.id} '{module.name}': method '{method}' is unknown; use one of "
                             f"{', '.join(METHODS)}", "template")
    uv, row, col = template_grid(module, outline)
    anchor = np.asarray(anchor, dtype=float).reshape(1, 3)
    p0, n0, _, gap = surface.closest(anchor)
    if gap[0] > FAR_ANCHOR:
        raise PlacementError(f"module {module.id} '{module.name}': anchor {_fmt(anchor[0])} is {gap[0] * 1e3:.0f} mm from "
                             f"the surface of '{surface.name}' (more than {FAR_ANCHOR * 1e3:.0f} mm); put the anchor on "
                             "the link (did you mean another body, or body-frame coordinates?)", "far_anchor",
                             (0, 0, tuple(map(float, anchor[0]))))
    x0 = frames_from_normals(n0, np.asarray(direction, dtype=float).reshape(1, 3))[:, :, 0]
    if method == "projection":
        pos, nrm, x = _project(surface, module, uv, row, col, p0, n0, x0)
    else:
        pos, nrm, x = _geodesic(surface, module, uv, row, col, p0, n0, x0, max_step)
    strain = module_strain(uv, row, col, pos, nrm)
    if strain.max > module.max_strain and method == "geodesic":
        pos, nrm, strain = relax(surface, uv, row, col, pos, nrm, strain, module.max_strain)
    frames = frames_from_normals(nrm, x)
    radius = _check_bend(module, surface.name, uv, row, col, pos, frames)
    if strain.max > module.max_strain:
        raise _stretched(module, surface, uv, row, col, pos, strain, anchor[0], direction, method, max_step)
    placed = PlacedModule(module, pos, frames, row, col, radius, p0[0], frames_from_normals(n0, x0)[0], strain.max)
    check_overlap(placed, others)
    return placed


RELAX_SWEEPS, RELAX_FROM = 60, 5.0  # sweeps at most; only a walk stretched under 5x the tolerance is relaxed


def relax(surface: Surface, uv, row, col, pos, nrm, strain: Strain, tol: float):
    """The least-strain wrap of a grid the walk stretched (a doubly curved patch): the circuit
    settles where its stretched and crowded pad pairs balance. Jacobi sweeps of distance
    constraints (position-based dynamics: each pair moves its two pads half its length error along
    its chord), each sweep projected back onto the surface, until the strain is under half the
    tolerance or stops improving. A walk stretched more than `RELAX_FROM` times the tolerance is
    left as it is (no relaxation brings it within). Returns (positions, normals, Strain)."""
    if strain.max > RELAX_FROM * tol:
        return pos, nrm, strain
    a, b = strain.a, strain.b
    flat = np.linalg.norm(uv[a] - uv[b], axis=1)
    count = np.maximum(np.bincount(np.r_[a, b], minlength=len(pos)), 1)[:, None]
    best, checked, s = (pos, nrm, strain), strain.max, strain.strain
    for sweep in range(1, RELAX_SWEEPS + 1):
        d = pos[b] - pos[a]
        move = (0.5 * s * flat / np.maximum(np.linalg.norm(d, axis=1), 1e-12))[:, None] * d
        delta = np.stack([np.bincount(a, move[:, k], len(pos)) - np.bincount(b, move[:, k], len(pos))
                          for k in range(3)], axis=1)
        pos, nrm = surface.closest(pos + 0.5 * delta / count)[:2]
        s = surface_length(pos[a], pos[b], nrm[a], nrm[b]) / flat - 1.0
        worst = float(np.abs(s).max())
        if worst < best[2].max:
            best = (pos, nrm, Strain(a, b, s))
        if best[2].max < tol / 2 or sweep % 10 == 0 and best[2].max > 0.95 * checked:
            break
        checked = best[2].max if sweep % 10 == 0 else checked
    return best


def largest_fit(surface: Surface, module: Module, anchor, direction, strain: Strain, row: np.ndarray,
                col: np.ndarray, method: str = "geodesic", max_step: float = 0.005, tries: int = 8) -> tuple[int, int]:
    """The largest cut (rows, cols) of `module` that places at the same anchor and direction within its
    strain tolerance ((0, 0) for none): what a refusal for strain offers. Cuts are tried largest first
    among those whose centred part of the refused grid (`strain`, its pad pairs) is stretched little
    enough to be placed (within the tolerance, or within relaxation's reach for the geodesic walk)."""
    reach = module.max_strain * (RELAX_FROM if method == "geodesic" else 1.0)
    worst = np.abs(strain.strain)
    sizes = []
    for r in range(1, module.rows + 1):
        for c in range(1, module.cols + 1):
            if r * c < 2 or (r, c) == (module.rows, module.cols):
                continue
            r0, c0 = (module.rows - r) // 2, (module.cols - c) // 2
            inside = (row >= r0) & (row < r0 + r) & (col >= c0) & (col < c0 + c)
            pairs = inside[strain.a] & inside[strain.b]
            if not pairs.any() or worst[pairs].max() <= reach:
                sizes.append((r, c))
    for r, c in sorted(sizes, key=lambda rc: (-rc[0] * rc[1], -rc[1]))[:tries]:
        try:
            place_module(surface, replace(module, rows=r, cols=c), anchor, direction, method, max_step=max_step)
            return r, c
        except PlacementError:
            continue
    return 0, 0


class StretchedError(PlacementError):
    """A refusal for in-plane strain; the cut that fits is worked out when the message is read (a cover
    counts thousands of refusals and reads none)."""

    def __init__(self, head: str, where: tuple, offer):
        super().__init__(head, "strain", where)
        self._offer, self._text = offer, None

    def __str__(self) -> str:
        if self._text is None:
            fit = self._offer()
            self._text = (f"{self.args[0]}: " + (f"a {fit[0]}x{fit[1]} module fits here" if fit[0] else
                                                  "no smaller cut of this grid fits here") +
                          ", or cut the outline to the patch (the 'curve' template), or run strips along the link")
        return self._text


def _stretched(module, surface, uv, row, col, pos, strain: Strain, anchor, direction, method, max_step) -> PlacementError:
    k = strain.worst
    i, j = int(strain.a[k]), int(strain.b[k])
    offer = (lambda: largest_fit(surface, module, anchor, direction, strain, row, col, method, max_step)) \
        if module.template == "rect" else \
        (lambda: (0, 0))
    return StretchedError(
        f"module {module.id} '{module.name}': in-plane strain {strain.strain[k] * 100:+.1f}% between taxels row "
        f"{row[i]} col {col[i]} and row {row[j]} col {col[j]} on '{surface.name}' at {_fmt(pos[i])} is over the FPC's "
        f"{module.max_strain * 100:.1f}% (a flat circuit cannot wrap this doubly curved patch)",
        (int(row[i]), int(col[i]), tuple(map(float, pos[i]))), offer)


def _off_surface(module, body, row, col, pos):
    return PlacementError(
        f"module {module.id} '{module.name}': taxel row {row} col {col} falls off the surface of '{body}' at "
        f"{_fmt(pos)} (the surface ends or folds there); move the module or use fewer rows/cols", "off_surface",
        (int(row), int(col), tuple(map(float, pos))))


def _project(surface, module, uv, row, col, p0, n0, x0):
    y0 = np.cross(n0, x0)
    flat = p0 + uv[:, :1] * x0 + uv[:, 1:] * y0
    pos, nrm, _, _ = surface.closest(flat)
    off = flat - pos
    tangential = np.linalg.norm(off - np.sum(off * nrm, axis=1, keepdims=True) * nrm, axis=1)
    bad = (tangential > 0.25 * module.pitch) | (np.sum(nrm * n0, axis=1) < 0)
    if bad.any():
        i = int(np.argmax(bad))
        raise _off_surface(module, surface.name, row[i], col[i], pos[i])
    return pos, nrm, np.broadcast_to(x0, pos.shape)


def _steps(dist: np.ndarray, max_step: float):
    """Step lengths reaching every distance in `dist` (>= 0), none longer than max_step, and the
    step index at which each distance is reached."""
    stops = np.unique(np.round(dist, 12))
    gaps = np.diff(np.concatenate([[0.0], stops[stops > 0]]))
    hs = np.concatenate([np.full(int(np.ceil(g / max_step - 1e-9)), g / np.ceil(g / max_step - 1e-9)) for g in gaps]) \
        if len(gaps) else np.zeros(0)
    cum = np.concatenate([[0.0], np.cumsum(hs)])
    idx = np.minimum(np.searchsorted(cum, dist - 1e-9), len(cum) - 1)
    return hs, idx


def _geodesic(surface, module, uv, row, col, p0, n0, x0, max_step):
    hu, ku = _steps(np.abs(uv[:, 0]), max_step)
    hv, kv = _steps(np.abs(uv[:, 1]), max_step)
    # Spine: both ways along x from the anchor.
    P, N, X, fail = _march(surface, np.repeat(p0, 2, 0), np.repeat(n0, 2, 0), np.concatenate([x0, -x0]),
                           np.concatenate([x0, x0]), hu)
    su = (uv[:, 0] < 0).astype(int)  # which spine walker
    fail_u = (fail[su] >= 0) & (fail[su] <= ku)
    if fail_u.any():
        i = int(np.argmax(fail_u))
        raise _off_surface(module, surface.name, row[i], col[i], P[fail[su[i]], su[i]])
    # Cross walks: from each distinct spine point, both ways along y = z cross x.
    keys, inv = np.unique(np.stack([ku, su], 1), axis=0, return_inverse=True)
    inv = inv.ravel()
    sp, sn, sx = P[keys[:, 0], keys[:, 1]], N[keys[:, 0], keys[:, 1]], X[keys[:, 0], keys[:, 1]]
    sy = np.cross(sn, sx)
    m = len(keys)
    Q, M, Y, fail2 = _march(surface, np.concatenate([sp, sp]), np.concatenate([sn, sn]),
                            np.concatenate([sy, -sy]), np.concatenate([sx, sx]), hv)
    walker = inv + m * (uv[:, 1] < 0)
    bad = (fail2[walker] >= 0) & (fail2[walker] <= kv)
    if bad.any():
        i = int(np.argmax(bad))
        raise _off_surface(module, surface.name, row[i], col[i], Q[fail2[walker[i]], walker[i]])
    return Q[kv, walker], M[kv, walker], Y[kv, walker]


def _check_bend(module, body, uv, row, col, pos, frames) -> float:
    """Smallest bend radius between grid neighbours (normal turn over surface distance)."""
    index = {(int(r), int(c)): i for i, (r, c) in enumerate(zip(row, col))}
    a, b = [], []
    for (r, c), i in index.items():
        for nb in ((r, c + 1), (r + 1, c)):
            j = index.get(nb)
            if j is not None:
                a.append(i), b.append(j)
    if not a:
        return float("inf")
    a, b = np.asarray(a), np.asarray(b)
    z = frames[:, :, 2]
    angle = np.arccos(np.clip(np.sum(z[a] * z[b], axis=1), -1.0, 1.0))
    dist = np.linalg.norm(pos[a] - pos[b], axis=1)
    with np.errstate(divide="ignore"):
        radius = np.where(angle > 1e-9, dist / np.maximum(angle, 1e-300), np.inf)
    k = int(np.argmin(radius))
    if radius[k] < module.min_bend_radius * (1 - 1e-3):
        i = a[k]
        raise PlacementError(
            f"module {module.id} '{module.name}': bend radius {radius[k] * 1e3:.1f} mm at taxel row {row[i]} col {col[i]} "
            f"on '{body}' at {_fmt(pos[i])} is below the FPC's minimum {module.min_bend_radius * 1e3:.1f} mm; "
            "place it on a flatter part, turn it so it bends along its stiffer axis, or use a more flexible FPC",
            "bend_radius", (int(row[i]), int(col[i]), tuple(map(float, pos[i]))))
    return float(radius[k])


def clearance(m: Module) -> float:
    return m.taxel_diameter / 2 + m.margin


def check_overlap(placed: PlacedModule, others: list[PlacedModule]) -> None:
    """Refuse a module whose FPC outline (taxel discs plus margin, grid cells) meets another's
    on the same body."""
    m = placed.module
    for o in others:
        if o.module.body != m.body or o.module.id == m.id or not len(o):
            continue
        limit = max(clearance(m) + clearance(o.module), 0.75 * max(m.pitch, o.module.pitch))
        d, j = cKDTree(o.positions).query(placed.positions, distance_upper_bound=limit)
        hit = np.isfinite(d)
        if hit.any():
            i = int(np.argmin(d))
            raise PlacementError(
                f"module {m.id} '{m.name}': taxel row {placed.row[i]} col {placed.col[i]} at {_fmt(placed.positions[i])} on "
                f"'{m.body}' overlaps module {o.module.id} '{o.module.name}' ({d[i] * 1e3:.1f} mm from its taxel, "
                f"{limit * 1e3:.1f} mm needed); move one of them", "overlap",
                (int(placed.row[i]), int(placed.col[i]), tuple(map(float, placed.positions[i]))))


def build_design(robot: RobotRef, placed: list[PlacedModule], capacity: int = 256, force_threshold: float = 2.0,
                 bodies: list[str] | None = None) -> SkinDesign:
    """A validated SkinDesign from placed modules: stable taxel ids (`ids.stable_ids`: module id x
    65,536 + index), whole modules on boards (`assign_boards`), channels numbered per board."""
    bodies = list(bodies or dict.fromkeys(p.module.body for p in placed))
    body_index = {b: i for i, b in enumerate(bodies)}
    sizes = {p.module.id: len(p) for p in placed}
    boards, of = assign_boards(np.array(list(sizes)), sizes, capacity)
    n = sum(sizes.values())
    mod = np.concatenate([np.full(len(p), p.module.id, np.int32) for p in placed]) if placed else np.zeros(0, np.int32)
    board = np.array([of[int(i)] for i in mod], dtype=np.int32)
    taxels = Taxels(
        ids=stable_ids(mod),
        body=np.concatenate([np.full(len(p), body_index[p.module.body], np.int32) for p in placed]) if placed
        else np.zeros(0, np.int32),
        positions=np.concatenate([p.positions for p in placed]) if placed else np.zeros((0, 3)),
        frames=np.concatenate([p.frames for p in placed]) if placed else np.zeros((0, 3, 3)),
        module=mod, board=board, channel=number_channels(mod, board),
        area=np.concatenate([np.full(len(p), np.pi * p.module.taxel_diameter ** 2 / 4) for p in placed]) if placed
        else np.zeros(0),
        enabled=np.ones(n, bool),
        thresholds={"force": np.full(n, float(force_threshold))},
    )
    modules = [replace(p.module, board=of[p.module.id]) for p in placed]
    design = SkinDesign(robot, bodies, modules, boards, taxels)
    design.validate("placement")
    return design


def placement_record(anchor, direction, method: str, outline=None) -> dict:
    """What goes into `Module.placement` so the module can be re-generated."""
    rec = {"method": method, "anchor": [float(c) for c in np.ravel(anchor)],
           "direction": [float(c) for c in np.ravel(direction)]}
    if outline is not None:
        rec["outline"] = np.asarray(outline, dtype=float).tolist()
    return rec


def replace_module(design: SkinDesign, placed: PlacedModule) -> SkinDesign:
    """The design with one module's taxels swapped for a re-generated placement (same ids where
    the count is unchanged; boards and channels re-assigned when it changed)."""
    t = design.taxels
    mid = placed.module.id
    on = t.module == mid
    if int(on.sum()) == len(placed) and placed.module.body in design.bodies:
        pos, frames = t.positions.copy(), t.frames.copy()
        idx = np.flatnonzero(on)
        pos[idx], frames[idx] = placed.positions, placed.frames
        new_t = replace(t, positions=pos, frames=frames)
        modules = [replace(placed.module, board=m.board) if m.id == mid else m for m in design.modules]
        return replace(design, taxels=new_t, modules=modules)
    parts = [placed_from_design(design, m.id) if m.id != mid else placed for m in design.modules]
    if mid not in {m.id for m in design.modules}:
        parts.append(placed)
    return build_design(design.robot, parts, max([b.capacity for b in design.boards], default=256),
                        float(np.median(t.thresholds["force"])) if len(t) else 2.0)


def module_grid(module: Module, n: int):
    """The flat pattern of a module of a design holding `n` taxels: (uv (n,2) m, row, col) in taxel
    order, from its template (and the outline its placement recorded); a mirrored module's (the
    add-on's mirror: taxel k at the template's u -> -u, a mirror-image circuit) in its own order. None
    when the template does not give `n` pads (the module was edited into another shape: it cannot be
    checked as a grid)."""
    placement = module.placement if isinstance(module.placement, dict) else {}
    outline = placement.get("outline")
    try:
        uv, row, col = template_grid(module, None if outline is None else np.asarray(outline, float))
    except PlacementError:
        return None
    if placement.get("mirrored"):
        k = np.lexsort((-col, row))
        uv, row, col = uv[k], row[k], col[k]
    return (uv, row, col) if len(uv) == n else None


def placed_from_design(design: SkinDesign, module_id: int) -> PlacedModule:
    """A module's taxels of a design as a PlacedModule (for overlap checks and re-assembly)."""
    t = design.taxels
    on = t.module == module_id
    m = next(m for m in design.modules if m.id == module_id)
    k = int(on.sum())
    grid = module_grid(m, k)
    if grid is None:
        idx = np.arange(k)
        grid = (None, idx // max(m.cols, 1), idx % max(m.cols, 1))
    return PlacedModule(m, t.positions[on], t.frames[on], grid[1], grid[2], float("inf"))


def ring_layout(model, body: str, module: Module, poses=None) -> list[tuple[np.ndarray, np.ndarray]]:
    """Anchors and row directions (body frame) tiling the straight part of a body's first
    capsule/cylinder geom with `module`: rows along the axis, modules side by side around it.
    With `poses` (`sample.turned_poses`), only slots whose cells no other geom covers at every
    pose (`sample.exposed_span`: under a joint housing, where `skinsafe check` refuses them)."""
    import mujoco

    from skinsafe.core.design.sample import exposed_span

    bid = model.body(body).id
    geoms = [g for g in np.flatnonzero(model.geom_bodyid == bid)
             if int(model.geom_type[g]) in (int(mujoco.mjtGeom.mjGEOM_CAPSULE), int(mujoco.mjtGeom.mjGEOM_CYLINDER))]
    if not geoms:
        raise DesignError(f"ring layout: body '{body}' has no capsule or cylinder geom; place modules one by one")
    g = int(geoms[0])
    R = np.zeros(9)
    mujoco.mju_quat2Mat(R, model.geom_quat[g])
    R = R.reshape(3, 3)
    r, half = model.geom_size[g][:2]
    along = (module.cols - 1) * module.pitch + 2 * clearance(module)
    around = (module.rows - 1) * module.pitch + 2 * clearance(module)
    n_along, n_around = int((2 * half) // along), int((2 * np.pi * r) // around)
    inner = along / 2 - module.pitch / 2  # from the slot's centre to its outermost ring of cells
    out = []
    for i in range(n_along):
        z = -half + (i + 0.5) * (2 * half / n_along)
        for k in range(n_around):
            phi = 2 * np.pi * k / max(n_around, 1)
            if poses is not None:
                span = exposed_span(model, poses, g, module.pitch, 0.5 * module.pitch,
                                    phi + np.linspace(-around / (2 * r), around / (2 * r), 7))
                if not span or not span[0] <= z - inner or not z + inner <= span[1]:
                    continue
            radial = np.cos(phi) * R[:, 0] + np.sin(phi) * R[:, 1]
            out.append((model.geom_pos[g] + z * R[:, 2] + r * radial, R[:, 2].copy()))
    return out


def tile_bodies(surfaces: dict[str, Surface], model, template: Module, bodies: list[str],
                limit: int | None = None, progress=None) -> tuple[list[PlacedModule], list[str]]:
    """Place copies of `template` by `ring_layout` on each body, skipping (and reporting) the
    refused ones, until `limit` taxels. Returns the placed modules and the refusal messages."""
    placed, refused = [], []
    for body in bodies:
        mine: list[PlacedModule] = []
        for anchor, direction in ring_layout(model, body, template):
            if limit is not None and sum(len(p) for p in placed) >= limit:
                return placed, refused
            m = replace(template, id=len(placed), name=f"{body}_m{len(mine)}", body=body)
            try:
                p = place_module(surfaces[body], m, anchor, direction, others=mine)
            except PlacementError as e:
                refused.append(e.args[0])  # a strain refusal without its offer (worked out only when read)
                continue
            p.module = replace(m, placement=placement_record(p.origin, p.origin_frame[:, 0], "geodesic"))
            placed.append(p), mine.append(p)
            if progress is not None:
                progress.update(len(p))
    return placed, refused
