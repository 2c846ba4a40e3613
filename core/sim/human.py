"""A person for scenes, as ISO/TS 15066 body regions (`skinsafe.core.safety.pfl.REGIONS`).

Only the regions a scene asks for are built. Each `Part` is a free body whose mass is the region's
effective mass (Table A.3), held up by gravity compensation and moved through a compliant
attachment: three slide joints and a ball joint whose springs (`attach_N_per_m`, N/m, damping
ratio `attach_damping`, light: ISO's m_H is a free mass on the time scale of an impact) pull it toward the pose the person intends (`move` sets the springs' set
points), so a push from the robot moves the part and the attachment pulls back. (An equality
constraint is not a spring in MuJoCo: at impedance d it cancels a fraction d of any push.)

Contact with a region uses its spring constant k (N/m) through MuJoCo's direct (negative) solref
form on explicit contact pairs between the part and every robot collision geom. MuJoCo's direct
stiffness is a reference acceleration per metre of penetration in constraint space: at impedance
`dmax` the contact's relative normal acceleration is `-stiffness * r - damping * v`, and the force
is that times the reduced mass mu of the two bodies. A physical spring of k N/m is therefore
`stiffness = k / mu_ref`, with `mu_ref = (1/m_H + 1/m_R,ref)^-1`, m_R,ref the robot's effective
mass where the scene expects the contact (`robot_mass`; the PFL tools give it per taxel). Where
the actual m_R differs the spring is `k * mu / mu_ref` (for a hand, 0.6 kg, against 5-50 kg of
robot, within 10%). The damping is a small ratio `contact_damping` of critical.
"""
from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from skinsafe.core.sim.body_regions import Region, region
from skinsafe.core.sim.scene import Obstacle
from skinsafe.core.skin.model import DesignError

CONTACT_DMAX = 0.99  # contact impedance (solimp dmin = dmax): the spring acts almost fully
ROT_ARM = 0.1  # m: the rotational attachment is the translational one at this lever arm


@dataclass
class Part:
    """One body region of the person: a geom (MuJoCo size semantics) at an initial pose."""

    region: str  # a key of body_regions.REGIONS
    kind: str  # "capsule" | "sphere" | "box"
    size: tuple
    pos: tuple = (0, 0, 0)
    quat: tuple = (1, 0, 0, 0)
    rgba: tuple = (0.85, 0.65, 0.55, 1)

    @property
    def name(self) -> str:
        return f"human_{self.region}"


class Human:
    """The person of a scene: `obstacles()` for `build_scene`, then `attach(spec, robot_geoms)` on
    the returned spec; after compiling, `bind(model)` and per step `move`/`forces`."""

    def __init__(self, parts, robot_mass: float = 10.0, attach_N_per_m: float = 1500.0,
                 attach_damping: float = 0.2, contact_damping: float = 0.1, friction: float = 0.5):
        self.parts = list(parts)
        names = [p.region for p in self.parts]
        if not self.parts or len(set(names)) != len(names):
            raise DesignError(f"human: give each body region once (got {names})")
        self.regions: list[Region] = [region(n) for n in names]
        for name, value in (("robot_mass", robot_mass), ("attach_N_per_m", attach_N_per_m)):
            if not (np.isfinite(value) and value > 0):
                raise DesignError(f"human: '{name}' is {value}; give a positive number")
        self.robot_mass, self.attach_k = float(robot_mass), float(attach_N_per_m)
        self.attach_damping, self.contact_damping, self.friction = attach_damping, contact_damping, friction

    def obstacles(self) -> list[Obstacle]:
        """Free bodies with the regions' effective masses (pass them to `build_scene`)."""
        return [Obstacle(p.name, p.kind, tuple(p.size), pos=tuple(p.pos), quat=tuple(p.quat), rgba=tuple(p.rgba),
                         free=True, mass=r.mass_kg) for p, r in zip(self.parts, self.regions)]

    def contact_solref(self, reg: Region) -> tuple[float, float]:
        """(-stiffness, -damping) for a contact with `reg` (module docstring)."""
        mu = 1.0 / (1.0 / reg.mass_kg + 1.0 / self.robot_mass)
        stiff = reg.k_N_per_m / mu
        return -stiff, -2.0 * self.contact_damping * np.sqrt(stiff)

    def attach(self, spec: mujoco.MjSpec, robot_geoms) -> None:
        """Make each part's attachment (three slide joints and a ball joint, springs toward the
        intended pose) and its contact pairs with `robot_geoms`."""
        names = [p.name for p in self.parts]
        k_rot = self.attach_k * ROT_ARM ** 2
        for p, reg in zip(self.parts, self.regions):
            body = spec.body(p.name)
            body.gravcomp = 1.0  # the person holds the part up
            for j in list(spec.joints):
                if j.parent.name == p.name:
                    spec.delete(j)
            c = 2.0 * self.attach_damping  # damping ratio -> 2 zeta sqrt(k m)
            for axis, tag in zip(np.eye(3), "xyz"):
                body.add_joint(name=f"{p.name}_{tag}", type=mujoco.mjtJoint.mjJNT_SLIDE, axis=axis.tolist(),
                               stiffness=[self.attach_k], damping=c * np.sqrt(self.attach_k * reg.mass_kg))
            body.add_joint(name=f"{p.name}_rot", type=mujoco.mjtJoint.mjJNT_BALL, stiffness=[k_rot],
                           damping=c * np.sqrt(k_rot * reg.mass_kg * ROT_ARM ** 2))
            geom = spec.geom(p.name)
            geom.contype, geom.conaffinity = 0, 0  # contacts only through the pairs below
            stiff, damp = self.contact_solref(reg)
            for g in robot_geoms:
                spec.add_pair(geomname1=g, geomname2=p.name, condim=3, solref=[stiff, damp],
                              solimp=[CONTACT_DMAX, CONTACT_DMAX, 0.001, 0.5, 2.0],
                              friction=[self.friction, self.friction, 0.005, 0.0001, 0.0001])
        for i, a in enumerate(names):
            for b in names[i + 1:]:
                spec.add_exclude(bodyname1=a, bodyname2=b)

    def bind(self, model: mujoco.MjModel) -> None:
        """Look up the ids the per-step calls use (and remember the model, whose spring set
        points `move` changes)."""
        self.model = model
        self.geom = np.array([model.geom(p.name).id for p in self.parts])
        self.body = np.array([model.body(p.name).id for p in self.parts])
        self.slide = np.array([model.jnt_qposadr[model.joint(f"{p.name}_x").id] for p in self.parts])
        self.ball = np.array([model.jnt_qposadr[model.joint(f"{p.name}_rot").id] for p in self.parts])
        self.dof = np.array([model.jnt_dofadr[model.joint(f"{p.name}_x").id] for p in self.parts])

    def move(self, part: int, pos, quat=None) -> None:
        """Set where part `part` (index into `parts`) is meant to be (world position, and
        orientation as a quaternion w, x, y, z); its springs pull it there."""
        p = self.parts[part]
        self.model.qpos_spring[self.slide[part]:self.slide[part] + 3] = np.asarray(pos, float) - np.asarray(p.pos, float)
        if quat is not None:
            rel = np.zeros(4)
            inv = np.zeros(4)
            mujoco.mju_negQuat(inv, np.asarray(p.quat, float))
            mujoco.mju_mulQuat(rel, inv, np.asarray(quat, float))
            self.model.qpos_spring[self.ball[part]:self.ball[part] + 4] = rel

    def position(self, data: mujoco.MjData, part: int) -> np.ndarray:
        """Where part `part` is now (world)."""
        return data.xpos[self.body[part]].copy()

    def forces(self, data: mujoco.MjData) -> np.ndarray:
        """(parts,) total normal contact force (N) on each part, from `mj_contactForce`."""
        out = np.zeros(len(self.parts))
        f = np.zeros(6)
        con = data.contact
        for i in range(data.ncon):
            g1, g2 = con.geom[i]
            k = np.flatnonzero((self.geom == g1) | (self.geom == g2))
            if len(k) and con.efc_address[i] >= 0:
                mujoco.mj_contactForce(self.model, data, i, f)
                out[k[0]] += f[0]
        return out


def robot_collision_geoms(model: mujoco.MjModel, bodies) -> list[str]:
    """Names of the geoms that collide on `bodies` (the robot links a person can touch)."""
    ids = {model.body(b).id for b in bodies}
    return [model.geom(g).name for g in range(model.ngeom)
            if model.geom_bodyid[g] in ids and (model.geom_contype[g] or model.geom_conaffinity[g])
            and model.geom(g).name]
