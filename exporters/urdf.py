"""A skin design as a URDF for ROS: the robot's kinematic tree, one fixed link per taxel, tactile sensors.

Layout of the written file (`export_urdf`):

* One `<link>` per MuJoCo body of the compiled `robot.model`, named as the body, with its
  `<inertial>` (body_mass, principal body_inertia at body_ipos/body_iquat). The robot's visual
  geoms become `<visual>`, its colliding geoms `<collision>` (both only for a robot with no
  visual geometry, like the built-ins): sphere, box and cylinder as such, a capsule as the
  cylinder of its straight part, meshes as `<urdf stem>_meshes/<mesh>.stl` beside the URDF (the
  robot's own meshes as MuJoCo compiled them, DAE visuals included, in a folder this URDF owns:
  the MJCF scene's `meshes/` in the same export folder is never touched); plane and other geoms
  are left out. The world body becomes a link "world" only when the tree needs it (several root
  bodies, a root away from the origin, or a root with a joint); its geoms (table, floor) are
  left out.
* One `<joint>` per body to its parent body, origin = body_pos/body_quat as xyz/rpy: a limited
  hinge is `revolute` (limits from jnt_range), an unlimited one `continuous`, a slide
  `prismatic`, a free joint `floating`, no joint `fixed`. Velocity limits come from
  `robot.vel_limits`, efforts from the joint's actuator force range (100 when unset).
* One fixed child link `taxel_<id>` per taxel (joint `taxel_<id>_joint`, parent = the taxel's
  body, origin = the taxel position and frame as rpy; z = outward normal).
* One tactile sensor per skin module, in the tactile_toolbox `urdf_tactile` "list of taxels"
  layout (github.com/ubi-agni/tactile_toolbox, urdf_tactile/README.md)::

      <sensor name="skin_module_<id>" group="<body>" update_rate="100">
        <parent link="<body>"/>
        <origin xyz="0 0 0" rpy="0 0 0"/>
        <tactile channel="<board name>">
          <taxel idx="<channel on that board>" xyz="..." rpy="...">
            <geometry><box size="s s 0.001"/></geometry>   (s = sqrt(taxel area))
          </taxel>
        </tactile>
      </sensor>

  `channel` names the board's data vector and `idx` indexes it (the board channel the FSR is
  wired to), so a TactileState per board maps straight onto the taxels; the taxel id is in the
  matching `taxel_<id>` link.
* A `<mujoco><compiler fusestatic="false" discardvisual="false"/></mujoco>` tag so that MuJoCo
  (`mujoco.MjModel.from_xml_path`) keeps the fixed taxel links; ROS parsers ignore it.
"""
from __future__ import annotations

import os
import tempfile
import xml.etree.ElementTree as ET
from pathlib import Path

import mujoco
import numpy as np

from skinsafe.core.robot.models import Robot
from skinsafe.core.skin.files import atomic_write
from skinsafe.core.skin.model import SkinDesign

URDF_FILE = "robot_skin.urdf"
DEFAULT_EFFORT = 100.0  # N m (or N) where the model gives no actuator force range
TAXEL_THICKNESS = 0.001  # m, thickness of the taxel marker box in the tactile sensor
_JOINT_TYPES = {int(mujoco.mjtJoint.mjJNT_HINGE): "revolute", int(mujoco.mjtJoint.mjJNT_SLIDE): "prismatic",
                int(mujoco.mjtJoint.mjJNT_FREE): "floating"}
_G = mujoco.mjtGeom


def _num(values) -> str:
    """Space-separated floats that round-trip exactly (repr)."""
    return " ".join(repr(float(v)) for v in np.ravel(values))


def rpy_from_matrices(R: np.ndarray) -> np.ndarray:
    """URDF roll, pitch, yaw (R = Rz(yaw) Ry(pitch) Rx(roll)) of rotation matrices (..., 3, 3).

    Pitch from a well-conditioned atan2; roll from the residual rotation once yaw is fixed, so the
    result stays exact to rounding also at gimbal lock (pitch = +-pi/2).
    """
    R = np.asarray(R, dtype=float)
    pitch = np.arctan2(-R[..., 2, 0], np.hypot(R[..., 0, 0], R[..., 1, 0]))
    yaw = np.arctan2(R[..., 1, 0], R[..., 0, 0])
    cy, sy, cp, sp = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch)
    # M = Ry(pitch)^T Rz(yaw)^T R = Rx(roll); roll = atan2(M[2,1], M[1,1])
    m11 = -sy * R[..., 0, 1] + cy * R[..., 1, 1]
    a = cy * R[..., 0, 1] + sy * R[..., 1, 1]  # (Rz^T R)[0,1]
    m21 = sp * a + cp * R[..., 2, 1]
    roll = np.arctan2(m21, m11)
    return np.stack([roll, pitch, yaw], axis=-1)


def _quat_rpy(q) -> np.ndarray:
    R = np.zeros(9)
    mujoco.mju_quat2Mat(R, np.asarray(q, dtype=float))
    return rpy_from_matrices(R.reshape(3, 3))


def _origin(parent: ET.Element, xyz, rpy) -> None:
    ET.SubElement(parent, "origin", xyz=_num(xyz), rpy=_num(rpy))


def _geometry(model: mujoco.MjModel, g: int) -> ET.Element | None:
    t, s = int(model.geom_type[g]), model.geom_size[g]
    geo = ET.Element("geometry")
    if t == int(_G.mjGEOM_SPHERE):
        ET.SubElement(geo, "sphere", radius=_num(s[:1]))
    elif t == int(_G.mjGEOM_BOX):
        ET.SubElement(geo, "box", size=_num(2 * s))
    elif t in (int(_G.mjGEOM_CYLINDER), int(_G.mjGEOM_CAPSULE)):
        ET.SubElement(geo, "cylinder", radius=_num(s[:1]), length=_num(2 * s[1:2]))
    else:
        return None
    return geo


def _check_robot(model: mujoco.MjModel, design: SkinDesign) -> None:
    names = [model.body(b).name for b in range(model.nbody)]
    for b in range(1, model.nbody):
        if not names[b]:
            raise ValueError(f"urdf export: body {b} of the robot has no name; name every body (URDF links need names)")
        jnts = range(model.body_jntadr[b], model.body_jntadr[b] + model.body_jntnum[b])
        if len(jnts) > 1:
            raise ValueError(f"urdf export: body '{names[b]}' has {len(jnts)} joints; URDF allows one per link, "
                             "split the body into a chain of bodies with one joint each")
        for j in jnts:
            jname = model.joint(j).name or f"#{j}"
            if int(model.jnt_type[j]) not in _JOINT_TYPES:
                raise ValueError(f"urdf export: joint '{jname}' of body '{names[b]}' is a ball joint, which URDF "
                                 "cannot express; replace it by three hinges")
            if int(model.jnt_type[j]) == int(mujoco.mjtJoint.mjJNT_FREE):
                if model.body_parentid[b] != 0:
                    raise ValueError(f"urdf export: free joint '{jname}' of body '{names[b]}' is not on a root body")
                continue
            if not model.joint(j).name:
                raise ValueError(f"urdf export: a joint of body '{names[b]}' has no name; name it")
            if np.abs(model.jnt_pos[j]).max() > 0:
                raise ValueError(f"urdf export: joint '{jname}' sits at {model.jnt_pos[j].tolist()} in body "
                                 f"'{names[b]}', URDF needs joints at the link origin; move the body frame onto "
                                 "the joint (pos=0)")
            if abs(model.qpos0[model.jnt_qposadr[j]]) > 0:
                raise ValueError(f"urdf export: joint '{jname}' has a non-zero reference position (ref); "
                                 "URDF joints are zero at the link origin, bake ref into the body pose")
    taken = set(names) | {"world"}
    for i in design.taxels.ids:
        if f"taxel_{int(i)}" in taken:
            raise ValueError(f"urdf export: taxel {int(i)}: link name 'taxel_{int(i)}' is already a robot body; "
                             "rename that body or renumber the taxel")


def _needs_world(model: mujoco.MjModel) -> bool:
    roots = [b for b in range(1, model.nbody) if model.body_parentid[b] == 0]
    if len(roots) != 1:
        return True
    b = roots[0]
    return bool(model.body_jntnum[b] or np.any(model.body_pos[b] != 0) or np.any(model.body_quat[b] != [1, 0, 0, 0]))


def mesh_dir_of(path: str | Path) -> str:
    """The folder a URDF's meshes go in, beside it and its own: `<stem>_meshes`."""
    return f"{Path(path).stem}_meshes"


def _mesh_geometry(model: mujoco.MjModel, g: int, meshes: dict, mesh_dir: str) -> ET.Element:
    """A mesh geom as `<mesh_dir>/<mesh>.stl` (the robot's own mesh as MuJoCo holds it, in the geom
    frame); its vertices and faces are collected in `meshes` for the caller to write."""
    m = int(model.geom_dataid[g])
    name = model.mesh(m).name or f"mesh{m}"
    if name not in meshes:
        v0, nv, f0, nf = model.mesh_vertadr[m], model.mesh_vertnum[m], model.mesh_faceadr[m], model.mesh_facenum[m]
        meshes[name] = (model.mesh_vert[v0:v0 + nv].astype(float), model.mesh_face[f0:f0 + nf].astype(np.int64))
    geo = ET.Element("geometry")
    ET.SubElement(geo, "mesh", filename=f"{mesh_dir}/{name}.stl")
    return geo


def _robot_elements(root: ET.Element, robot: Robot, meshes: dict | None, mesh_dir: str) -> None:
    model = robot.model
    world = _needs_world(model)
    has_visual = any(model.geom_bodyid[g] and not (model.geom_contype[g] or model.geom_conaffinity[g])
                     for g in range(model.ngeom))
    if world:
        ET.SubElement(root, "link", name="world")
    for b in range(1, model.nbody):
        name = model.body(b).name
        link = ET.SubElement(root, "link", name=name)
        if model.body_mass[b] > 0:
            inertial = ET.SubElement(link, "inertial")
            _origin(inertial, model.body_ipos[b], _quat_rpy(model.body_iquat[b]))
            ET.SubElement(inertial, "mass", value=_num(model.body_mass[b:b + 1]))
            ixx, iyy, izz = (repr(float(v)) for v in model.body_inertia[b])
            ET.SubElement(inertial, "inertia", ixx=ixx, ixy="0.0", ixz="0.0", iyy=iyy, iyz="0.0", izz=izz)
        geoms = [int(g) for g in np.flatnonzero(model.geom_bodyid == b)]
        collides = {g: bool(model.geom_contype[g] or model.geom_conaffinity[g]) for g in geoms}
        for g in geoms:
            mesh = int(model.geom_type[g]) == int(_G.mjGEOM_MESH) and meshes is not None
            if not mesh and _geometry(model, g) is None:
                continue
            gname = model.geom(g).name or f"{name}_geom{g}"
            # the robot's visual geoms are its visuals, its colliding geoms its collisions; a
            # robot with no visual geometry (the built-ins) shows its collision shapes
            tags = [("collision", gname)] if collides[g] else [("visual", f"{gname}_visual")]
            if collides[g] and not has_visual:
                tags.insert(0, ("visual", f"{gname}_visual"))
            for tag, el_name in tags:
                el = ET.SubElement(link, tag, name=el_name)
                _origin(el, model.geom_pos[g], _quat_rpy(model.geom_quat[g]))
                el.append(_mesh_geometry(model, g, meshes, mesh_dir) if mesh else _geometry(model, g))
        parent = int(model.body_parentid[b])
        if parent == 0 and not world:
            continue  # the single root link
        j = model.body_jntadr[b] if model.body_jntnum[b] else -1
        jtype = "fixed" if j < 0 else _JOINT_TYPES[int(model.jnt_type[j])]
        if jtype == "revolute" and not model.jnt_limited[j]:
            jtype = "continuous"
        jname = model.joint(j).name if j >= 0 and model.joint(j).name else f"{name}_joint"
        joint = ET.SubElement(root, "joint", name=jname, type=jtype)
        _origin(joint, model.body_pos[b], _quat_rpy(model.body_quat[b]))
        ET.SubElement(joint, "parent", link=model.body(parent).name if parent else "world")
        ET.SubElement(joint, "child", link=name)
        if jtype in ("revolute", "continuous", "prismatic"):
            ET.SubElement(joint, "axis", xyz=_num(model.jnt_axis[j]))
            dof = model.jnt_dofadr[j]
            velocity = float(robot.vel_limits[dof]) if dof < len(robot.vel_limits) else 1.0
            frc = model.jnt_actfrcrange[j]
            effort = float(np.abs(frc).max()) if model.jnt_actfrclimited[j] else DEFAULT_EFFORT
            limit = {"effort": repr(effort), "velocity": repr(velocity)}
            if jtype != "continuous":
                limit.update(lower=repr(float(model.jnt_range[j][0])), upper=repr(float(model.jnt_range[j][1])))
            ET.SubElement(joint, "limit", **limit)


def _taxel_elements(root: ET.Element, design: SkinDesign, update_rate: float) -> None:
    t = design.taxels
    rpy = rpy_from_matrices(t.frames)
    for i in range(len(t)):
        tid, body = int(t.ids[i]), design.body_of(i)
        ET.SubElement(root, "link", name=f"taxel_{tid}")
        joint = ET.SubElement(root, "joint", name=f"taxel_{tid}_joint", type="fixed")
        _origin(joint, t.positions[i], rpy[i])
        ET.SubElement(joint, "parent", link=body)
        ET.SubElement(joint, "child", link=f"taxel_{tid}")
    boards = {b.id: b.name for b in design.boards}
    modules = {m.id: m for m in design.modules}
    seen: dict[tuple[int, int], int] = {}
    for mid in dict.fromkeys(int(m) for m in t.module):  # modules in order of first taxel
        rows = np.flatnonzero(t.module == mid)
        bodies = {design.body_of(i) for i in rows}
        if mid not in modules:
            raise ValueError(f"urdf export: taxel {int(t.ids[rows[0]])} belongs to module {mid}, which the design "
                             "does not list; add the module or fix the taxel's module id")
        if len(bodies) > 1:
            raise ValueError(f"urdf export: module {mid} '{modules[mid].name}' has taxels on several bodies "
                             f"{sorted(bodies)}; a module (one tactile sensor) must ride on one body")
        body = bodies.pop()
        sensor = ET.SubElement(root, "sensor", name=f"skin_module_{mid}", group=body, update_rate=repr(float(update_rate)))
        ET.SubElement(sensor, "parent", link=body)
        _origin(sensor, (0, 0, 0), (0, 0, 0))
        for board in dict.fromkeys(int(b) for b in t.board[rows]):
            if board not in boards:
                raise ValueError(f"urdf export: taxel {int(t.ids[rows[0]])} is wired to board {board}, which the "
                                 "design does not list; add the board or fix the taxel's board id")
            tactile = ET.SubElement(sensor, "tactile", channel=boards[board])
            for i in rows[t.board[rows] == board]:
                key = (board, int(t.channel[i]))
                if key in seen:
                    raise ValueError(f"urdf export: taxels {seen[key]} and {int(t.ids[i])} share channel {key[1]} "
                                     f"of board {board}; give every taxel its own channel")
                seen[key] = int(t.ids[i])
                taxel = ET.SubElement(tactile, "taxel", idx=str(int(t.channel[i])), xyz=_num(t.positions[i]),
                                      rpy=_num(rpy[i]))
                side = float(np.sqrt(t.area[i]))
                ET.SubElement(ET.SubElement(taxel, "geometry"), "box", size=_num([side, side, TAXEL_THICKNESS]))


def build_urdf(design: SkinDesign, robot: Robot, update_rate: float = 100.0, name: str | None = None,
               meshes: dict | None = None, mesh_dir: str = mesh_dir_of(URDF_FILE)) -> str:
    """The URDF text (see the module docstring); ValueError (naming the body/taxel and the fix) on
    bad input. With a `meshes` dict, mesh geoms are kept (as `<mesh_dir>/<name>.stl`, their vertices
    and faces put in the dict for `write_urdf`); without, they are left out."""
    if not update_rate > 0:
        raise ValueError(f"urdf export: update_rate {update_rate} Hz must be positive")
    design.validate("urdf export", robot.body_names)  # DesignError (a ValueError) names the body/taxel at fault
    _check_robot(robot.model, design)
    root = ET.Element("robot", name=name or f"{robot.name}_skin")
    mj = ET.SubElement(root, "mujoco")
    ET.SubElement(mj, "compiler", fusestatic="false", discardvisual="false", strippath="false")
    _robot_elements(root, robot, meshes, mesh_dir)
    _taxel_elements(root, design, update_rate)
    ET.indent(root, space="  ")
    return '<?xml version="1.0"?>\n' + ET.tostring(root, encoding="unicode") + "\n"


def write_urdf(path: str | Path, text: str, meshes: dict) -> Path:
    """The URDF at `path` and its meshes as binary STL in `mesh_dir_of(path)` beside it: the mesh
    folder is written whole in a temporary folder and swapped in (a stale mesh of an earlier
    export never survives), then the URDF is written atomically."""
    import trimesh

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    dest = path.parent / mesh_dir_of(path)
    with tempfile.TemporaryDirectory(prefix=f".{dest.name}.", dir=path.parent) as tmp:
        stage = Path(tmp) / "new"
        stage.mkdir()
        for mesh_name, (v, f) in meshes.items():
            trimesh.Trimesh(v, f, process=False).export(str(stage / f"{mesh_name}.stl"), file_type="stl")
        if dest.exists():
            os.replace(dest, Path(tmp) / "old")
        if meshes:
            os.chmod(stage, 0o777 & ~_umask())
            os.replace(stage, dest)
    return atomic_write(path, text)


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def export_urdf(design: SkinDesign, robot: Robot, path: str | Path, update_rate: float = 100.0) -> Path:
    """Write the design's URDF (robot tree with its own meshes, taxel links, tactile sensors) to
    `path`, the meshes beside it in its own `mesh_dir_of(path)` (`write_urdf`)."""
    meshes: dict = {}
    text = build_urdf(design, robot, update_rate, meshes=meshes, mesh_dir=mesh_dir_of(path))
    return write_urdf(path, text, meshes)
