"""A person for scenes, as ISO/TS 15066 body regions (`body_regions.REGIONS`).

Only the regions a scene asks for are built. Each `Part` is a body whose mass is the region's
effective mass (Table A.3), held up by gravity compensation, on three slide joints (world x, y, z)
and three hinges, and moved by the person's muscles (`drive`, every physics step): a spring of
`attach_N_per_m` (N/m; damping ratio `attach_damping`, light: ISO's m_H is a free mass on the time
scale of an impact) toward the pose the person intends (`move`), its force limited in magnitude to
`push_N`; the rotations alike at the part's radius of gyration r_g = sqrt(I/m) (stiffness
`attach_N_per_m r_g^2`, torque up to `push_N r_g`: the same frequency as the translation, which an
explicit damper keeps stable; a lever of 0.1 m on a 2 cm fist went unstable at a 2 ms step and
flung it into the robot). A push from the robot moves the part and the person
pulls back, but never harder than a person can: a part pinned by the robot sees at most the
robot's push plus `push_N`, not an unbounded spring.

Contact with a region uses its spring constant k (N/m) through MuJoCo's direct (negative) solref
form on explicit contact pairs between the part and every robot collision geom. With solref
`(-S, -B)` MuJoCo's soft contact moves in constraint space as `r'' = (1 - d) a0 - S r - B r'` (d the
impedance, a0 the acceleration the other forces give; measured: a free impact peaks at
`v sqrt(k / A)` for `S = k A` at any d, a steady push F sinks `(1 - d) F / k`). At MuJoCo's usual
d = 0.9-0.99 a sustained push (a servo pressing, a clamp) would meet a contact 10-100 times stiffer
than k; a small d makes the contact an explicit spring that a servo pressing a 0.6 kg hand drives
unstable at a 2 ms step (measured: d = 0.01 and 0.1 blew up, 0.2 in one of two presses). So
`CONTACT_D` = 0.3 (a steady press meets k / 0.7), `S = k A`, `B = 2 zeta sqrt(k A)`, with
`A = a^T M^-1 a` the contact's inverse effective mass (`a` the normal's Jacobian row, robot side
minus the part's): the impact is the region's k exactly, a press within 1.43 k.
This needs the elliptic friction cone (`attach` sets it): with the pyramidal one a small impedance
multiplies the normal force (measured at d = 0.01: a 274 N impact gave 1,016 N). `update` computes A for every robot-part
pair at their closest points from the model itself (`mj_jac`, `mj_solveM`) each control tick: the
spring is the region's k at any robot pose, whatever robot link meets it (not one robot mass for
every region).

Fixtures (`attach(..., fixtures=...)`, e.g. the table a hand rests on) collide with the parts too.
A part pressed against a fixture by the robot (`state`: `trapped`) is compressed between two
contacts; the fixture's (`FIXTURE_D` 0.5, `FIXTURE_RATIO` 2: 2k in an impact, a steady press sinks
F / 4k) in series with the robot's (0.7 F / k) give 0.95 F / k, the region's clamping stiffness k
(a stiffer fixture would need a shorter timestep: the part between two springs rings at
`sqrt((k_1 + k_2) / m_H)`).
"""
from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np
from scipy.spatial.transform import Rotation

from skinsafe.core.sim.body_regions import Region, region
from skinsafe.core.sim.scene import Obstacle
from skinsafe.core.skin.model import DesignError

CONTACT_D = 0.3  # contact impedance (solimp dmin = dmax): the spring mostly the reference's (module doc)
FIXTURE_D = 0.5  # a fixture's impedance
FIXTURE_RATIO = 2.0  # a fixture's spring in an impact, in the region's k
NEAR = 0.25  # m: pairs farther apart than this keep their last spring (no contact can form within a tick)
OPPOSED = -0.5  # cosine below which two pushes on a part oppose (trapped or pinched)


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


@dataclass
class PartState:
    """What the parts feel at one physics step (arrays over parts): `robot_N` the normal force from
    the robot, `fixture_N` from fixtures, `trapped` pressed by the robot against a fixture,
    `pinched` pressed from opposite sides by the robot, `body` the robot body of the strongest
    robot contact (-1: none)."""

    robot_N: np.ndarray
    fixture_N: np.ndarray
    trapped: np.ndarray
    pinched: np.ndarray
    body: np.ndarray


class Human:
    """The person of a scene: `obstacles()` for `build_scene`, then `attach(spec, robot_geoms)` on
    the returned spec; after compiling, `bind(model)`; each control tick `move` and `update(data)`,
    each physics step `drive(data)` before it and `state(data)` (or `forces`) after."""

    def __init__(self, parts, attach_N_per_m: float = 1500.0, attach_damping: float = 0.2,
                 contact_damping: float = 0.1, friction: float = 0.5, push_N: float = 200.0):
        self.parts = list(parts)
        names = [p.region for p in self.parts]
        if not self.parts or len(set(names)) != len(names):
            raise DesignError(f"human: give each body region once (got {names})")
        self.regions: list[Region] = [region(n) for n in names]
        for name, value, ok in (("attach_N_per_m", attach_N_per_m, attach_N_per_m > 0),
                                ("push_N", push_N, push_N > 0),
                                ("contact_damping", contact_damping, 0 <= contact_damping <= 2)):
            if not (np.isfinite(value) and ok):
                raise DesignError(f"human: '{name}' is {value}; give a positive number "
                                  "(contact_damping a ratio in [0, 2])")
        self.attach_k, self.push_N = float(attach_N_per_m), float(push_N)
        self.attach_damping, self.contact_damping, self.friction = attach_damping, float(contact_damping), friction
        self.fixture_names: tuple = ()

    def obstacles(self) -> list[Obstacle]:
        """Free bodies with the regions' effective masses (pass them to `build_scene`)."""
        return [Obstacle(p.name, p.kind, tuple(p.size), pos=tuple(p.pos), quat=tuple(p.quat), rgba=tuple(p.rgba),
                         free=True, mass=r.mass_kg) for p, r in zip(self.parts, self.regions)]

    def _solref(self, k: float, inv_mass: float, share: int = 1) -> list[float]:
        """(-stiffness, -damping) of a spring k (N/m) on a contact of inverse effective mass A, one
        of `share` contacts in parallel (each k/share and c/share)."""
        return [-k * inv_mass / share, -2.0 * self.contact_damping * np.sqrt(k * inv_mass) / share]

    def attach(self, spec: mujoco.MjSpec, robot_geoms, fixtures=()) -> None:
        """Make each part's joints and force-limited actuators (toward the intended pose) and its
        contact pairs with `robot_geoms` and `fixtures` (geom names)."""
        names = [p.name for p in self.parts]
        spec.option.cone = mujoco.mjtCone.mjCONE_ELLIPTIC  # module docstring
        for p, reg in zip(self.parts, self.regions):
            body = spec.body(p.name)
            body.gravcomp = 1.0  # the person holds the part up
            for j in list(spec.joints):
                if j.parent.name == p.name:
                    spec.delete(j)
            R = Rotation.from_quat(np.roll(np.asarray(p.quat, float), -1)).as_matrix()  # body -> world
            for axis, tag in zip(R.T, "xyz"):  # world x, y, z in the body frame
                body.add_joint(name=f"{p.name}_{tag}", type=mujoco.mjtJoint.mjJNT_SLIDE, axis=axis.tolist())
            for axis, tag in zip(np.eye(3), "xyz"):  # intrinsic X-Y-Z rotations about the part
                body.add_joint(name=f"{p.name}_r{tag}", type=mujoco.mjtJoint.mjJNT_HINGE, axis=axis.tolist())
            geom = spec.geom(p.name)
            geom.contype, geom.conaffinity = 0, 0  # contacts only through the pairs below
            friction = [self.friction, self.friction, 0.005, 0.0001, 0.0001]
            for g in robot_geoms:  # solref set by `update` from the pose; a 10 kg robot until then
                spec.add_pair(geomname1=g, geomname2=p.name, condim=3, friction=friction,
                              solimp=[CONTACT_D, CONTACT_D, 0.001, 0.5, 2.0],
                              solref=self._solref(reg.k_N_per_m, 1 / reg.mass_kg + 0.1))
            for g in fixtures:  # fixed: the part's own mass
                spec.add_pair(geomname1=g, geomname2=p.name, condim=3, friction=friction,
                              solimp=[FIXTURE_D, FIXTURE_D, 0.001, 0.5, 2.0],
                              solref=self._solref(FIXTURE_RATIO * reg.k_N_per_m, 1 / reg.mass_kg))
        for i, a in enumerate(names):
            for b in names[i + 1:]:
                spec.add_exclude(bodyname1=a, bodyname2=b)
        self.fixture_names = tuple(fixtures)

    def bind(self, model: mujoco.MjModel) -> None:
        """Look up the ids the per-step calls use; remember the model (whose pair springs `update`
        sets). Every part is meant to be at its initial pose until `move`."""
        self.model = model
        self.target = np.zeros((len(self.parts), 6))  # slide and hinge positions the person means
        m = np.array([r.mass_kg for r in self.regions])[:, None]
        inertia = np.array([model.body_inertia[model.body(p.name).id] for p in self.parts])  # (P, 3) principal
        self._gyration = np.sqrt(inertia.mean(axis=1) / m[:, 0])  # (P,) m
        self._kp = np.c_[np.full((len(m), 3), self.attach_k), self.attach_k * inertia / m]
        self._kv = 2.0 * self.attach_damping * np.sqrt(self._kp * np.c_[np.repeat(m, 3, 1), inertia])
        self.geom = np.array([model.geom(p.name).id for p in self.parts])
        self.body = np.array([model.body(p.name).id for p in self.parts])
        self.slide = np.array([model.jnt_qposadr[model.joint(f"{p.name}_x").id] for p in self.parts])
        self.dof = np.array([model.jnt_dofadr[model.joint(f"{p.name}_x").id] for p in self.parts])
        fixture = {model.geom(g).id for g in self.fixture_names}
        pairs = []  # (pair index, part, other geom, is fixture)
        for i in range(model.npair):
            k = np.flatnonzero(self.geom == model.pair_geom2[i])
            if len(k):
                pairs.append((i, int(k[0]), int(model.pair_geom1[i]), int(model.pair_geom1[i]) in fixture))
        self.robot_pairs = [(i, k, g) for i, k, g, f in pairs if not f]
        self.fixture_geoms = np.array(sorted(fixture), dtype=int)
        self.inv_mass = np.zeros(model.npair)  # A of each robot pair at its last update
        self.points = np.ones(len(self.parts), int)  # robot contact points per part at the last step (>= 1)
        self._normal = {}

    def move(self, part: int, pos, quat=None) -> None:
        """Set where part `part` (index into `parts`) is meant to be (world position, and
        orientation as a quaternion w, x, y, z); its actuators pull it there."""
        p = self.parts[part]
        self.target[part, :3] = np.asarray(pos, float) - np.asarray(p.pos, float)
        if quat is not None:
            rel = Rotation.from_quat(np.roll(np.asarray(p.quat, float), -1)).inv() * \
                Rotation.from_quat(np.roll(np.asarray(quat, float), -1))
            self.target[part, 3:] = rel.as_euler("XYZ")

    def drive(self, data: mujoco.MjData) -> None:
        """Before a physics step: the springs shared among the contacts the step will have (module
        docstring), and the person's muscles: per part a damped spring toward its target, the force
        (and the torque) saturated in magnitude at `push_N` (`push_N` at the radius of gyration)."""
        m = self.model
        mujoco.mj_kinematics(m, data)
        mujoco.mj_collision(m, data)
        points = np.zeros(len(self.parts), int)
        for i in range(data.ncon):
            g1, g2 = data.contact.geom[i]
            for g, other in ((g1, g2), (g2, g1)):
                k = np.flatnonzero(self.geom == g)
                if len(k) and other not in self.fixture_geoms and other not in self.geom:
                    points[k[0]] += 1
        points = np.maximum(points, 1)
        changed = np.flatnonzero(points != self.points)
        if len(changed):
            self.points = points
            self._set_springs(set(changed.tolist()))
        for k, dof in enumerate(self.dof):
            s = self.slide[k]
            err = self.target[k] - data.qpos[s:s + 6]
            u = self._kp[k] * err - self._kv[k] * data.qvel[dof:dof + 6]
            for part, limit in ((u[:3], self.push_N), (u[3:], self.push_N * self._gyration[k])):
                norm = np.linalg.norm(part)
                if norm > limit:
                    part *= limit / norm
            data.qfrc_applied[dof:dof + 6] = u

    def place(self, data: mujoco.MjData, part: int, pos) -> None:
        """Put part `part` at `pos` now, unturned and at rest (and mean it to be there)."""
        self.target[part] = 0.0
        self.move(part, pos)
        s = self.slide[part]
        data.qpos[s:s + 6] = self.target[part]
        data.qvel[self.dof[part]:self.dof[part] + 6] = 0.0

    def position(self, data: mujoco.MjData, part: int) -> np.ndarray:
        """Where part `part` is now (world)."""
        return data.xpos[self.body[part]].copy()

    def velocity(self, data: mujoco.MjData, part: int) -> np.ndarray:
        """How fast part `part` moves now (world, m/s: its slide joints)."""
        return data.qvel[self.dof[part]:self.dof[part] + 3].copy()

    def update(self, data: mujoco.MjData) -> None:
        """Set every robot-part pair's spring from the contact's inverse effective mass at the
        pair's closest points (module docstring); pairs farther than `NEAR` keep theirs."""
        m, d = self.model, data
        fromto = np.zeros(6)
        jr, jh = np.zeros((3, m.nv)), np.zeros((3, m.nv))
        x = np.zeros((1, m.nv))
        for i, k, g in self.robot_pairs:
            dist = mujoco.mj_geomDistance(m, d, g, int(self.geom[k]), NEAR, fromto)
            if dist >= NEAR:
                continue
            pr, ph = fromto[:3].copy(), fromto[3:].copy()
            n = ph - pr
            if dist > 1e-4:
                n /= np.linalg.norm(n)
                self._normal[i] = n
            else:  # touching: keep the normal from before the contact (or point at the part's centre)
                c = d.xpos[self.body[k]] - pr
                n = self._normal.get(i, c / max(np.linalg.norm(c), 1e-9))
            mujoco.mj_jac(m, d, jr, None, pr, int(m.geom_bodyid[g]))
            mujoco.mj_jac(m, d, jh, None, ph, int(self.body[k]))
            a = (n @ jr - n @ jh)[None]
            mujoco.mj_solveM(m, d, x, a)
            self.inv_mass[i] = float(a[0] @ x[0])
        self._set_springs(range(len(self.parts)))

    def _set_springs(self, parts) -> None:
        for i, k, _ in self.robot_pairs:
            if k in parts and self.inv_mass[i] > 0:
                self.model.pair_solref[i] = self._solref(self.regions[k].k_N_per_m, self.inv_mass[i], self.points[k])

    def state(self, data: mujoco.MjData) -> PartState:
        """What each part feels now (`PartState`, from `mj_contactForce`)."""
        P = len(self.parts)
        robot, fixture = np.zeros(P), np.zeros(P)
        push_r, push_f = np.zeros((P, 3)), np.zeros((P, 3))
        best, body = np.zeros(P), -np.ones(P, int)
        f = np.zeros(6)
        con = data.contact
        for i in range(data.ncon):
            g1, g2 = con.geom[i]
            side = 1.0 if g2 in self.geom else -1.0 if g1 in self.geom else 0.0
            if not side or con.efc_address[i] < 0:
                continue
            if side < 0:  # the part is geom1 (MuJoCo orders a pair's geoms by type)
                g1, g2 = g2, g1
            k = int(np.flatnonzero(self.geom == g2)[0])
            mujoco.mj_contactForce(self.model, data, i, f)
            push = side * con.frame[i][:3] * f[0]  # on the part, along the normal from geom1 to geom2
            if g1 in self.fixture_geoms:
                fixture[k] += f[0]
                push_f[k] += push
            else:
                robot[k] += f[0]
                push_r[k] += push
                if f[0] > best[k]:
                    best[k], body[k] = f[0], int(self.model.geom_bodyid[g1])
        nr, nf = np.linalg.norm(push_r, axis=1), np.linalg.norm(push_f, axis=1)
        trapped = (nr > 0) & (nf > 0) & (np.einsum("ij,ij->i", push_r, push_f) < OPPOSED * nr * nf)
        pinched = (robot > 0) & (nr < (1 + OPPOSED) * robot)  # robot pushes that largely cancel
        return PartState(robot, fixture, trapped, pinched, body)

    def forces(self, data: mujoco.MjData) -> np.ndarray:
        """(parts,) total normal contact force (N) on each part from the robot."""
        return self.state(data).robot_N


def robot_collision_geoms(model: mujoco.MjModel, bodies) -> list[str]:
    """Names of the geoms that collide on `bodies` (the robot links a person can touch)."""
    ids = {model.body(b).id for b in bodies}
    return [model.geom(g).name for g in range(model.ngeom)
            if model.geom_bodyid[g] in ids and (model.geom_contype[g] or model.geom_conaffinity[g])
            and model.geom(g).name]
