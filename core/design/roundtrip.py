"""The round trip: wrap each module's flat pattern back onto its link by a computation independent
of the placement, and compare its pads with the taxel map.

The placement walks the surface in steps from the anchor and relaxes what a doubly curved patch
stretches (`placement.place_module`). Here instead every pad is laid at the end of the geodesic
that leaves the anchor along the pad's flat offset (u along the rows, v across them) for its flat
distance: the exponential map, traced on the link's mesh by geometry-central through
potpourri3d's `GeodesicTracer`. On a developable surface it is the inextensible wrap itself; on a
doubly curved patch within the FPC's strain tolerance the two wraps agree to a fraction of a
millimetre. Modules placed with a recorded anchor use it; others (the sample's cylinder wraps) are
laid by their pad nearest the pattern's centre and its row direction, as a circuit is aligned by
hand.

Where the two wraps disagree by more than `TOL` (a module laid over a crease, a hole or a crack of
the link's mesh, where the path taken decides where a pad lands) the module is not built: `cover`
does not place it and `skinsafe check` names it.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from skinsafe.core.design.placement import PlacedModule, module_grid
from skinsafe.core.design.surface import Surface, cached_surfaces
from skinsafe.core.skin.model import Module, SkinDesign

HOPS, HOP = 16, 2e-4  # a trace hops at most 16 cracks, 0.2 mm each
TOL = 1e-3  # m: a module whose pads the two wraps put farther apart is not built (where its pads land is unsure)


@dataclass(frozen=True)
class RoundTrip:
    """One module's pads wrapped independently: `positions` (n,3) body frame, `error` (n,) m from the map's."""

    module: int
    positions: np.ndarray
    error: np.ndarray


def _manifold_faces(t: np.ndarray) -> np.ndarray:
    """(T,) which faces to keep so every edge has at most two faces, oriented opposite ways (CAD
    meshes repeat, flip and fan faces along their seams; a geodesic needs a manifold to run on)."""
    keep = np.zeros(len(t), bool)
    directed: set = set()
    count: dict = {}
    for i, (a, b, c) in enumerate(t.tolist()):
        edges = ((a, b), (b, c), (c, a))
        if any(e in directed or count.get(frozenset(e), 0) >= 2 for e in edges):
            continue
        keep[i] = True
        for e in edges:
            directed.add(e)
            count[frozenset(e)] = count.get(frozenset(e), 0) + 1
    return keep


def _split_fans(v: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The mesh with each vertex where separate fans of faces meet (two parts touching at a point)
    given one copy per fan, so every vertex is manifold."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    corners = t.ravel()  # corner i = face i // 3, its vertex corners[i]
    nxt, prv = np.roll(t, -1, axis=1).ravel(), np.roll(t, 1, axis=1).ravel()
    # two corners of one vertex are in one fan when their faces share an edge from that vertex
    key = np.concatenate([np.stack([corners, nxt], 1), np.stack([corners, prv], 1)])
    idx = np.tile(np.arange(len(corners)), 2)
    order = np.lexsort((key[:, 1], key[:, 0]))
    key, idx = key[order], idx[order]
    same = (key[1:] == key[:-1]).all(axis=1)
    a, b = idx[:-1][same], idx[1:][same]
    n = len(corners)
    _, fan = connected_components(coo_matrix((np.ones(len(a)), (a, b)), shape=(n, n)), directed=False)
    pairs, new = np.unique(np.stack([corners, fan], 1), axis=0, return_inverse=True)
    return v[pairs[:, 0]], new.reshape(-1, 3)


class Wrapper:
    """Exponential-map wraps on one link: its surface's mesh with coincident corners merged (the
    primitives' creases and the CAD parts joined into one manifold where they touch) and a
    geodesic tracer over it."""

    def __init__(self, surface: Surface):
        import potpourri3d as pp3d
        import trimesh

        mesh = trimesh.Trimesh(surface.vertices, surface.triangles, process=True)
        mesh.update_faces(mesh.nondegenerate_faces(height=1e-12) & mesh.unique_faces())
        mesh.update_faces(_manifold_faces(np.array(mesh.faces, np.int64)))
        mesh.remove_unreferenced_vertices()
        self.vertices, self.triangles = _split_fans(np.array(mesh.vertices, float), np.array(mesh.faces, np.int64))
        self.surface = Surface.from_mesh(self.vertices, self.triangles, name=surface.name)
        self.tracer = pp3d.GeodesicTracer(self.vertices, self.triangles)

    def _face(self, p: np.ndarray) -> tuple[int, np.ndarray, np.ndarray, np.ndarray]:
        """The face under point p: its index, barycentric coordinates, the point on it and its unit normal."""
        q, _, (k,), _ = self.surface.closest(p[None])
        a, b, c = self.vertices[self.triangles[k]]
        n = np.cross(b - a, c - a)
        nn = float(n @ n)
        bary = np.clip(np.array([np.cross(c - b, q[0] - b) @ n, np.cross(a - c, q[0] - c) @ n,
                                 np.cross(b - a, q[0] - a) @ n]) / nn, 0.0, None)
        return int(k), bary / bary.sum(), q[0], n / np.sqrt(nn)

    def _trace(self, start: np.ndarray, step: np.ndarray) -> np.ndarray:
        """The end of the geodesic from `start` along `step` (its length the distance), hopping the
        hair-line cracks of CAD meshes (a trace stops at a boundary: it goes on from the surface
        just across it)."""
        left, d, p = float(np.linalg.norm(step)), step / max(float(np.linalg.norm(step)), 1e-300), start
        for _ in range(HOPS):
            k, bary, p, n = self._face(p)
            d = d - (d @ n) * n
            d /= max(float(np.linalg.norm(d)), 1e-300)
            path = self.tracer.trace_geodesic_from_face(k, bary, d * left)
            left -= float(np.linalg.norm(np.diff(path, axis=0), axis=1).sum())
            if left < 1e-7:
                return path[-1]
            if len(path) > 1:
                d = (path[-1] - path[-2]) / max(float(np.linalg.norm(path[-1] - path[-2])), 1e-300)
            hop = min(left, HOP)
            p, left = path[-1] + d * hop, left - hop
        return self._face(p)[2]

    def wrap(self, uv: np.ndarray, anchor: np.ndarray, direction: np.ndarray) -> np.ndarray:
        """(n,3) where the flat pads `uv` (n,2; u along the rows) land when the pattern is wrapped
        about `anchor` with its rows along `direction` (body frame)."""
        _, _, p0, n = self._face(np.asarray(anchor, float))
        x = np.asarray(direction, float) - (np.asarray(direction, float) @ n) * n
        x /= np.linalg.norm(x)
        y = np.cross(n, x)
        return np.array([self._trace(p0, u * x + v * y) if u or v else p0 for u, v in uv])


def wrapper_of(surface: Surface) -> Wrapper:
    """The surface's `Wrapper`, built at its first use and kept with it."""
    if getattr(surface, "_wrapper", None) is None:
        surface._wrapper = Wrapper(surface)
    return surface._wrapper


def disagreement(surface: Surface, placed: PlacedModule) -> float:
    """m: the farthest a pad of a just-placed module is from where the independent wrap of its flat
    pattern about the same anchor and direction puts it (over `TOL`: the module is not built)."""
    grid = module_grid(placed.module, len(placed))
    if grid is None:
        return float("inf")
    uv = grid[0]
    at = wrapper_of(surface).wrap(uv, placed.origin, placed.origin_frame[:, 0])
    return float(np.linalg.norm(at - placed.positions, axis=1).max())


def module_roundtrip(design: SkinDesign, module: Module, wrapper: Wrapper) -> RoundTrip | None:
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
    else:  # aligned by the pad nearest the pattern's centre and its row direction
        c = int(np.argmin(np.linalg.norm(uv, axis=1)))
        uv = uv - uv[c]
        anchor, direction = t.positions[on[c]], t.frames[on[c], :, 0]
    positions = wrapper.wrap(uv, anchor, direction)
    return RoundTrip(module.id, positions, np.linalg.norm(positions - t.positions[on], axis=1))


def roundtrip(design: SkinDesign, model, progress=None) -> list[RoundTrip]:
    """Every module's round trip on its link's design surface (`cached_surfaces`)."""
    surfaces = cached_surfaces(model, list(design.bodies))
    out = []
    for m in design.modules:
        r = module_roundtrip(design, m, wrapper_of(surfaces[m.body]))
        if r is not None:
            out.append(r)
        if progress is not None:
            progress.update(1)
    return out
