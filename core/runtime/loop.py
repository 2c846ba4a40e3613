"""The safety loop: every period of the robot's clock, newest readings -> `SafetyStack.tick` -> the driver.

`Runtime.control(state)` is the driver's callback (core/runtime/protocol.py). One tick:
1. watchdogs, in this order (the first that fires names the stop): the skin source's named faults
   (a board silent for more than 2 frame periods, a CRC storm, frames from another uid, a counter
   that went back, a link lost), the robot's state not updating (its `seq` unchanged for
   `state_periods` ticks), a stale command source (`age() > stale_s`), then anything non-finite
   (robot clock, q, qd, a reading of a taxel that is not excluded, the planned command);
2. the readings (excluded taxels as 0 N, read after the plan so that a frame arriving while it was
   computed is used), the command source's planned velocity at the robot's clock
   since the start, and the MEASURED dt and qd go through `SafetyStack.tick`; a non-finite result
   is a stop too;
3. the command goes back to the driver; the recorder and the tap get the tick (never waited on).
A watchdog raises `StopRobot(reason)`: the driver sends zero velocity, then the robot's own stop.
Nothing resumes: the operator starts a new run. `stop_by_operator` (Ctrl-C) asks the driver to stop
from any thread.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from skinsafe.core.runtime.protocol import StopRobot
from skinsafe.core.runtime.tap import Frame, Tap
from skinsafe.core.runtime.tick_figures import Figure
from skinsafe.core.safety.limits import finite

STALE_KINDS = ("skin-silent", "robot-state", "command-stale")


@dataclass
class Outcome:
    reason: str  # one line: why the robot stopped
    kind: str  # end | fault | operator | driver
    watchdog: str = ""  # the watchdog that fired (fault): skin, skin-silent, robot-state, command-stale, nonfinite
    t: float = 0.0  # the robot's clock at the stop
    detected_mono: float = 0.0  # host time the stop was decided
    ticks: int = 0
    stats: dict = field(default_factory=dict)


class Runtime:
    """The loop for one driver, readings source, stack and command source."""

    def __init__(self, driver, source, stack, command, excluded: np.ndarray, thresholds: np.ndarray,
                 recorder=None, tap: Tap | None = None, seconds: float | None = None, state_periods: int = 2,
                 stale_s: float | None = None):
        self.driver, self.source, self.stack, self.command = driver, source, stack, command
        self.excluded = np.asarray(excluded, bool)
        self.thresholds = np.asarray(thresholds, float)
        self.recorder, self.tap, self.seconds = recorder, tap or Tap(), seconds
        self.state_periods, self.stale_s = int(state_periods), stale_s if stale_s is not None else command.stale_s
        self.outcome: Outcome | None = None
        self.ticks = 0
        self.period = Figure()  # s between the starts of consecutive ticks (host clock)
        self.robot_period = Figure()  # the same on the robot's clock
        self.work = Figure()  # s each tick took
        self.latency = Figure()  # s from a frame holding a contact to its command leaving
        self.waited = Figure()  # s of each such latency before the tick that used the frame began
        self.latency_at = Figure()  # the index of each such latency's tick
        self._t0 = self._prev_t = self._seq = self._start = self._last_t = self._first_start = None
        self._repeats = 0
        self._reading_seq = None
        self._force = None
        self._stopped = False
        self._state = None  # (state, readings) of the last tick

    # -- the callback ----------------------------------------------------------------------------
    def control(self, state) -> np.ndarray:
        start = time.monotonic()
        q, qd, t = state.q, state.qd, state.t
        if self._t0 is None:
            self._t0, self._prev_t, self._first_start = t, t, start
            self.command.start(q)
        else:
            self.period.add(start - self._start)
            self.robot_period.add(t - self._last_t)
        self._start, self._last_t = start, t
        planned, unplanned = self._plan(t, q)
        r = self.source.newest()  # after the plan: a frame that arrived meanwhile is this tick's
        self._state = (state, r)
        watchdog, why = self._watch(state, r)
        new = r.seq != self._reading_seq
        if new and not watchdog:
            self._force = np.where(self.excluded, 0.0, r.force)
            self._reading_seq = r.seq
            if not finite(self._force):
                bad = np.flatnonzero(~np.isfinite(self._force))
                watchdog, why = "nonfinite", f"non-finite reading on {len(bad)} taxel(s), first taxel {bad[0]}"
        if not watchdog and unplanned:
            watchdog, why, planned = "nonfinite", unplanned, None
        if not watchdog and self.seconds is not None and t - self._t0 >= self.seconds:
            self._stop(state, r, start, "end", "", f"the run ended after {self.seconds:g} s (--seconds)")
        if watchdog:
            self._stop(state, r, start, "fault", watchdog, why)
        dt = t - self._prev_t if self.ticks else self.driver.period_s  # measured on the robot's clock
        self._prev_t = t
        v = self.stack.tick(t, q, {"force": self._force}, planned, dt, qdot=qd)
        if not finite(v):
            self._stop(state, r, start, "fault", "nonfinite", "the layers' command is not finite")
        info = self.stack.info
        d = self.stack.defensiveness
        retracting, pool = bool(d is not None and d.active), int(len(d.pool)) if d is not None else 0
        now = time.monotonic()
        if new and (self._force > self.thresholds).any():
            self.latency.add(now - r.t)
            self.waited.add(start - r.t)
            self.latency_at.add(self.ticks)
        self.ticks += 1
        self.work.add(now - start)
        frame = Frame(t, q, self._force, v, retracting, pool, info.flags, "", planned, d.pool if retracting else None,
                      self.stack.last_f, speed_factor(v, planned), r.board_age_s, r.frames_lost)
        self.tap.publish(frame)
        if self.recorder is not None:
            self.recorder.put((time.time_ns(), self.ticks, t, dt, q, qd, self._force if new else None, float(r.seq),
                               planned, v, info.flags, retracting, pool, r.board_age_s, r.frames_lost,
                               self.command.age(), 1.0, frame.potential, frame.speed_factor, frame.pool_taxels))
        return v

    def _plan(self, t: float, q: np.ndarray) -> tuple[np.ndarray | None, str]:
        """The command source's planned velocity, or (None, why it has none)."""
        try:
            planned = np.asarray(self.command(t - self._t0, q), float)
        except StopRobot as e:
            return None, str(e)
        if not finite(planned):
            return None, f"command: {self.command.spec} planned a non-finite velocity"
        return planned, ""

    def _watch(self, state, r) -> tuple[str, str]:
        if r.faults:
            return ("skin-silent" if "silent" in r.faults[0] else "skin"), f"skin: {r.faults[0]}"
        if state.seq == self._seq:
            self._repeats += 1
            if self._repeats >= self.state_periods:
                return "robot-state", (f"robot: state not updating (seq {state.seq} for {self._repeats + 1} periods "
                                       f"of {self.driver.period_s * 1e3:g} ms)")
        else:
            self._seq, self._repeats = state.seq, 0
        age = self.command.age()
        if self.stale_s is not None and age > self.stale_s:
            return "command-stale", f"command: {self.command.spec} silent for {age:.3f} s (> {self.stale_s:g} s)"
        for name, x in (("robot clock", state.t), ("q", state.q), ("qd", state.qd)):
            if not finite(x):
                return "nonfinite", f"robot: non-finite {name}"
        return "", ""

    def _stop(self, state, r, start: float, kind: str, watchdog: str, reason: str) -> None:
        self.outcome = Outcome(reason, kind, watchdog, float(state.t), start, self.ticks)
        self._zero(state, r, reason)
        raise StopRobot(reason)

    def _zero(self, state, r, reason: str) -> None:
        """The stop's tick for the tap and the record: zero velocity, the stack not ticked."""
        self._stopped = True
        zero = np.zeros(len(state.q))
        self.tap.publish(Frame(state.t, state.q, self._force, zero, False, 0, (), reason, None, None, 0.0, 0.0,
                               r.board_age_s, r.frames_lost))
        if self.recorder is not None:
            self.recorder.put((time.time_ns(), self.ticks + 1, state.t, 0.0, state.q, state.qd, None,
                               float(r.seq), zero, zero, ("stop",), False, 0, r.board_age_s, r.frames_lost,
                               self.command.age(), 0.0))

    # -- the run ---------------------------------------------------------------------------------
    def stop_by_operator(self, why: str = "interrupted by the operator (Ctrl-C)") -> None:
        """Thread- and signal-safe: the driver stops at its next period."""
        if self.outcome is None:
            self.outcome = Outcome(why, "operator", "", float(self._prev_t or 0.0), time.monotonic(), self.ticks)
        self.driver.stop(why)

    def run(self, settle_s: float = 1.0) -> Outcome:
        """Hand `control` to the driver until the robot stops; the outcome names why. First every board must be
        streaming fresh frames (within `settle_s`): a board that went quiet while the stack was set up is
        no reason to stop, one that stays quiet, or any other skin fault, is."""
        deadline = time.monotonic() + settle_s
        while True:
            r = self.source.newest()
            other = [f for f in r.faults if "silent" not in f]
            fresh = max(r.board_age_s.values(), default=0.0) <= self.source.frame_period_s
            if other or (not fresh and time.monotonic() > deadline):
                why = other[0] if other else r.faults[0] if r.faults else "boards not streaming"
                self.outcome = Outcome(f"skin: {why} (before the robot moved)", "fault", "skin", 0.0, time.monotonic())
                return self.outcome
            if fresh:
                break
            time.sleep(self.source.frame_period_s / 4)
        reason = self.driver.run(self.control)
        if self.outcome is None:  # the driver stopped on its own (a communication fault, its own limits)
            self.outcome = Outcome(reason, "driver", "robot", float(self._prev_t or 0.0), time.monotonic(), self.ticks)
        if not self._stopped and self._state is not None:  # the operator's or the driver's stop: zero went out too
            self._zero(*self._state, self.outcome.reason)
        self.outcome.ticks = self.ticks
        self.outcome.stats = self.timing()
        return self.outcome

    def timing(self) -> dict:
        """Loop rate, period jitter (host clock; `_robot`: the robot's clock), work per tick and contact latency
        (ms) over the run; `latency_ms_all`, `latency_wait_ms_all` (its part before the tick began), `period_ms_all`
        (while a run has at most `tick_figures.KEEP` of them): every sample (a bench pools several runs'), with
        `latency_tick_all` (each latency's tick) and `start_mono` (the first tick's start, time.monotonic): tick k
        began at start_mono + the sum of the first k periods."""
        period, robot, work, lat = self.period, self.robot_period, self.work, self.latency

        def ms(f: Figure, p: float, empty: float = 0.0) -> float:
            return f.percentile(p) * 1e3 if f.n else empty

        def every(f: Figure) -> list[float]:
            x = f.exact()
            return [] if x is None else [round(float(v), 4) for v in x * 1e3]
        return {"ticks": self.ticks, "loop_hz_p50": 1e3 / ms(period, 50) if period.n else 0.0,
                "period_ms_p50": ms(period, 50), "period_ms_p99": ms(period, 99),
                "period_ms_max": period.max * 1e3 if period.n else 0.0,
                "loop_hz_robot_p50": 1e3 / ms(robot, 50) if robot.n and ms(robot, 50) > 0 else 0.0,
                "period_ms_robot_p99": ms(robot, 99), "period_ms_robot_max": robot.max * 1e3 if robot.n else 0.0,
                "robot_s": float(self._last_t - self._t0) if self._t0 is not None else 0.0,
                "work_ms_p50": ms(work, 50), "work_ms_p99": ms(work, 99),
                "work_ms_max": work.max * 1e3 if work.n else 0.0,
                "latency_samples": lat.n, "latency_ms_p50": ms(lat, 50, np.nan),
                "latency_ms_p99": ms(lat, 99, np.nan), "latency_ms_max": lat.max * 1e3 if lat.n else np.nan,
                "latency_ms_all": every(lat), "latency_wait_ms_all": every(self.waited), "period_ms_all": every(period),
                "latency_tick_all": [] if self.latency_at.exact() is None else self.latency_at.exact().astype(int).tolist(),
                "start_mono": self._first_start}


def speed_factor(v: np.ndarray, planned: np.ndarray | None) -> float:
    """|v| / |planned| (1 for a plan at rest): how much the layers slowed the plan this tick (> 1: a retraction)."""
    p = float(np.sqrt(planned @ planned)) if planned is not None else 0.0
    return float(np.sqrt(v @ v)) / p if p > 1e-12 else 1.0


def warm_up(stack, q: np.ndarray, thresholds: np.ndarray, dt: float, ticks: int = 20) -> None:
    """Tick the stack through contacts before the robot moves, then forget it all: numba compiles its
    kernels on the first retraction (seconds on a fresh install) and the QP solver loads on the first
    level where a constraint binds (milliseconds): neither may land on the robot's first contact. The
    contacts come while the arm moves fast each way, so the limits and no-push rows bind."""
    n = len(thresholds)
    zero = np.zeros(len(stack.vel_limits))
    for sign in (1.0, -1.0):
        for taxels in (np.array([n // 2]), np.linspace(0, n - 1, min(n, 3)).astype(int)):
            force = np.zeros(n)
            force[taxels] = 2 * thresholds.max() + 1.0
            moving = sign * 0.9 * stack.vel_limits
            for k in range(ticks):
                stack.tick(k * dt, q, {"force": force if k < 2 else np.zeros(n)}, zero, dt,
                           qdot=moving if k < 3 else zero)
            stack.reset()
    stack.flags.clear()
    if stack.defensiveness is not None:
        stack.defensiveness.flags.clear()
