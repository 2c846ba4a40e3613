"""Coverage report: how much of each link the skin covers."""
from __future__ import annotations

import mujoco
import numpy as np
from scipy.spatial import cKDTree

from skinsafe.core.skin.model import SkinDesign

G = mujoco.mjtGeom


def geom_area(model: mujoco.MjModel, g: int) -> float:
    """Surface area of one geom in m^2 (primitives analytically, meshes from their triangles)."""
    t, s = int(model.geom_type[g]), model.geom_size[g]
    if t == G.mjGEOM_CAPSULE:
        return 2 * np.pi * s[0] * 2 * s[1] + 4 * np.pi * s[0] ** 2
    if t == G.mjGEOM_CYLINDER:
        return 2 * np.pi * s[0] * 2 * s[1] + 2 * np.pi * s[0] ** 2
    if t == G.mjGEOM_SPHERE:
        return 4 * np.pi * s[0] ** 2
    if t == G.mjGEOM_ELLIPSOID:  # Knud Thomsen's approximation
        p = 1.6075
        a, b, c = s ** p
        return 4 * np.pi * ((a * b + a * c + b * c) / 3) ** (1 / p)
    if t == G.mjGEOM_BOX:
        x, y, z = 2 * s
        return 2 * (x * y + y * z + x * z)
    if t == G.mjGEOM_MESH:
        m = model.geom_dataid[g]
        v0, nv = model.mesh_vertadr[m], model.mesh_vertnum[m]
        f0, nf = model.mesh_faceadr[m], model.mesh_facenum[m]
        v = model.mesh_vert[v0:v0 + nv]
        f = model.mesh_face[f0:f0 + nf]
        return float(0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1).sum())
    return 0.0


def body_area(model: mujoco.MjModel, body: str) -> float:
    """Outer surface area of a body's skin surface (its visual geometry where it has any, else
    its colliding shapes; overlaps counted once), m^2."""
    from skinsafe.core.design.surface import cached_surfaces

    return cached_surfaces(model, [body])[body].area


def reach(design: SkinDesign, body_index: int) -> float:
    """How far a link's taxels cover: the root mean square pitch of their modules (0 without taxels)."""
    pitch = {m.id: m.pitch for m in design.modules}
    cell = np.array([pitch.get(int(m), 0.0) ** 2 for m in design.taxels.module[design.taxels.body == body_index]])
    return float(np.sqrt(cell.mean())) if len(cell) else 0.0


def _distances(design: SkinDesign, model: mujoco.MjModel, body_index: int):
    """The link's surface (vertices, triangles, body frame) and each vertex's distance to its nearest taxel
    on the link (None without taxels)."""
    from skinsafe.core.design.surface import cached_surfaces

    on = design.taxels.body == body_index
    surf = cached_surfaces(model, [design.bodies[body_index]])[design.bodies[body_index]]
    d = cKDTree(design.taxels.positions[on]).query(surf.vertices)[0] if on.any() else None
    return surf.vertices, surf.triangles, d


def uncovered_points(design: SkinDesign, model: mujoco.MjModel, body_index: int) -> np.ndarray:
    """The bare area `gaps` measures, as points: the link's surface vertices (body frame) farther than
    `reach` from every taxel; the whole surface of a link without taxels."""
    v, _, d = _distances(design, model, body_index)
    return v.copy() if d is None else v[d > reach(design, body_index)]


def gaps(design: SkinDesign, model: mujoco.MjModel, body_index: int, pitch: float) -> dict:
    """Where the skin leaves the link bare: the share of the link's surface (its tessellation,
    vertices weighted by area) farther than one pitch from every taxel, and `largest_gap_mm`, the
    farthest any surface point is from a taxel (the radius of the biggest bare patch)."""
    v, tri, d = _distances(design, model, body_index)
    if d is None:
        return {"bare_fraction": 1.0, "largest_gap_mm": float("inf")}
    # each vertex stands for a third of the area of its triangles
    area = 0.5 * np.linalg.norm(np.cross(v[tri[:, 1]] - v[tri[:, 0]], v[tri[:, 2]] - v[tri[:, 0]]), axis=1)
    weight = np.bincount(tri.ravel(), np.repeat(area / 3, 3), len(v))
    return {"bare_fraction": float(weight[d > pitch].sum() / weight.sum()), "largest_gap_mm": float(d.max() * 1e3)}


SAMPLES = 20_000  # area-uniform points per link for the covered area: +-0.7% of the link at 20,000


def covered_points(design: SkinDesign, body_index: int, q: np.ndarray, qn: np.ndarray) -> np.ndarray:
    """(m,) which surface points q (body frame) with normals qn the taxels' cells cover: a cell is the
    pitch x pitch square around a pad in its own frame, within half a pitch of its surface, on surface
    facing the pad's way (the inside of a thin housing is not covered by the skin outside it)."""
    t = design.taxels
    on = np.flatnonzero(t.body == body_index)
    if not len(on):
        return np.zeros(len(q), bool)
    pitch = {m.id: m.pitch for m in design.modules}
    half = np.array([pitch.get(int(k), 0.0) / 2 for k in t.module[on]])
    d, j = cKDTree(t.positions[on]).query(q, k=min(4, len(on)), distance_upper_bound=float(half.max()) * 1.5)
    d, j = d.reshape(len(q), -1), j.reshape(len(q), -1)
    ok = np.isfinite(d)
    jj = np.where(ok, j, 0)
    rel = q[:, None, :] - t.positions[on][jj]  # (m, k, 3) in the body frame
    local = np.abs(np.einsum("nkj,nkji->nki", rel, t.frames[on][jj]))  # components along x, y, z
    facing = np.einsum("nj,nkj->nk", qn, t.frames[on][jj][..., 2]) > 0.5
    return (ok & facing & (local <= half[jj][..., None]).all(axis=-1)).any(axis=1)


def covered_area(design: SkinDesign, model: mujoco.MjModel, body_index: int, n: int = SAMPLES) -> float:
    """The link's surface area (m^2) the taxels' cells actually cover (`covered_points`), counted once:
    overlapping or crowded cells add nothing and stretched ones cover what they reach (Monte Carlo over
    `n` area-uniform points of the link's surface, seed fixed)."""
    from skinsafe.core.design.surface import cached_surfaces

    name = design.bodies[body_index]
    surf = cached_surfaces(model, [name])[name]
    q, qn = surf.closest(surf.random_points(n, seed=2))[:2]
    return float(covered_points(design, body_index, q, qn).mean() * surf.area)


def coverage_report(design: SkinDesign, model: mujoco.MjModel) -> dict:
    """Per skinned body: taxel count, skinned area (`covered_area`: the cells actually covering the
    link, overlaps once), link area, fraction, density (taxels per cm^2 of skin) and gaps (see
    `gaps`); plus totals."""
    t = design.taxels
    out = {}
    for i, name in enumerate(design.bodies):
        on = t.body == i
        n = int(on.sum())
        skinned = covered_area(design, model, i)
        area = body_area(model, name)
        out[name] = {
            "taxels": n,
            "skinned_area_m2": skinned,
            "link_area_m2": area,
            "fraction": skinned / area if area > 0 else 0.0,
            "density_per_cm2": n / (skinned * 1e4) if skinned > 0 else 0.0,
            "modules": len({int(m) for m in t.module[on]}),
            **gaps(design, model, i, reach(design, i)),
        }
    out["total"] = {
        "taxels": len(t),
        "skinned_area_m2": float(sum(r["skinned_area_m2"] for r in out.values())),
        "modules": len(design.modules),
        "boards": len(design.boards),
    }
    return out


def format_report(report: dict) -> str:
    """The coverage report as an aligned text table."""
    lines = [f"{'body':<16}{'taxels':>8}{'modules':>9}{'skin cm2':>10}{'link cm2':>10}{'covered':>9}{'per cm2':>9}"
             f"{'bare':>7}{'gap mm':>8}"]
    for name, r in report.items():
        if name == "total":
            continue
        lines.append(f"{name:<16}{r['taxels']:>8}{r['modules']:>9}{r['skinned_area_m2'] * 1e4:>10.1f}"
                     f"{r['link_area_m2'] * 1e4:>10.1f}{r['fraction'] * 100:>8.1f}%{r['density_per_cm2']:>9.2f}"
                     f"{r['bare_fraction'] * 100:>6.0f}%{r['largest_gap_mm']:>8.0f}")
    tot = report["total"]
    lines.append(f"{'total':<16}{tot['taxels']:>8}{tot['modules']:>9}{tot['skinned_area_m2'] * 1e4:>10.1f}"
                 f"   on {tot['boards']} boards")
    return "\n".join(lines)
