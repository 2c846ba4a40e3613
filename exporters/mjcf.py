"""Write a skin design's MuJoCo scene (`skinsafe.core.sim.scene.build_scene`) to files.

`export_scene` writes `scene.xml`, its meshes under `meshes/` and the taxel map `taxel_map.json`
into one folder, all or nothing. `meshes/` is the scene's own: another export into the same folder
(the URDF's `robot_skin_meshes/`) never writes there, and a new scene replaces it whole.
"""
from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

import mujoco
import numpy as np

from skinsafe.core.robot.models import Robot
from skinsafe.core.sim.scene import MAP_FILE, SceneOptions, build_scene, mesh_path
from skinsafe.core.skin import taxel_map
from skinsafe.core.skin.model import DesignError, SkinDesign

MESH_DIR = "meshes"
SCENE_FILE = "scene.xml"


def export_scene(design: SkinDesign, robot: Robot, out_dir: str | Path, obstacles=(),
                 options: SceneOptions = SceneOptions(taxel_sites=True)) -> Path:
    """Write `scene.xml`, `meshes/` and `taxel_map.json` into `out_dir`; returns the scene path.

    Everything is staged in a temporary folder and checked with a plain
    `mujoco.MjModel.from_xml_path` before it is moved into place: a failure writes nothing.
    """
    spec = build_scene(design, robot, obstacles, options)
    out_dir = Path(out_dir)
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    stage = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.", dir=out_dir.parent))
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(stage, 0o777 & ~umask)  # mkdtemp makes it private; the result is an ordinary folder
    try:
        _write_meshes(spec, stage)
        (stage / SCENE_FILE).write_text(spec.to_xml())
        try:
            mujoco.MjModel.from_xml_path(str(stage / SCENE_FILE))
        except ValueError as e:
            raise DesignError(f"scene: the written MJCF does not load in MuJoCo: {e}") from None
        taxel_map.save(design, stage / MAP_FILE, robot.body_names)
        _move_into(stage, out_dir)
    finally:
        shutil.rmtree(stage, ignore_errors=True)
    return out_dir / SCENE_FILE


def _write_meshes(spec: mujoco.MjSpec, stage: Path) -> None:
    """Every mesh to `meshes/<name>.stl` (or its own file copied), referenced relative to the scene."""
    import trimesh

    if not spec.meshes:
        return
    out = stage / MESH_DIR
    out.mkdir()
    for m in spec.meshes:
        if m.file:
            src = mesh_path(spec, m)
            dst = out / f"{m.name}{src.suffix}"
            shutil.copyfile(src, dst)
        else:
            v = np.asarray(m.uservert, float).reshape(-1, 3)
            f = np.asarray(m.userface, int).reshape(-1, 3)
            dst = out / f"{m.name}.stl"
            trimesh.Trimesh(*((v, f) if len(f) else _hull(v)), process=False).export(str(dst))
            m.uservert, m.userface = [], []
        m.file = dst.name
    spec.meshdir = MESH_DIR
    spec.modelfiledir = str(stage)  # to_xml re-reads the meshes from where they now are


def _hull(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A point set's convex hull as vertices and outward-wound triangles, as MuJoCo reads the points
    (scipy's qhull directly: trimesh's hull repairs each mesh, 3 ms per piece for ~1,000 pieces)."""
    from scipy.spatial import ConvexHull

    h = ConvexHull(v)
    f = h.simplices.copy()
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    flip = np.einsum("ij,ij->i", n, h.equations[:, :3]) < 0
    f[flip] = f[flip][:, ::-1]
    return v, f


def _move_into(stage: Path, out_dir: Path) -> None:
    if not out_dir.exists():
        os.replace(stage, out_dir)
        stage.mkdir()  # so the caller's cleanup has something to remove
        return
    if (out_dir / MESH_DIR).exists():  # the scene's own folder: other exports keep theirs elsewhere
        shutil.rmtree(out_dir / MESH_DIR)
    for p in stage.iterdir():
        os.replace(p, out_dir / p.name)
