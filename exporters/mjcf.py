"""A skin design as one MuJoCo scene (MJCF), built by editing the robot's own `MjSpec`.

The scene holds the robot (collision meshes simplified as asked), one site per taxel in its
body frame oriented as the taxel frame (`taxel_<id>`, a box the size of the taxel's cell), an
optional MuJoCo `touch` sensor per taxel (`touch_<id>`, the accuracy reference), and the
obstacles. `export_scene` writes `scene.xml`, its meshes under `meshes/` and the taxel map
`taxel_map.json` into one folder, all or nothing.
"""
from __future__ import annotations

import os
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np
from scipy.spatial.transform import Rotation

from ..core import taxel_map
from ..core.robots import Robot
from ..core.skin import DesignError, SkinDesign
from . import meshes as meshlib

GEOM_TYPES = {
    "sphere": (mujoco.mjtGeom.mjGEOM_SPHERE, 1),
    "box": (mujoco.mjtGeom.mjGEOM_BOX, 3),
    "capsule": (mujoco.mjtGeom.mjGEOM_CAPSULE, 2),
    "cylinder": (mujoco.mjtGeom.mjGEOM_CYLINDER, 2),
    "mesh": (mujoco.mjtGeom.mjGEOM_MESH, 0),
}
MESH_DIR = "meshes"
SCENE_FILE = "scene.xml"
MAP_FILE = "taxel_map.json"
SITE_GROUP = 3  # hidden in the viewer by default: a dense skin would hide the robot


@dataclass
class Obstacle:
    """Something in the scene the skin can touch: a body named `name` with one geom named `name`.

    `mocap`: a kinematic body moved through `data.mocap_pos/mocap_quat` (probes, a human arm);
    `free`: a dynamic body with a free joint (falls, rests on the robot); neither: fixed.
    """

    name: str
    kind: str  # "sphere" | "box" | "capsule" | "cylinder" | "mesh"
    size: tuple  # MuJoCo geom size semantics (sphere (r,), box half-extents, capsule (r, half-length))
    pos: tuple = (0, 0, 0)
    quat: tuple = (1, 0, 0, 0)
    mocap: bool = False
    mesh_file: str | None = None
    rgba: tuple = (0.8, 0.3, 0.3, 1)
    free: bool = False
    mass: float | None = None  # kg, for free bodies (default: density of water)


@dataclass
class ExportOptions:
    """Every modelling choice of the export, with defaults that suit the vectorised readout."""

    collision: str = "primitive"  # mesh robots: "primitive" | "hull" | "decimate" | "full"
    target_faces: int = 500  # for "decimate"
    visual: bool = True  # keep visual meshes (geoms that never collide)
    taxel_sites: bool = True  # one site per taxel ("taxel_<id>")
    touch_sensors: bool = False  # one MuJoCo touch sensor per taxel (accuracy reference; slow)
    prune_contacts: bool = True  # robot bodies nothing can touch get contype/conaffinity 0
    timestep: float | None = None

    def check(self) -> None:
        if self.collision not in meshlib.MODES:
            raise ValueError(f"ExportOptions.collision is '{self.collision}'; use one of {meshlib.MODES}")
        if self.collision == "decimate" and self.target_faces < 4:
            raise ValueError(f"ExportOptions.target_faces is {self.target_faces}; give at least 4")
        if self.touch_sensors and not self.taxel_sites:
            raise ValueError("ExportOptions.touch_sensors needs taxel_sites=True (a touch sensor reads a site)")
        if self.timestep is not None and not (0 < self.timestep <= 0.05):
            raise ValueError(f"ExportOptions.timestep is {self.timestep}; give seconds in (0, 0.05]")


def build_scene(design: SkinDesign, robot: Robot, obstacles=(), options: ExportOptions = ExportOptions()
                ) -> mujoco.MjSpec:
    """The scene as an `MjSpec` (an edited copy of `robot.spec`; `robot` is left as it was).

    Raises DesignError naming the body, mesh or obstacle at fault; ValueError for bad options.
    """
    options.check()
    design.validate("design", robot.body_names)
    spec = robot.spec.copy()
    if options.timestep is not None:
        spec.option.timestep = float(options.timestep)
    _process_meshes(spec, options)
    _add_obstacles(spec, list(obstacles))
    if options.taxel_sites:
        _add_taxel_sites(spec, design, options.touch_sensors)
    try:
        model = spec.compile()
    except ValueError as e:
        raise DesignError(f"scene: MuJoCo could not compile the scene: {e}") from None
    _drop_unused_meshes(spec, model)
    if options.prune_contacts:
        _prune_contacts(spec, model, list(obstacles))
    spec.add_text(name="skinsafe.taxel_map", data=MAP_FILE)
    return spec


def export_scene(design: SkinDesign, robot: Robot, out_dir: str | Path, obstacles=(),
                 options: ExportOptions = ExportOptions()) -> Path:
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


# --- robot meshes -------------------------------------------------------------------------

def _mesh_path(spec: mujoco.MjSpec, mesh) -> Path:
    p = Path(mesh.file)
    if p.is_absolute():
        return p
    meshdir = Path(spec.meshdir or "")
    if not meshdir.is_absolute():
        meshdir = Path(spec.modelfiledir or ".") / meshdir
    return meshdir / p


def _process_meshes(spec: mujoco.MjSpec, options: ExportOptions) -> None:
    """Check every collision mesh, simplify it as asked, drop visual meshes if not wanted."""
    MESH = mujoco.mjtGeom.mjGEOM_MESH
    meshes = {m.name: m for m in spec.meshes}
    made: dict[str, str] = {}
    for g in list(spec.geoms):
        if g.type != MESH or g.meshname not in meshes:
            continue
        collides = bool(g.contype or g.conaffinity)
        if not collides:
            if not options.visual:
                spec.delete(g)
            continue
        src = meshes[g.meshname]
        if not src.file:  # vertices given inline: nothing to check on disk
            continue
        where = f"mesh '{src.name}' (geom '{g.name}' of body '{g.parent.name}')"
        mesh = meshlib.load_checked(_mesh_path(spec, src), where)
        if options.collision == "primitive":
            spec.compiler.fitaabb = True  # a box-fitted primitive covers the mesh; an inertia fit is smaller
            # size 0: MuJoCo fits it; a capsule for elongated shapes, else a box
            ext = np.sort(mesh.bounding_box_oriented.primitive.extents)
            long = ext[2] > ext[1] * 1.2
            g.type = mujoco.mjtGeom.mjGEOM_CAPSULE if long else mujoco.mjtGeom.mjGEOM_BOX
            g.size = [0.0, 0.0, 0.0]
            continue
        if options.collision == "full":
            continue
        key = src.name
        if key not in made:
            simple = meshlib.simplify(mesh, options.collision, options.target_faces)
            new = spec.add_mesh(name=f"{src.name}_{options.collision}", scale=src.scale)
            new.uservert = np.asarray(simple.vertices, float).ravel().tolist()
            new.userface = np.asarray(simple.faces, int).ravel().tolist()
            made[key] = new.name
        g.meshname = made[key]


def _drop_unused_meshes(spec: mujoco.MjSpec, model: mujoco.MjModel) -> None:
    """Freeze primitives fitted to meshes at their compiled size and pose; delete unused meshes."""
    MESH = mujoco.mjtGeom.mjGEOM_MESH
    used = {g.meshname for g in spec.geoms if g.type == MESH}
    for g in spec.geoms:
        if g.type != MESH and g.meshname:
            g.size, g.pos, g.quat = model.geom_size[g.id].tolist(), model.geom_pos[g.id].tolist(), \
                model.geom_quat[g.id].tolist()
            g.meshname = ""
    for m in list(spec.meshes):
        if m.name not in used:
            spec.delete(m)


def _write_meshes(spec: mujoco.MjSpec, stage: Path) -> None:
    """Every mesh to `meshes/<name>.stl` (or its own file copied), referenced relative to the scene."""
    import trimesh

    if not spec.meshes:
        return
    out = stage / MESH_DIR
    out.mkdir()
    for m in spec.meshes:
        if m.file:
            src = _mesh_path(spec, m)
            dst = out / f"{m.name}{src.suffix}"
            shutil.copyfile(src, dst)
        else:
            v = np.asarray(m.uservert, float).reshape(-1, 3)
            f = np.asarray(m.userface, int).reshape(-1, 3)
            dst = out / f"{m.name}.stl"
            trimesh.Trimesh(v, f, process=False).export(str(dst))
            m.uservert, m.userface = [], []
        m.file = dst.name
    spec.meshdir = MESH_DIR
    spec.modelfiledir = str(stage)  # to_xml re-reads the meshes from where they now are


def _move_into(stage: Path, out_dir: Path) -> None:
    if not out_dir.exists():
        os.replace(stage, out_dir)
        stage.mkdir()  # so the caller's cleanup has something to remove
        return
    if (out_dir / MESH_DIR).exists() and (stage / MESH_DIR).exists():
        shutil.rmtree(out_dir / MESH_DIR)
    for p in stage.iterdir():
        os.replace(p, out_dir / p.name)


# --- skin and obstacles -------------------------------------------------------------------

def _taxel_quats(frames: np.ndarray) -> np.ndarray:
    """(N,4) MuJoCo quaternions (w, x, y, z) of taxel frames (columns x, y, z)."""
    if not len(frames):
        return np.zeros((0, 4))
    q = Rotation.from_matrix(frames).as_quat()  # x, y, z, w
    return np.concatenate([q[:, 3:], q[:, :3]], axis=1)


def taxel_cell(design: SkinDesign) -> np.ndarray:
    """(N,) the side of each taxel's square cell on its FPC (the module pitch), m."""
    pitch = {m.id: m.pitch for m in design.modules}
    return np.array([pitch[int(k)] for k in design.taxels.module], float)


def _add_taxel_sites(spec: mujoco.MjSpec, design: SkinDesign, touch: bool) -> None:
    t = design.taxels
    quats = _taxel_quats(t.frames)
    cell = taxel_cell(design)
    BOX = mujoco.mjtGeom.mjGEOM_BOX
    bodies = [spec.body(name) for name in design.bodies]
    for i in range(len(t)):
        name = f"taxel_{int(t.ids[i])}"
        half = cell[i] / 2
        bodies[t.body[i]].add_site(name=name, type=BOX, pos=t.positions[i].tolist(), quat=quats[i].tolist(),
                                   size=[half, half, half / 2], group=SITE_GROUP,
                                   rgba=[0.1, 0.8, 0.2, 0.5] if t.enabled[i] else [0.5, 0.5, 0.5, 0.5])
        if touch:
            spec.add_sensor(name=f"touch_{int(t.ids[i])}", type=mujoco.mjtSensor.mjSENS_TOUCH,
                            objtype=mujoco.mjtObj.mjOBJ_SITE, objname=name)


def _add_obstacles(spec: mujoco.MjSpec, obstacles: list[Obstacle]) -> None:
    taken = {b.name for b in spec.bodies} | {g.name for g in spec.geoms}
    for k, ob in enumerate(obstacles):
        where = f"obstacle #{k} '{getattr(ob, 'name', '?')}'"
        if not isinstance(ob, Obstacle):
            raise DesignError(f"{where}: is a {type(ob).__name__}, expected an Obstacle")
        if not ob.name or ob.name in taken:
            raise DesignError(f"{where}: field 'name' is empty or already used in the robot/scene; give a unique name")
        taken.add(ob.name)
        if ob.kind not in GEOM_TYPES:
            raise DesignError(f"{where}: field 'kind' is '{ob.kind}'; use one of {sorted(GEOM_TYPES)}")
        if ob.mocap and ob.free:
            raise DesignError(f"{where}: is both mocap and free; choose one")
        gtype, nsize = GEOM_TYPES[ob.kind]
        size = [float(s) for s in ob.size]
        if len(size) != nsize or not all(np.isfinite(size)) or any(s <= 0 for s in size):
            if ob.kind != "mesh":
                raise DesignError(f"{where}: field 'size' is {tuple(ob.size)}; a {ob.kind} needs {nsize} positive numbers")
        body = spec.worldbody.add_body(name=ob.name, pos=list(ob.pos), quat=list(ob.quat), mocap=bool(ob.mocap))
        if ob.free:
            body.add_freejoint(name=f"{ob.name}_free")
        geom = dict(name=ob.name, type=gtype, rgba=list(ob.rgba))
        if ob.kind == "mesh":
            if not ob.mesh_file:
                raise DesignError(f"{where}: kind 'mesh' needs 'mesh_file'")
            m = meshlib.load_checked(ob.mesh_file, where)
            mesh = spec.add_mesh(name=f"{ob.name}_mesh")
            mesh.uservert = np.asarray(m.vertices, float).ravel().tolist()
            mesh.userface = np.asarray(m.faces, int).ravel().tolist()
            geom["meshname"] = mesh.name
        else:
            geom["size"] = size + [0.0] * (3 - nsize)
        if ob.free and ob.mass is not None:
            geom["mass"] = float(ob.mass)
        body.add_geom(**geom)


# --- contact pruning ----------------------------------------------------------------------

def _prune_contacts(spec: mujoco.MjSpec, model: mujoco.MjModel, obstacles: list[Obstacle]) -> None:
    """Switch contacts off for robot bodies that nothing can ever touch.

    A moving body can touch a fixed geom only within its reach from the anchor of its chain
    (sum of body offsets down the chain plus its geoms' bounding spheres); it can touch another
    moving body when their contact masks meet and no exclude or parent/child relation filters
    them. Mocap or free obstacles can go anywhere: with one in the scene nothing is pruned.
    """
    if any(o.mocap or o.free for o in obstacles):
        return
    data = mujoco.MjData(model)
    if model.nkey:
        mujoco.mj_resetDataKeyframe(model, data, 0)
    mujoco.mj_kinematics(model, data)
    weld = model.body_weldid
    moving = [b for b in range(1, model.nbody) if weld[b] != 0]
    if any(model.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE for j in range(model.njnt)):
        return
    excluded = {frozenset((e.bodyname1, e.bodyname2)) for e in spec.excludes}
    names = [model.body(b).name for b in range(model.nbody)]
    geoms_of = {b: [g for g in range(model.ngeom) if model.geom_bodyid[g] == b and
                    (model.geom_contype[g] or model.geom_conaffinity[g])] for b in range(model.nbody)}
    fixed = [g for g in range(model.ngeom) if weld[model.geom_bodyid[g]] == 0 and
             (model.geom_contype[g] or model.geom_conaffinity[g])]

    def can_pair(g1, g2):
        return bool((model.geom_contype[g1] & model.geom_conaffinity[g2]) or
                    (model.geom_contype[g2] & model.geom_conaffinity[g1]))

    for b in moving:
        gs = geoms_of[b]
        if not gs:
            continue
        root = b
        while weld[model.body_parentid[root]] != 0:
            root = model.body_parentid[root]
        anchor = data.xpos[root]
        chain, node = 0.0, b
        while node != root:
            chain += float(np.linalg.norm(model.body_pos[node]))
            node = model.body_parentid[node]
        reach = chain + max(float(np.linalg.norm(model.geom_pos[g])) + model.geom_rbound[g] for g in gs)
        touchable = False
        for f in fixed:
            if not any(can_pair(g, f) for g in gs):
                continue
            if model.geom_type[f] == mujoco.mjtGeom.mjGEOM_PLANE:
                normal = data.geom_xmat[f].reshape(3, 3)[:, 2]
                dist = float(np.dot(anchor - data.geom_xpos[f], normal))
            else:
                dist = float(np.linalg.norm(anchor - data.geom_xpos[f])) - model.geom_rbound[f]
            if dist <= reach:
                touchable = True
                break
        if not touchable:
            for o in moving:
                if o == b or model.body_parentid[o] == b or model.body_parentid[b] == o:
                    continue
                if frozenset((names[b], names[o])) in excluded:
                    continue
                if any(can_pair(g, h) for g in gs for h in geoms_of[o]):
                    touchable = True
                    break
        if not touchable:
            for g in spec.body(names[b]).geoms:
                g.contype, g.conaffinity = 0, 0
