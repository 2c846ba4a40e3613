"""The safety monitor: one small state machine decides every stop, its reason and its exit code.

    preflight -> armed -> moving <-> retracting
                   |        |           |
                   +--------+-----------+--> protective_stop (latched) --> ended
                                 moving --> ended (the run's planned end)

Every fault source (the boards' reader, the readings source, the robot's state, the driver, the command
source, the layers, the operator's signal) reports a typed `Fault` (its `Kind`, the source, a one-line
message and, where known, its onset on the host's `time.monotonic()`); the first one latches the
protective stop: zero velocity, then the robot's own stop, and nothing resumes (a new run is the
acknowledgement). No text is matched: the kind decides. A fault met while stopping (the driver's ramp,
the robot's stop, the link lost mid-stop) is kept too (`stop_failed`): the run's reason names it and
its exit code is 4, whatever stopped it. `report` takes no lock (a signal handler
calls it). Each kind has a stated detection bound (`bounds`); `skinsafe run` prints them with the
distance a taxel can travel blind within each (`table`); docs/run/safety.md's fault table is
`python -m skinsafe.core.runtime.monitor`'s output.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from enum import Enum

import numpy as np

HANDOFF_S = 0.005  # the boards' reader's wake-up on an event and its message through the pipe to the loop
OVERRUNS = 3  # consecutive overruns that stop (bound: K periods while the host's ticks are on time; a late host adds
# its lateness to each)
OVERRUN_PERIODS = 1.5  # a tick more than this many control periods after the last, on the robot's clock, is an overrun


class State(str, Enum):
    PREFLIGHT = "preflight"
    ARMED = "armed"
    MOVING = "moving"
    RETRACTING = "retracting"
    PROTECTIVE_STOP = "protective_stop"
    ENDED = "ended"


class Kind(str, Enum):
    """What went wrong (the values are what hardware/ reports: it cannot import this module)."""

    READER_DIED = "reader-died"
    READER_STALLED = "reader-stalled"
    LINK_LOST = "link-lost"
    BOARD_SILENT = "board-silent"
    BOARD_LATE = "board-late"
    COUNTER_BACK = "counter-back"
    FOREIGN_UID = "foreign-uid"
    CRC_STORM = "crc-storm"
    READING_NONFINITE = "reading-nonfinite"
    ROBOT_FROZEN = "robot-frozen"
    ROBOT_CLOCK_BACK = "robot-clock-back"
    ROBOT_NONFINITE = "robot-nonfinite"
    DRIVER = "driver"
    COMMAND_STALE = "command-stale"
    COMMAND_BAD = "command-bad"
    COMMAND_INTRUDER = "command-intruder"
    STACK_NONFINITE = "stack-nonfinite"
    STACK_LATCH = "stack-latch"
    OVERRUN = "overrun"
    OPERATOR = "operator"
    AFTER_CONTACT = "after-contact"


@dataclass(frozen=True)
class Fault:
    kind: Kind
    source: str  # who reported it: skin, board '<name>', robot, command, layers, operator
    message: str  # one line
    onset: float | None = None  # host time.monotonic() the fault began, where its source knows it


@dataclass(frozen=True)
class Spec:
    detection: str
    leaves: str  # the state the robot is left in
    test: str  # the test that shows it


STOP = "zero velocity, then the robot's own stop; latched until a new run"
SPECS = {
    Kind.READER_DIED: Spec("the reader process's pidfd and pipe polled every tick (not its silence); + 5 ms for its exit", STOP,
                           "tests/runtime/test_runtime_safety.py::test_reader_death_after_a_settle_stall_is_named"),
    Kind.READER_STALLED: Spec("the reader's heartbeat older than a board may be silent (host overloaded)", STOP,
                              "tests/runtime/test_fault_bench.py::test_every_sim_fault_kind_is_one_row_stopped_within_"
                              "its_bound"),
    Kind.LINK_LOST: Spec("the port's hang-up (EPOLLHUP) or a failed read; that board's taxels read NaN", STOP,
                         "tests/runtime/test_runtime_closed_loop.py::test_every_watchdog_stops_the_robot_naming_why"),
    Kind.BOARD_SILENT: Spec("no frame for 2 frame periods + --link-latency; that board's taxels read NaN", STOP,
                            "tests/runtime/test_runtime_closed_loop.py::test_every_watchdog_stops_the_robot_naming_why"),
    Kind.BOARD_LATE: Spec("a frame older than the silence bound by the board's own clock (not by arrival), or "
                          "between arrivals its newest frame older than that + half a frame period; taxels NaN", STOP, "tests/runtime/test_runtime_safety.py::test_late_but_steady_frames_stop_the_robot"),
    Kind.COUNTER_BACK: Spec("a frame counter not ahead of the last (replayed or stale frame, board reset); every "
                            "frame of a burst", STOP,
                            "tests/runtime/test_fault_bench.py::test_every_sim_fault_kind_is_one_row_stopped_within_its_"
                            "bound"),
    Kind.FOREIGN_UID: Spec("a frame with another board's uid on a board's port", STOP,
                           "tests/runtime/test_fault_bench.py::test_every_sim_fault_kind_is_one_row_stopped_within_its_"
                           "bound"),
    Kind.CRC_STORM: Spec("a board silent with corrupt frames since its last good one, or 5 corrupt frames within 1 s",
                         STOP,
                         "tests/runtime/test_runtime_closed_loop.py::test_every_watchdog_stops_the_robot_naming_why"),
    Kind.READING_NONFINITE: Spec("a non-finite reading on a taxel that is not excluded, at the loop's next tick after "
                                 "its frame", STOP,
                                 "tests/runtime/test_runtime_safety.py::test_stack_and_reading_faults_are_named_from_"
                                 "their_source"),
    Kind.ROBOT_FROZEN: Spec("the robot's own clock unchanged for 2 periods (not a host counter)", STOP,
                            "tests/runtime/test_runtime_safety.py::test_the_robot_watchdog_watches_the_robots_own_clock"),
    Kind.ROBOT_CLOCK_BACK: Spec("the robot's own clock going back", STOP,
                                "tests/runtime/test_runtime_safety.py::test_the_robot_watchdog_watches_the_robots_own_clock"),
    Kind.ROBOT_NONFINITE: Spec("a non-finite robot clock, q or qd", STOP,
                               "tests/runtime/test_runtime_safety.py::test_a_non_finite_robot_state_or_teleop_target_is_"
                               "typed"),
    Kind.DRIVER: Spec("the driver's own fault, reported with its onset (communication lost, the simulation failed, "
                      "the robot's reflex, the control callback failed)",
                      "the robot's own stop (the robot or its driver stopped it)",
                      "tests/runtime/test_fr3_driver.py::test_fr3_robot_gone_is_named; tests/runtime/test_stopping.py::"
                      "test_a_driver_fault_reaches_the_monitor_with_its_onset"),
    Kind.COMMAND_STALE: Spec("no teleop datagram for --command-timeout", STOP,
                             "tests/runtime/test_runtime_closed_loop.py::test_every_watchdog_stops_the_robot_naming_why"),
    Kind.COMMAND_BAD: Spec("a non-finite plan or teleop target", STOP,
                           "tests/runtime/test_runtime_safety.py::test_a_non_finite_robot_state_or_teleop_target_is_"
                           "typed"),
    Kind.COMMAND_INTRUDER: Spec("3 teleop datagrams refused within 1 s (not from the leader, malformed, failing the "
                                "key's HMAC, replayed, jumped ahead, off the clock), at the next tick; none of them "
                                "moves the robot; onset: the first's arrival", STOP,
                                "tests/runtime/test_teleop.py::test_an_intruder_never_moves_the_robot_and_is_named"),
    Kind.STACK_NONFINITE: Spec("a non-finite command from the layers, in the tick that made it", STOP,
                               "tests/runtime/test_runtime_safety.py::test_stack_and_reading_faults_are_named_from_"
                               "their_source"),
    Kind.STACK_LATCH: Spec("the retraction's QP solve failed (in that tick), a retraction pushed a contacted taxel 2 "
                           "mm further into its contact than braking allows (in that tick), or a retraction with "
                           "ticks flagged infeasible ended (it never resumes the plan)", STOP,
                           "tests/runtime/test_runtime_safety.py::test_stack_and_reading_faults_are_named_from_their_"
                           "source; tests/runtime/test_runtime_closed_loop.py::test_a_trajectory_into_the_post_is_"
                           "turned_back; tests/runtime/test_stopping.py::test_pushing_into_a_contact_beyond_braking_"
                           "latches"),
    Kind.OVERRUN: Spec("--overruns K (default 3) consecutive ticks, each more than 1.5 control periods after the last "
                       "on the robot's own clock (its states missed, as libfranka counts them); onset: the first's "
                       "start", STOP,
                       "tests/runtime/test_runtime_safety.py::test_consecutive_overruns_on_the_robots_clock_stop_it"),
    Kind.OPERATOR: Spec("SIGINT or SIGTERM (each further signal only sets the same flag)", STOP,
                        "tests/runtime/test_fr3_driver.py::test_fr3_ctrl_c_twice_stops_once_and_keeps_the_record"),
    Kind.AFTER_CONTACT: Spec("a retraction ended under --after-contact hold", STOP,
                             "tests/runtime/test_runtime_safety.py::test_after_contact_hold_latches_after_the_retraction"),
}


@dataclass(frozen=True)
class Timing:
    """What the bounds depend on (s)."""

    period_s: float  # the robot's control period
    frame_period_s: float  # a board's frame period
    silence_s: float  # a board is silent after this long (2 frame periods + --link-latency)
    stale_s: float | None = None  # the command source's timeout (teleop)
    state_periods: int = 2
    overruns: int = OVERRUNS  # consecutive overruns that stop (0: off)


def bounds(tm: Timing) -> dict[Kind, float]:
    """Each kind's detection bound, s: from its onset to the tick that stops (the zero goes out in that tick). A kind
    the loop judges from a time (the command source's age) is seen by the tick after the time passes, whose zero
    goes out at the end of its work: 2 periods."""
    p, board = tm.period_s, 2 * tm.period_s + HANDOFF_S  # a reader's event reaches the loop's next tick
    return {Kind.READER_DIED: 2 * p + HANDOFF_S, Kind.READER_STALLED: tm.silence_s + 2 * p, Kind.LINK_LOST: board,
            Kind.BOARD_SILENT: tm.silence_s + board, Kind.BOARD_LATE: tm.silence_s + tm.frame_period_s + board,
            Kind.COUNTER_BACK: board, Kind.FOREIGN_UID: board, Kind.CRC_STORM: tm.silence_s + board,
            Kind.READING_NONFINITE: 2 * p, Kind.ROBOT_FROZEN: (tm.state_periods + 1) * p, Kind.ROBOT_CLOCK_BACK: p,
            Kind.ROBOT_NONFINITE: p, Kind.DRIVER: p,
            Kind.COMMAND_STALE: (tm.stale_s or 0.0) + 2 * p, Kind.COMMAND_BAD: p, Kind.COMMAND_INTRUDER: 2 * p, Kind.STACK_NONFINITE: p,
            Kind.STACK_LATCH: p, Kind.OVERRUN: tm.overruns * p, Kind.OPERATOR: 2 * p, Kind.AFTER_CONTACT: p}


def fastest_taxel_speed(J: np.ndarray, qd_max: np.ndarray) -> float:
    """An upper bound of the fastest taxel's speed, m/s: max over taxels of sum_j |J_lin[:, j]| qd_max_j
    (J (N, 6, n), linear rows first)."""
    return float((np.linalg.norm(J[:, :3], axis=1) @ np.asarray(qd_max, float)).max()) if len(J) else 0.0


STOP_CATEGORY = {k: 2 for k in Kind} | {Kind.DRIVER: None}
# IEC 60204-1's stop category each kind gets: 2, a controlled stop with power kept (the runtime's zero velocity, the
# drivers' ramps at their acceleration limits, then the arm held: the sim's servos where it rests, the FR3's controller);
# None for `driver`: the robot's (or its driver's) own stop, not this runtime's to state


def braking(qd, qdd, qddd=None) -> tuple[np.ndarray, np.ndarray]:
    """The braking model of the printed stopping bounds, per joint from speed `qd` after the zero command: at the
    acceleration limit `qdd`, and with a jerk limit `qddd` the acceleration first reversed and then ramped (2 qdd /
    qddd more, counted at full speed): (time to rest s, angle rad) = (qd/qdd + 2 qdd/qddd, qd^2/(2 qdd) + 2 qd
    qdd/qddd)."""
    qd, qdd = np.abs(np.asarray(qd, float)), np.asarray(qdd, float)
    ramp = 0.0 if qddd is None else 2 * qdd / np.asarray(qddd, float)
    return qd / qdd + ramp, qd ** 2 / (2 * qdd) + qd * ramp


RESPONSE_PERIODS = 2  # the zero reaches the robot in its next period, its measured state shows it one period later


def stopping(tm: Timing, J: np.ndarray, qd, qdd, qddd=None) -> dict[Kind, tuple[float, float]]:
    """Each kind's stopping bound with every joint at `qd` when the fault begins: (time s: its detection bound, the
    robot's response (RESPONSE_PERIODS periods at speed), then the slowest joint's braking; distance m: the furthest
    taxel's, sum_j |J_lin[:, j]| (qd_j x (detection + response) + its braking angle_j), J (N, 6, n) at the pose)."""
    t_b, angle = braking(qd, qdd, qddd)
    arm = np.linalg.norm(J[:, :3], axis=1) if len(J) else np.zeros((0, len(t_b)))
    qd = np.abs(np.asarray(qd, float))
    lag = RESPONSE_PERIODS * tm.period_s
    return {k: (b + lag + float(t_b.max()), float((arm @ (qd * (b + lag) + angle)).max()) if len(arm) else 0.0)
            for k, b in bounds(tm).items()}


def travel(kin, q_path, most: int = 50) -> np.ndarray:
    """Each taxel's stopping distance (N,), m: the furthest it got from where it was at the first of the measured
    joint states `q_path` (the onset), over them (at most `most`, evenly chosen; a state with a non-finite q places no
    taxel and is skipped). `kin`: the arm's TaxelKinematics."""
    path = np.asarray(q_path, float)
    path = path[np.isfinite(path).all(axis=1)] if path.ndim == 2 else np.zeros((0, 0))
    if not len(path):
        return np.full(kin.n, np.nan)
    path = path[np.unique(np.linspace(0, len(path) - 1, min(len(path), most)).round().astype(int))]
    p0 = kin.poses(path[0])[0].copy()
    far = np.zeros(kin.n)
    for q in path[1:]:
        np.maximum(far, np.linalg.norm(kin.poses(q)[0] - p0, axis=1), out=far)
    return far


def table(tm: Timing, speed: float = 0.0) -> list[tuple[str, float, float, str]]:
    """[(kind, bound ms, blind distance mm = speed x bound, detection)] for the kinds that apply."""
    b = bounds(tm)
    return [(k.value, b[k] * 1e3, speed * b[k] * 1e3, SPECS[k].detection) for k in Kind
            if (k not in (Kind.COMMAND_STALE, Kind.COMMAND_INTRUDER) or tm.stale_s is not None) and (k is not Kind.OVERRUN or tm.overruns)]


@dataclass
class Decision:
    """The monitor's verdict at the end of a run."""

    state: State
    fault: Fault | None
    reason: str
    exit_code: int
    detected: float  # host time.monotonic() the stop was decided
    during_stop: tuple = ()  # the faults met while stopping (the stop itself failed)

    @property
    def kind(self) -> str:
        """end | operator | driver | fault (what `skinsafe run` prints and records)."""
        if self.fault is None:
            return "end"
        return {Kind.OPERATOR: "operator", Kind.DRIVER: "driver"}.get(self.fault.kind, "fault")


AFTER_CONTACT = {"resume": "the plan goes on after a clean retraction, as in the paper (default); one with ticks "
                            "flagged infeasible latches a protective stop when it ends",
                 "hold": "a protective stop once any retraction ends",
                 "always-resume": "the plan goes on after every retraction, flagged or not: for benches that measure "
                                  "repeated contacts, never near people (refused on a hardware robot)"}


class Monitor:
    """The state machine (module docstring). `after_contact`: what a retraction's end does (`AFTER_CONTACT`)."""

    def __init__(self, after_contact: str = "resume"):
        if after_contact not in AFTER_CONTACT:
            raise ValueError(f"--after-contact {after_contact}: use {', '.join(AFTER_CONTACT)}")
        self.after_contact = after_contact
        self.state = State.PREFLIGHT
        self.fault: Fault | None = None
        self.detected = 0.0
        self.signum = 0
        self._end = ""
        self.during_stop: list[Fault] = []  # faults met while stopping (`stop_failed`)
        self._unclean: set[str] = set()  # the flags of concern seen during the current retraction

    @property
    def stopped(self) -> bool:
        return self.fault is not None or bool(self._end)

    @property
    def reason(self) -> str:
        return self.fault.message if self.fault is not None else self._end

    def report(self, fault: Fault) -> None:
        """A fault: the first latches the protective stop (no lock: a signal handler calls this)."""
        if self.fault is None and not self._end:
            self.fault, self.detected = fault, time.monotonic()
            self.state = State.PROTECTIVE_STOP

    def stop_failed(self, fault: Fault) -> None:
        """A fault met while stopping (the ramp, the robot's stop, the link lost mid-stop): kept, named in the reason,
        and the run's exit code is 4. Before any stop it is the stop's own fault."""
        if not self.stopped:
            self.report(fault)
        else:
            self.during_stop.append(fault)

    def signal(self, signum: int, name: str) -> None:
        """The operator's SIGINT / SIGTERM: the first one is the stop; every further one only sets the same flag."""
        if not self.signum:
            self.signum = signum
        self.report(Fault(Kind.OPERATOR, "operator", f"interrupted by the operator ({name})", time.monotonic()))

    def arm(self) -> None:
        if self.state is State.PREFLIGHT:
            self.state = State.ARMED

    def tick(self, retracting: bool, flags: tuple = ()) -> None:
        """A tick went out: moving, or retracting (`flags`: the layers' flags of concern this tick). The end of a
        retraction whose ticks were flagged, or any under `hold`, latches the stop: only a clean one resumes."""
        if self.stopped:
            return
        if retracting and flags and self.after_contact != "always-resume":
            self._unclean.update(flags)
        if self.state is State.RETRACTING and not retracting and self._unclean:
            self.report(Fault(Kind.STACK_LATCH, "layers", f"layers: the retraction ended after ticks flagged "
                              f"{', '.join(sorted(self._unclean))}: protective stop (latched until a new run)",
                              time.monotonic()))
        elif self.state is State.RETRACTING and not retracting and self.after_contact == "hold":
            self.report(Fault(Kind.AFTER_CONTACT, "layers", "the retraction ended; --after-contact hold keeps the "
                              "robot stopped until a new run", time.monotonic()))
        else:
            self.state = State.RETRACTING if retracting else State.MOVING

    def end(self, reason: str) -> None:
        """The run's planned end (--seconds): not a fault."""
        if not self.stopped:
            self._end, self.detected = reason, time.monotonic()

    def decide(self) -> Decision:
        """After the driver returned: the run is over; its reason and exit code."""
        stop = self.state
        self.state = State.ENDED
        during = tuple(self.during_stop)
        then = "".join(f"; then, while stopping: {f.message}" for f in during)
        if self.fault is None:
            return Decision(stop, None, (self._end or "the run ended") + then, 4 if during else 0, self.detected, during)
        code = 4 if during else 128 + self.signum if self.fault.kind is Kind.OPERATOR else 1
        return Decision(stop, self.fault, self.fault.message + then, code, self.detected, during)


def markdown(tm: Timing, speed: float, stops: dict[Kind, tuple[float, float]] | None = None) -> str:
    """The fault table of docs/run/safety.md (`stops`: `stopping`'s bounds, for the stop columns)."""
    b = bounds(tm)
    rows = ["| fault | detection | bound (ms) | blind distance (mm) | stop within (ms) | stopping distance (mm) | "
            "leaves the robot (stop category) | test |", "|---|---|---:|---:|---:|---:|---|---|"]
    for k in Kind:
        s = SPECS[k]
        t, d = (stops or {}).get(k, (float("nan"), float("nan")))
        cat = "the robot's own" if STOP_CATEGORY[k] is None else str(STOP_CATEGORY[k])
        rows.append(f"| `{k.value}` | {s.detection} | {b[k] * 1e3:.1f} | {speed * b[k] * 1e3:.1f} | {t * 1e3:.0f} | "
                    f"{d * 1e3:.0f} | {s.leaves} ({cat}) | `{s.test}` |")
    return "\n".join(rows)


def sim_defaults_table() -> tuple[float, str]:
    """The fastest taxel's speed (m/s) and the table for `skinsafe run --robot sim`'s defaults (2 ms period, boards
    at 100 Hz, no link latency, teleop timeout 0.1 s) on the UR5 sample skin, its fastest taxel at home with every
    joint at its limit (docs/run/safety.md's fault table)."""
    from skinsafe.core.design.sample import make_sample_design
    from skinsafe.core.robot.kinematics import TaxelKinematics
    from skinsafe.core.robot.models import build_ur5

    robot = build_ur5()
    design = make_sample_design("ur5", robot=robot)
    J = TaxelKinematics(robot.model, design).jacobians_of(np.arange(design.n_taxels), robot.home)[0]
    speed = fastest_taxel_speed(J, robot.vel_limits)
    tm = Timing(0.002, 0.01, 0.02, 0.1)
    return speed, markdown(tm, speed, stopping(tm, J, robot.vel_limits, robot.acc_limits))


def main() -> None:
    speed, text = sim_defaults_table()
    print(f"UR5 sample skin, fastest taxel {speed:.2f} m/s; `skinsafe run --robot sim` defaults\n")
    print(text)


if __name__ == "__main__":
    main()
