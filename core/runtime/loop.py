"""The safety loop: every period of the robot's clock, newest readings -> `SafetyStack.tick` -> the driver.

`Runtime.control(state)` is the driver's callback (core/runtime/protocol.py). One tick:
1. every fault source reports to the safety monitor (core/runtime/monitor.py) as a typed fault: the
   command source (a non-finite plan), the skin source's faults (the reader's death from its pidfd, a
   board lost, silent, late by its own clock, replayed, foreign, a CRC storm), the robot's own clock
   (unchanged for `state_periods` ticks, or going back: never a host counter; `overruns` ticks in a row more
   than 1.5 periods apart on it: its states were missed), a stale command source
   (`age() > stale_s`), a sender other than the teleop leader that keeps trying (`intrusion`), anything non-finite (robot clock, q, qd, a reading of a taxel that is not
   excluded); the monitor alone decides the stop;
2. the readings (excluded taxels as 0 N, read after the plan so that a frame arriving while it was
   computed is used), the command source's planned velocity at the robot's clock since the start, and
   the MEASURED dt and qd go through `SafetyStack.tick`; a non-finite result or a failed QP solve
   latches a stop too; a retraction with ticks flagged infeasible latches one when it ends (a contact
   at speed flags its first ticks by physics: the retraction is let finish, the plan never resumes),
   as does any retraction's end under `--after-contact hold`;
3. the one command limiter (core/runtime/limiter.py: position, velocity, acceleration, jerk) makes the
   command the driver sends (never non-finite), which is checked as sent, the stack is told it, and that
   is what the recorder and the tap get (never waited on).
A stop raises `StopRobot(reason)`: the driver sends zero velocity (the FR3: a ramp), then the robot's own
stop; every command it sends meanwhile comes back through `sent` with the measured state, until the arm
rests, so the record holds what was sent and the stop's end (`Outcome.stopping`: onset -> every joint
below REST_QD on the robot's clock, and the arm's path since the onset). The driver reports the faults it
meets itself through `report` (with their onset), those while stopping too: the monitor decides and names.
Nothing resumes: the operator starts a new run. `stop_by_operator` (a signal) asks the driver to stop
from any thread; every further signal only sets the same flag.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from skinsafe.core.runtime.limiter import Limiter
from skinsafe.core.runtime.monitor import OVERRUN_PERIODS, OVERRUNS, Fault, Kind, Monitor
from skinsafe.core.runtime.protocol import StopRobot
from skinsafe.core.runtime.tap import Tap
from skinsafe.core.runtime.tick import Tick
from skinsafe.core.runtime.tick_figures import Figure
from skinsafe.core.safety.limits import finite

# the flag of a tick that makes its retraction latch a stop when it ends: no command met the no-push rows within the
# limits. Not `pushing`: it flags any measured motion into a contact above 1e-9 (franky-sim's joint-velocity jitter
# under a hand's touch flags it in a clean retraction)
UNCLEAN = ("infeasible",)
SETTLING = (Kind.BOARD_SILENT, Kind.BOARD_LATE, Kind.READER_STALLED)  # may pass before the robot moves (a stall)
BRAKES = ("nonfinite:tdm", "nonfinite:potential")  # the layers' own brakes on a non-finite model output: latched
REST_QD = 0.02  # rad/s: the arm is at rest when every joint's measured speed is below this
# m a retraction may push a contacted taxel into its contact beyond braking from its speed into it: 100x what
# franky-sim's joint-velocity jitter integrates to under a hand's touch (0.007-0.017 mm in 6 s runs, clean
# retractions), and above the sim's servo lag through a contact at 0.2 rad/s (1.2 mm in all, braking included)
PUSH_MARGIN_M = 0.002
HISTORY = 4096  # ticks of the arm's state kept for the stop's figures (4 s at 1 kHz)


@dataclass
class Outcome:
    reason: str  # one line: why the robot stopped
    kind: str  # end | fault | operator | driver
    watchdog: str = ""  # the fault's kind (monitor.Kind value); "" for the planned end
    t: float = 0.0  # the robot's clock at the stop
    detected_mono: float = 0.0  # host time the stop was decided
    ticks: int = 0
    stats: dict = field(default_factory=dict)
    onset_mono: float | None = None  # host time the fault began, where its source knows it
    exit_code: int = 0
    state: str = ""  # the monitor's state when the run ended (protective_stop: latched)
    stopping: dict = field(default_factory=dict)  # `Runtime.stopping()`: onset -> rest, the arm's path meanwhile
    during_stop: tuple = ()  # the faults met while stopping


def _skin_faults(r) -> list[Fault]:
    return [Fault(Kind(kind), source, f"skin: {text}", onset) for kind, source, text, onset in r.faults]


class Runtime:
    """The loop for one driver, readings source, stack and command source."""

    def __init__(self, driver, source, stack, command, excluded: np.ndarray, thresholds: np.ndarray,
                 recorder=None, tap: Tap | None = None, seconds: float | None = None, state_periods: int = 2,
                 stale_s: float | None = None, monitor: Monitor | None = None, limiter: Limiter | None = None,
                 overruns: int = OVERRUNS, faults=None):
        """`faults`: a run's FaultPlan (core/runtime/fault_plan.py): from its `command-nan` on, the command source's
        plan is non-finite."""
        self.faults = faults
        self.driver, self.source, self.stack, self.command = driver, source, stack, command
        self.excluded = np.asarray(excluded, bool)
        self.thresholds = np.asarray(thresholds, float)
        self.recorder, self.tap, self.seconds = recorder, tap or Tap(), seconds
        self.state_periods, self.stale_s = int(state_periods), stale_s if stale_s is not None else command.stale_s
        self.monitor = monitor or Monitor()
        self.limiter = limiter
        self.outcome: Outcome | None = None
        self.ticks = 0
        self.period = Figure()  # s between the starts of consecutive ticks (host clock)
        self.robot_period = Figure()  # the same on the robot's clock
        self.work = Figure()  # s each tick took
        self.off_cpu = Figure()  # s of each tick's work its thread was not on a CPU (wall - the thread's CPU time)
        self._slowest = (0.0, 0.0)  # the slowest tick's work and its off-CPU part, s
        self.latency = Figure()  # s from a frame holding a contact to its command leaving
        self.waited = Figure()  # s of each such latency before the tick that used the frame began
        self.latency_at = Figure()  # the index of each such latency's tick
        self._t0 = self._prev_t = self._start = self._last_t = self._first_start = None
        self._repeats, self._repeat_onset = 0, 0.0
        self._pushed = self.push_mm_max = 0.0  # m into a contact during the current retraction; its largest, mm
        self._push_bound: float | None = None  # m: the current retraction's (`_push`)
        self.overruns = int(overruns)  # consecutive overruns that stop (0: off)
        self._overran, self._overrun_onset = 0, 0.0  # the current run of overruns, its first tick's start
        self.overrun_ticks = self.overrun_run_max = 0
        self._reading_seq = None
        self._force = None
        self._stopped = False
        self._state = None  # (state, readings) of the last tick
        self._sent = None  # the last command the driver sent
        self._after = 0  # ticks after the stop (the driver's ramp or hold)
        self._hist = None  # (mono, t, max |qd|, q) of the last HISTORY ticks, before and after the stop
        self._n = 0

    # -- the callback ----------------------------------------------------------------------------
    def control(self, state) -> np.ndarray:
        start, cpu = time.monotonic(), time.thread_time()
        m = self.monitor
        q, qd, t = state.q, state.qd, state.t
        if self._t0 is None:
            self._t0, self._prev_t, self._first_start = t, t, start
            self.command.start(q)
            m.tick(False)
        else:
            self.period.add(start - self._start)
            self.robot_period.add(t - self._last_t)
            self._overrun(t - self._last_t, start)
        self._keep(start, state)
        self._watch_robot(state)  # first: a broken robot state is named as such, not by what it breaks downstream
        planned = self._plan(t, q)
        r = self.source.newest()  # after the plan: a frame that arrived meanwhile is this tick's
        self._state = (state, r)
        self._watch(r)
        new = r.seq != self._reading_seq
        if new and not m.stopped:
            self._force = np.where(self.excluded, 0.0, r.force)
            self._reading_seq = r.seq
            if not finite(self._force):
                bad = np.flatnonzero(~np.isfinite(self._force))
                m.report(Fault(Kind.READING_NONFINITE, "skin", f"non-finite reading on {len(bad)} taxel(s), first "
                               f"taxel {bad[0]}", start))
        if self.seconds is not None and t - self._t0 >= self.seconds:
            m.end(f"the run ended after {self.seconds:g} s (--seconds)")
        self._start, self._last_t = start, t
        if m.stopped:
            self._stop(state, r)
        dt = t - self._prev_t if self.ticks else self.driver.period_s  # measured on the robot's clock
        self._prev_t = t
        # a repeated robot clock (dt 0) is the robot watchdog's to name: the layers tick on the period meanwhile
        v = self.stack.tick(t, q, {"force": self._force}, planned, dt if dt > 0 else self.driver.period_s, qdot=qd)
        self._judge(v, start)
        if self.limiter is not None and not m.stopped:
            v = self.stack.last = self.limiter(v, q, dt)  # what is sent: the stack's next tick starts from it
        self._check_sent(v, len(q), start)
        info = self.stack.info
        d = self.stack.defensiveness
        retracting, pool = bool(d is not None and d.active), int(len(d.pool)) if d is not None else 0
        self._push(retracting, info.push_speed, dt, d, start)
        m.tick(retracting, tuple(f for f in info.flags if f in UNCLEAN))
        if m.stopped:
            self._stop(state, r)
        now = time.monotonic()
        if new and (self._force > self.thresholds).any():
            self.latency.add(now - r.t)
            self.waited.add(start - r.t)
            self.latency_at.add(self.ticks)
        self.ticks += 1
        self.work.add(now - start)
        off = max(0.0, (now - start) - (time.thread_time() - cpu))
        self.off_cpu.add(off)
        if now - start > self._slowest[0]:
            self._slowest = (now - start, off)
        tick = Tick(t=t, q=q, qd=qd, dt=dt, command=v, force=self._force, force_new=new, reading_seq=float(r.seq),
                    planned=planned, retracting=retracting, pool=pool, pool_taxels=d.pool if retracting else None,
                    flags=info.flags, potential=self.stack.last_f, speed_factor=speed_factor(v, planned),
                    board_age_s=r.board_age_s, frames_lost=r.frames_lost, command_age=self.command.age(),
                    command_refused=self.command.refused, index=self.ticks, ns=time.time_ns())
        self.tap.publish(tick)
        if self.recorder is not None:
            self.recorder.put(tick)
        return v

    def _plan(self, t: float, q: np.ndarray) -> np.ndarray | None:
        """The command source's planned velocity (None, reported, when it has none)."""
        try:
            planned = np.asarray(self.command(t - self._t0, q), float)
            if self.faults is not None and self.faults.due("command-nan"):
                planned = np.full_like(planned, np.nan)
        except StopRobot as e:
            self.monitor.report(Fault(Kind.COMMAND_BAD, "command", str(e), time.monotonic()))
            return None
        if not finite(planned):
            self.monitor.report(Fault(Kind.COMMAND_BAD, "command", f"command: {self.command.spec} planned a "
                                      "non-finite velocity", time.monotonic()))
            return None
        return planned

    def _watch(self, r) -> None:
        """The skin's faults, the command source's age and its intruders."""
        m = self.monitor
        for f in _skin_faults(r):
            m.report(f)
        intrusion = self.command.intrusion
        if intrusion is not None:
            m.report(Fault(Kind.COMMAND_INTRUDER, "command", intrusion.message, intrusion.onset))
        age = self.command.age()
        if self.stale_s is not None and age > self.stale_s:
            m.report(Fault(Kind.COMMAND_STALE, "command", f"command: {self.command.spec} silent for {age:.3f} s "
                           f"(> {self.stale_s:g} s)", time.monotonic() - (age - self.stale_s)))

    def _watch_robot(self, state) -> None:
        """The robot's own clock (frozen, going back) and a non-finite robot state."""
        m = self.monitor
        for name, x in (("robot clock", state.t), ("q", state.q), ("qd", state.qd)):
            if not finite(x):
                m.report(Fault(Kind.ROBOT_NONFINITE, "robot", f"robot: non-finite {name}", time.monotonic()))
        if self._last_t is not None and state.t < self._last_t:
            m.report(Fault(Kind.ROBOT_CLOCK_BACK, "robot", f"robot: its clock went back from {self._last_t:.4f} s to "
                           f"{state.t:.4f} s", time.monotonic()))
        elif self._last_t is not None and state.t == self._last_t:
            self._repeats += 1
            self._repeat_onset = self._start if self._repeats == 1 else self._repeat_onset  # the state that repeats
            if self._repeats >= self.state_periods:
                m.report(Fault(Kind.ROBOT_FROZEN, "robot", f"robot: state not updating (its clock at {state.t:.4f} s "
                               f"for {self._repeats + 1} periods of {self.driver.period_s * 1e3:g} ms)",
                               self._repeat_onset))
        else:
            self._repeats = 0

    def _overrun(self, gap: float, start: float) -> None:
        """A tick more than OVERRUN_PERIODS after the last on the robot's clock: its states were missed; `overruns`
        in a row stop (onset: the first one's start)."""
        if not gap > OVERRUN_PERIODS * self.driver.period_s:  # NaN or a clock going back: _watch names them
            self._overran = 0
            return
        self._overran += 1
        self._overrun_onset = start if self._overran == 1 else self._overrun_onset
        self.overrun_ticks += 1
        self.overrun_run_max = max(self.overrun_run_max, self._overran)
        if self.overruns and self._overran >= self.overruns:
            self.monitor.report(Fault(Kind.OVERRUN, "robot", f"robot: {self._overran} consecutive overruns (its clock "
                                      f"advanced {gap * 1e3:.1f} ms in the last tick, more than {OVERRUN_PERIODS:g} "
                                      f"periods of {self.driver.period_s * 1e3:g} ms: its states were missed)",
                                      self._overrun_onset))

    def _push(self, retracting: bool, speed: float, dt: float, d, now: float) -> None:
        """How far the arm has moved a contacted taxel into its contact during this retraction (the measured joint
        velocity along the no-push rows, integrated; `push_mm_max` over the run). More than braking from the speed
        it had into the contact when the retraction began allows (v0^2 / (2 a), a the slowest deceleration any
        contacted taxel's row allows at the acceleration limits) + PUSH_MARGIN_M latches the stop (not under
        --after-contact always-resume, for benches): the arm is pushing into what it touched."""
        if not retracting:
            self._pushed, self._push_bound = 0.0, None
            return
        if self._push_bound is None and d is not None and len(d.A):
            a = float((np.abs(d.A) @ d.limits.acc).min())
            self._push_bound = (speed ** 2 / (2 * a) if a > 0 else np.inf) + PUSH_MARGIN_M
        self._pushed += speed * max(dt, 0.0)
        self.push_mm_max = max(self.push_mm_max, self._pushed * 1e3)
        if self._push_bound is not None and self._pushed > self._push_bound and \
                self.monitor.after_contact != "always-resume":
            self.monitor.report(Fault(Kind.STACK_LATCH, "layers", f"layers: the arm pushed a contacted taxel "
                                      f"{self._pushed * 1e3:.1f} mm into its contact during the retraction, more "
                                      f"than braking allows ({self._push_bound * 1e3:.1f} mm): protective stop "
                                      "(latched until a new run)", now))

    def _check_sent(self, v: np.ndarray, n: int, now: float) -> None:
        """What goes to the driver, checked as sent: n finite joint velocities (else the stop, named)."""
        if v.shape != (n,) or not finite(v):
            self.monitor.report(Fault(Kind.STACK_NONFINITE, "layers", f"the command to send is not {n} finite joint "
                                      "velocities", now))
        else:
            self._sent = v

    def _judge(self, v: np.ndarray, now: float) -> None:
        """The layers' command: non-finite, a brake of their own on a non-finite model output, or the retraction's QP
        solve failed, latches a stop."""
        braked = [f for f in self.stack.info.flags if f in BRAKES]
        if not finite(v):
            self.monitor.report(Fault(Kind.STACK_NONFINITE, "layers", "the layers' command is not finite", now))
        elif braked:
            self.monitor.report(Fault(Kind.STACK_NONFINITE, "layers", f"layers: braked on a non-finite output "
                                      f"({', '.join(f.split(':')[1] for f in braked)}): protective stop", now))
        elif self.stack.defensiveness is not None and self.stack.defensiveness.info.solver_failed:
            self.monitor.report(Fault(Kind.STACK_LATCH, "layers", "layers: the retraction's QP solve failed: protective "
                                      "stop (latched until a new run)", now))

    def _stop(self, state, r) -> None:
        raise StopRobot(self.monitor.reason)

    def _driver_fault(self, kind: str, message: str, onset: float | None, during_stop: bool = False) -> None:
        """The driver's `report`: a fault it met itself, typed, to the monitor (while stopping: the stop failed)."""
        k = Kind(kind) if kind in Kind._value2member_map_ else Kind.DRIVER
        f = Fault(k, self.driver.name, message, onset)
        self.monitor.stop_failed(f) if during_stop else self.monitor.report(f)

    def _on_sent(self, state, command) -> None:
        """The driver's `sent`: a command of the stop (the zero, the ramp, the hold) with the state it went out on,
        for the tap and the record (the stack not ticked), and the arm's state kept until it rests. `command` None:
        nothing was sent (the driver lost the robot's command link and watches its own stop): recorded as the last
        command sent, flagged `nothing-sent`."""
        self._keep(time.monotonic(), state)
        if command is not None:
            self._sent = np.array(command, float)
        r = self._state[1] if self._state is not None else None
        last = self._sent if self._sent is not None else np.zeros(len(state.q))
        self._publish_stop(state, r, last, ("stop",) if command is not None else ("stop", "nothing-sent"))

    def _publish_stop(self, state, r, command: np.ndarray, flags: tuple) -> None:
        self._stopped = True
        self._after += 1
        zero = np.zeros(len(state.q))
        tick = Tick(t=state.t, q=state.q, qd=state.qd, command=command, force=self._force,
                    reading_seq=float(r.seq) if r is not None else 0.0, planned=zero, flags=flags,
                    speed_factor=0.0, stop=self.monitor.reason, ticked=False,
                    board_age_s=r.board_age_s if r is not None else None, frames_lost=r.frames_lost if r is not None
                    else 0, command_age=self.command.age(), command_refused=self.command.refused,
                    index=self.ticks + self._after, ns=time.time_ns())
        self.tap.publish(tick)
        if self.recorder is not None:
            self.recorder.put(tick)

    def _keep(self, mono: float, state) -> None:
        """The arm's state for the stop's figures (a ring of HISTORY ticks)."""
        if self._hist is None:
            n = len(state.q)
            self._hist = (np.zeros(HISTORY), np.zeros(HISTORY), np.zeros((HISTORY, n)), np.zeros((HISTORY, n)))
        mono_, t_, qd_, q_ = self._hist
        i = self._n % HISTORY
        mono_[i], t_[i] = mono, state.t
        qd_[i] = state.qd
        q_[i] = state.q
        self._n += 1

    @property
    def last_q(self) -> np.ndarray | None:
        """The arm's last measured joint positions kept (after a stop: where the driver's stop left it)."""
        return None if self._hist is None else self._hist[3][(self._n - 1) % HISTORY].copy()

    def stopping(self, onset: float | None) -> dict:
        """The stop measured as a safety engineer does, from the arm's measured state: `onset` (host time) -> every
        joint below REST_QD for good, on the robot's clock (`stop_time_ms`; None: not at rest by the end of the
        record, or the onset older than the history), `speed_at_onset` and `speed_max` (the fastest joint's speed
        then, and its top speed until the rest), `qd_peak` (each joint's top speed until the rest), and `q_path`, the measured joint positions from the onset to the
        rest (the caller turns it into each taxel's travel: monitor.travel)."""
        if self._hist is None or onset is None:
            return {}
        k = min(self._n, HISTORY)
        order = (np.arange(self._n - k, self._n)) % HISTORY
        mono, t, qd, q = (a[order] for a in self._hist)
        qd = np.abs(qd)
        speed = qd.max(axis=1) if qd.shape[1] else np.zeros(len(t))
        before = np.flatnonzero(mono <= onset)
        out = {"rest_qd": REST_QD, "onset_mono": onset, "stop_time_ms": None, "q_path": []}
        if not len(before):
            if self._n > HISTORY or onset < mono[0] - 2 * self.driver.period_s:
                return out | {"why": "the onset is older than the arm's kept history"}
            before = np.array([0])
        i0 = int(before[-1])
        t_onset = t[i0] + (onset - mono[i0] if mono[i0] <= onset else 0.0)
        moving = np.flatnonzero(speed[i0:] >= REST_QD)
        rest = max(i0 + (int(moving[-1]) + 1 if len(moving) else 0), min(i0 + 1, len(t) - 1))
        out["speed_at_onset"] = float(speed[i0])
        out["speed_max"] = float(np.nanmax(speed[i0:]))  # the fastest joint's top speed from the onset on
        out["qd_peak"] = np.nanmax(qd[i0:], axis=0).tolist()  # each joint's top speed from the onset on
        if rest >= len(t):
            return out | {"why": f"not at rest when the record ends (fastest joint {speed[-1]:.3f} rad/s)",
                          "q_path": q[i0:].tolist()}
        at_rest = not len(moving)  # at rest from the onset on: nothing to stop
        return out | {"stop_time_ms": 0.0 if at_rest else (t[rest] - t_onset) * 1e3, "q_path": q[i0:rest + 1].tolist(),
                      "speed_max": float(np.nanmax(speed[i0:rest + 1])),
                      "qd_peak": np.nanmax(qd[i0:rest + 1], axis=0).tolist()}

    # -- the run ---------------------------------------------------------------------------------
    def stop_by_operator(self, signum: int, name: str) -> None:
        """Signal-safe (no lock): the monitor latches the operator's stop, the driver stops at its next period."""
        self.monitor.signal(signum, name)
        self.driver.stop(self.monitor.reason)

    def run(self, settle_s: float = 1.0) -> Outcome:
        """Hand `control` to the driver until the robot stops; the outcome names why. First every board must be
        streaming fresh frames, on time by its own clock (within `settle_s`): a board that went quiet, or the reader stalled, while the
        stack was set up is no reason to stop, one that stays quiet, or any other skin fault, is."""
        m = self.monitor
        deadline = time.monotonic() + settle_s
        while not m.stopped:
            r = self.source.newest()
            other = [f for f in _skin_faults(r) if f.kind not in SETTLING]
            aged = max(r.board_age_s.values(), default=0.0) <= self.source.frame_period_s
            fresh = aged and finite(np.where(self.excluded, 0.0, r.force))  # a late board's taxels read NaN
            late = time.monotonic() > deadline
            if aged and late and not other:
                break  # fresh frames, NaN readings: the loop's first tick names them
            if other or (not fresh and late):
                f = other[0] if other else Fault(Kind.BOARD_SILENT, "skin", "skin: boards not streaming")
                m.report(Fault(f.kind, f.source, f"{f.message} (before the robot moved)", f.onset))
            elif fresh:
                break
            else:
                time.sleep(self.source.frame_period_s / 4)
        if not m.stopped:
            m.arm()
            reason = self.driver.run(self.control, report=self._driver_fault, sent=self._on_sent)
            if not m.stopped:  # a driver that stopped without reporting why
                m.report(Fault(Kind.DRIVER, "robot", reason, time.monotonic()))
        if not self._stopped and self._state is not None:  # nothing went out after the stop (the driver died)
            state, r = self._state
            self._publish_stop(state, r, self._sent if self._sent is not None else np.zeros(len(state.q)),
                               ("stop", "nothing-sent"))
        d = m.decide()
        onset = (d.fault.onset or d.detected) if d.fault else d.detected
        self.outcome = Outcome(d.reason, d.kind, d.fault.kind.value if d.fault else "", float(self._prev_t or 0.0),
                               d.detected, self.ticks, self.timing() if self._t0 is not None else {},
                               d.fault.onset if d.fault else None, d.exit_code, d.state.value,
                               self.stopping(onset) if self._t0 is not None else {},
                               tuple(f"{f.kind.value}: {f.message}" for f in d.during_stop))
        return self.outcome

    def timing(self) -> dict:
        """Loop rate, period jitter (host clock; `_robot`: the robot's clock), work per tick and contact latency
        (ms) over the run; `off_cpu_ms_*`: the part of a tick's work its thread was not on a CPU (wall - the thread's
        CPU time: preempted, the hypervisor's steal, interrupts on its core); `latency_ms_all`, `latency_wait_ms_all`
        (its part before the tick began), `period_ms_all`
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
                "off_cpu_ms_max": self.off_cpu.max * 1e3 if self.off_cpu.n else 0.0,
                "off_cpu_ms_p99": ms(self.off_cpu, 99), "slowest_tick_off_cpu_ms": self._slowest[1] * 1e3,
                "push_mm_max": self.push_mm_max,
                "latency_samples": lat.n, "latency_ms_p50": ms(lat, 50, np.nan),
                "latency_ms_p99": ms(lat, 99, np.nan), "latency_ms_max": lat.max * 1e3 if lat.n else np.nan,
                "latency_ms_all": every(lat), "latency_wait_ms_all": every(self.waited), "period_ms_all": every(period),
                "latency_tick_all": [] if self.latency_at.exact() is None else self.latency_at.exact().astype(int).tolist(),
                "start_mono": self._first_start, "overrun_ticks": self.overrun_ticks,
                "overrun_run_max": self.overrun_run_max}


def speed_factor(v: np.ndarray, planned: np.ndarray | None) -> float:
    """|v| / |planned| (1 for a plan at rest): how much the layers slowed the plan this tick (> 1: a retraction)."""
    p = float(np.sqrt(planned @ planned)) if planned is not None else 0.0
    return float(np.sqrt(v @ v)) / p if p > 1e-12 else 1.0


def warm_up(stack, q: np.ndarray, thresholds: np.ndarray, dt: float, ticks: int = 20) -> None:
    """Tick the stack through contacts and through a plan before the robot moves, then forget it all:
    numba compiles (or loads from its cache: tens of ms) each kernel on its first call, and the QP
    solver loads on the first level where a constraint binds: none of it may land on the robot's first
    tick or first contact. The contacts come while the arm moves fast each way and the last command sent
    is that motion, so the acceleration box, the limits and the no-push rows bind (the retraction's first
    level then goes to the QP solver: `qp._first_level`, once loaded on the FR3's first contact, a 6-19 ms
    tick); the plan, with no contact, runs the strategy filter and the modulation of a plan (kernels a
    retraction never calls)."""
    n = len(thresholds)
    zero = np.zeros(len(stack.vel_limits))
    for sign in (1.0, -1.0):
        for taxels in (np.array([n // 2]), np.linspace(0, n - 1, min(n, 3)).astype(int)):
            force = np.zeros(n)
            force[taxels] = 2 * thresholds.max() + 1.0
            moving = sign * 0.9 * stack.vel_limits
            stack.last = moving.copy()
            for k in range(ticks):
                stack.tick(k * dt, q, {"force": force if k < 2 else np.zeros(n)}, zero, dt,
                           qdot=moving if k < 3 else zero)
            stack.reset()
        for k in range(3):
            stack.tick(k * dt, q, {"force": np.zeros(n)}, sign * 0.1 * stack.vel_limits, dt)
        stack.reset()
    stack.flags.clear()
    if stack.defensiveness is not None:
        stack.defensiveness.flags.clear()
