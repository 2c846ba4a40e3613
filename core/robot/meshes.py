"""Collision meshes: load and check (trimesh), repair, and simplify (convex hull, pymeshlab
quadric decimation) to what the physics needs.

pymeshlab is imported lazily: imported before bpy it breaks bpy in the same process.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from skinsafe.core.skin.model import DesignError

MODES = ("primitive", "hull", "decimate", "full")


def load_checked(path: str | Path, what: str, manifold: bool = True):
    """A repaired trimesh of `path` (STL, OBJ, PLY, DAE through pycollada, ...); DesignError naming
    `what` and the file if it is broken or (with `manifold`) non-manifold.

    Repair merges duplicate vertices, drops degenerate and duplicate faces and fixes winding;
    an edge shared by more than two faces (non-manifold) cannot be repaired and is refused where
    the mesh must bound a solid (`manifold`); visual meshes (CAD exports often have such edges) pass.
    """
    import trimesh

    path = Path(path)
    if not path.is_file():
        raise DesignError(f"{what}: mesh file '{path}' not found; check the path in the robot file")
    try:
        mesh = trimesh.load(str(path), force="mesh", process=False)
    except Exception as e:  # trimesh raises many kinds on a corrupt file
        raise DesignError(f"{what}: mesh file '{path}' is broken ({type(e).__name__}: {e}); "
                          "re-export it from your CAD/mesh tool") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0 or len(mesh.vertices) < 4:
        raise DesignError(f"{what}: mesh file '{path}' is broken (no faces); re-export it from your CAD/mesh tool")
    if not np.isfinite(mesh.vertices).all():
        raise DesignError(f"{what}: mesh file '{path}' is broken (NaN/Inf vertices); re-export it")
    mesh.merge_vertices(merge_tex=True, merge_norm=True)  # smooth normals come from shared vertices
    mesh.update_faces(mesh.nondegenerate_faces())
    mesh.update_faces(mesh.unique_faces())
    mesh.remove_unreferenced_vertices()
    if len(mesh.faces) == 0:
        raise DesignError(f"{what}: mesh file '{path}' is broken (all faces degenerate); re-export it")
    if not manifold:
        return mesh
    edges = np.sort(mesh.edges, axis=1)
    key = edges[:, 0] * (int(edges.max()) + 1) + edges[:, 1]  # one integer per edge: a 1-D unique
    _, counts = np.unique(key, return_counts=True)
    if (counts > 2).any():
        raise DesignError(f"{what}: mesh file '{path}' is non-manifold ({int((counts > 2).sum())} edges shared by "
                          "more than two faces); repair it (e.g. Blender 'Select Non Manifold', MeshLab) and re-export")
    trimesh.repair.fix_winding(mesh)
    return mesh


def simplify(mesh, mode: str, target_faces: int = 500):
    """The collision mesh for `mode`: "full" as is, "hull" its convex hull, "decimate" a quadric
    decimation to `target_faces` (pymeshlab). ("primitive" is fitted by MuJoCo, not here.)"""
    if mode == "full":
        return mesh
    if mode == "hull":
        return mesh.convex_hull
    if mode == "decimate":
        return decimate(mesh, target_faces)
    raise ValueError(f"collision mode '{mode}' has no mesh; use one of {MODES}")


def decimate(mesh, target_faces: int):
    """Quadric edge-collapse decimation (pymeshlab) to about `target_faces` faces."""
    import pymeshlab
    import trimesh

    if target_faces < 4:
        raise ValueError(f"target_faces is {target_faces}; give at least 4")
    if len(mesh.faces) <= target_faces:
        return mesh
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=np.asarray(mesh.vertices, float),
                               face_matrix=np.asarray(mesh.faces, np.int32)))
    ms.meshing_decimation_quadric_edge_collapse(targetfacenum=int(target_faces), preservetopology=True,
                                                preserveboundary=True, planarquadric=True)
    m = ms.current_mesh()
    return trimesh.Trimesh(m.vertex_matrix(), m.face_matrix(), process=True)
