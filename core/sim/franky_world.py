"""The FR3 of franky-sim with a skin: its world, its contacts read as taxel forces, its 1 kHz clock kept.

Runs inside franky-sim's own virtual environment (`make franky-sim` -> `.venv-franky`: franky-sim
1.0.4 needs numpy >= 2, which bpy forbids), never in skinsafe's; it imports only mujoco, numpy,
franky_sim and the numpy/numba parts of skinsafe (`SkinReadout`, the taxel map, the force feed).

    python -m skinsafe.core.sim.franky_world mjcf OUT.xml
        franky-sim's FR3 MJCF with its mesh directory pointed at its meshes/ (the shipped file says
        `meshdir="assets"`), for `skinsafe design OUT.xml`.
    python -m skinsafe.core.sim.franky_world serve MAP --feed NAME [--obstacle X,Y,Z,R] [--stats FILE]
        franky-sim's MuJoCo FR3 served over the libfranka protocol on a free loopback address, a sphere
        in its world, and after every physics step the skin's taxel forces from MuJoCo's contacts
        (the project's `SkinReadout`, the same readout as every other scene) written to the
        shared-memory force feed NAME that the emulated boards (`skinsafe emulate --map MAP --feed
        NAME`) stream over serial. Prints `fr3 HOST`, `feed NAME`, `ready`; runs until SIGTERM/SIGINT.

What franky-sim leaves out and the real FR3 does, added here (`CheckedRobotServer`): the robot's
communication constraint. A motion whose client sends no command for 20 cycles in a row is aborted
by reflex with `communication_constraints_violation` (libfranka raises it, as on the robot), and the
state's `control_command_success_rate` is the fraction of the last 100 cycles that got a command
(franky-sim reports 1.0 always). The physics steps are paced against absolute 1 ms deadlines
(franky-sim sleeps 1 ms minus the step, which drifts to ~0.9 kHz); a step that falls behind is never
caught up in a burst (the robot's clock never speeds up), so under load the world runs slower than
real time and says so (`realtime_factor` in the stats).
"""
from __future__ import annotations

import argparse
import dataclasses
import gc
import importlib.util
import json
import os
import signal
import subprocess
import sys
import time
import xml.etree.ElementTree as ET
from collections import deque
from pathlib import Path

import mujoco
import numpy as np
from scipy.spatial import cKDTree

from skinsafe.core.robot.kinematics import TaxelKinematics
from skinsafe.core.sim.readout import SkinReadout
from skinsafe.core.sim.scene import TIP_MASS, TIP_SOLREF
from skinsafe.core.skin import taxel_map
from skinsafe.core.skin.files import atomic_write
from skinsafe.core.skin.force_feed import ForceFeed
from skinsafe.core.skin.model import DesignError
from skinsafe.core.system import MissingPart

PREFIX = "robot0_"  # franky-sim's names for its first robot's bodies
OBSTACLE = "skinsafe_obstacle"
MISSED_LIMIT = 20  # cycles without a command in a row: the FR3 aborts the motion (libfranka's docs)
SUCCESS_WINDOW = 100  # cycles over which control_command_success_rate is counted
INITIAL_Q = (0.0, 0.0, 0.0, -1.57, 0.0, 1.57, 0.785)  # franky-sim's DEFAULT_INITIAL_JOINT_POS
COMM_ERROR = 25  # communication_constraints_violation in the wire's error array (libfranka 0.21 names it so)
EXIT_S = 5.0  # s a world left running gets to stop on SIGINT before it is killed
CONTACT_GAP_S = 0.05  # a contact after this long without one is a new contact (an onset)
RETRACT_SPEED = 1e-3  # m/s out of the obstacle: the touched point's measured motion follows the retraction


def franky_assets() -> Path:
    """franky-sim's assets folder (fr3.xml, meshes/), found without importing franky_sim."""
    spec = importlib.util.find_spec("franky_sim")
    if spec is None or spec.origin is None:
        raise SystemExit("franky_sim is not installed here; run this with franky-sim's environment "
                         "(make franky-sim, then .venv-franky/bin/python -m skinsafe.core.sim.franky_world ...)")
    return Path(spec.origin).parent / "assets"


def write_mjcf(out: str | Path) -> Path:
    """franky-sim's fr3.xml with `meshdir` pointed at its meshes/ folder (absolute), written to `out`."""
    assets = franky_assets()
    root = ET.parse(assets / "fr3.xml").getroot()
    root.find("compiler").set("meshdir", str(assets / "meshes"))
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(out, ET.tostring(root, encoding="unicode"))
    return out


def checked_server_class():
    """`FrankaRobotServer` with the FR3's communication constraint (imported here: franky_sim needs numpy 2)."""
    from franky_sim.franka_robot_protocol import MoveStatus, RobotCommand, RobotMode
    from franky_sim.franka_robot_server import BaseCommand, FrankaRobotServer

    class CheckedRobotServer(FrankaRobotServer):
        """Counts the cycles of a motion that got no command; 20 in a row abort it by reflex."""

        def __init__(self, robot, hostnames):
            self.msg_id = 0  # id of the next state sent: the robot's clock in ms (libfranka's RobotState.time)
            self.fresh = False
            self.window: deque[bool] = deque(maxlen=SUCCESS_WINDOW)
            self.run = self.longest_run = self.missed = self.commands = self.cycles = self.aborts = 0
            self.errors = (False,) * 41
            self.reflex = False
            self.motion = 0  # the motion being counted
            self.motion_cycle = 0  # `cycles` when it began
            self.aborted = 0  # a motion aborted this cycle: its answer follows the state that shows why
            super().__init__(robot, hostnames)

        def _setup_udp_connection(self, port):
            super()._setup_udp_connection(port)
            self.msg_id = 0

        def send_state(self):
            if self.udp_connected:
                super().send_state()
                self.msg_id += 1
            if self.aborted:
                BaseCommand.send_response(self._tcp_socket, RobotCommand.kMove, self.aborted,
                                          MoveStatus.kReflexAborted)
                self.aborted = 0

        def _pre_process_commands(self):
            super()._pre_process_commands()
            self.fresh = False

        def _handle_udp_command(self, data):
            self.fresh = True
            self.commands += 1
            super()._handle_udp_command(data)

        def _post_process_commands(self):
            motion = self.current_motion_id
            if motion:
                if motion != self.motion:  # a new motion: nothing missed yet
                    self.motion, self.run, self.reflex, self.motion_cycle = motion, 0, False, self.cycles
                    self.window.extend([True] * SUCCESS_WINDOW)
                self.cycles += 1
                self.window.append(self.fresh)
                self.run = 0 if self.fresh else self.run + 1
                self.missed += not self.fresh
                self.longest_run = max(self.longest_run, self.run)
                if self.run >= MISSED_LIMIT:
                    self._abort(motion)
            super()._post_process_commands()

        def _abort(self, motion):
            errors = [False] * 41
            errors[COMM_ERROR] = True
            self.errors, self.reflex, self.aborted = tuple(errors), True, motion
            self.aborts += 1
            self.stop_motion(send_preemption_signal=False)
            self.reset_current_motion_id()

        @property
        def motion_time(self) -> float | None:
            """Seconds of robot time since the current motion began (None: no motion)."""
            return (self.cycles - self.motion_cycle) * 1e-3 if self.current_motion_id else None

        @property
        def robot_state(self):
            st = super().robot_state
            extra = dict(control_command_success_rate=float(np.mean(self.window)) if self.window else 1.0,
                         reflex_reason=self.errors)  # libfranka's last_motion_errors
            if self.reflex:
                extra.update(robot_mode=RobotMode.kReflex, errors=self.errors)  # current_errors
            return st.replace(**extra)

    return CheckedRobotServer


def obstacle_in_path(map_path: str, qd, q0, lead_s: float = 0.5, radius: float = 0.05,
                     candidates: int = 64) -> tuple[float, ...]:
    """A sphere (x, y, z, r) in the path of the joint velocity `qd` from `q0` whose first contact is on skin.

    Candidates: the taxels moving fastest along their own outward normal; each gets the sphere that
    touches it after `lead_s` s of the motion, and is kept when sweeping the motion shows the first
    contact sensed by the skin (`SkinReadout` gives force, no contact on bare surface). Any design,
    any motion; a ValueError when none of the candidates is clear.
    """
    design = taxel_map.load(map_path)
    model, data, kin, readout = _scene(map_path, design, radius)
    qd, q0 = np.asarray(qd, float), np.asarray(q0, float)
    q = np.zeros(model.nq)
    qd_full = np.zeros(model.nv)
    qd_full[:7] = qd
    q[:7] = q0
    J, _, frames = kin.jacobians(q)
    lead = np.einsum("nij,j,ni->n", J[:, :3], qd_full, frames[:, :, 2])
    q[:7] = q0 + lead_s * qd
    pos, frames = (a.copy() for a in kin.poses(q))
    for i in np.argsort(-lead)[:candidates]:
        if not lead[i] > 0:
            break
        data.mocap_pos[0] = pos[i] + radius * frames[i][:, 2]
        for s in np.linspace(0.0, 1.2, 61):
            data.qpos[:] = q
            data.qpos[:7] = q0 + s * lead_s * qd
            mujoco.mj_forward(model, data)
            if data.ncon:
                touched = (data.contact.geom[: data.ncon] == model.geom(OBSTACLE).id).any()
                if touched:
                    if readout.read(data).max() > 0 and readout.last_missed == 0:
                        return (*map(float, data.mocap_pos[0]), float(radius))
                    break
    raise ValueError(f"no sphere of radius {radius} m in this motion's path meets skin first (tried {candidates} "
                     "leading taxels); choose another motion or start pose")


@dataclasses.dataclass
class Hand:
    """A hand (a sphere of `radius`, m, on a spring of `stiffness`) that reaches into the arm again and again: its
    holder moves along -`normal` through `touch` (where the hand first touches the skin, the arm at rest), from
    `gap` outside to `depth` inside at `speed` (m/s), stays `hold` s, goes back, rests `rest` s; on the robot's
    clock of each motion, the first approach after `start` s. An arm that yields (a retraction) meets it less
    deep, or not at all."""

    touch: tuple[float, float, float]
    normal: tuple[float, float, float]
    radius: float
    stiffness: float = 20e3  # N/m of the spring it rides on (the sim's contacts'): a hand, not a rigid body
    gap: float = 0.03
    depth: float = 0.02
    speed: float = 0.1
    hold: float = 0.2
    rest: float = 0.8
    start: float = 0.5

    @property
    def period(self) -> float:
        return 2 * (self.gap + self.depth) / self.speed + self.hold + self.rest

    def position(self, t: float | None) -> np.ndarray:
        """The centre at `t` s into a motion (None, or before `start`: out at `gap`)."""
        reach, go = self.gap + self.depth, (self.gap + self.depth) / self.speed
        s = -1.0 if t is None or t < self.start else (t - self.start) % self.period
        d = 0.0 if s < 0 else s * self.speed if s < go else reach if s < go + self.hold else \
            max(0.0, reach - (s - go - self.hold) * self.speed)
        return np.asarray(self.touch) + np.asarray(self.normal) * (self.gap - d)

    def arg(self) -> str:
        """The `serve --hand=` value."""
        return ",".join(f"{v:.9g}" for v in (*self.touch, self.radius, *self.normal))


def hand_in_reach(map_path: str, q0, radius: float = 0.04, gap: float = 0.03, depth: float = 0.02,
                  candidates: int = 512) -> Hand:
    """A `Hand` reaching into the arm at rest at `q0` whose first contact is on skin, from `gap` outside the skin
    to `depth` inside. Candidates: the taxels facing out from the base's axis (a hand comes from the room) that
    the arm's joints move best along their normal (it can get out of the hand's way), in the middle of the most
    skin (taxels within half the hand's radius: a hand lands on skin, not on the bare link beside a small
    module), the first `candidates` whose start is clear of the arm each checked by sweeping the hand along its
    normal; a ValueError when none is clear."""
    design = taxel_map.load(map_path)
    model, data, kin, readout = _scene(map_path, design, radius)
    q = np.zeros(model.nq)
    q[:7] = np.asarray(q0, float)
    J, pos, frames = (a.copy() for a in kin.jacobians(q))
    normal = frames[:, :, 2]
    reach = np.linalg.norm(pos[:, :2], axis=1)
    out = np.einsum("ni,ni->n", normal[:, :2], pos[:, :2] / np.maximum(reach, 1e-9)[:, None])
    lever = np.linalg.norm(np.einsum("nij,ni->nj", J[:, :3, :7], normal), axis=1)  # m/s along n per rad/s
    skin = np.array([len(n) for n in cKDTree(pos).query_ball_point(pos, 0.5 * radius)], float)
    geom = model.geom(OBSTACLE).id
    swept = 0
    for i in np.argsort(-np.maximum(out, 0) * lever * skin / skin.max()):
        touch = pos[i] + radius * normal[i]
        data.qpos[:] = q
        data.mocap_pos[0] = touch + gap * normal[i]
        mujoco.mj_forward(model, data)
        if (data.contact.geom[: data.ncon] == geom).any():
            continue  # the hand's start already meets the arm (a neighbouring link): no room to come in
        swept += 1
        for k, s in enumerate(np.linspace(gap, -depth, 51)):
            data.qpos[:] = q
            data.mocap_pos[0] = touch + s * normal[i]
            mujoco.mj_forward(model, data)
            if (data.contact.geom[: data.ncon] == geom).any():
                if k and readout.read(data).max() > 0 and readout.last_missed == 0:
                    return Hand(tuple(map(float, touch)), tuple(map(float, normal[i])), radius, gap=gap, depth=depth)
                break
        if swept == candidates:
            break
    raise ValueError(f"no hand of radius {radius} m reaches skin first at this pose (tried {candidates} outward-facing "
                     "taxels); give another pose or radius")


def _scene(map_path: str, design, radius: float):
    """The map's robot with a mocap sphere named OBSTACLE: (model, data, TaxelKinematics, SkinReadout)."""
    ref = Path(design.robot.path)
    spec = mujoco.MjSpec.from_file(str(ref if ref.is_absolute() else Path(map_path).parent / ref))
    body = spec.worldbody.add_body(name=OBSTACLE, mocap=True)
    body.add_geom(name=OBSTACLE, type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[radius, 0, 0])
    model = spec.compile()
    return model, mujoco.MjData(model), TaxelKinematics(model, design), SkinReadout(model, design)


def onboard_design(map_path: str):
    """The taxel map, its body names as franky-sim names them (`robot0_fr3_link1`, ...)."""
    design = taxel_map.load(map_path)
    return design, dataclasses.replace(design, bodies=[PREFIX + b for b in design.bodies])


class FrankyWorld:
    """franky-sim's MuJoCo FR3, a sphere obstacle or a moving hand, the skin readout into a force feed, and the stats."""

    def __init__(self, map_path: str, feed_name: str | None, obstacle: tuple[float, float, float, float] | None,
                 initial_q=None, hostname: str | None = None, hand: Hand | None = None):
        from franky_sim import SimulationServer
        from franky_sim.mujoco_simulator import MujocoSimulator

        self.design, design = onboard_design(map_path)
        self.sim = MujocoSimulator()
        self.robot = self.sim.add_robot(initial_q=INITIAL_Q if initial_q is None else initial_q)
        self.hand = hand
        if hand is not None:  # a mocap holder; the hand rides on a sprung tip along its path (as scene.Obstacle's)
            x, y, z = hand.position(None)
            body = ET.SubElement(self.sim.worldbody, "body", name=f"{OBSTACLE}_holder", pos=f"{x} {y} {z}", mocap="true")
            body = ET.SubElement(body, "body", name=f"{OBSTACLE}_tip", gravcomp="1")
            ET.SubElement(body, "joint", name=f"{OBSTACLE}_spring", type="slide", axis=" ".join(map(str, hand.normal)),
                          stiffness=str(hand.stiffness), damping=str(2 * np.sqrt(hand.stiffness * TIP_MASS)))
            ET.SubElement(body, "geom", name=OBSTACLE, type="sphere", size=f"{hand.radius}", mass=str(TIP_MASS),
                          priority="1", solref=" ".join(map(str, TIP_SOLREF)), rgba="0.9 0.6 0.5 1")
        elif obstacle is not None:
            x, y, z, r = obstacle
            body = ET.SubElement(self.sim.worldbody, "body", name=OBSTACLE, pos=f"{x} {y} {z}")
            ET.SubElement(body, "geom", name=OBSTACLE, type="sphere", size=f"{r}", rgba="0.9 0.6 0.5 1")
        server_cls = checked_server_class()

        class Server(SimulationServer):
            def init(srv):  # franky-sim's init, with the checked robot server
                for robot in srv.sim.robots:
                    rs = server_cls(robot, srv._remaining_hostname_candidates)
                    rs.init()
                    srv.robot_servers.append(rs)
                srv.sim.start()

        self.sim.init()
        self.server = Server(self.sim, **({"hostname_candidates": [hostname]} if hostname else {}))
        self.server.init()
        self.rs = self.server.robot_servers[0]
        model = self.sim.model
        self.readout = SkinReadout(model, design)
        self.readout.read(self.sim.data, warm=True)
        self.feed = ForceFeed.create(feed_name, self.design.n_taxels)
        self.obstacle_geom = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, OBSTACLE)
        self.mocap = int(model.body_mocapid[model.body(f"{OBSTACLE}_holder").id]) if hand is not None else -1
        self.peak_n = 0.0  # the largest taxel force
        self.contact_n = 0.0  # the largest normal force between the obstacle and the robot (its contacts summed)
        self.depth_worst = 0.0
        self.onsets: list[float] = []  # robot times at which a contact of the obstacle with the robot began
        self.reactions: list[float | None] = []  # per onset: when the touched point first moved away from it
        self._touch = None  # (body, point in its frame, direction out of the obstacle) of the open contact
        self.last_touch = -np.inf  # robot time the obstacle last touched the robot
        self.missed_contacts = 0
        self.readout_s: deque[float] = deque(maxlen=100_000)
        self._jac = np.zeros((3, model.nv))
        self._centre = None  # the obstacle's centre at the last step
        self.sim.register_post_step_callback(self._after_step)

    @property
    def hostname(self) -> str:
        return self.rs.hostname

    def _after_step(self, _sim) -> None:
        t0 = time.perf_counter()
        data = self.sim.data
        forces = self.readout.read(data)
        t = self.rs.msg_id * 1e-3  # the robot time of the state this step is sent as
        self.feed.write(forces, t)
        self.readout_s.append(time.perf_counter() - t0)
        self.missed_contacts += self.readout.last_missed
        if forces.size:
            self.peak_n = max(self.peak_n, float(forces.max()))
        if self.mocap >= 0:  # the hand's place at the next step
            data.mocap_pos[self.mocap] = self.hand.position(self.rs.motion_time)
        self._contact_stats(data, t)

    def _contact_stats(self, data, t: float) -> None:
        """Onsets (a contact after CONTACT_GAP_S without), the deepest penetration, the largest contact force, and
        per onset the robot time the touched point first moved out of the obstacle by itself: faster than
        RETRACT_SPEED, and faster than the obstacle comes after it (a hand pushing the arm along is no reaction)."""
        model, con = self.sim.model, data.contact
        centre = data.geom_xpos[self.obstacle_geom].copy() if self.obstacle_geom >= 0 else np.zeros(3)
        v_obstacle = (centre - self._centre) / model.opt.timestep if self._centre is not None else np.zeros(3)
        self._centre = centre
        hit = np.flatnonzero((con.geom[: data.ncon] == self.obstacle_geom).any(axis=1)) if data.ncon else []
        if len(hit):
            self.depth_worst = max(self.depth_worst, float(-con.dist[hit].min()))
            f, total = np.zeros(6), 0.0
            for k in hit:
                mujoco.mj_contactForce(model, data, int(k), f)
                total += abs(f[0])
            self.contact_n = max(self.contact_n, total)
            if not 0 <= t - self.last_touch <= CONTACT_GAP_S:  # (the robot's clock restarts with each connection)
                k = int(hit[np.argmin(con.dist[hit])])
                g = int(con.geom[k][0] if con.geom[k][1] == self.obstacle_geom else con.geom[k][1])
                body, point = int(model.geom_bodyid[g]), con.pos[k].copy()
                out = (point - centre) / max(np.linalg.norm(point - centre), 1e-9)
                local = data.xmat[body].reshape(3, 3).T @ (point - data.xpos[body])
                self.onsets.append(t)
                self.reactions.append(None)
                self._touch = (body, local, out)
            self.last_touch = t
        if self._touch is not None and self.reactions[-1] is None:
            body, local, out = self._touch
            point = data.xpos[body] + data.xmat[body].reshape(3, 3) @ local
            mujoco.mj_jac(model, data, self._jac, None, point, body)
            v = self._jac @ data.qvel
            if float(out @ v) > RETRACT_SPEED and float(out @ (v - v_obstacle)) > RETRACT_SPEED:
                self.reactions[-1] = t

    def run(self, stop: list[int], period: float = 1e-3) -> dict:
        """Step at the robot's 1 kHz until `stop` is non-empty; the stats. Each cycle starts at its deadline, and
        never sooner than half a period after the last state went out: a world behind real time still gives the
        client the time to answer that the robot's cycle gives it (stepping on at once would count cycles as
        missed that a real FR3 would not). No collector pass over everything imported holds a cycle up (a robot's
        controller has none)."""
        gc.freeze()
        wall0 = nxt = time.perf_counter()
        steps = 0
        while not stop:
            self.server.run_once(realtime=False)
            sent = time.perf_counter()
            steps += 1
            nxt += period
            if sent - nxt > period:  # behind by more than a cycle: slow down, never burst
                nxt = sent
            wait = max(nxt, sent + period / 2) - sent
            if wait > 0:
                time.sleep(wait)
        wall = time.perf_counter() - wall0
        rs, rd = self.rs, np.asarray(self.readout_s) * 1e3
        return {"steps": steps, "wall_s": round(wall, 3), "realtime_factor": round(steps * period / wall, 3),
                "motion_cycles": rs.cycles, "commands": rs.commands, "missed_cycles": rs.missed,
                "longest_missed_run": rs.longest_run, "communication_stops": rs.aborts,
                "onsets": self.onsets, "reactions": self.reactions, "peak_N": round(self.contact_n, 3),
                "taxel_peak_N": round(self.peak_n, 3),
                "into_contact_mm_worst": round(1e3 * self.depth_worst, 3),
                "contacts_on_bare_surface": self.missed_contacts, "taxels": self.design.n_taxels,
                "readout_ms_p50": round(float(np.percentile(rd, 50)), 4) if rd.size else None,
                "readout_ms_max": round(float(rd.max()), 4) if rd.size else None}

    def close(self) -> None:
        self.server.cleanup()
        self.sim.cleanup()
        self.feed.close()


def franky_python() -> Path:
    """franky-sim's interpreter: $SKINSAFE_FRANKY_PYTHON, else `.venv-franky` of this checkout (`make franky-sim`)."""
    if os.environ.get("SKINSAFE_FRANKY_PYTHON"):
        return Path(os.environ["SKINSAFE_FRANKY_PYTHON"])
    return Path(__file__).resolve().parents[2] / ".venv-franky" / "bin" / "python"


def require_franky_python() -> Path:
    """franky_python(), or MissingPart when it is not there."""
    py = franky_python()
    if not py.exists():
        raise MissingPart(f"franky-sim's environment ({py})", "build it: `make franky-sim` (.venv-franky), or set "
                          "SKINSAFE_FRANKY_PYTHON to its interpreter")
    return py


class WorldProcess:
    """`serve` in franky-sim's own interpreter as a child process; `.host` and `.feed` once it is ready,
    `.stop()` ends it (SIGINT) and returns its stats."""

    def __init__(self, map_path: str | Path, stats_path: str | Path, obstacle=None, q0=None, timeout: float = 60.0,
                 hand: Hand | None = None, realtime: bool = False):
        py = require_franky_python()
        cmd = [str(py), "-m", "skinsafe.core.sim.franky_world", "serve", str(map_path), "--stats", str(stats_path)]
        if obstacle is not None:
            cmd.append("--obstacle=" + ",".join(f"{v:.9g}" for v in obstacle))  # "=": values may start with "-"
        if q0 is not None:
            cmd.append("--q0=" + ",".join(f"{v:.9g}" for v in q0))
        if hand is not None:
            cmd += ["--hand=" + hand.arg(), "--hand-speed", str(hand.speed), "--hand-rest", str(hand.rest)]
        if realtime:
            cmd.append("--realtime")
        self.stats_path = Path(stats_path)
        self.proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, text=True)
        self.host = self.feed = None
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            line = self.proc.stdout.readline()
            if not line:
                raise RuntimeError(f"franky world exited with {self.proc.wait()} before it was ready: {' '.join(cmd)}")
            key, _, value = line.strip().partition(" ")
            if key == "fr3":
                self.host = value
            elif key == "feed":
                self.feed = value
            elif key == "ready":
                return
        self.kill()
        raise RuntimeError("franky world did not become ready")

    def stop(self, timeout: float = 10.0) -> dict:
        """SIGINT, wait, the stats it wrote."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.kill()
                raise
        self.proc.stdout.close()
        return json.loads(self.stats_path.read_text())

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()
        self.proc.stdout.close()

    def __enter__(self) -> "WorldProcess":
        return self

    def __exit__(self, *exc) -> None:
        """Not stopped yet: SIGINT, so the world removes its force feed itself (killed, its shared memory was left to
        the resource tracker's clean-up, with a leak warning); killed after EXIT_S."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(EXIT_S)
            except subprocess.TimeoutExpired:
                pass
        self.kill()


def _floats(text: str, n: int, what: str) -> tuple[float, ...]:
    try:
        v = tuple(float(x) for x in text.split(","))
    except ValueError:
        v = ()
    if len(v) != n or not all(np.isfinite(v)):
        raise SystemExit(f"{what} is '{text}'; give {n} comma-separated numbers")
    return v


def _realtime() -> None:
    """SCHED_FIFO for this process where the system allows it (else normal priority, silently)."""
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(10))
    except (AttributeError, PermissionError, OSError):
        pass


def serve(args) -> int:
    stop: list[int] = []
    for s in (signal.SIGTERM, signal.SIGINT):
        signal.signal(s, lambda signum, _f: stop.append(signum))
    obstacle = _floats(args.obstacle, 4, "--obstacle") if args.obstacle else None
    q0 = _floats(args.q0, 7, "--q0") if args.q0 else None
    hand = None
    if args.hand:
        v = _floats(args.hand, 7, "--hand")
        hand = Hand(v[:3], v[4:], v[3], speed=args.hand_speed, rest=args.hand_rest)
    if args.realtime:
        _realtime()
    try:
        world = FrankyWorld(args.map, args.feed, obstacle, q0, args.hostname, hand)
    except (DesignError, OSError) as e:
        print(f"franky_world: error: {e}", file=sys.stderr)
        return 1
    print(f"fr3 {world.hostname}\nfeed {world.feed.name}\nready", flush=True)
    try:
        stats = world.run(stop)
    finally:
        world.close()
    if args.stats:
        atomic_write(args.stats, json.dumps(stats, indent=1))
    print(json.dumps(stats), flush=True)
    return 0


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m skinsafe.core.sim.franky_world", description=__doc__.split("\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    m = sub.add_parser("mjcf", help="write franky-sim's FR3 MJCF with its mesh directory fixed")
    m.add_argument("out")
    pl = sub.add_parser("place", help="print X,Y,Z,R of a sphere in the path of a joint velocity from q0")
    pl.add_argument("map")
    pl.add_argument("--qd", required=True, metavar="QD1,...,QD7", help="joint velocity of the motion, rad/s")
    pl.add_argument("--q0", metavar="Q1,...,Q7", help="start (default franky-sim's initial pose)")
    pl.add_argument("--lead", type=float, default=0.5, help="seconds of that motion before the first contact")
    pl.add_argument("--radius", type=float, default=0.05, help="sphere radius, m")
    s = sub.add_parser("serve", help="serve the FR3 with a skin over the libfranka protocol")
    s.add_argument("map", help="taxel map designed on the FR3 from `mjcf`")
    s.add_argument("--feed", help="name of the shared-memory force feed to create (default: a unique name)")
    s.add_argument("--obstacle", metavar="X,Y,Z,R", help="a sphere in the world, m")
    s.add_argument("--hand", metavar="X,Y,Z,R,NX,NY,NZ", help="a hand (sphere) reaching into the arm again and again "
                   "along -N through X,Y,Z (from `hand MAP`)")
    s.add_argument("--hand-speed", type=float, default=Hand.speed, help="m/s of the hand")
    s.add_argument("--hand-rest", type=float, default=Hand.rest, help="s the hand rests out of reach between reaches")
    s.add_argument("--realtime", action="store_true", help="run at real-time priority (SCHED_FIFO) where allowed, "
                   "as the robot's own controller does")
    s.add_argument("--q0", metavar="Q1,...,Q7", help="initial joint positions (default franky-sim's)")
    s.add_argument("--hostname", help="loopback address to serve on (default: the first free 127.x.y.z)")
    s.add_argument("--stats", help="write the run's stats (JSON) here at exit")
    h = sub.add_parser("hand", help="print X,Y,Z,R,NX,NY,NZ of a hand that reaches the arm at rest on skin first")
    h.add_argument("map")
    h.add_argument("--q0", metavar="Q1,...,Q7", help="the arm's pose (default franky-sim's initial pose)")
    h.add_argument("--radius", type=float, default=0.04, help="hand radius, m")
    args = p.parse_args(argv)
    if args.cmd == "hand":
        q0 = _floats(args.q0, 7, "--q0") if args.q0 else INITIAL_Q
        try:
            print(hand_in_reach(args.map, q0, args.radius).arg())
        except (DesignError, ValueError) as e:
            raise SystemExit(f"franky_world hand: error: {e}") from None
        return 0
    if args.cmd == "mjcf":
        print(write_mjcf(args.out))
        return 0
    if args.cmd == "place":
        q0 = _floats(args.q0, 7, "--q0") if args.q0 else INITIAL_Q
        try:
            sphere = obstacle_in_path(args.map, _floats(args.qd, 7, "--qd"), q0, args.lead, args.radius)
        except (DesignError, ValueError) as e:
            raise SystemExit(f"franky_world place: error: {e}") from None
        print(",".join(f"{v:.6f}" for v in sphere))
        return 0
    return serve(args)


if __name__ == "__main__":
    sys.exit(main())
