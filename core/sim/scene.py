"""A skin design as one MuJoCo scene, built by editing the robot's own `MjSpec`.

The scene holds the robot (collision meshes simplified as asked), one site per taxel in its
body frame oriented as the taxel frame (`taxel_<id>`, a box the size of the taxel's cell), an
optional MuJoCo `touch` sensor per taxel (`touch_<id>`, the accuracy reference), and the
obstacles. `skinsafe.exporters.mjcf.export_scene` writes it to files.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np

from skinsafe.core.robot import meshes as meshlib
from skinsafe.core.robot.kinematics import taxel_quats
from skinsafe.core.robot.models import Robot
from skinsafe.core.sim.contacts import prune_contacts
from skinsafe.core.sim.skin_collision import fit_to_skin, taxel_clearance
from skinsafe.core.skin.model import DesignError, SkinDesign

GEOM_TYPES = {
    "sphere": (mujoco.mjtGeom.mjGEOM_SPHERE, 1),
    "box": (mujoco.mjtGeom.mjGEOM_BOX, 3),
    "capsule": (mujoco.mjtGeom.mjGEOM_CAPSULE, 2),
    "cylinder": (mujoco.mjtGeom.mjGEOM_CYLINDER, 2),
    "mesh": (mujoco.mjtGeom.mjGEOM_MESH, 0),
}
MAP_FILE = "taxel_map.json"
SITE_GROUP = 3
TACTILE_POINTS = (1, 7, 19, 37)  # tactile mesh vertices per taxel: hexagonal rings 0, 1, 2, 3
TIP_MASS = 0.5  # kg, a sprung obstacle's tip: its contacts are stiff (about 35 kN/m) against its spring
TIP_SOLREF = (0.004, 1.0)  # s: the stiffest contact MuJoCo keeps stable at a 2 ms step
COLLISION_MODES = ("skin",) + meshlib.MODES  # hidden in the viewer by default: a dense skin would hide the robot


@dataclass
class Obstacle:
    """Something in the scene the skin can touch: a body named `name` with one geom named `name`.

    `mocap`: a kinematic body moved through `data.mocap_pos/mocap_quat` (probes, a human arm);
    `free`: a dynamic body with a free joint (falls, rests on the robot); neither: fixed.
    `spring` (N/m, mocap only): the geom rides on a light tip (`<name>_tip`, `TIP_MASS` kg) that
    slides along the obstacle's local z on a critically damped spring (joint `<name>_spring`),
    like a finger or a force gauge. A rigid mocap body driven to a depth meets MuJoCo's contact
    model, whose force at a given penetration scales with the robot's effective mass there
    (kN at sub-mm depths near a joint axis); through the spring the force is about
    `spring` x compression on any robot. The tip's joint comes after the robot's in `qpos`.
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
    spring: float | None = None  # N/m: a sprung tip on a mocap holder (see above)


@dataclass
class SceneOptions:
    """Every modelling choice of the scene, with defaults that suit the vectorised readout."""

    collision: str = "skin"  # "skin" (fitted to the skin, see sim.skin_collision) | mesh robots: "primitive" | "hull" | "decimate" | "full"
    target_faces: int = 500  # for "decimate"
    visual: bool = True  # keep visual meshes (geoms that never collide)
    taxel_sites: bool = False  # one site per taxel ("taxel_<id>"), for viewing and touch sensors; the readout needs none
    clearance_tol: float = 1e-3  # m: warn when a taxel is farther than this from the contact surface
    touch_sensors: bool = False  # one MuJoCo touch sensor per taxel (accuracy reference; slow)
    tactile_sensors: bool = False  # MuJoCo's native `tactile` sensor, one per skinned link (a reference)
    tactile_points: int = 1  # its mesh vertices per taxel: 1, 7, 19, ... (hexagonal rings filling the cell)
    prune_contacts: bool = True  # robot bodies nothing can touch get contype/conaffinity 0
    timestep: float | None = None

    def check(self) -> None:
        if self.collision not in COLLISION_MODES:
            raise ValueError(f"SceneOptions.collision is '{self.collision}'; use one of {COLLISION_MODES}")
        if self.collision == "decimate" and self.target_faces < 4:
            raise ValueError(f"SceneOptions.target_faces is {self.target_faces}; give at least 4")
        if self.tactile_points not in TACTILE_POINTS:
            raise ValueError(f"SceneOptions.tactile_points is {self.tactile_points}; use one of {TACTILE_POINTS}")
        if self.timestep is not None and not (0 < self.timestep <= 0.05):
            raise ValueError(f"SceneOptions.timestep is {self.timestep}; give seconds in (0, 0.05]")


def build_scene(design: SkinDesign | None, robot: Robot, obstacles=(), options: SceneOptions = SceneOptions()
                ) -> mujoco.MjSpec:
    """The scene as an `MjSpec` (an edited copy of `robot.spec`; `robot` is left as it was).

    `design=None` builds the same scene with no skin (the reference for what the skin costs).
    Raises DesignError naming the body, mesh or obstacle at fault; ValueError for bad options.
    """
    options.check()
    spec = robot.spec.copy()
    if options.timestep is not None:
        spec.option.timestep = float(options.timestep)
    _process_meshes(spec, options)
    if design is not None:
        design.validate("design", robot.body_names)
    if options.collision == "skin":
        fit_to_skin(spec, design, options.clearance_tol)
    if design is not None:
        _warn_clearance(spec, design, robot, options)
    _add_obstacles(spec, list(obstacles))
    if design is not None and (options.taxel_sites or options.touch_sensors):  # a touch sensor reads a site
        _add_taxel_sites(spec, design, options.touch_sensors)
    if design is not None and options.tactile_sensors:
        _add_tactile_sensors(spec, design, options.tactile_points)
    try:
        model = spec.compile()
    except ValueError as e:
        raise DesignError(f"scene: MuJoCo could not compile the scene: {e}") from None
    _drop_unused_meshes(spec, model)
    if options.prune_contacts:
        prune_contacts(spec, model, list(obstacles))
    spec.add_text(name="skinsafe.taxel_map", data=MAP_FILE)
    return spec


def _warn_clearance(spec, design: SkinDesign, robot: Robot, options: SceneOptions) -> None:
    """Warn where a taxel is farther than `options.clearance_tol` from the contact surface."""
    if not len(design.taxels):
        return
    gap = taxel_clearance(spec, design, robot.home)
    far = np.abs(gap) > options.clearance_tol
    if far.any():
        w = int(np.argmax(np.abs(gap)))
        fix = ("the taxel is buried inside the link's own shape: move its module onto the outer surface"
               if gap[w] < 0 else "use SceneOptions(collision='skin')")
        warnings.warn(f"scene: taxel {int(design.taxels.ids[w])} on '{design.bodies[design.taxels.body[w]]}' is "
                      f"{gap[w] * 1e3:+.1f} mm from the contact surface ({int(far.sum())} taxels beyond "
                      f"{options.clearance_tol * 1e3:.1f} mm): contacts there are sensed late or not at all; {fix}",
                      stacklevel=3)


# --- robot meshes -------------------------------------------------------------------------

def mesh_path(spec: mujoco.MjSpec, mesh) -> Path:
    p = Path(mesh.file)
    if p.is_absolute():
        return p
    meshdir = Path(spec.meshdir or "")
    if not meshdir.is_absolute():
        meshdir = Path(spec.modelfiledir or ".") / meshdir
    return meshdir / p


def _process_meshes(spec: mujoco.MjSpec, options: SceneOptions) -> None:
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
        mesh = meshlib.load_checked(mesh_path(spec, src), where)
        if options.collision == "primitive":
            spec.compiler.fitaabb = True  # a box-fitted primitive covers the mesh; an inertia fit is smaller
            # size 0: MuJoCo fits it; a capsule for elongated shapes, else a box
            ext = np.sort(mesh.bounding_box_oriented.primitive.extents)
            long = ext[2] > ext[1] * 1.2
            g.type = mujoco.mjtGeom.mjGEOM_CAPSULE if long else mujoco.mjtGeom.mjGEOM_BOX
            g.size = [0.0, 0.0, 0.0]
            continue
        if options.collision in ("full", "skin"):
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


# --- skin and obstacles -------------------------------------------------------------------

def taxel_cell(design: SkinDesign) -> np.ndarray:
    """(N,) the side of each taxel's square cell on its FPC (the module pitch), m."""
    pitch = {m.id: m.pitch for m in design.modules}
    return np.array([pitch[int(k)] for k in design.taxels.module], float)


def _add_taxel_sites(spec: mujoco.MjSpec, design: SkinDesign, touch: bool) -> None:
    t = design.taxels
    quats = taxel_quats(t.frames)
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


def cell_points(design: SkinDesign, per_taxel: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Points filling each taxel's cell: `per_taxel` points on hexagonal rings in the taxel's plane
    (spacing pitch / (2 rings + 1), so they stay inside the cell). Returns ((N*k, 3) positions in
    the body frame, (N*k,) taxel index)."""
    t = design.taxels
    rings = TACTILE_POINTS.index(per_taxel)
    offsets = [(0.0, 0.0)]
    for k in range(1, rings + 1):  # ring k of a hexagonal lattice: 6k points
        corners = [np.array([np.cos(a), np.sin(a)]) * k for a in np.arange(6) * np.pi / 3]
        for c in range(6):
            for j in range(k):
                offsets.append(tuple(corners[c] + (corners[(c + 1) % 6] - corners[c]) * j / k))
    off = np.array(offsets) / (2 * rings + 1)  # in units of the pitch
    step = taxel_cell(design)[:, None, None] * off[None]  # (N, k, 2)
    pts = t.positions[:, None, :] + step[..., :1] * t.frames[:, None, :, 0] + step[..., 1:] * t.frames[:, None, :, 1]
    return pts.reshape(-1, 3), np.repeat(np.arange(len(t)), len(off))


def _add_tactile_sensors(spec: mujoco.MjSpec, design: SkinDesign, per_taxel: int = 1) -> None:
    """MuJoCo's native `tactile` sensor per skinned link: a mesh whose vertices are `per_taxel`
    points in each of the link's taxel cells (`tactile_<body>`), on a non-colliding geom of that
    mesh (the sensor's frame). The sensor reads each vertex's depth inside the geoms touching the link."""
    t = design.taxels
    pts, owner = cell_points(design, per_taxel)
    for bi, body in enumerate(design.bodies):
        on = t.body[owner] == bi
        if on.sum() < 4:
            continue
        name = f"tactile_{body}"
        mesh = spec.add_mesh(name=name)
        mesh.uservert = pts[on].ravel().tolist()
        spec.body(body).add_geom(name=name, type=mujoco.mjtGeom.mjGEOM_MESH, meshname=name, contype=0,
                                 conaffinity=0, group=SITE_GROUP + 1, density=0)
        spec.add_sensor(name=name, type=mujoco.mjtSensor.mjSENS_TACTILE, objtype=mujoco.mjtObj.mjOBJ_MESH,
                        objname=name, reftype=mujoco.mjtObj.mjOBJ_GEOM, refname=name)


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
        if ob.spring is not None and not (ob.mocap and np.isfinite(ob.spring) and ob.spring > 0):
            raise DesignError(f"{where}: field 'spring' is {ob.spring}; give a positive stiffness in N/m on a mocap obstacle")
        gtype, nsize = GEOM_TYPES[ob.kind]
        size = [float(s) for s in ob.size]
        if len(size) != nsize or not all(np.isfinite(size)) or any(s <= 0 for s in size):
            if ob.kind != "mesh":
                raise DesignError(f"{where}: field 'size' is {tuple(ob.size)}; a {ob.kind} needs {nsize} positive numbers")
        body = spec.worldbody.add_body(name=ob.name, pos=list(ob.pos), quat=list(ob.quat), mocap=bool(ob.mocap))
        if ob.free:
            body.add_freejoint(name=f"{ob.name}_free")
        geom = dict(name=ob.name, type=gtype, rgba=list(ob.rgba))
        if ob.spring is not None:
            body = body.add_body(name=f"{ob.name}_tip", gravcomp=1.0)  # its weight would load the skin
            body.add_joint(name=f"{ob.name}_spring", type=mujoco.mjtJoint.mjJNT_SLIDE, axis=[0, 0, 1],
                           stiffness=float(ob.spring), damping=2 * float(np.sqrt(ob.spring * TIP_MASS)))
            geom.update(mass=TIP_MASS, priority=1, solref=list(TIP_SOLREF))
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
