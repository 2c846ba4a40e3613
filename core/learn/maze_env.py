"""The strategy-layer maze (paper Fig. 9a) as a Gymnasium environment simulated in MuJoCo.

A disc robot with a ring of taxels drives on a block maze. Four macro-actions (forward, backward,
turn left, turn right) each move a position servo toward the next cell (or the next heading) for a
few MuJoCo steps; if the skin reports a danger event on the way, the robot backs off to where it
started. Reward: +100 at the goal (the episode ends). Cost: 1 per macro-action with a contact event,
in `info["cost"]` (the safe-RL convention), with the per-taxel events in `info["taxel_danger"]`.
The observation is the robot's position and heading `[x, y, cos(yaw), sin(yaw)]`.
"""
from __future__ import annotations

import gymnasium as gym
import mujoco
import numpy as np

from skinsafe.core.safety.events import danger_events
from skinsafe.core.skin.model import Board, Module, RobotRef, SkinDesign, Taxels, frames_from_normals

# '#' wall block, 'S' start, 'G' goal, '.' free; row 0 is the top (largest y).
LAYOUT = (
    "#######",
    "#S..#.#",
    "#.#...#",
    "#.#.###",
    "#...#G#",
    "##....#",
    "#######",
)
FORWARD, BACKWARD, LEFT, RIGHT = range(4)
ACTION_NAMES = ("forward", "backward", "turn left", "turn right")
CELL = 0.4  # m
ROBOT_RADIUS = 0.14  # m
N_TAXELS = 16
FORCE_THRESHOLD = 0.5  # N


def parse_layout(layout=LAYOUT) -> tuple[np.ndarray, tuple[int, int], tuple[int, int]]:
    """(walls (R,C) bool, start (row, col), goal (row, col)) from rows of '#', '.', 'S', 'G'."""
    rows = [str(r) for r in layout]
    if not rows or len({len(r) for r in rows}) != 1:
        raise ValueError("maze layout: every row must have the same length")
    bad = {ch for r in rows for ch in r} - set("#.SG")
    if bad:
        raise ValueError(f"maze layout: unknown characters {sorted(bad)}; use '#', '.', 'S' and 'G'")
    grid = np.array([list(r) for r in rows])
    found = {}
    for ch in "SG":
        where = np.argwhere(grid == ch)
        if len(where) != 1:
            raise ValueError(f"maze layout: needs exactly one '{ch}', found {len(where)}")
        found[ch] = tuple(int(v) for v in where[0])
    walls = grid == "#"
    if not (walls[0].all() and walls[-1].all() and walls[:, 0].all() and walls[:, -1].all()):
        raise ValueError("maze layout: the border must be walls ('#') so the robot cannot leave")
    return walls, found["S"], found["G"]


def ring_skin(n_taxels: int = N_TAXELS, radius: float = ROBOT_RADIUS, threshold: float = FORCE_THRESHOLD) -> SkinDesign:
    """A ring of taxels around the robot's body (taxel 0 looks forward, counter-clockwise)."""
    ang = 2 * np.pi * np.arange(n_taxels) / n_taxels
    normals = np.stack([np.cos(ang), np.sin(ang), np.zeros(n_taxels)], axis=1)
    n = n_taxels
    taxels = Taxels(
        ids=np.arange(n, dtype=np.int64), body=np.zeros(n, np.int32), positions=radius * normals,
        frames=frames_from_normals(normals, np.array([0.0, 0.0, 1.0])), module=np.zeros(n, np.int32),
        board=np.zeros(n, np.int32), channel=np.arange(n, dtype=np.int32),
        area=np.full(n, (2 * np.pi * radius / n) * 0.02), enabled=np.ones(n, bool),
        thresholds={"force": np.full(n, float(threshold))},
    )
    design = SkinDesign(
        robot=RobotRef(kind="mjcf", name="maze_robot"), bodies=["robot"],
        modules=[Module(id=0, name="ring", body="robot", template="strip", rows=1, cols=n,
                        pitch=float(2 * np.pi * radius / n))],
        boards=[Board(id=0, name="ring board", uid=0x5A, capacity=max(n, 16))], taxels=taxels)
    design.validate("maze ring skin")
    return design


def build_maze_model(walls: np.ndarray, cell: float = CELL, radius: float = ROBOT_RADIUS) -> mujoco.MjModel:
    """MuJoCo model: wall boxes and a disc robot on planar joints (x, y, yaw) with position servos."""
    spec = mujoco.MjSpec()
    spec.option.timestep = 0.01
    spec.option.gravity = [0, 0, 0]
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    wb = spec.worldbody
    for r, c in np.argwhere(walls):
        x, y = cell_center(r, c, walls.shape[0], cell)
        wb.add_geom(name=f"wall_{r}_{c}", type=mujoco.mjtGeom.mjGEOM_BOX, size=[cell / 2, cell / 2, 0.05],
                    pos=[x, y, 0.05], rgba=[0.4, 0.4, 0.45, 1])
    body = wb.add_body(name="robot", pos=[0, 0, 0.05])
    for name, jtype, axis in (("x", mujoco.mjtJoint.mjJNT_SLIDE, [1, 0, 0]), ("y", mujoco.mjtJoint.mjJNT_SLIDE, [0, 1, 0]),
                              ("yaw", mujoco.mjtJoint.mjJNT_HINGE, [0, 0, 1])):
        body.add_joint(name=name, type=jtype, axis=axis, damping=40.0 if name != "yaw" else 2.0)
    body.add_geom(name="robot", type=mujoco.mjtGeom.mjGEOM_CYLINDER, size=[radius, 0.03, 0], mass=2.0,
                  rgba=[0.2, 0.5, 0.9, 1])
    for name, kp in (("x", 400.0), ("y", 400.0), ("yaw", 20.0)):
        act = spec.add_actuator(name=f"{name}_servo", target=name, trntype=mujoco.mjtTrn.mjTRN_JOINT)
        act.set_to_position(kp=kp)
    return spec.compile()


def cell_center(row: int, col: int, n_rows: int, cell: float = CELL) -> tuple[float, float]:
    return (col + 0.5) * cell, (n_rows - 1 - row + 0.5) * cell


class MazeEnv(gym.Env):
    """Safe-RL maze: reward +100 at the goal, `info["cost"]` 1 per contact event (see module doc)."""

    metadata = {"render_modes": []}

    def __init__(self, layout=LAYOUT, max_steps: int = 100, steps_per_phase: int = 25, n_taxels: int = N_TAXELS):
        self.walls, self.start, self.goal = parse_layout(layout)
        self.n_rows = self.walls.shape[0]
        self.model = build_maze_model(self.walls)
        self.data = mujoco.MjData(self.model)
        self.design = ring_skin(n_taxels)
        self.n_taxels = n_taxels
        self.max_steps, self.steps_per_phase = int(max_steps), int(steps_per_phase)
        self.robot_geom = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_GEOM, "robot")
        self.robot_body = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_BODY, "robot")
        self.action_space = gym.spaces.Discrete(4)
        lo = np.array([0, 0, -1, -1], np.float32)
        hi = np.array([self.walls.shape[1] * CELL, self.n_rows * CELL, 1, 1], np.float32)
        self.observation_space = gym.spaces.Box(lo, hi, dtype=np.float32)
        self._force = np.zeros(6)
        self.cell = self.start
        self.heading = 0  # multiples of 90 degrees; 0 looks along +x
        self.t = 0

    # -- state -------------------------------------------------------------------------------------
    def place(self, row: int, col: int, heading: int = 0) -> np.ndarray:
        """Put the robot at the centre of a free cell with a heading (0..3 quarter turns); returns the observation."""
        if not (0 <= row < self.n_rows and 0 <= col < self.walls.shape[1]) or self.walls[row, col]:
            raise ValueError(f"MazeEnv.place: cell ({row}, {col}) is a wall or outside the maze; pick a free cell")
        self.cell, self.heading = (int(row), int(col)), int(heading) % 4
        mujoco.mj_resetData(self.model, self.data)
        self._set_target(self.cell, self.heading, snap=True)
        return self._obs()

    def _set_target(self, cell, heading, snap=False):
        x, y = cell_center(cell[0], cell[1], self.n_rows)
        yaw = heading * np.pi / 2
        if snap:
            self.data.qpos[:] = (x, y, yaw)
            self.data.qvel[:] = 0
            mujoco.mj_forward(self.model, self.data)
        self.data.ctrl[:] = (x, y, yaw)

    def _obs(self) -> np.ndarray:
        x, y, yaw = self.data.qpos
        return np.array([x, y, np.cos(yaw), np.sin(yaw)], np.float32)

    # -- skin --------------------------------------------------------------------------------------
    def taxel_forces(self) -> np.ndarray:
        """(n_taxels,) normal force (N) of the robot's contacts binned to the nearest taxel by angle."""
        f = np.zeros(self.n_taxels)
        d = self.data
        for i in range(d.ncon):
            c = d.contact[i]
            if c.geom1 != self.robot_geom and c.geom2 != self.robot_geom:
                continue
            mujoco.mj_contactForce(self.model, d, i, self._force)
            rel = c.pos[:2] - d.xpos[self.robot_body, :2]
            ang = np.arctan2(rel[1], rel[0]) - d.qpos[2]
            k = int(np.round(ang / (2 * np.pi) * self.n_taxels)) % self.n_taxels
            f[k] += abs(self._force[0])
        return f

    # -- gym API -----------------------------------------------------------------------------------
    def reset(self, *, seed=None, options=None):
        """Back to the start cell facing +x; `options={"start": (row, col, heading)}` starts elsewhere."""
        super().reset(seed=seed)
        self.t = 0
        start = (options or {}).get("start", (*self.start, 0))
        return self.place(*start), {}

    def step(self, action):
        if not self.action_space.contains(int(action)):
            raise ValueError(f"MazeEnv.step: action {action!r} is not one of 0..3 ({', '.join(ACTION_NAMES)})")
        action = int(action)
        cell, heading = self.cell, self.heading
        if action in (FORWARD, BACKWARD):
            sign = 1 if action == FORWARD else -1
            dr, dc = ((0, 1), (-1, 0), (0, -1), (1, 0))[heading]
            cell = (cell[0] + sign * dr, cell[1] + sign * dc)
        else:
            heading = (heading + (1 if action == LEFT else -1)) % 4
        danger = self._drive(cell, heading)
        if danger.any():  # bumped: back off to where the action started
            cell, heading = self.cell, self.heading
            self._drive(cell, heading)
        self._set_target(cell, heading, snap=True)  # settle exactly on the grid
        self.cell, self.heading = cell, heading
        self.t += 1
        reached = cell == self.goal
        reward = 100.0 if reached else 0.0
        cost = float(danger.any())
        info = {"cost": cost, "taxel_danger": danger, "cell": cell, "heading": heading}
        return self._obs(), reward, reached, self.t >= self.max_steps and not reached, info

    def _drive(self, cell, heading) -> np.ndarray:
        """Servo toward (cell, heading) for one phase; (n_taxels,) bool danger events seen on the way."""
        self._set_target(cell, heading)
        thr = self.design.taxels.thresholds
        danger = np.zeros(self.n_taxels, bool)
        for _ in range(self.steps_per_phase):
            mujoco.mj_step(self.model, self.data)
            if self.data.ncon:
                danger |= danger_events({"force": self.taxel_forces()}, thr)
        return danger


def wall_moves(walls: np.ndarray) -> int:
    """How many (free cell, heading, forward/backward) moves run into a wall: the contacts a learner
    that cannot see the walls (the observation is position and heading) makes at least once each
    before it can know them, unless it never tries them."""
    n = 0
    for r, c in np.argwhere(~walls):
        for dr, dc in ((0, 1), (-1, 0), (0, -1), (1, 0)):  # heading 0..3; forward and backward per heading
            n += int(walls[r + dr, c + dc]) + int(walls[r - dr, c - dc])
    return n


def random_rollouts(env: MazeEnv, n: int, rng: np.random.Generator, length: int = 20) -> dict:
    """`n` transitions of uniformly random actions in rollouts of `length` from uniformly random (free
    cell, heading) placements (recovery-rl's offline `transition_function`). Arrays `obs`, `actions`,
    `costs`, `next_obs`, `terminated` and `dangers` (the per-taxel events)."""
    free = np.argwhere(~env.walls)
    out = {k: [] for k in ("obs", "actions", "costs", "next_obs", "terminated", "dangers")}
    while len(out["actions"]) < n:
        r, c = free[rng.integers(len(free))]
        obs, _ = env.reset(options={"start": (int(r), int(c), int(rng.integers(4)))})
        for _ in range(min(length, n - len(out["actions"]))):
            a = int(rng.integers(env.action_space.n))
            nxt, _, term, _, info = env.step(a)
            for k, v in zip(out, (obs, a, info["cost"], nxt, term, info["taxel_danger"])):
                out[k].append(v)
            obs = nxt
            if term:
                break
    return {k: np.asarray(v) for k, v in out.items()}


class MazeFeatures:
    """Network input from an observation: Gaussian bumps at every cell centre and the heading's 4 signs.

    Generic MLPs learn the maze's value function from raw `[x, y, cos, sin]` slowly; these features
    keep it a function of the position and heading alone (no walls or goal are given away).
    """

    def __init__(self, walls: np.ndarray, cell: float = CELL, width: float = 0.5):
        rows, cols = walls.shape
        self.centers = np.array([cell_center(r, c, rows, cell) for r in range(rows) for c in range(cols)])
        self.inv = 1.0 / (2 * (width * cell) ** 2)
        self.dim = len(self.centers) + 4

    def __call__(self, obs) -> np.ndarray:
        obs = np.atleast_2d(np.asarray(obs, dtype=np.float64))
        d2 = ((obs[:, None, :2] - self.centers[None]) ** 2).sum(-1)
        c, s = obs[:, 2:3], obs[:, 3:4]
        head = np.maximum(np.concatenate([c, -c, s, -s], axis=1), 0.0)
        return np.concatenate([np.exp(-d2 * self.inv), head], axis=1).astype(np.float32)
