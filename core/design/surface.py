"""Body surfaces: triangle meshes of a MuJoCo body's geoms in the body frame, with closest-point
and normal queries (pure numpy + scipy).

Primitives (sphere, capsule, cylinder, ellipsoid, box) are tessellated finely enough that the
mesh stays within `tol` (default 0.05 mm) of the true shape, with exact normals at the vertices;
mesh geoms come from the model (the visual meshes by default, decimated to a per-link triangle
budget, never subdivided). Triangles buried inside another primitive of the same body are
dropped, so the surface is the outside of the union. Every triangle corner carries its own normal
(smooth across a curved patch, split at creases), interpolated barycentrically at query points.
"""
from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from skinsafe.core.skin.model import DesignError

G = mujoco.mjtGeom


@dataclass
class Surface:
    """A triangle mesh with per-corner normals and a bounding-volume hierarchy for closest-point queries."""

    vertices: np.ndarray  # (V, 3) float64
    triangles: np.ndarray  # (T, 3) int64, counter-clockwise seen from outside
    corner_normals: np.ndarray  # (T, 3, 3) unit normal at each corner of each triangle
    name: str = "surface"

    def __post_init__(self):
        if len(self.triangles) == 0:
            raise DesignError(f"surface '{self.name}': no triangles; the body has no geometry to place a skin on")
        tri = self.vertices[self.triangles]
        a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
        self._a, self._b, self._c = a, b, c
        # Per triangle, packed for one gather per query: a, ab, ac, bc, n/|n|^2, 1/|ab|^2, 1/|ac|^2, 1/|bc|^2.
        ab, ac, bc = b - a, c - a, c - b
        n = np.cross(ab, ac)
        inv = lambda e: 1.0 / np.maximum(np.sum(e * e, axis=1, keepdims=True), 1e-300)  # noqa: E731
        self._pack = np.ascontiguousarray(np.concatenate(
            [a, ab, ac, bc, n * inv(n), inv(ab), inv(ac), inv(bc)], axis=1))
        # a bounding-volume hierarchy over the triangles: exact closest points, O(log T) each
        from skinsafe.core.design.surface_kernels import build_bvh

        bvh = build_bvh(np.minimum(np.minimum(a, b), c), np.maximum(np.maximum(a, b), c), tri.mean(axis=1))
        self.kernel = (self._pack, self.corner_normals, *bvh)  # what compiled queries take (`closest_one`)
        self.lo, self.hi = self.vertices.min(axis=0), self.vertices.max(axis=0)  # bounding box

    @classmethod
    def from_mesh(cls, vertices, triangles, corner_normals=None, name: str = "surface",
                  crease_deg: float = 45.0) -> "Surface":
        """A surface from arrays; without corner normals, each triangle corner gets the area-weighted
        normal of the triangles around its vertex that meet this one at less than `crease_deg`
        (smooth across a curved patch, sharp at a crease: a prism's flat face stays flat)."""
        v = np.asarray(vertices, dtype=float).reshape(-1, 3)
        t = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
        if t.size and (t.min() < 0 or t.max() >= len(v)):
            raise DesignError(f"surface '{name}': triangle index outside 0..{len(v) - 1}; fix the mesh")
        fn = np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]])
        area2 = np.linalg.norm(fn, axis=1)
        keep = area2 > 1e-14
        t, fn, area2 = t[keep], fn[keep], area2[keep]
        if corner_normals is None:
            cn = _smooth_corner_normals(t, fn, np.cos(np.radians(crease_deg)))
        else:
            cn = np.asarray(corner_normals, dtype=float).reshape(-1, 3, 3)[keep]
            cn = cn / np.linalg.norm(cn, axis=2, keepdims=True)
        return cls(v, t, cn, name)

    @property
    def face_normals(self) -> np.ndarray:
        n = np.cross(self._b - self._a, self._c - self._a)
        return n / np.linalg.norm(n, axis=1, keepdims=True)

    def random_points(self, n: int, seed: int = 0) -> np.ndarray:
        """`n` points uniformly distributed over the surface's area."""
        area = 0.5 * np.linalg.norm(np.cross(self._b - self._a, self._c - self._a), axis=1)
        rng = np.random.default_rng(seed)
        k = rng.choice(len(area), n, p=area / area.sum())
        r = rng.random((n, 2))
        flip = r.sum(axis=1) > 1
        r[flip] = 1 - r[flip]
        return self._a[k] + r[:, :1] * (self._b[k] - self._a[k]) + r[:, 1:] * (self._c[k] - self._a[k])

    @property
    def area(self) -> float:
        return float(0.5 * np.linalg.norm(np.cross(self._b - self._a, self._c - self._a), axis=1).sum())

    def closest(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Closest surface points (m,3), interpolated unit normals (m,3), triangle index (m,) and
        distance (m,) for query points (m,3)."""
        p = np.ascontiguousarray(np.asarray(points, dtype=float).reshape(-1, 3))
        from skinsafe.core.design.surface_kernels import bvh_closest

        q, n, tri, d2 = bvh_closest(p, *self.kernel)
        return q, n, tri, np.sqrt(d2)


def _smooth_corner_normals(t: np.ndarray, fn: np.ndarray, cos_crease: float) -> np.ndarray:
    """(T, 3, 3) corner normals: per corner, the sum of the area-weighted normals `fn` of the
    triangles sharing its vertex whose unit normal is within the crease angle of its own."""
    unit = fn / np.linalg.norm(fn, axis=1, keepdims=True)
    vert = t.ravel()
    order = np.argsort(vert, kind="stable")
    _, start, count = np.unique(vert[order], return_index=True, return_counts=True)
    # every pair of corners at the same vertex (a, b): b's face contributes to a's normal
    size = count.astype(np.int64) ** 2
    group = np.repeat(np.arange(len(count)), size)
    local = np.arange(size.sum()) - np.repeat(np.cumsum(size) - size, size)
    a = order[start[group] + local // count[group]]
    b = order[start[group] + local % count[group]]
    fa, fb = a // 3, b // 3
    keep = np.sum(unit[fa] * unit[fb], axis=1) >= cos_crease
    out = np.zeros((len(vert), 3))
    np.add.at(out, a[keep], fn[fb[keep]])
    out /= np.maximum(np.linalg.norm(out, axis=1, keepdims=True), 1e-300)
    return out.reshape(-1, 3, 3)


# ---- tessellation of MuJoCo geoms -------------------------------------------------------------

def _revolve(patches, n_seg):
    """Surfaces of revolution about z from profile patches [(rho, z, n_rho, n_z), ...] (arrays);
    returns vertices, triangles and vertex normals (patches keep their own vertices: creases)."""
    phi = np.linspace(0, 2 * np.pi, n_seg, endpoint=False)
    cs, sn = np.cos(phi), np.sin(phi)
    verts, norms, tris, base = [], [], [], 0
    for rho, z, nr, nz in patches:
        k = len(rho)
        verts.append(np.stack([np.outer(rho, cs), np.outer(rho, sn), np.repeat(z[:, None], n_seg, 1)], -1).reshape(-1, 3))
        norms.append(np.stack([np.outer(nr, cs), np.outer(nr, sn), np.repeat(nz[:, None], n_seg, 1)], -1).reshape(-1, 3))
        i, j = np.meshgrid(np.arange(k - 1), np.arange(n_seg), indexing="ij")
        a = base + i * n_seg + j
        b = base + i * n_seg + (j + 1) % n_seg
        c, d = a + n_seg, b + n_seg
        tris.append(np.concatenate([np.stack([a, b, d], -1).reshape(-1, 3), np.stack([a, d, c], -1).reshape(-1, 3)]))
        base += k * n_seg
    return np.concatenate(verts), np.concatenate(tris), np.concatenate(norms)


def _n_seg(r: float, tol: float) -> int:
    return int(np.clip(np.ceil(np.pi / np.arccos(max(1 - tol / r, -1.0))), 12, 256))


def _arc(r, z0, a0, a1, n):
    ang = np.linspace(a0, a1, n)
    return (r * np.cos(ang), z0 + r * np.sin(ang), np.cos(ang), np.sin(ang))


def _line(r0, z0, r1, z1, nr, nz, n):
    s = np.linspace(0, 1, n)
    return (r0 + s * (r1 - r0), z0 + s * (z1 - z0), np.full(n, nr), np.full(n, nz))


def tessellate_geom(gtype: int, size: np.ndarray, tol: float = 5e-5, max_edge: float = 0.005):
    """Vertices, triangles and vertex normals of a primitive geom in its own frame."""
    r = float(size[0])
    n_arc = lambda rr, angle: max(3, int(np.ceil(angle / np.arccos(max(1 - tol / rr, -1.0)))) + 1)  # noqa: E731
    n_len = lambda length: max(2, int(np.ceil(length / max_edge)) + 1)  # noqa: E731
    if gtype in (G.mjGEOM_SPHERE, G.mjGEOM_ELLIPSOID):
        rr = float(np.max(size)) if gtype == G.mjGEOM_ELLIPSOID else r
        v, t, n = _revolve([_arc(1.0, 0.0, -np.pi / 2, np.pi / 2, n_arc(rr, np.pi))], _n_seg(rr, tol))
        s = np.asarray(size[:3] if gtype == G.mjGEOM_ELLIPSOID else [r, r, r], dtype=float)
        return v * s, t, n / s
    if gtype == G.mjGEOM_CAPSULE:
        h = float(size[1])
        return _revolve([_arc(r, -h, -np.pi / 2, 0, n_arc(r, np.pi / 2)), _line(r, -h, r, h, 1, 0, n_len(2 * h)),
                         _arc(r, h, 0, np.pi / 2, n_arc(r, np.pi / 2))], _n_seg(r, tol))
    if gtype == G.mjGEOM_CYLINDER:
        h = float(size[1])
        return _revolve([_line(0, -h, r, -h, 0, -1, n_len(r)), _line(r, -h, r, h, 1, 0, n_len(2 * h)),
                         _line(r, h, 0, h, 0, 1, n_len(r))], _n_seg(r, tol))
    if gtype == G.mjGEOM_BOX:
        return _box(np.asarray(size[:3], dtype=float), max_edge)
    raise DesignError(f"geom type {gtype} cannot be tessellated; use a sphere, capsule, cylinder, ellipsoid, box or mesh")


def _box(s, max_edge):
    verts, tris, norms, base = [], [], [], 0
    for axis in range(3):
        for sign in (-1.0, 1.0):
            u_ax, v_ax = (axis + 1) % 3, (axis + 2) % 3
            nu, nv = (max(2, int(np.ceil(2 * s[a] / max_edge)) + 1) for a in (u_ax, v_ax))
            uu, vv = np.meshgrid(np.linspace(-s[u_ax], s[u_ax], nu), np.linspace(-s[v_ax], s[v_ax], nv), indexing="ij")
            p = np.zeros((nu * nv, 3))
            p[:, axis], p[:, u_ax], p[:, v_ax] = sign * s[axis], uu.ravel(), vv.ravel()
            n = np.zeros_like(p)
            n[:, axis] = sign
            i, j = np.meshgrid(np.arange(nu - 1), np.arange(nv - 1), indexing="ij")
            a = base + i * nv + j
            b, c, d = a + nv, a + 1, a + nv + 1
            t = np.concatenate([np.stack([a, b, d], -1).reshape(-1, 3), np.stack([a, d, c], -1).reshape(-1, 3)])
            verts.append(p), norms.append(n), tris.append(t)
            base += len(p)
    return np.concatenate(verts), np.concatenate(tris), np.concatenate(norms)


def _inside_primitive(p, gtype, size, tol=1e-6):
    """Points (geom frame) strictly inside a primitive geom (mesh geoms: never)."""
    r = size[0]
    if gtype == G.mjGEOM_SPHERE:
        return np.linalg.norm(p, axis=1) < r - tol
    if gtype == G.mjGEOM_CAPSULE:
        zc = np.clip(p[:, 2], -size[1], size[1])
        return np.linalg.norm(p - np.stack([0 * zc, 0 * zc, zc], 1), axis=1) < r - tol
    if gtype == G.mjGEOM_CYLINDER:
        return (np.hypot(p[:, 0], p[:, 1]) < r - tol) & (np.abs(p[:, 2]) < size[1] - tol)
    if gtype == G.mjGEOM_BOX:
        return (np.abs(p) < size[:3] - tol).all(axis=1)
    if gtype == G.mjGEOM_ELLIPSOID:
        return np.sum((p / size[:3]) ** 2, axis=1) < (1 - tol / max(size[:3])) ** 2
    return np.zeros(len(p), bool)


def _geom_pose(model, g):
    R = np.zeros(9)
    mujoco.mju_quat2Mat(R, model.geom_quat[g])
    return R.reshape(3, 3), model.geom_pos[g].copy()


SOURCES = ("visual", "collision")
TRIANGLE_BUDGET = 20000  # per link: CAD visuals above it are decimated, never subdivided


def skin_geoms(model: mujoco.MjModel, bid: int, source: str = "visual") -> list[int]:
    """The geoms of body `bid` that make its skin surface: its visual geoms (non-colliding) by
    default, its colliding geoms for `source="collision"` or when it has no visual geoms."""
    if source not in SOURCES:
        raise DesignError(f"surface: source '{source}' is unknown; use one of {', '.join(SOURCES)}")
    geoms = [int(g) for g in np.flatnonzero(model.geom_bodyid == bid) if model.geom_type[g] != G.mjGEOM_PLANE]
    collides = {g: bool(model.geom_contype[g] or model.geom_conaffinity[g]) for g in geoms}
    visual = [g for g in geoms if not collides[g]]
    return visual if source == "visual" and visual else [g for g in geoms if collides[g]] or visual


def _mesh_part(model, g, budget: int):
    """A mesh geom's vertices (shared where they coincide) and triangles, decimated to `budget`."""
    m = model.geom_dataid[g]
    v0, nv = model.mesh_vertadr[m], model.mesh_vertnum[m]
    f0, nf = model.mesh_faceadr[m], model.mesh_facenum[m]
    v = model.mesh_vert[v0:v0 + nv].astype(float)
    t = model.mesh_face[f0:f0 + nf].astype(np.int64)
    v, inv = np.unique(np.round(v, 9), axis=0, return_inverse=True)
    t = inv.ravel()[t]
    t = t[(t[:, 0] != t[:, 1]) & (t[:, 1] != t[:, 2]) & (t[:, 0] != t[:, 2])]
    if len(t) > budget:
        import trimesh

        from skinsafe.core.robot.meshes import decimate

        small = decimate(trimesh.Trimesh(v, t, process=False), budget)
        v, t = np.asarray(small.vertices, float), np.asarray(small.faces, np.int64)
    return v, t


def body_surface(model: mujoco.MjModel, body: str, tol: float = 5e-5, max_edge: float = 0.005,
                 source: str = "visual", budget: int = TRIANGLE_BUDGET) -> Surface:
    """The outside surface of one body in the body frame, made of `skin_geoms` (visual by default,
    counted once). Primitives are tessellated within `tol`; meshes are used as they are, decimated
    (pymeshlab) to `budget` triangles per link when above it, with smooth vertex normals split
    only at creases, so normals do not depend on the faceting."""
    bid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, body)
    if bid < 0:
        raise DesignError(f"surface: body '{body}' does not exist in the robot model; "
                          f"use one of {[model.body(i).name for i in range(model.nbody)]}")
    geoms = skin_geoms(model, bid, source)
    if not geoms:
        raise DesignError(f"surface: body '{body}' has no geoms; give the link a mesh or primitive to place a skin on")
    poses = {g: _geom_pose(model, g) for g in geoms}
    mesh_faces = {g: int(model.mesh_facenum[model.geom_dataid[g]]) for g in geoms
                  if model.geom_type[g] == G.mjGEOM_MESH}
    total = max(sum(mesh_faces.values()), 1)
    verts, tris, corners, owner, base = [], [], [], [], 0
    for g in geoms:
        gtype = int(model.geom_type[g])
        R, c = poses[g]
        if gtype == G.mjGEOM_MESH:
            v, t = _mesh_part(model, g, max(200, int(budget * mesh_faces[g] / total)))
            part = Surface.from_mesh(v @ R.T + c, t, name=body)
            v, t, cn = part.vertices, part.triangles, part.corner_normals
        else:
            v, t, n = tessellate_geom(gtype, model.geom_size[g], tol, max_edge)
            v = v @ R.T + c
            n = (n / np.linalg.norm(n, axis=1, keepdims=True)) @ R.T
            ok = _nondegenerate(v, t)
            t = t[ok]
            cn = n[t]
        verts.append(v)
        tris.append(t + base)
        corners.append(cn)
        owner.append(np.full(len(t), g))
        base += len(v)
    v, t, cn, owner = (np.concatenate(a) for a in (verts, tris, corners, owner))
    # Drop triangles whose centroid lies inside another primitive of the same body.
    cen = v[t].mean(axis=1)
    keep = np.ones(len(t), bool)
    for g in geoms:
        R, c = poses[g]
        inside = _inside_primitive((cen - c) @ R, int(model.geom_type[g]), model.geom_size[g])
        keep &= ~(inside & (owner != g))
    return Surface(v, t[keep], cn[keep], body)


def _nondegenerate(v, t):
    return np.linalg.norm(np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]]), axis=1) > 1e-14


def body_surfaces(model: mujoco.MjModel, bodies: list[str] | None = None, **kw) -> dict[str, Surface]:
    """Surfaces of the named bodies (default: every body with geoms except the world)."""
    if bodies is None:
        bodies = [model.body(i).name for i in range(1, model.nbody)
                  if any(model.geom_type[g] != G.mjGEOM_PLANE for g in np.flatnonzero(model.geom_bodyid == i))]
    return {b: body_surface(model, b, **kw) for b in bodies}


def surface_bodies(model: mujoco.MjModel, moving: bool = False) -> list[str]:
    """Bodies with a real outer surface: those with visual geometry where the robot has any
    (helper links that carry only coarse or inflated collision shapes are left out), else every
    body with geometry; `moving`: only bodies not welded to the world."""
    bodies = [b for b in range(1, model.nbody) if (not moving or model.body_weldid[b] != 0)
              and any(model.geom_type[g] != G.mjGEOM_PLANE for g in np.flatnonzero(model.geom_bodyid == b))]
    visual = [b for b in bodies if any(model.geom_contype[g] == 0 and model.geom_conaffinity[g] == 0
                                       for g in np.flatnonzero(model.geom_bodyid == b))]
    return [model.body(b).name for b in (visual or bodies)]


_CACHE: dict = {}


def cached_surfaces(model: mujoco.MjModel, bodies: list[str], **kw) -> dict[str, Surface]:
    """`body_surfaces` built once per model (by identity) and options: the design, `check` and
    the readout checks of one process share them instead of rebuilding every surface."""
    key = (id(model), tuple(sorted(kw.items())))
    store = _CACHE.get(key)
    if store is None or store[0] is not model:
        store = _CACHE[key] = (model, {})
        if len(_CACHE) > 16:
            _CACHE.pop(next(iter(_CACHE)))
    missing = [b for b in bodies if b not in store[1]]
    store[1].update(body_surfaces(model, missing, **kw) if missing else {})
    return {b: store[1][b] for b in bodies}
