"""Robots: the built-in UR5 and Franka Panda, generated with MjSpec from published kinematics,
and any URDF or MJCF the user has.

A `Robot` bundles the MuJoCo spec and model with what MuJoCo does not keep: joint velocity and
acceleration limits and a home configuration.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from pathlib import Path

import mujoco
import numpy as np

from skinsafe.core.skin.model import DesignError, RobotRef

HINGE = mujoco.mjtJoint.mjJNT_HINGE
CAPSULE = mujoco.mjtGeom.mjGEOM_CAPSULE
CYLINDER = mujoco.mjtGeom.mjGEOM_CYLINDER
BOX = mujoco.mjtGeom.mjGEOM_BOX

# UR5 (CB3) standard DH parameters, from Universal Robots' published kinematics.
UR5_DH = dict(
    d=[0.089159, 0.0, 0.0, 0.10915, 0.09465, 0.0823],
    a=[0.0, -0.425, -0.39225, 0.0, 0.0, 0.0],
    alpha=[np.pi / 2, 0.0, 0.0, np.pi / 2, -np.pi / 2, 0.0],
)
UR5_JOINTS = ["shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint",
              "wrist_1_joint", "wrist_2_joint", "wrist_3_joint"]
UR5_BODIES = ["shoulder_link", "upper_arm_link", "forearm_link", "wrist_1_link", "wrist_2_link", "wrist_3_link"]
UR5_MASS = [3.7, 8.393, 2.275, 1.219, 1.219, 0.1879]
UR5_HOME = np.array([0.0, -1.2, 1.6, -1.97, -1.5708, 0.0])

# Franka Emika Panda modified (Craig) DH parameters and limits, from Franka's published data.
PANDA_MDH = dict(
    a=[0.0, 0.0, 0.0, 0.0825, -0.0825, 0.0, 0.088],
    d=[0.333, 0.0, 0.316, 0.0, 0.384, 0.0, 0.0],
    alpha=[0.0, -np.pi / 2, np.pi / 2, np.pi / 2, -np.pi / 2, np.pi / 2, np.pi / 2],
)
PANDA_FLANGE_D = 0.107
PANDA_RANGE = [(-2.8973, 2.8973), (-1.7628, 1.7628), (-2.8973, 2.8973), (-3.0718, -0.0698),
               (-2.8973, 2.8973), (-0.0175, 3.7525), (-2.8973, 2.8973)]
PANDA_VMAX = [2.175, 2.175, 2.175, 2.175, 2.61, 2.61, 2.61]
PANDA_AMAX = [15.0, 7.5, 10.0, 12.5, 15.0, 20.0, 20.0]
PANDA_MASS = [4.97, 0.646, 3.228, 3.587, 1.226, 1.666, 0.735]
PANDA_HOME = np.array([0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785])


@dataclass
class Robot:
    """A robot ready for simulation and kinematics."""

    name: str
    spec: mujoco.MjSpec
    model: mujoco.MjModel
    vel_limits: np.ndarray  # (nv,) rad/s or m/s
    acc_limits: np.ndarray  # (nv,)
    home: np.ndarray  # (nq,)
    arm_bodies: list[str] = field(default_factory=list)  # bodies of the kinematic chain, base to tip

    @property
    def body_names(self) -> set[str]:
        return {self.model.body(i).name for i in range(self.model.nbody)}


def _quat_x(angle: float) -> list[float]:
    return [np.cos(angle / 2), np.sin(angle / 2), 0.0, 0.0]


def _add_table(spec: mujoco.MjSpec, top: float = 0.0) -> None:
    spec.worldbody.add_geom(name="table", type=BOX, size=[0.6, 0.6, 0.02], pos=[0.0, 0.0, top - 0.02],
                            rgba=[0.55, 0.45, 0.35, 1])
    spec.worldbody.add_geom(name="floor", type=mujoco.mjtGeom.mjGEOM_PLANE, size=[3, 3, 0.1],
                            pos=[0, 0, -0.75], rgba=[0.8, 0.8, 0.8, 1])


def _add_position_actuators(spec: mujoco.MjSpec, joints: list[str], kp: list[float]) -> None:
    for name, k in zip(joints, kp):
        act = spec.add_actuator(name=f"{name}_pos", target=name, trntype=mujoco.mjtTrn.mjTRN_JOINT)
        act.set_to_position(kp=k, dampratio=1.0)


def home_ctrl(model: mujoco.MjModel, q: np.ndarray) -> np.ndarray:
    """(nu,) the controls that hold configuration q: each joint position servo's target is its
    joint's position (other actuators 0), so a model reset to its `home` keyframe stays there."""
    ctrl = np.zeros(model.nu)
    for a in range(model.nu):
        servo = model.actuator_biasprm[a, 1] == -model.actuator_gainprm[a, 0] != 0
        if model.actuator_trntype[a] == mujoco.mjtTrn.mjTRN_JOINT and servo:
            ctrl[a] = q[model.jnt_qposadr[model.actuator_trnid[a, 0]]]
    return ctrl


def _set_home_key(spec: mujoco.MjSpec, q: np.ndarray) -> None:
    """The `home` keyframe (the first key, added if there is none) with q and the servo targets
    that hold it (a key without ctrl resets every servo to target 0: the arm swings at start)."""
    model = spec.compile()
    ctrl = home_ctrl(model, q)
    if not spec.keys:
        spec.add_key(name="home", qpos=np.asarray(q, float).tolist(), ctrl=ctrl.tolist())
    elif not np.any(model.key_ctrl[0]):
        spec.keys[0].ctrl = ctrl.tolist()


def _exclude_near_links(spec: mujoco.MjSpec, bodies: list[str], reach: int = 2) -> None:
    """No contacts between links at most `reach` apart in the chain (their shapes meet at joints)."""
    for i, a in enumerate(bodies):
        for b in bodies[i + 1:i + 1 + reach]:
            spec.add_exclude(bodyname1=a, bodyname2=b)


def _new_spec(name: str) -> mujoco.MjSpec:
    """An empty built-in robot scene: 2 ms timestep, joint ranges in radians, a table and a floor."""
    spec = mujoco.MjSpec()
    spec.modelname = name
    spec.option.timestep = 0.002
    spec.compiler.degree = False
    _add_table(spec)
    return spec


def build_ur5() -> Robot:
    """UR5 from its DH parameters; links are capsules/cylinders sized to the real arm (SI units)."""
    spec = _new_spec("ur5")
    base = spec.worldbody.add_body(name="base_link")
    base.add_geom(name="base", type=CYLINDER, size=[0.075, 0.043, 0], pos=[0, 0, 0.043], mass=4.0,
                  rgba=[0.3, 0.3, 0.35, 1])
    # Offsets of the link tubes along the shoulder/elbow axes (they sum to d4 in the DH model).
    shoulder_off, elbow_off = 0.13585, 0.13585 - 0.1197
    geoms = {
        "shoulder_link": [
            dict(type=CYLINDER, fromto=[0, 0, 0.05, 0, 0, UR5_DH["d"][0]], size=[0.06, 0, 0]),
            dict(type=CYLINDER, fromto=[0, 0.0, UR5_DH["d"][0], 0, -shoulder_off - 0.06, UR5_DH["d"][0]], size=[0.06, 0, 0]),
        ],
        "upper_arm_link": [
            dict(type=CAPSULE, fromto=[-0.03, 0, shoulder_off, -0.395, 0, shoulder_off], size=[0.05, 0, 0]),
            dict(type=CYLINDER, fromto=[-0.425, 0, elbow_off - 0.05, -0.425, 0, shoulder_off + 0.06], size=[0.05, 0, 0]),
        ],
        "forearm_link": [
            dict(type=CAPSULE, fromto=[-0.02, 0, elbow_off, -0.36, 0, elbow_off], size=[0.04, 0, 0]),
        ],
        "wrist_1_link": [
            dict(type=CYLINDER, fromto=[0, 0, elbow_off - 0.04, 0, 0, UR5_DH["d"][3] + 0.04], size=[0.0375, 0, 0]),
        ],
        "wrist_2_link": [
            dict(type=CYLINDER, fromto=[0, 0, -0.04, 0, 0, UR5_DH["d"][4] + 0.0], size=[0.0375, 0, 0]),
        ],
        "wrist_3_link": [
            dict(type=CYLINDER, fromto=[0, 0, 0.0, 0, 0, UR5_DH["d"][5] - 0.01], size=[0.0375, 0, 0]),
        ],
    }
    parent, pos, quat = base, [0, 0, 0], [1, 0, 0, 0]
    for i, (bname, jname) in enumerate(zip(UR5_BODIES, UR5_JOINTS)):
        body = parent.add_body(name=bname, pos=pos, quat=quat)
        body.add_joint(name=jname, type=HINGE, axis=[0, 0, 1], range=[-2 * np.pi, 2 * np.pi],
                       limited=mujoco.mjtLimited.mjLIMITED_TRUE, damping=1.0, armature=0.1)
        for k, g in enumerate(geoms[bname]):
            body.add_geom(name=f"{bname}_{k}", mass=UR5_MASS[i] if k == 0 else 0.2,
                          rgba=[0.7, 0.72, 0.75, 1] if k == 0 else [0.2, 0.4, 0.8, 1], **g)
        # Frame of the next joint: Tz(d) Tx(a) Rx(alpha) (standard DH).
        pos, quat = [UR5_DH["a"][i], 0, UR5_DH["d"][i]], _quat_x(UR5_DH["alpha"][i])
        parent = body
    parent.add_site(name="flange", pos=pos, quat=quat)
    _add_position_actuators(spec, UR5_JOINTS, [3000, 3000, 1500, 300, 300, 300])
    _exclude_near_links(spec, ["base_link"] + UR5_BODIES)
    _set_home_key(spec, UR5_HOME)
    model = spec.compile()
    return Robot("ur5", spec, model, vel_limits=np.full(6, np.pi), acc_limits=np.full(6, 15.0),
                 home=UR5_HOME.copy(), arm_bodies=["base_link"] + UR5_BODIES)


def build_panda() -> Robot:
    """Franka Panda (7 DoF) from its modified DH parameters, links as capsules."""
    spec = _new_spec("panda")
    base = spec.worldbody.add_body(name="link0")
    base.add_geom(name="link0_0", type=CYLINDER, fromto=[-0.04, 0, 0.0, -0.04, 0, 0.14], size=[0.09, 0, 0],
                  mass=3.06, rgba=[0.9, 0.9, 0.9, 1])
    # Capsules along each link, from this joint's frame toward the next one.
    link_geoms = [
        [dict(fromto=[0, 0, -0.19, 0, 0, -0.03], size=[0.075, 0, 0])],
        [dict(fromto=[0, 0, -0.06, 0, 0, 0.06], size=[0.06, 0, 0]), dict(fromto=[0, -0.05, 0, 0, -0.25, 0], size=[0.055, 0, 0])],
        [dict(fromto=[0, 0, -0.18, 0, 0, -0.06], size=[0.06, 0, 0]), dict(fromto=[0.0825, 0, -0.05, 0.0825, 0, 0.03], size=[0.055, 0, 0])],
        [dict(fromto=[0, 0, -0.05, 0, 0, 0.05], size=[0.055, 0, 0]), dict(fromto=[-0.0825, 0.03, 0, -0.0825, 0.10, 0], size=[0.055, 0, 0])],
        [dict(fromto=[0, 0, -0.26, 0, 0, -0.08], size=[0.045, 0, 0]), dict(fromto=[0, 0.08, -0.1, 0, 0.08, -0.2], size=[0.035, 0, 0])],
        [dict(fromto=[0, 0, -0.03, 0, 0, 0.02], size=[0.05, 0, 0]), dict(fromto=[0.02, 0, 0, 0.088, 0, 0], size=[0.045, 0, 0])],
        [dict(fromto=[0, 0, -0.01, 0, 0, 0.08], size=[0.045, 0, 0])],
    ]
    parent = base
    a, d, al = PANDA_MDH["a"], PANDA_MDH["d"], PANDA_MDH["alpha"]
    joints = [f"joint{i + 1}" for i in range(7)]
    bodies = [f"link{i + 1}" for i in range(7)]
    for i in range(7):
        # Modified DH: Rx(alpha_{i-1}) Tx(a_{i-1}) Rz(theta_i) Tz(d_i).
        pos = [a[i], -np.sin(al[i]) * d[i], np.cos(al[i]) * d[i]]
        body = parent.add_body(name=bodies[i], pos=pos, quat=_quat_x(al[i]))
        body.add_joint(name=joints[i], type=HINGE, axis=[0, 0, 1], range=list(PANDA_RANGE[i]),
                       limited=mujoco.mjtLimited.mjLIMITED_TRUE, damping=1.0, armature=0.1)
        for k, g in enumerate(link_geoms[i]):
            body.add_geom(name=f"{bodies[i]}_{k}", type=CAPSULE, mass=PANDA_MASS[i] if k == 0 else 0.1,
                          rgba=[0.92, 0.92, 0.92, 1], **g)
        parent = body
    flange = parent.add_body(name="link8", pos=[0, 0, PANDA_FLANGE_D])
    flange.add_site(name="flange")
    _add_position_actuators(spec, joints, [2000, 2000, 2000, 1500, 500, 300, 200])
    _exclude_near_links(spec, ["link0"] + bodies + ["link8"])
    _set_home_key(spec, PANDA_HOME)
    model = spec.compile()
    return Robot("panda", spec, model, vel_limits=np.array(PANDA_VMAX), acc_limits=np.array(PANDA_AMAX),
                 home=PANDA_HOME.copy(), arm_bodies=["link0"] + bodies + ["link8"])


BUILTIN = {"ur5": build_ur5, "panda": build_panda}


def load_robot(ref: RobotRef, base_dir: str | Path | None = None,
               default_vel_limit: float = np.pi, default_acc_limit: float = 15.0) -> Robot:
    """The robot a design refers to: built in, or a URDF/xacro/MJCF file (relative to `base_dir`,
    as are `ref.package_dirs`).

    Imported robots (see `urdf_import`) keep fixed-joint links as their own bodies and their
    visual meshes; they get position servos when they have no actuators, contact exclusions
    between links at most two joints apart, and a home pose from their first keyframe or else the
    zero pose moved inside the joint limits.
    """
    if ref.kind == "builtin":
        if ref.name not in BUILTIN:
            raise DesignError(f"robot: builtin name '{ref.name}' is unknown; use one of {sorted(BUILTIN)}")
        return BUILTIN[ref.name]()
    if ref.kind not in ("urdf", "mjcf"):
        raise DesignError(f"robot: field 'kind' is '{ref.kind}'; use 'builtin', 'urdf' or 'mjcf'")
    if not ref.path:
        raise DesignError(f"robot: kind '{ref.kind}' needs a 'path' to the file")

    def rel(p):
        return Path(p) if Path(p).is_absolute() or base_dir is None else Path(base_dir) / p

    path = rel(ref.path)
    if not path.is_file():
        raise DesignError(f"robot: file '{path}' not found; check the path in the taxel map")
    vel_by_name: dict[str, float] = {}
    if ref.kind == "mjcf":
        try:
            spec = mujoco.MjSpec.from_file(str(path))
        except ValueError as e:
            raise DesignError(f"robot: MuJoCo could not load '{path}': {e}") from None
    else:
        from skinsafe.core.robot.urdf_import import urdf_spec

        spec, vel_by_name, guessed = urdf_spec(path, [rel(d) for d in ref.package_dirs], ref.xacro_args)
    robot = robot_from_spec(spec, ref.name or path.name.split(".")[0], vel_by_name, default_vel_limit,
                            default_acc_limit, path=str(path))
    if ref.kind == "urdf" and guessed:
        _warn_guessed_inertia(robot, path, guessed)
    return robot


class InertiaWarning(UserWarning):
    """An imported robot whose link masses MuJoCo had to guess from their shapes."""


def _warn_guessed_inertia(robot: Robot, path: Path, links: list[str]) -> None:
    from skinsafe.core.robot.urdf_import import xacro_arg_names

    m = robot.model
    welds = {int(m.body_weldid[m.body(b).id]) for b in links if b in robot.body_names}
    mass = float(sum(m.body_mass[b] for b in range(m.nbody) if m.body_weldid[b] in welds))
    declared = xacro_arg_names(path) if path.suffix == ".xacro" else []
    fix = (f"pass the xacro argument that adds them (--xacro-arg NAME:=VALUE; this file declares "
           f"{', '.join(declared)})" if declared else "add <inertial> elements to those links")
    warnings.warn(InertiaWarning(
        f"robot file '{path.name}': {len(links)} moving links have no <inertial> ({', '.join(links[:3])}"
        f"{', ...' if len(links) > 3 else ''}): MuJoCo guessed {mass:.1f} kg for them from their collision "
        f"shapes at the density of water, so gravity, servo gains and effective masses are guesses; {fix}"),
        stacklevel=3)


def robot_from_spec(spec: mujoco.MjSpec, name: str, vel_by_name: dict | None = None,
                    default_vel_limit: float = np.pi, default_acc_limit: float = 15.0, path: str = "") -> Robot:
    """A Robot of any spec: servos added where it has none, near links excluded, a home inside the limits."""
    try:
        model = spec.compile()
    except ValueError as e:
        raise DesignError(f"robot: MuJoCo could not compile '{path or name}': {e}") from None
    moving = [model.body(b).name for b in range(1, model.nbody) if model.body_weldid[b] != 0]
    joints = [model.joint(j).name for j in range(model.njnt)
              if int(model.jnt_type[j]) in (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE))]
    if model.nu == 0 and joints:
        # kp scaled by the mass each joint carries: stiff enough to hold the arm against gravity;
        # joints without armature or damping get the built-ins' (0.1 kg m^2, 1 N m s), so the
        # servos stay stable at a 2 ms step on light wrist links
        carried = [float(model.body_subtreemass[model.jnt_bodyid[model.joint(j).id]]) for j in joints]
        _add_position_actuators(spec, joints, [max(200.0, 400.0 * m) for m in carried])
        for j in joints:
            sj = spec.joint(j)
            sj.armature = float(sj.armature) or 0.1
            if not np.any(sj.damping):
                sj.damping = np.full_like(np.asarray(sj.damping, float), 1.0)
    _exclude_tree_neighbours(spec, model)
    home = model.key_qpos[0].copy() if model.nkey else _inside_limits(model)
    try:
        _set_home_key(spec, home)
        model = spec.compile()
    except ValueError as e:
        raise DesignError(f"robot: MuJoCo could not compile '{path or name}': {e}") from None
    vel = np.full(model.nv, default_vel_limit)
    for jname, v in (vel_by_name or {}).items():
        jid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, jname)
        if jid >= 0 and v > 0:
            vel[model.jnt_dofadr[jid]] = v
    return Robot(name, spec, model, vel_limits=vel, acc_limits=np.full(model.nv, default_acc_limit),
                 home=home, arm_bodies=moving)


def _inside_limits(model: mujoco.MjModel) -> np.ndarray:
    """qpos0 with every limited hinge/slide joint moved inside its range (the middle if 0 is outside)."""
    q = model.qpos0.copy()
    for j in range(model.njnt):
        if model.jnt_limited[j] and int(model.jnt_type[j]) in (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE)):
            lo, hi = model.jnt_range[j]
            a = model.jnt_qposadr[j]
            if not lo <= q[a] <= hi:
                q[a] = 0.5 * (lo + hi)
    return q


def _exclude_tree_neighbours(spec: mujoco.MjSpec, model: mujoco.MjModel, reach: int = 2) -> None:
    """No contacts between moving links at most `reach` joints apart (their shapes meet at the
    joints); bodies welded together (fixed joints) count as one link."""
    weld = model.body_weldid
    parent = {int(w): int(weld[model.body_parentid[w]]) for w in set(weld.tolist()) if w != 0}
    members: dict[int, list[str]] = {}
    for b in range(1, model.nbody):
        members.setdefault(int(weld[b]), []).append(model.body(b).name)
    done = {frozenset((e.bodyname1, e.bodyname2)) for e in spec.excludes}
    for w in parent:
        a, hops = w, 0
        while a in parent and hops < reach:
            a, hops = parent[a], hops + 1
            for b1 in members[w]:
                for b2 in members.get(a, []):
                    if frozenset((b1, b2)) not in done:
                        spec.add_exclude(bodyname1=b1, bodyname2=b2)
                        done.add(frozenset((b1, b2)))


def mesh_ur5(folder: Path, sections: int = 64) -> Robot:
    """The UR5 with every capsule/cylinder link geom replaced by a fine STL mesh of the same shape."""
    import trimesh

    robot = build_ur5()
    spec = robot.spec
    model = robot.model
    for g in list(spec.geoms):
        gid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, g.name)
        kind = int(model.geom_type[gid])
        if model.body_weldid[model.geom_bodyid[gid]] == 0 or kind not in (
                int(mujoco.mjtGeom.mjGEOM_CAPSULE), int(mujoco.mjtGeom.mjGEOM_CYLINDER)):
            continue
        r, half = model.geom_size[gid][:2]
        if kind == int(mujoco.mjtGeom.mjGEOM_CAPSULE):
            mesh = trimesh.creation.capsule(height=2 * half, radius=r, count=[sections, sections])
        else:
            mesh = trimesh.creation.cylinder(radius=r, height=2 * half, sections=sections)
        path = folder / f"{g.name}.stl"
        mesh.export(str(path))
        spec.add_mesh(name=g.name, file=str(path))
        mass = float(model.body_mass[model.geom_bodyid[gid]]) if g.name.endswith("_0") else 0.2
        g.type, g.meshname, g.fromto = mujoco.mjtGeom.mjGEOM_MESH, g.name, [np.nan] * 6
        g.pos, g.quat, g.mass = model.geom_pos[gid].tolist(), model.geom_quat[gid].tolist(), mass
    robot.model = spec.compile()
    return robot
