"""How deep points lie inside a MuJoCo geom: primitives exactly, meshes by their convex hull
(what MuJoCo collides). The skin-fitted collision model and the sample skin's layout use it."""
from __future__ import annotations

import mujoco
import numpy as np
from scipy.spatial import ConvexHull


def inside_depth(model: mujoco.MjModel, g: int, p: np.ndarray) -> np.ndarray:
    """Depth (m, <= 0 outside) of points p (geom frame) inside geom g (meshes: their convex hull)."""
    kind, s = int(model.geom_type[g]), model.geom_size[g]
    G = mujoco.mjtGeom
    if kind == G.mjGEOM_SPHERE:
        return s[0] - np.linalg.norm(p, axis=1)
    if kind == G.mjGEOM_CAPSULE:
        z = np.clip(p[:, 2], -s[1], s[1])
        return s[0] - np.linalg.norm(p - np.stack([0 * z, 0 * z, z], 1), axis=1)
    if kind == G.mjGEOM_CYLINDER:
        return np.minimum(s[0] - np.hypot(p[:, 0], p[:, 1]), s[1] - np.abs(p[:, 2]))
    if kind == G.mjGEOM_BOX:
        return (s[:3] - np.abs(p)).min(axis=1)
    if kind == G.mjGEOM_ELLIPSOID:
        return (1 - np.linalg.norm(p / s[:3], axis=1)) * s[:3].min()
    if kind == G.mjGEOM_MESH:
        eq = ConvexHull(mesh_vertices(model, g)).equations
        return -(p @ eq[:, :3].T + eq[:, 3]).max(axis=1)
    return np.full(len(p), -np.inf)


def mesh_vertices(model: mujoco.MjModel, g: int) -> np.ndarray:
    """(V, 3) the vertices of mesh geom g's mesh (mesh frame)."""
    m = model.geom_dataid[g]
    return model.mesh_vert[model.mesh_vertadr[m]:model.mesh_vertadr[m] + model.mesh_vertnum[m]].astype(float)
