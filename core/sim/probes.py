"""Probing scenes: mocap spheres pressing into the top of skinned links and sliding along them,
on the UR5 held at home by its servos (the sensing bench and the trade sweep use them)."""
from __future__ import annotations

import mujoco
import numpy as np

from skinsafe.core.design.sample import make_sample_design
from skinsafe.core.robot.kinematics import TaxelKinematics
from skinsafe.core.robot.models import Robot
from skinsafe.core.sim.scene import Obstacle, SceneOptions, build_scene

BASE_PITCH, BASE_COUNT = 0.01, 2149  # the UR5 sample skin at 1 cm pitch has 2,149 taxels
PROBE_BODIES = ["upper_arm_link", "forearm_link", "wrist_1_link"]
PROBE_R, DEPTH, SLIDE, SLIDE_HZ = 0.015, 0.005, 0.02, 1.0


def design_for(n_target: int):
    """The UR5 sample skin with its pitch scaled to about `n_target` taxels."""
    return make_sample_design("ur5", pitch=BASE_PITCH * np.sqrt(BASE_COUNT / n_target))


class Probes:
    """Mocap probes pressing into the top of some skinned links and sliding along them."""

    def __init__(self, design, robot: Robot, bodies=PROBE_BODIES):

        self.q = settled(robot)
        kin = TaxelKinematics(robot.model, design)
        pos, frames = kin.poses(self.q)
        self.centres, self.axes = [], []
        for b in bodies:
            on = np.flatnonzero(np.asarray(design.bodies)[design.taxels.body] == b)
            up = on[np.argsort(-frames[on, 2, 2], kind="stable")[:64]]  # the most upward-facing taxels
            inside = _inside(pos[on], pos[up], frames[up, :, 1])
            i = up[np.argmax(inside)] if inside.any() else up[0]  # facing up, the probe sliding over skin
            self.centres.append(pos[i] + frames[i][:, 2] * (PROBE_R - DEPTH))
            self.axes.append(frames[i][:, 1])  # along the link
        self.obstacles = [Obstacle(f"probe{k}", "sphere", (PROBE_R,), pos=tuple(c), mocap=True)
                          for k, c in enumerate(self.centres)]
        self.obstacles.append(Obstacle("crate", "box", (0.1, 0.1, 0.1), pos=(0.6, -0.6, 0.1)))

    def move(self, data, t: float) -> None:
        s = SLIDE * np.sin(2 * np.pi * SLIDE_HZ * t)
        for k, (c, a) in enumerate(zip(self.centres, self.axes)):
            data.mocap_pos[k] = c + s * a


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
