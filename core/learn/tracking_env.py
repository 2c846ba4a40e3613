"""The modulation-layer task of the paper (Fig. 11) as a Gymnasium environment: a UR5 with the sample
skin follows a joint-space sweep among compliant balls, simulated in MuJoCo.

The desired path `q_d(t)` pans the shoulder from -1 rad to 1 and back in `duration` seconds; every
other joint is held at home. `n_balls` solid balls sit under the forearm/wrist at evenly spread
times of the outward sweep, reaching `penetration` into the arm's nominal sweep: by construction
the exact path touches every ball (the paper places "several solid balls along the trajectory to
generate collision"), so a controller can only avoid contact by leaving the path.
`TrackingScene.path_contact_ticks` counts the ticks at which the desired configuration itself
overlaps a ball (taxel positions within a ball's radius).

Action: joint velocities (6,) in rad/s (clipped to the robot's limits, integrated into the
position servos' targets, which never run more than `lead` ahead of the joints). Observation:
`[q (6), q_d (6), qdot_d (6)]` at the start of the tick. Reward: minus the end-effector distance
to the desired path (m); cost: 1 for a tick in which any taxel's force exceeded its threshold, in
`info["cost"]`, with the per-taxel events in `info["taxel_danger"]`.
"""
from __future__ import annotations

from dataclasses import dataclass

import gymnasium as gym
import mujoco
import numpy as np

MOVING = 4  # pan, lift, elbow, wrist 1: the joints whose state the TDM sees (wrist 2 and 3 are held)


@dataclass(frozen=True)
class TrackingTask:
    """The scene and the path."""

    duration: float = 6.0  # s per episode (one sweep out and back)
    control_dt: float = 0.02  # s per control tick
    gain: float = 3.0  # 1/s, joint-space position feedback of the nominal controller
    max_error: float = 0.15  # rad, the feedback error is saturated here (no wind-up into an obstacle)
    lead: float = 0.2  # rad, most the servo target may run ahead of the joint (anti wind-up)
    pitch: float = 0.01  # sample skin pitch (m)
    n_balls: int = 3
    ball_radius: float = 0.06
    penetration: float = 0.02  # m the balls reach into the nominal sweep of the arm
    ball_solimp: tuple = (0.0, 0.1, 0.05, 0.5, 2.0)  # compliant balls (MuJoCo solimp): the arm pushes through
    jitter: float = 0.01  # m, ball position noise per seed
    traj_noise: float = 0.01  # rad, path offset noise per episode (moving joints)

    @property
    def ticks(self) -> int:
        return int(round(self.duration / self.control_dt))


class TrackingScene:
    """The UR5 + sample skin + balls as a MuJoCo model, the desired path and the skin readout."""

    def __init__(self, task: TrackingTask, seed: int):
        from skinsafe.core.design.sample import make_sample_design
        from skinsafe.core.robot.kinematics import TaxelKinematics
        from skinsafe.core.robot.models import build_ur5
        from skinsafe.core.sim.readout import SkinReadout
        from skinsafe.core.sim.scene import Obstacle, build_scene

        self.task = task
        self.robot = build_ur5()
        self.design = make_sample_design("ur5", pitch=task.pitch, robot=self.robot)
        self.kin = TaxelKinematics(self.robot.model, self.design)
        self.balls = self._ball_centers(np.random.default_rng(1000 + seed))
        obstacles = [Obstacle(f"ball{k}", "sphere", (task.ball_radius,), pos=tuple(c), rgba=(0.9, 0.5, 0.1, 1))
                     for k, c in enumerate(self.balls)]
        spec = build_scene(self.design, self.robot, obstacles)
        for k in range(len(self.balls)):  # compliant balls: the arm can push through, the skin feels it
            spec.geom(f"ball{k}").solimp = list(task.ball_solimp)
        self.model = spec.compile()
        self.data = mujoco.MjData(self.model)
        self.readout = SkinReadout(self.model, self.design)
        self.thresholds = self.design.taxels.thresholds["force"]
        self.substeps = max(1, int(round(task.control_dt / self.model.opt.timestep)))
        self.flange = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_SITE, "flange")
        self.kin_flange = mujoco.mj_name2id(self.robot.model, mujoco.mjtObj.mjOBJ_SITE, "flange")
        self.qadr = np.array([self.model.jnt_qposadr[mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_JOINT, j)]
                              for j in ("shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint",
                                        "wrist_1_joint", "wrist_2_joint", "wrist_3_joint")])

    def desired(self, t: float, offset: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """q_d(t) and its rate: a pan sweep from -1 rad to 1 and back (pan = -cos(w t))."""
        w = 2 * np.pi / self.task.duration
        amp = np.array([-1.0, 0.0, 0.0, 0.0, 0.0, 0.0])
        q = self.robot.home + amp * np.cos(w * t) + (0 if offset is None else offset)
        return q, -amp * w * np.sin(w * t)

    def _ball_centers(self, rng: np.random.Generator) -> np.ndarray:
        """Balls under the arm's sweep: below a forearm/wrist taxel at evenly spread times."""
        task, t = self.task, self.design.taxels
        names = self.design.bodies
        on = np.isin(t.body, [names.index(b) for b in ("forearm_link", "wrist_1_link") if b in names])
        out = []
        for k in range(task.n_balls):
            tk = task.duration * (0.1 + 0.3 * (k + 0.5) / task.n_balls)  # spread over the outward sweep
            pos, _ = self.kin.poses(self.desired(tk)[0])
            p = pos[on]
            lo = p[np.argsort(p[:, 2])[: max(1, len(p) // 20)]].mean(0)  # the underside
            c = lo - np.array([0, 0, task.ball_radius - task.penetration])
            out.append(c + rng.normal(0, task.jitter, 3))
        return np.array(out)

    def ball_distance(self, q: np.ndarray) -> float:
        """Smallest signed distance (m) from any taxel at joint angles q to a ball's surface (< 0: inside)."""
        return float(self.ball_distances(q).min())

    def danger_at(self, S: np.ndarray) -> np.ndarray:
        """(len(S), N) taxel events of the skin at rest at each state S (the first MOVING joint angles, the
        others at home): MuJoCo's contacts at that pose (`mj_forward`), read by the episodes' readout and
        thresholds. The label of a state nobody visited (a noisy copy of a visited one)."""
        d = mujoco.MjData(self.model)
        out = np.zeros((len(S), self.design.n_taxels), bool)
        q = self.robot.home.copy()
        for k, s in enumerate(np.asarray(S, float)):
            q[:MOVING] = s
            d.qpos[self.qadr] = q
            d.ctrl[:] = q
            mujoco.mj_forward(self.model, d)
            out[k] = self.readout.read(d) > self.thresholds
        return out

    def ball_distances(self, q: np.ndarray) -> np.ndarray:
        """(n_balls,) smallest signed distance (m) from any taxel at joint angles q to each ball's surface."""
        pos, _ = self.kin.poses(q)
        return (np.linalg.norm(pos[:, None] - self.balls[None], axis=2) - self.task.ball_radius).min(0)

    def path_contact_ticks(self) -> int:
        """Ticks at which the exact desired path itself puts a taxel inside a ball."""
        dt = self.task.control_dt
        return int(sum(self.ball_distance(self.desired((k + 1) * dt)[0]) < 0 for k in range(self.task.ticks)))

    def reset(self, q0: np.ndarray) -> None:
        mujoco.mj_resetData(self.model, self.data)
        self.data.qpos[self.qadr] = q0
        self.data.ctrl[:] = q0
        mujoco.mj_forward(self.model, self.data)


class TrackingEnv(gym.Env):
    """UR5 path tracking among balls (module doc); `nominal(obs)` is the plain velocity controller."""

    metadata = {"render_modes": []}

    def __init__(self, task: TrackingTask | None = None, seed: int = 0, scene: TrackingScene | None = None, **overrides):
        self.task = task or TrackingTask(**overrides)
        self.scene = scene or TrackingScene(self.task, seed)
        vmax = self.scene.robot.vel_limits.astype(np.float32)
        self.action_space = gym.spaces.Box(-vmax, vmax, dtype=np.float32)
        big = np.full(18, 50.0, np.float32)
        self.observation_space = gym.spaces.Box(-big, big, dtype=np.float32)
        self.offset = np.zeros(6)
        self.k = 0
        self.q_cmd = np.zeros(6)

    def _obs(self) -> np.ndarray:
        t = self.k * self.task.control_dt
        qd, vd = self.scene.desired(t + self.task.control_dt, self.offset)
        q = self.scene.data.qpos[self.scene.qadr]
        return np.concatenate([q, qd, vd]).astype(np.float32)

    def nominal(self, obs) -> np.ndarray:
        """The plain tracking command `qdot_d + K clip(q_d - q)` for an observation (6,)."""
        obs = np.asarray(obs, float)
        q, qd, vd = obs[:6], obs[6:12], obs[12:18]
        return vd + self.task.gain * np.clip(qd - q, -self.task.max_error, self.task.max_error)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.offset = self.np_random.normal(0, self.task.traj_noise, 6) * np.array([1, 1, 1, 1, 0, 0])
        self.k = 0
        q0, _ = self.scene.desired(0.0, self.offset)
        self.scene.reset(q0)
        self.q_cmd = q0.copy()
        return self._obs(), {}

    def step(self, action):
        v = np.asarray(action, float).reshape(-1)
        if v.shape != (6,):
            raise ValueError(f"TrackingEnv.step: action has shape {v.shape}; give 6 joint velocities (rad/s)")
        sc, task = self.scene, self.task
        if not np.isfinite(v).all():  # a broken command: hold the joints where they are
            v = np.zeros(6)
        vmax = sc.robot.vel_limits
        v = v * min(1.0, float(np.min(vmax / np.maximum(np.abs(v), 1e-12))))
        q = sc.data.qpos[sc.qadr].copy()
        self.q_cmd = np.clip(self.q_cmd + v * task.control_dt, q - task.lead, q + task.lead)
        sc.data.ctrl[:] = self.q_cmd
        peak = np.zeros(sc.design.n_taxels)
        for _ in range(sc.substeps):
            mujoco.mj_step(sc.model, sc.data)
            peak = np.maximum(peak, sc.readout.read(sc.data))
        danger = peak > sc.thresholds
        t = (self.k + 1) * task.control_dt
        sc.kin.update(sc.desired(t, self.offset)[0])
        ee, ee_d = sc.data.site_xpos[sc.flange].copy(), sc.kin.data.site_xpos[sc.kin_flange].copy()
        self.k += 1
        info = {"cost": float(danger.any()), "taxel_danger": danger, "ee": ee, "ee_desired": ee_d}
        return self._obs(), -float(np.linalg.norm(ee - ee_d)), False, self.k >= task.ticks, info
