"""The Franka FR3 over libfranka (pylibfranka 0.21): a robot driver whose clock is the robot's 1 kHz.

The control loop is libfranka's: every `readOnce` blocks until the robot's next 1 ms state, the
runtime's tick runs on it (`control(state)`), and its joint velocities go back with `writeOnce`
in the same cycle. The robot stops the arm when 20 cycles in a row bring no command
(`communication_constraints_violation`), so the tick must fit the cycle; `stats` counts the robot
states a slow tick let pass (`states_skipped`, `longest_gap_ms`) and the robot's own
`control_command_success_rate`; `zero_mono`: host time the stop's first command (its ramp to zero) went out (after
`robot-die`: the robot's own stop was asked).

Chosen over franky-control 2.0.0 by measurement (README, "The FR3 case"): franky runs its own 1 kHz
loop in C++ and takes new targets asynchronously through a jerk-limited planner, so a tick's
command reaches the robot after a planner delay and not in the cycle its state came from.

Every command is rate limited to the FR3's published acceleration and jerk (libfranka's
`limitRate` rule): a step change in the commanded velocity would otherwise trip the robot's
discontinuity reflexes. With `rate_limited=False` (`skinsafe run`: the runtime's one limiter,
core/runtime/limiter.py, already did it and recorded what is sent) commands go out as given; a stop's
ramp is limited here either way. A stop -- `control` returning None or raising, `stop(reason)` from any
thread, a non-finite or ill-shaped command -- ramps the velocity to zero at those limits, one
command per cycle, finishes the motion and calls the robot's own `stop()`. A stop asked before `run` (a
Ctrl-C while the run was being set up) is honoured by that run (the arm never starts); it is consumed
when the run that honoured it ends. A communication fault
(libfranka's network, control or command exceptions) ends the motion where the robot already
stopped it; its reason is named. numpy and pylibfranka only (never mujoco, torch or bpy).
"""
from __future__ import annotations

import contextlib
import os
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from skinsafe.core.runtime import limiter

JOINT_NAMES = [f"fr3_joint{i}" for i in range(1, 8)]
PERIOD_S = 0.001
# Franka Robotics, FR3 "Robot and interface specifications" (the limits libfranka's FR3 rate limiter uses)
Q_MIN = np.array([-2.7437, -1.7837, -2.9007, -3.0421, -2.8065, 0.5445, -3.0159])
Q_MAX = np.array([2.7437, 1.7837, 2.9007, -0.1518, 2.8065, 4.5169, 3.0159])
QD_MAX = np.array([2.62, 2.62, 2.62, 2.62, 5.26, 4.18, 5.26])
QDD_MAX = np.full(7, 10.0)
QDDD_MAX = np.full(7, 5000.0)
SWITCH_S = 1e-4  # Python's thread switch interval while run() runs (see FrankaDriver.run)
RAMP_MAX_S = 2.0  # a stop's ramp to zero never takes longer (2.62 rad/s at 10 rad/s^2 takes 0.27 s)
REST_QD = 0.02  # rad/s: after its ramp the stop holds zero until every joint's measured speed is below this
ROBOT_FAULTS = ("robot-freeze", "robot-clock-back", "robot-nan", "robot-overrun", "robot-die")  # `faults` kinds here
CLOCK_BACK_S = 0.01
OVERRUN_STEP = 3


class FrankaError(Exception):
    """The FR3 could not be reached or refused to start a motion (the text names why and the fix)."""


@dataclass
class FrankaState:
    t: float  # the robot's clock (libfranka RobotState.time), s
    q: np.ndarray  # measured joint positions (7,)
    qd: np.ndarray  # measured joint velocities (7,)
    seq: int  # increments with every robot state read
    qd_sent: np.ndarray = field(default_factory=lambda: np.zeros(7))  # the previous cycle's command, after limits
    success_rate: float = 1.0  # the robot's control_command_success_rate


def rate_limit(qd_cmd: np.ndarray, qd_last: np.ndarray, qdd_last: np.ndarray, dt: float = PERIOD_S,
               qd_max: np.ndarray = QD_MAX, qdd_max: np.ndarray = QDD_MAX, qddd_max: np.ndarray = QDDD_MAX
               ) -> tuple[np.ndarray, np.ndarray]:
    """libfranka's `limitRate` at the FR3's limits (core/runtime/limiter.py). Returns (velocity, acceleration)."""
    return limiter.rate_limit(qd_cmd, qd_last, qdd_last, dt, qd_max, qdd_max, qddd_max)


def realtime_kernel() -> bool:
    """True on a PREEMPT_RT kernel (where libfranka's real-time scheduling is enforced)."""
    try:
        return Path("/sys/kernel/realtime").read_text().strip() == "1"
    except OSError:
        return False


def _fault(e: Exception) -> str:
    import pylibfranka as pf

    kind = {pf.NetworkException: "communication with the robot lost",
            pf.ControlException: "the robot stopped the motion",
            pf.CommandException: "the robot refused a command",
            pf.RealtimeException: "real-time scheduling failed"}.get(type(e), type(e).__name__)
    return f"fr3: {kind}: {' '.join(str(e).split())}"


class FrankaDriver:
    """A `RobotDriver` (core/runtime/protocol.py) for the FR3 at `host` (an FCI address, or franky-sim's)."""

    name = "fr3"
    joint_names = JOINT_NAMES
    period_s = PERIOD_S

    def __init__(self, host: str, realtime: bool | None = None, rate_limited: bool = True, robot=None, faults=None):
        """`robot`: an already connected robot with pylibfranka's `Robot` interface (tests: a scripted one) instead of
        connecting to `host`. `faults`: a run's fault plan (core/runtime/fault_plan.py) for the robot's side, as the
        loop would see a faulty robot's states (ROBOT_FAULTS): from `robot-freeze` on the state stops updating (the
        read count still counts), `robot-clock-back` its clock goes back CLOCK_BACK_S once, `robot-nan` its first
        joint position reads NaN, `robot-overrun` its clock advances OVERRUN_STEP periods a state (states missed),
        `robot-die` the driver stops talking to the robot (no ramp: the robot's own stop ends the motion, watched on
        the robot's state stream until the arm rests: `_observe`)."""
        import pylibfranka as pf

        self._pf = pf
        rt = realtime_kernel() if realtime is None else realtime
        try:
            with _own_scheduling():
                self._robot = robot or pf.Robot(host, pf.RealtimeConfig.kEnforce if rt else pf.RealtimeConfig.kIgnore)
        except (pf.NetworkException, pf.RealtimeException, pf.InvalidOperationException,
                pf.FrankaException, RuntimeError) as e:
            raise FrankaError(f"fr3: cannot connect to {host}: {' '.join(str(e).split())}; check the robot's "
                              "address, that FCI is activated in Desk and the brakes are open") from None
        self.host = host
        self.rate_limited = rate_limited
        self.faults = faults
        self._frozen: FrankaState | None = None
        self._skew, self._back = 0.0, False
        self._reason: str | None = None
        self.stats: dict = {}

    def limits(self) -> limiter.JointLimits:
        """The FR3's published limits: q_min, q_max (rad), qd_max (rad/s), qdd_max (rad/s^2), qddd_max (rad/s^3), and
        qd_bounds "fr3": libfranka's position-dependent velocity limits (core/runtime/limiter.py) hold too."""
        return limiter.JointLimits(Q_MIN, Q_MAX, QD_MAX, QDD_MAX, QDDD_MAX, "fr3")

    def stop(self, reason: str) -> None:
        """End the motion at the next cycle (any thread, a signal handler too: no lock, which the interrupted
        thread could hold); the first reason given is kept."""
        if self._reason is None:
            self._reason = reason

    def run(self, control, report=None, sent=None) -> str:
        """Joint-velocity control at the robot's clock until a stop; returns its reason (one line). `report(kind,
        message, onset, during_stop)`: a fault this driver met itself (libfranka's exceptions, a bad command, a
        failure of `control`; during the stop: the ramp, the robot's stop), before it stops; `sent(state, command)`:
        each command of the stop (its ramp, then zero until the arm rests) with the state it was sent on.

        pylibfranka 0.21.3's `readOnce` keeps the interpreter lock while it waits for the robot's state
        (measured: a thread sleeping 0.5 ms at a time woke 122 times a second beside this loop, 1,857
        alone), so a reader thread in this process (the boards') would run once per 5 ms switch
        interval; while it runs, the interval is 0.1 ms, which gives such threads the interpreter once
        per cycle, between the robot's state and the tick (494 wakes a second)."""
        previous = sys.getswitchinterval()
        sys.setswitchinterval(SWITCH_S)
        try:
            with _own_scheduling():
                return self._run(control, report or _ignore, sent or _ignore)
        finally:
            sys.setswitchinterval(previous)
            self._reason = None  # honoured: the next run starts afresh

    def _run(self, control, report, on_sent) -> str:
        pf = self._pf
        errors = (pf.NetworkException, pf.ControlException, pf.CommandException, pf.RealtimeException,
                  pf.InvalidOperationException, pf.FrankaException)
        self.stats = st = {"ticks": 0, "states_skipped": 0, "longest_gap_ms": 0.0, "success_rate_min": 1.0,
                           "ramp_ticks": 0, "rate_limited_ticks": 0}
        if self._reason is not None:  # asked before the motion started: it never starts
            return self._end(self._reason, False, report)
        try:
            active = self._robot.start_joint_velocity_control(pf.ControllerMode.JointImpedance)
        except errors as e:
            report("driver", _fault(e), time.monotonic(), False)
            return _fault(e)
        sent, acc = np.zeros(7), np.zeros(7)
        seq = 0
        reason = None
        while reason is None:
            try:
                rs, gap = active.readOnce()
            except errors as e:  # the robot ended the motion (its reflex, the link): its own stop, watched to rest
                report("driver", _fault(e), time.monotonic(), False)
                st["zero_mono"] = time.monotonic()
                reason = self._end(_fault(e), False, report)
                self._observe(seq, on_sent)
                return reason
            seq += 1
            gap_ms = gap.to_sec() * 1e3
            st["ticks"] = seq
            if seq > 1:  # the first read's gap is the time since the motion was requested
                st["states_skipped"] += max(0, round(gap_ms) - 1)
                st["longest_gap_ms"] = max(st["longest_gap_ms"], gap_ms)
            st["success_rate_min"] = min(st["success_rate_min"], rs.control_command_success_rate)
            state = FrankaState(rs.time.to_sec(), np.array(rs.q), np.array(rs.dq), seq, sent.copy(),
                                rs.control_command_success_rate)
            if self.faults is not None:
                if self.faults.due("robot-die"):
                    died = "fr3: the driver stopped talking to the robot (injected)"
                    report("driver", died, self.faults.onsets["robot-die"], False)
                    st["zero_mono"] = time.monotonic()  # no ramp: the robot's own stop, asked now, is the stop
                    died = self._end(died, True, report)
                    self._observe(seq, on_sent)
                    return died
                state = self._faulty(state)
            reason = self._reason
            if reason is None:
                reason, cmd = _command(control, state)
                if reason is not None:  # the monitor's own stop (it ignores this report) or a failure of control
                    report("driver", reason, time.monotonic(), False)
            if reason is None:
                want = cmd
            else:  # this cycle already starts the ramp down
                want = np.zeros(7)
            if reason is None and not self.rate_limited:  # limited before (core/runtime/limiter.py): sent as is
                nxt, acc = want, (want - sent) / PERIOD_S
            else:  # a stop's first command is always limited: its ramp starts here
                nxt, acc = rate_limit(want, sent, acc)
            st["rate_limited_ticks"] += bool(reason is None and not np.array_equal(nxt, want))
            try:
                active.writeOnce(pf.JointVelocities(nxt.tolist()))
            except errors as e:
                report("driver", _fault(e), time.monotonic(), reason is not None)
                return self._end(_fault(e) if reason is None else f"{reason}; then {_fault(e)}", False, report)
            sent = nxt
        st["zero_mono"] = time.monotonic()  # the stop's first command went out: the ramp to zero has begun
        on_sent(state, sent)
        return self._ramp_down(active, sent, acc, reason, errors, report, on_sent)

    def _faulty(self, s: FrankaState) -> FrankaState:
        """The state through the plan's robot faults (`__init__`)."""
        f = self.faults
        if f.due("robot-freeze"):
            self._frozen = self._frozen or s
            return FrankaState(self._frozen.t, self._frozen.q, self._frozen.qd, s.seq, s.qd_sent, s.success_rate)
        if f.due("robot-nan"):
            s.q[0] = np.nan
        if f.due("robot-clock-back") and not self._back:
            self._back = True
            s.t -= CLOCK_BACK_S
        if f.due("robot-overrun"):
            self._skew += (OVERRUN_STEP - 1) * PERIOD_S
            s.t += self._skew
        return s

    def _ramp_down(self, active, sent, acc, reason: str, errors, report, on_sent) -> str:
        """Zero velocity at the robot's acceleration and jerk limits, one command per cycle, then zero until every
        joint's measured speed is below REST_QD, then finish; within RAMP_MAX_S, or a fault during the stop."""
        pf = self._pf
        seq = self.stats["ticks"]
        for _ in range(int(RAMP_MAX_S / PERIOD_S)):
            ramped = np.abs(sent).max() <= QDD_MAX.min() * PERIOD_S and np.abs(acc).max() <= QDDD_MAX.min() * PERIOD_S
            try:
                rs, _ = active.readOnce()
                seq += 1
                state = FrankaState(rs.time.to_sec(), np.array(rs.q), np.array(rs.dq), seq, sent.copy(),
                                    rs.control_command_success_rate)
                self.stats["rest_qd"] = float(np.abs(state.qd).max())  # the arm's speed as the ramp ends
                if ramped and self.stats["rest_qd"] < REST_QD:
                    cmd = pf.JointVelocities([0.0] * 7)
                    cmd.motion_finished = True
                    active.writeOnce(cmd)
                    on_sent(state, np.zeros(7))
                    return self._end(reason, False, report)
                sent, acc = rate_limit(np.zeros(7), sent, acc)
                active.writeOnce(pf.JointVelocities(sent.tolist()))
                on_sent(state, sent)
                self.stats["ramp_ticks"] += 1
            except errors as e:
                report("driver", f"fr3: during the stop: {_fault(e)[5:]}", time.monotonic(), True)
                return self._end(f"{reason}; then {_fault(e)}", False, report)
        report("driver", f"fr3: the stop's ramp did not bring the arm to rest in {RAMP_MAX_S:g} s (fastest joint "
               f"{self.stats.get('rest_qd', float('nan')):.3f} rad/s)", time.monotonic(), True)
        return self._end(f"{reason}; the ramp to zero did not finish in {RAMP_MAX_S} s", True, report)

    def _observe(self, seq: int, on_sent) -> None:
        """After the robot ended the motion itself (a libfranka exception) or the driver stopped talking (`robot-die`):
        the robot's own stop, watched from its state stream (`read_once`, no command) until every joint is below
        REST_QD, for at most RAMP_MAX_S; each state goes to
        `on_sent(state, None)` (nothing sent). `stats["rest_observed"]`: the arm was seen at rest; a state stream
        that fails ends the watch (the rest then unknown)."""
        self.stats["rest_observed"] = False
        for _ in range(int(RAMP_MAX_S / PERIOD_S)):
            try:
                rs = self._robot.read_once()
            except Exception:  # noqa: BLE001 - a robot gone entirely: the rest is unknown, and named so by the caller
                return
            seq += 1
            state = FrankaState(rs.time.to_sec(), np.array(rs.q), np.array(rs.dq), seq, np.zeros(7),
                                rs.control_command_success_rate)
            on_sent(state, None)
            if np.abs(state.qd).max() < REST_QD:
                self.stats["rest_observed"] = True
                return

    def _end(self, reason: str, motion_open: bool, report=None) -> str:
        """The robot's own stop after every motion (it ends one still open); its failure is named, and reported as a
        fault during the stop."""
        try:
            self._robot.stop()
        except Exception as e:  # noqa: BLE001 - a robot in reflex may refuse; the reason says so
            if motion_open:
                text = f"robot stop failed: {' '.join(str(e).split())}"
                reason = f"{reason}; {text}"
                if report is not None:
                    report("driver", f"fr3: {text}", time.monotonic(), True)
        return reason

    def close(self) -> None:
        """Disconnect (libfranka closes the connection when the robot object goes)."""
        self._robot = None


@contextlib.contextmanager
def _own_scheduling():
    """libfranka raises the calling thread to SCHED_FIFO 99 (its control loop's priority) and leaves it there:
    the caller's scheduling comes back after (a process that goes on, e.g. to start a browser, must not
    hand it that priority)."""
    policy, param = os.sched_getscheduler(0), os.sched_getparam(0)
    try:
        yield
    finally:
        with contextlib.suppress(OSError):
            os.sched_setscheduler(0, policy, param)


def _command(control, state: FrankaState) -> tuple[str | None, np.ndarray | None]:
    """(stop reason, None) or (None, the 7 joint velocities control returned)."""
    try:
        cmd = control(state)
    except Exception as e:  # noqa: BLE001 - any exception from control is a stop with its text as the reason
        return (str(e) or type(e).__name__), None
    if cmd is None:
        return "control ended the motion", None
    cmd = np.asarray(cmd, dtype=float)
    if cmd.shape != (7,) or not np.isfinite(cmd).all():
        return f"fr3: control returned {cmd.shape} joint velocities {np.round(cmd, 3).tolist()}; 7 finite values " \
               "expected", None
    return None, cmd


def _ignore(*_) -> None:
    pass
