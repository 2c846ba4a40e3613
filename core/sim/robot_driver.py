"""The `sim` robot driver: a MuJoCo scene of the exported design, stepped in real time at its period.

It keeps the runtime's robot-driver contract (core/runtime/protocol.py): `run(control)` owns the
clock; every period it hands `control` the measured state (`SimState`: the sim's clock, q, qd and a
sequence number), integrates the returned joint velocity into the position servos' targets
(gravity compensated, as the arm's own controller would) and steps the physics one period. After
each step the skin's contact forces (`SkinReadout`) go to the shared-memory `ForceFeed`, from which
the emulated boards stream them over pseudo-terminals: the whole chain (contact -> board firmware
-> serial -> host -> layers -> driver) runs closed-loop on one machine.

Before `run` the arm stands still and the feed is refreshed every period (the pre-flight's tare sees
live sensors). A stop (control returned None, raised, `stop(reason)`, a physics failure) is a Category 2 stop
(IEC 60204-1), as the FR3 driver's: from the arm's measured joint speeds, the velocity command ramped to zero at the
driver's own joint limits (`limits()`: qdd_max, and qddd_max where given; core/robot/rate_limit.py), the servos
tracking it (velocity and inertia feed-forward, as a velocity-controlled arm's joint controller), then holding the
pose the ramp left the arm at until the arm is at rest. A dead simulation sends nothing.

`Contact` puts something in the arm's world to touch:
- `poke`: a sprung probe jabs one skin taxel along its normal (the arm holding still is enough);
- `post`: a sprung post stands `gap` in front of a taxel that rotating `joint` positively from
  home sweeps into it (a trajectory or teleop command drives the arm into it).
Sensor faults on demand (`taxel_faults`, for the pre-flight's health checks): a stuck taxel feeds a
constant `STUCK_N`, a noisy one adds uniform noise up to its threshold.
`WorldStats` measures what the robot's world saw: contact onset, peak contact force, how far the
touched taxel went into its contact after the onset, and when the measured motion turned out of it.
"""
from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field

import mujoco
import numpy as np

from skinsafe.core.robot.kinematics import TaxelKinematics
from skinsafe.core.robot.models import Robot
from skinsafe.core.robot.rate_limit import rate_limit
from skinsafe.core.sim.readout import SkinReadout
from skinsafe.core.sim.scene import Obstacle, SceneOptions, build_scene
from skinsafe.core.skin.model import SkinDesign

PROBE_RADIUS = 0.015  # m
SERVO_LEAD = 0.2  # rad: the servo target never runs further than this ahead of the measured joint
REST_SPEED = 1e-3  # rad/s: the stop's hold ends when every joint is slower than this ...
REST_TIMEOUT_S = 0.5  # ... or this long after its ramp ended
RETRACT_SPEED = 1e-3  # m/s out of the contact: the measured motion follows the retraction
TAXEL_FAULTS = ("stuck", "noisy")  # sensor faults on demand: stuck reads STUCK_N always, noisy adds U(0, threshold)
STUCK_N = 5.0
CLOCK_BACK_S = 0.01
PERIOD_S = (0.0002, 0.05)  # the control periods the sim steps at (s)
OVERRUN_STEP = 3  # periods the state's clock advances per tick under an injected overrun (states missed)


@dataclass
class SimState:
    t: float
    q: np.ndarray
    qd: np.ndarray
    seq: int


@dataclass
class Contact:
    """Something to touch (module docstring). `taxel` None: chosen by the rule of `kind`."""

    kind: str = "poke"  # "poke" | "post"
    at: float = 1.0  # s (sim clock): when the poke starts moving
    taxel: int | None = None
    joint: int = 0  # post: the joint whose positive rotation sweeps the skin into the post
    gap: float = 0.01  # m between the skin and the probe / post at home
    depth: float = 0.004  # m: how far past the skin the poke drives its holder
    speed: float = 0.1  # m/s of the poke
    hold: float = 0.05  # s at full depth
    stiffness: float = 20e3  # N/m of the sprung tip

    def __post_init__(self):
        if self.kind not in ("poke", "post"):
            raise ValueError(f"contact '{self.kind}': use 'poke' or 'post'")
        for k in ("gap", "depth", "speed", "stiffness"):
            v = getattr(self, k)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"contact {k} = {v}: give a positive number")


@dataclass
class SimFaults:
    """Faults of the robot's side for the fault bench: the state stops updating, its clock freezes or goes back (as
    a robot's would, while the driver's own counter still counts every read, as the FR3 driver's does), it advances
    OVERRUN_STEP periods per tick (a robot whose states the host missed: every tick an overrun; the sim's own clock
    advances one period per tick, whatever the host's load), or the physics dies. `WorldStats.fault_mono`: host time
    the first one took effect."""

    freeze_at: float | None = None  # s (sim clock): the state stops updating (the control still runs)
    die_at: float | None = None  # s: the simulation fails (the driver stops, naming it)
    clock_freeze_at: float | None = None  # s: the state's clock stays (q, qd and seq go on)
    clock_back_at: float | None = None  # s: the state's clock jumps CLOCK_BACK_S back, once
    overrun_at: float | None = None  # s: from here the state's clock advances OVERRUN_STEP periods per tick
    nan_at: float | None = None  # s: from here the state's first joint position reads NaN (a broken encoder)


@dataclass
class WorldStats:
    onset_t: float | None = None  # sim time of the first contact force on the touched obstacle
    peak_N: float = 0.0  # largest contact force between the arm and the obstacle, over the run (every contact)
    first_peak_N: float = 0.0  # largest contact force of the first contact (the onset until the force is first 0 again)
    into_contact_m: float = 0.0  # furthest the touched taxel moved along its normal from the onset to the reaction
    reaction_t: float | None = None  # first time after the onset its measured motion pointed out of the contact
    ticks: int = 0
    overruns: int = 0  # periods whose work took longer than the period
    stop_t: float | None = None  # sim time of the stop
    zero_mono: float | None = None  # host time the stop began (its ramp's first command went out)
    ramp_ticks: int = 0  # periods the stop's ramp to zero took
    fault_mono: float | None = None  # host time an injected fault (SimFaults) took effect
    rest_qd: float = float("nan")  # largest joint speed when the stop's hold ended
    extra: dict = field(default_factory=dict)


def _quat_z_to(n: np.ndarray) -> tuple:
    """A MuJoCo quaternion (w, x, y, z) turning the z axis onto the unit vector n."""
    z = np.array([0.0, 0.0, 1.0])
    c = float(z @ n)
    if c < -1 + 1e-12:
        return (0.0, 1.0, 0.0, 0.0)
    axis = np.cross(z, n)
    w = 1.0 + c
    q = np.array([w, *axis])
    return tuple(q / np.linalg.norm(q))


def pick_taxel(design: SkinDesign, robot: Robot, contact: Contact) -> tuple[int, np.ndarray, np.ndarray]:
    """(taxel, its position, its normal) at home for the contact: a poke takes the most upward-facing
    taxel among those the arm moves well along their normal (lever >= 70% of the best); a post the
    taxel that rotating `contact.joint` moves fastest along its own normal."""
    kin = TaxelKinematics(robot.model, design)
    idx = np.flatnonzero(design.taxels.enabled) if contact.taxel is None else np.array([contact.taxel])
    if not len(idx) or idx.max() >= design.n_taxels or idx.min() < 0:
        raise ValueError(f"contact taxel {contact.taxel}: the skin has {design.n_taxels} taxels")
    J, pos, frames = kin.jacobians_of(idx, robot.home)
    n = frames[:, :, 2]
    if contact.taxel is None and contact.kind == "poke":
        lever = np.linalg.norm(np.einsum("kin,ki->kn", J[:, :3], n), axis=1)
        score = np.where(lever >= 0.7 * lever.max(), n[:, 2], -np.inf)
    else:
        if not 0 <= contact.joint < robot.model.nv:
            raise ValueError(f"contact joint {contact.joint}: the robot has joints 0..{robot.model.nv - 1}")
        score = np.einsum("ki,ki->k", J[:, :3, contact.joint], n)
    k = int(np.argmax(score))
    return int(idx[k]), pos[k], n[k]


class SimDriver:
    """The MuJoCo robot of a skin design, stepped at `period_s` (real time unless `realtime=False`)."""

    name = "sim"

    def __init__(self, design: SkinDesign, robot: Robot, feed=None, period_s: float = 0.002,
                 contact: Contact | None = None, realtime: bool = True, faults: SimFaults | None = None,
                 taxel_faults: dict[int, str] | None = None):
        if not (np.isfinite(period_s) and PERIOD_S[0] <= period_s <= PERIOD_S[1]):
            raise ValueError(f"sim period {period_s} s: give {PERIOD_S[0]}..{PERIOD_S[1]} s")
        self.design, self.robot, self.feed, self.period_s = design, robot, feed, float(period_s)
        self.contact, self.realtime, self.faults = contact, realtime, faults or SimFaults()
        obstacles = []
        if contact is not None:
            self.taxel, p, n = pick_taxel(design, robot, contact)
            self.normal = n
            self.start = p + n * (PROBE_RADIUS + contact.gap)
            obstacles.append(Obstacle("contact", "sphere", (PROBE_RADIUS,), pos=tuple(self.start),
                                      quat=_quat_z_to(n), mocap=True, spring=contact.stiffness,
                                      rgba=(0.9, 0.5, 0.2, 1)))
        spec = build_scene(design, robot, obstacles, SceneOptions(timestep=self.period_s))
        self.model = spec.compile()
        self.data = mujoco.MjData(self.model)
        self.nq = robot.model.nq
        self.data.qpos[:self.nq] = robot.home
        mujoco.mj_forward(self.model, self.data)
        self.readout = SkinReadout(self.model, design)
        self.kin = TaxelKinematics(robot.model, design)
        self.joint_names = [robot.model.joint(j).name for j in range(robot.model.njnt)][:robot.model.nv]
        self.contact_geom = self.model.geom("contact").id if contact is not None else -1
        self.target = robot.home.copy()
        self._kv = -self.model.actuator_biasprm[:self.nq, 2]  # the joint servos' damping (their dampratio's)
        self._track = None  # the stop's ramp: (velocity, acceleration) the servos track (`_step`)
        self.forces = np.zeros(design.n_taxels)  # the last step's taxel forces (what the boards are fed)
        self.stats = WorldStats()
        self.taxel_faults = {}
        for i, kind in (taxel_faults or {}).items():
            if kind not in TAXEL_FAULTS or not 0 <= i < design.n_taxels:
                raise ValueError(f"taxel fault {kind}:{i}: use stuck:I or noisy:I with 0 <= I < {design.n_taxels}")
            self.taxel_faults.setdefault(kind, []).append(i)
        self._rng = np.random.default_rng(0)
        self._publish()
        self._stop: str | None = None
        self._dead = False  # the simulation failed: no arm to hold
        self._seq = 0
        self._skew = 0.0  # s the state's clock runs ahead of the sim's (an injected overrun)
        self._contact_p0 = None
        self._first = False  # the first contact goes on
        self._moving = False  # until `run`, the arm stands still and its skin keeps streaming (pre-flight, tare)
        self._idle = threading.Thread(target=self._stand_still, name="sim-idle", daemon=True) if feed is not None else None
        if self._idle is not None:
            self._idle.start()

    # -- the contract ------------------------------------------------------------------------
    def limits(self) -> dict[str, np.ndarray]:
        m = self.robot.model
        lo = np.where(m.jnt_limited[:m.nv].astype(bool), m.jnt_range[:m.nv, 0], -np.inf)
        hi = np.where(m.jnt_limited[:m.nv].astype(bool), m.jnt_range[:m.nv, 1], np.inf)
        return {"q_min": lo, "q_max": hi, "qd_max": np.array(self.robot.vel_limits, float),
                "qdd_max": np.array(self.robot.acc_limits, float)}

    def stop(self, reason: str) -> None:
        """Thread- and signal-safe (one attribute store, no lock): the run stops at its next period."""
        if self._stop is None:
            self._stop = reason

    def close(self) -> None:
        self.stop("closed")
        if self._idle is not None:
            self._idle.join()

    def state(self) -> SimState:
        d = self.data
        return SimState(float(d.time), d.qpos[:self.nq].copy(), d.qvel[:self.nq].copy(), self._seq)

    def _stand_still(self) -> None:
        while not self._moving and self._stop is None:
            self._publish()
            time.sleep(self.period_s)

    def run(self, control, report=None, sent=None) -> str:
        """Blocks: control every period until a stop; returns the reason (module docstring). `report(kind, message,
        onset, during_stop)`: a fault this driver met itself (kind a monitor Kind value; onset host
        time.monotonic()), before it stops; `sent(state, command)`: every command sent after the stop (the hold) with
        the state it was sent on, until the arm rests (core/runtime/protocol.py)."""
        report = report or _ignore
        self._moving = True
        if self._idle is not None:
            self._idle.join()
        reason = ""
        next_t = time.monotonic()
        frozen = None
        while not reason:
            if self._stop is not None:
                reason = self._stop
                break
            t = float(self.data.time)
            if self.faults.freeze_at is not None and t >= self.faults.freeze_at and frozen is None:
                frozen = self.state()
                self.stats.fault_mono = time.monotonic()
            try:
                v = control(frozen or self._faulty(self.state()))
            except Exception as e:  # StopRobot (the monitor's: it ignores this report) or a failure of the control
                reason = str(e) or type(e).__name__
                report("driver", f"sim: the control failed: {reason}", time.monotonic(), False)
                break
            if v is None:
                reason = "the control ended the motion"
                report("driver", f"sim: {reason}", time.monotonic(), False)
                break
            v = np.asarray(v, dtype=float)
            if v.shape != (self.nq,) or not np.isfinite(v).all():
                reason = f"the control sent {v.shape} non-finite or misshapen joint velocities (expected {self.nq})"
                report("driver", f"sim: {reason}", time.monotonic(), False)
                break
            try:
                self._step(v)
            except Exception as e:
                reason = f"sim: the simulation failed ({e}); robot state lost"
                report("driver", reason, self.stats.fault_mono or time.monotonic(), False)
                self._dead = True
                break
            next_t = self._pace(next_t)
        self._halt(report, sent or _ignore)
        return reason

    def _faulty(self, s: SimState) -> SimState:
        """The state through the clock's injected faults (SimFaults)."""
        f = self.faults
        if f.nan_at is not None and s.t >= f.nan_at:
            self.stats.fault_mono = self.stats.fault_mono or time.monotonic()
            s.q[0] = np.nan
        if f.clock_freeze_at is not None and s.t >= f.clock_freeze_at:
            self.stats.fault_mono = self.stats.fault_mono or time.monotonic()
            s.t = f.clock_freeze_at
        elif f.clock_back_at is not None and s.t >= f.clock_back_at and self.stats.fault_mono is None:
            self.stats.fault_mono = time.monotonic()
            s.t -= CLOCK_BACK_S
        elif f.overrun_at is not None and s.t >= f.overrun_at:
            self.stats.fault_mono = self.stats.fault_mono or time.monotonic()
            self._skew += (OVERRUN_STEP - 1) * self.period_s
            s.t += self._skew
        return s

    # -- the world ---------------------------------------------------------------------------
    def _step(self, v: np.ndarray) -> None:
        d, nq = self.data, self.nq
        if self.faults.die_at is not None and d.time >= self.faults.die_at:
            self.stats.fault_mono = self.stats.fault_mono or time.monotonic()
            raise RuntimeError(f"physics stopped at t = {d.time:.3f} s (injected)")
        q = d.qpos[:nq]
        self.target = np.clip(self.target + v * self.period_s, q - SERVO_LEAD, q + SERVO_LEAD)
        self._move_contact(d.time)
        d.qfrc_applied[:nq] = d.qfrc_bias[:nq]  # gravity (and Coriolis) compensation
        if self._track is not None:  # the stop's ramp: velocity and inertia feed-forward, the servos track it
            M = np.zeros((self.model.nv, self.model.nv))
            mujoco.mj_fullM(self.model, d, M)
            d.qfrc_applied[:nq] += self._kv * self._track[0] + M[:nq, :nq] @ self._track[1]
        d.ctrl[:nq] = self.target
        mujoco.mj_step(self.model, d)
        if not (np.isfinite(d.qpos).all() and np.isfinite(d.qvel).all()):
            raise RuntimeError(f"physics diverged at t = {d.time:.3f} s")
        self.forces = self.readout.read(d)
        self._publish()
        self._seq += 1
        self.stats.ticks += 1
        self._world_stats()

    def _publish(self) -> None:
        """The step's forces to the boards' feed, through the sensors' faults (module docstring)."""
        if self.feed is None:
            return
        out = self.forces
        if self.taxel_faults:
            out = out.copy()
            th = self.design.taxels.thresholds["force"]
            for kind, idx in self.taxel_faults.items():
                out[idx] = STUCK_N if kind == "stuck" else out[idx] + self._rng.uniform(0, th[idx])
        self.feed.write(out, self.data.time)

    def _move_contact(self, t: float) -> None:
        c = self.contact
        if c is None or c.kind != "poke":
            return
        reach = c.gap + c.depth
        s = t - c.at
        t_in = reach / c.speed
        path = 0.0 if s <= 0 else s * c.speed if s <= t_in else reach if s <= t_in + c.hold else \
            max(0.0, reach - (s - t_in - c.hold) * c.speed)
        self.data.mocap_pos[0] = self.start - self.normal * path

    def contact_force(self) -> float:
        """The normal force between the arm and the contact obstacle now, N."""
        d, total, f = self.data, 0.0, np.zeros(6)
        for i in range(d.ncon):
            if self.contact_geom in (d.contact[i].geom1, d.contact[i].geom2):
                mujoco.mj_contactForce(self.model, d, i, f)
                total += abs(f[0])
        return total

    def _world_stats(self) -> None:
        if self.contact is None:
            return
        s, f = self.stats, self.contact_force()
        if s.onset_t is None and f <= 0:
            return
        J, pos, _ = self.kin.jacobians_of(np.array([self.taxel]), self.data.qpos[:self.nq])
        if s.onset_t is None:
            s.onset_t, self._contact_p0, self._first = float(self.data.time), pos[0].copy(), True
        s.peak_N = max(s.peak_N, f)
        self._first = self._first and f > 0
        if self._first:
            s.first_peak_N = max(s.first_peak_N, f)
        if s.reaction_t is None:  # how far into the contact before the motion turned out of it
            s.into_contact_m = max(s.into_contact_m, float((pos[0] - self._contact_p0) @ self.normal))
        v_n = float(self.normal @ (J[0, :3] @ self.data.qvel[:self.nq]))
        if s.reaction_t is None and v_n < -RETRACT_SPEED:
            s.reaction_t = float(self.data.time)

    def _pace(self, next_t: float) -> float:
        next_t += self.period_s
        now = time.monotonic()
        if now > next_t:
            self.stats.overruns += 1
            return now if now - next_t > self.period_s else next_t
        if self.realtime:
            time.sleep(next_t - now)
        return next_t

    def _halt(self, report, sent) -> None:
        """The stop (module docstring): from the arm's measured pose and joint speeds, the velocity command ramped to
        zero at the driver's own limits (the servos track it: velocity and inertia feed-forward), then zero, the
        servos holding the pose the ramp left the arm at, until every joint is below REST_SPEED (every step's command and
        state to `sent`); a simulation that fails meanwhile, or an arm not at rest REST_TIMEOUT_S after the ramp, is
        reported as a fault during the stop. A dead simulation has no arm: nothing is sent."""
        self.stats.stop_t, self.stats.zero_mono = float(self.data.time), time.monotonic()
        d, nq, dt = self.data, self.nq, self.period_s
        if self._dead:
            self.stats.rest_qd = float("nan")
            return
        lim = self.limits()
        zero = np.zeros(nq)
        self.target = d.qpos[:nq].copy()
        v, acc = np.clip(d.qvel[:nq], -lim["qd_max"], lim["qd_max"]), zero
        try:
            while np.any(np.abs(v) > lim["qdd_max"] * dt):  # within one step of zero, the zero follows
                last = v
                v, acc = rate_limit(zero, v, acc, dt, lim["qd_max"], lim["qdd_max"], lim.get("qddd_max"))
                self._track = (v, (v - last) / dt)
                sent(self.state(), v)
                self._step(v)
                self.stats.ramp_ticks += 1
            self._track, self.target = None, d.qpos[:nq].copy()  # held where the arm is (in a contact: no further)
            end = d.time + REST_TIMEOUT_S
            sent(self.state(), zero)
            while d.time < end and np.abs(d.qvel[:nq]).max() > REST_SPEED:
                self._step(zero)
                sent(self.state(), zero)
        except Exception as e:  # noqa: BLE001 - the stop itself failed: named, never silent
            report("driver", f"sim: the simulation failed during the stop ({e})", time.monotonic(), True)
        self.stats.rest_qd = float(np.abs(d.qvel[:nq]).max())
        if not self.stats.rest_qd <= REST_SPEED:
            report("driver", f"sim: the arm not at rest {REST_TIMEOUT_S:g} s after the stop's ramp (fastest joint "
                   f"{self.stats.rest_qd:.4f} rad/s)", time.monotonic(), True)


def _ignore(*_) -> None:
    pass
