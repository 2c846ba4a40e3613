"""Probing scenes: mocap spheres pressing into the top of skinned links and sliding along them,
on the UR5 held at home by its servos (the sensing bench and the trade sweep use them), and the
ground truth a readout is judged against (`Probes.truth`)."""
from __future__ import annotations

import mujoco
import numpy as np
from scipy.spatial import cKDTree

from skinsafe.core.design.sample import make_sample_design
from skinsafe.core.robot.kinematics import TaxelKinematics, body_ids
from skinsafe.core.robot.models import Robot
from skinsafe.core.sim.scene import Obstacle, SceneOptions, build_scene, taxel_cell

BASE_PITCH, BASE_COUNT = 0.01, 2149  # the UR5 sample skin at 1 cm pitch has 2,149 taxels
PROBE_R, DEPTH, SLIDE, SLIDE_HZ = 0.015, 0.005, 0.02, 1.0


def probe_bodies(design, n: int = 3) -> list[str]:
    """The `n` skinned links with the most taxels (ties to the link listed first): on the UR5
    sample skin at any pitch, upper_arm_link, forearm_link and wrist_1_link."""
    counts = np.bincount(design.taxels.body, minlength=len(design.bodies))
    return [design.bodies[i] for i in np.argsort(-counts, kind="stable")[:n] if counts[i]]


def design_for(n_target: int):
    """The UR5 sample skin with its pitch scaled to about `n_target` taxels."""
    return make_sample_design("ur5", pitch=BASE_PITCH * np.sqrt(BASE_COUNT / n_target))


class Probes:
    """Mocap probes pressing into the top of skinned links (`bodies`, default `probe_bodies`) and sliding along them."""

    def __init__(self, design, robot: Robot, bodies=None):

        self.q = settled(robot)
        kin = TaxelKinematics(robot.model, design)
        pos, frames = kin.poses(self.q)
        self.centres, self.axes = [], []
        for b in bodies or probe_bodies(design):
            on = np.flatnonzero(np.asarray(design.bodies)[design.taxels.body] == b)
            up = on[np.argsort(-frames[on, 2, 2], kind="stable")[:64]]  # the most upward-facing taxels
            inside = _inside(pos[on], pos[up], frames[up, :, 1])
            i = up[np.argmax(inside)] if inside.any() else up[0]  # facing up, the probe sliding over skin
            self.centres.append(pos[i] + frames[i][:, 2] * (PROBE_R - DEPTH))
            self.axes.append(frames[i][:, 1])  # along the link
        self.obstacles = [Obstacle(f"probe{k}", "sphere", (PROBE_R,), pos=tuple(c), mocap=True)
                          for k, c in enumerate(self.centres)]
        self.obstacles.append(Obstacle("crate", "box", (0.1, 0.1, 0.1), pos=(0.6, -0.6, 0.1)))

    def truth(self, model, design) -> "Truth":
        """The ground truth of what these probes press in `model` (see `Truth`)."""
        return Truth(model, design, [model.geom(ob.name).id for ob in self.obstacles if ob.mocap])

    def move(self, data, t: float) -> None:
        s = SLIDE * np.sin(2 * np.pi * SLIDE_HZ * t)
        for k, (c, a) in enumerate(zip(self.centres, self.axes)):
            data.mocap_pos[k] = c + s * a


def _disc(rings: int = 6) -> np.ndarray:
    """Points of a hexagonal lattice inside the unit disc (x, y)."""
    k = np.arange(-rings, rings + 1)
    i, j = np.meshgrid(k, k)
    xy = np.stack([i + 0.5 * j, j * np.sqrt(3) / 2], -1).reshape(-1, 2) / rings
    return xy[(xy ** 2).sum(1) <= 1.0]


DISC = _disc()
CENTRE = ((DISC ** 2).sum(1) == 0).astype(float)  # all pressure at the contact point


class Truth:
    """What the probes really press: each probe contact's patch on the skin, split over the taxel
    cells it covers.

    A sphere of radius r pressed a depth d into a surface touches it over a disc of radius
    a = sqrt(2 r d - d^2) around the contact point, where the local indentation (the pressure of a
    thin elastic skin, Winkler's model) falls off as 1 - rho^2 / a^2. The disc is sampled on a
    hexagonal lattice; each sample belongs to the cell of the nearest taxel of the touched link
    whose normal faces the probe (cells tile the skin; a sample farther than one pitch from every
    taxel is bare surface). A taxel is pressed when a sample with pressure lands in its cell; its
    force is the contact's normal force (`mj_contactForce`) times its share of the pressure.
    Independent of the readouts: geometry and MuJoCo's contact forces only.
    """

    def __init__(self, model, design, probe_geoms, probe_radius: float = PROBE_R):
        t = design.taxels
        self.n, self.r = len(t), float(probe_radius)
        self.body_ids = body_ids(model, design)
        self.skin = -np.ones(model.nbody, np.int64)
        self.skin[self.body_ids] = np.arange(len(self.body_ids))
        self.probes = set(int(g) for g in probe_geoms)
        self.cell = taxel_cell(design) if len(design.modules) else np.full(self.n, 0.01)
        self.on = [np.flatnonzero((t.body == b) & t.enabled) for b in range(len(design.bodies))]
        self.trees = [cKDTree(t.positions[i]) if len(i) else None for i in self.on]
        self.pos, self.normals = t.positions, t.normals
        self.unsensed = 0.0  # N of contact force on bare surface (summed over calls)

    def read(self, model, data) -> np.ndarray:
        """(N,) the true force on each taxel [N]; pressed taxels are the ones > 0."""
        out = np.zeros(self.n)
        force = np.zeros(6)
        for c in range(data.ncon):
            con = data.contact[c]
            g = (int(con.geom[0]), int(con.geom[1]))
            side = 0 if g[1] in self.probes else 1 if g[0] in self.probes else -1
            if side < 0 or con.efc_address < 0:
                continue
            skin = self.skin[model.geom_bodyid[g[side]]]
            if skin < 0 or self.trees[skin] is None:
                continue
            mujoco.mj_contactForce(model, data, c, force)
            if force[0] <= 0:
                continue
            depth = max(-float(con.dist), 0.0)
            a = np.sqrt(max(2 * self.r * depth - depth ** 2, 0.0))
            frame = con.frame.reshape(3, 3)  # rows: normal (geom 0 -> geom 1), two tangents
            pts = con.pos + a * (DISC[:, :1] * frame[1] + DISC[:, 1:] * frame[2])
            weight = 1.0 - (DISC ** 2).sum(1) if a > 0 else CENTRE
            b = self.body_ids[skin]
            R, x = data.xmat[b].reshape(3, 3), data.xpos[b]
            local = (pts - x) @ R  # body frame
            outward = R.T @ frame[0] * (1.0 if side == 0 else -1.0)  # from the link toward the probe
            on = self.on[skin]
            dist, k = self.trees[skin].query(local, k=min(4, len(on)))
            dist, k = dist.reshape(len(pts), -1), on[k.reshape(len(pts), -1)]
            facing = (self.normals[k] @ outward > 0) & (dist <= self.cell[k])
            first = np.argmax(facing, axis=1)
            hit = facing[np.arange(len(pts)), first]
            taxel = k[np.arange(len(pts)), first]
            share = weight * hit
            if share.sum() <= 0:
                self.unsensed += force[0]
                continue
            self.unsensed += force[0] * (1 - share.sum() / weight.sum())
            np.add.at(out, taxel[hit], force[0] * share[hit] / weight.sum())
        return out


def _inside(pos: np.ndarray, start: np.ndarray, along: np.ndarray) -> np.ndarray:
    """(k,) True where a probe at `start` sliding +-SLIDE along `along` stays over the skin at `pos`:
    taxels lie beyond SLIDE + PROBE_R both ways along it (within a probe radius of the line)."""
    rel = pos[:, None] - start[None]  # (n, k, 3)
    d = np.einsum("jki,ki->jk", rel, along)  # d[j, k]: taxel j along k's axis
    off = np.linalg.norm(rel - d[..., None] * along[None], axis=2)
    near = off < PROBE_R
    reach = SLIDE + PROBE_R
    return ((d > reach) & near).any(axis=0) & ((d < -reach) & near).any(axis=0)


def settled(robot: Robot, seconds: float = 1.0) -> np.ndarray:
    """The joint angles the servos hold under gravity with targets at home (probes must meet these)."""
    data = mujoco.MjData(robot.model)
    data.qpos[:] = robot.home
    data.ctrl[:] = robot.home
    for _ in range(int(seconds / robot.model.opt.timestep)):
        mujoco.mj_step(robot.model, data)
    return data.qpos.copy()


def probe_scene(design, robot, obstacles, q=None, **opts):

    model = build_scene(design, robot, obstacles, SceneOptions(**opts)).compile()
    data = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, data, 0)
    data.ctrl[:] = robot.home
    if q is not None:
        data.qpos[: len(q)] = q
    return model, data
