"""The round trip: wrap each module's flat pattern back onto its link by a computation independent
of the placement, and compare its pads with the taxel map.

The placement walks the surface from the anchor (`placement.place_module`). Here instead the
link's surface patch under the module is cut out (vertices within a graph-geodesic radius of the
anchor), refined to edges under a third of the pitch, and flattened by libigl: LSCM to start,
then ARAP, the parameterization that keeps every triangle as rigid as it can (what an
inextensible circuit pressed onto the patch does). The flat pattern is laid in that plane with
its centre on the anchor and its rows along the anchor's direction, and each pad is carried back
onto the surface through the flattening (barycentric in its flat triangle). Modules placed with
a recorded anchor use it; others (the sample's cylinder wraps) are laid by their pad nearest the
pattern's centre and its row direction, as a circuit is aligned by hand.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components, dijkstra
from scipy.spatial import cKDTree

from skinsafe.core.design.placement import module_grid
from skinsafe.core.design.surface import Surface, cached_surfaces
from skinsafe.core.skin.model import DesignError, Module, SkinDesign


@dataclass(frozen=True)
class RoundTrip:
    """One module's pads wrapped independently: `positions` (n,3) body frame, `error` (n,) m from the map's."""

    module: int
    positions: np.ndarray
    error: np.ndarray


def _edges_graph(vertices: np.ndarray, triangles: np.ndarray):
    e = np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]])
    w = np.linalg.norm(vertices[e[:, 0]] - vertices[e[:, 1]], axis=1)
    n = len(vertices)
    return coo_matrix((np.r_[w, w], (np.r_[e[:, 0], e[:, 1]], np.r_[e[:, 1], e[:, 0]])), shape=(n, n)).tocsr()


def _patch(vertices, triangles, centre: np.ndarray, radius: float):
    """The triangles whose corners all lie within `radius` of `centre` along the mesh's edges,
    connected to the triangle nearest the centre: (vertices, triangles) of the patch."""
    seeds = np.argsort(np.linalg.norm(vertices - centre, axis=1))[:3]
    start = np.linalg.norm(vertices[seeds] - centre, axis=1)
    dist = dijkstra(_edges_graph(vertices, triangles), indices=seeds, limit=radius + start.max(), min_only=True)
    near = dist <= radius
    tri = triangles[near[triangles].all(axis=1)]
    used, inverse = np.unique(tri, return_inverse=True)
    tri = inverse.reshape(-1, 3)
    v = vertices[used]
    _, label = connected_components(_edges_graph(v, tri), directed=False)
    home = label[int(np.argmin(np.linalg.norm(v - centre, axis=1)))]
    tri = tri[label[tri[:, 0]] == home]
    used, inverse = np.unique(tri, return_inverse=True)
    return v[used], inverse.reshape(-1, 3)


def _refine(v, t, max_edge: float):
    import trimesh

    v, t = trimesh.remesh.subdivide_to_size(v, t, max_edge=max_edge)
    return np.asarray(v, float), np.asarray(t, np.int64)


def flatten(v: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(V,2) ARAP parameterization of a disk-like patch (LSCM start, two boundary points pinned there)."""
    import igl

    loop = igl.boundary_loop(t)
    if len(loop) < 3:
        raise DesignError("round trip: the surface patch has no boundary (a closed surface); use a smaller module")
    far = loop[int(np.argmax(np.linalg.norm(v[loop] - v[loop[0]], axis=1)))]
    b = np.array([loop[0], far], np.int64)
    bc = np.array([[0.0, 0.0], [float(np.linalg.norm(v[far] - v[loop[0]])), 0.0]])
    uv, _ = igl.lscm(v, t, b, bc)
    data = igl.ARAPData()
    data.max_iter, data.with_dynamics = 30, True  # libigl's parameterization set-up: no pinned vertex
    igl.arap_precomputation(v, t, 2, np.zeros(0, np.int32), data)
    return igl.arap_solve(np.zeros((0, 2)), data, uv)


def _barycentric(tri: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Barycentric coordinates (..., 3) of points q (..., 2) in flat triangles tri (..., 3, 2)."""
    a, b, c = tri[..., 0, :], tri[..., 1, :], tri[..., 2, :]
    v0, v1, v2 = b - a, c - a, q - a
    den = v0[..., 0] * v1[..., 1] - v1[..., 0] * v0[..., 1]
    den = np.where(np.abs(den) < 1e-30, 1e-30, den)
    l1 = (v2[..., 0] * v1[..., 1] - v1[..., 0] * v2[..., 1]) / den
    l2 = (v0[..., 0] * v2[..., 1] - v2[..., 0] * v0[..., 1]) / den
    return np.stack([1 - l1 - l2, l1, l2], -1)


def _locate(uv: np.ndarray, t: np.ndarray, q: np.ndarray):
    """Triangle and barycentric coordinates of points q (m,2) in the flat triangulation (uv, t):
    the nearest triangles' centroids first, every triangle for a point none of them holds (a
    point outside the patch takes the triangle it is least outside of)."""
    tri = uv[t]
    cand = cKDTree(tri.mean(axis=1)).query(q, k=min(24, len(t)))[1].reshape(len(q), -1)
    bary = _barycentric(tri[cand], q[:, None])
    k = np.argmax(bary.min(axis=-1), axis=1)
    rows = np.arange(len(q))
    found, bary = cand[rows, k], bary[rows, k]
    for i in np.flatnonzero(bary.min(axis=1) < -1e-9):
        every = _barycentric(tri, q[i][None])
        j = int(np.argmax(every.min(axis=1)))
        found[i], bary[i] = j, every[j]
    return found, bary


def wrap_pattern(surface: Surface, uv_pads: np.ndarray, anchor: np.ndarray, direction: np.ndarray,
                 pitch: float) -> np.ndarray:
    """(n,3) where the flat pads `uv_pads` (n,2; u along the rows) land when the pattern is pressed
    onto `surface` centred on `anchor` with its rows along `direction` (body frame)."""
    radius = float(np.linalg.norm(uv_pads, axis=1).max()) * 2 + 2 * pitch
    v, t = _patch(surface.vertices, surface.triangles, np.asarray(anchor, float), radius)
    v, t = _refine(v, t, pitch / 3)
    flat = flatten(v, t)
    # the anchor and its row direction in the flat plane, through the triangle under the anchor
    p0, n0, _, _ = surface.closest(np.asarray(anchor, float)[None])
    k = int(np.argmin(np.linalg.norm(v[t].mean(axis=1) - p0, axis=1)))
    P, U = v[t[k]], flat[t[k]]
    E = np.stack([P[1] - P[0], P[2] - P[0]], 1)  # 3x2: the triangle's edges in 3D
    A = np.stack([U[1] - U[0], U[2] - U[0]], 1)  # 2x2: the same edges flat
    coef = np.linalg.lstsq(E, np.stack([p0[0] - P[0], np.asarray(direction, float)], 1), rcond=None)[0]
    origin, x2 = U[0] + A @ coef[:, 0], A @ coef[:, 1]
    x2 /= np.linalg.norm(x2)
    y3 = np.cross(n0[0], direction)
    y2 = A @ np.linalg.lstsq(E, y3, rcond=None)[0]
    side = np.sign(x2[0] * y2[1] - x2[1] * y2[0]) or 1.0  # a mirrored flattening keeps y = z x x
    y2 = side * np.array([-x2[1], x2[0]])
    q = origin + uv_pads[:, :1] * x2 + uv_pads[:, 1:] * y2
    tri, bary = _locate(flat, t, q)
    return np.einsum("nk,nkj->nj", bary, v[t[tri]])


def module_roundtrip(design: SkinDesign, module: Module, surface: Surface) -> RoundTrip | None:
    """The round trip of one module (None where its taxels are not its template's pads)."""
    t = design.taxels
    on = np.flatnonzero(t.module == module.id)
    grid = module_grid(module, len(on))
    if grid is None:
        return None
    uv = grid[0]
    placement = module.placement if isinstance(module.placement, dict) else {}
    if "anchor" in placement and "direction" in placement:
        anchor, direction = np.asarray(placement["anchor"], float), np.asarray(placement["direction"], float)
        n0 = surface.closest(anchor[None])[1][0]
        direction = direction - (direction @ n0) * n0
        direction /= np.linalg.norm(direction)
    else:  # aligned by the pad nearest the pattern's centre and its row direction
        c = int(np.argmin(np.linalg.norm(uv, axis=1)))
        uv = uv - uv[c]
        anchor, direction = t.positions[on[c]], t.frames[on[c], :, 0]
    positions = wrap_pattern(surface, uv, anchor, direction, module.pitch)
    return RoundTrip(module.id, positions, np.linalg.norm(positions - t.positions[on], axis=1))


def roundtrip(design: SkinDesign, model, progress=None) -> list[RoundTrip]:
    """Every module's round trip on its link's design surface (`cached_surfaces`)."""
    surfaces = cached_surfaces(model, list(design.bodies))
    out = []
    for m in design.modules:
        r = module_roundtrip(design, m, surfaces[m.body])
        if r is not None:
            out.append(r)
        if progress is not None:
            progress.update(1)
    return out
