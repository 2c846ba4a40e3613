"""Every stop through the monitor, and what was sent in the record until the arm rests (issue 50): the limiter never
makes a non-finite command (any dt, q, v); a repeated FR3 timestamp sends no NaN and the stop is named by its cause;
a driver's own fault goes to the monitor with its onset; a stop that fails (the FR3's ramp never brings the arm to
rest) changes the exit code; the record's last command is the driver's last one sent (the ramp recorded); a slow
writer drops telemetry, never a tick's safety topics (the stop's included). The FR3 here is pylibfranka's interface
as a script (`Scripted`: its clock as given, the arm following each command exactly), handed to the driver."""
import json
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pylibfranka
import pytest
import test_runtime_loop as loop
from hypothesis import given, settings
from hypothesis import strategies as st
from mcap.reader import make_reader

from skinsafe.core.runtime.fault_plan import FaultPlan, Injection
from skinsafe.core.runtime.limiter import JointLimits, Limiter, limits_config
from skinsafe.core.runtime.loop import Runtime
from skinsafe.core.runtime.record import Recorder
from skinsafe.core.runtime.record_read import read_record
from skinsafe.core.runtime.tick import Tick
from skinsafe.core.safety.defensiveness import TickInfo
from skinsafe.core.sim.robot_driver import SimFaults
from skinsafe.hardware import franka
from skinsafe.hardware.franka import FrankaDriver

ur5 = loop.ur5  # its fixture
FR3 = {"q_min": franka.Q_MIN, "q_max": franka.Q_MAX, "qd_max": franka.QD_MAX, "qdd_max": franka.QDD_MAX,
       "qddd_max": franka.QDDD_MAX, "qd_bounds": "fr3"}
SIM = {"q_min": np.array([-1.0, -np.inf]), "q_max": np.array([1.0, np.inf]), "qd_max": np.array([2.0, 1.0]),
       "qdd_max": np.array([4.0, 100.0])}
SWING = np.array([0.3, 0, 0, 0, 0, 0, 0])

odd = st.sampled_from([0.0, -0.001, 1e-300, 5e-324, 1e-9, 1e300, np.inf, -np.inf, np.nan])
dts = st.one_of(odd, st.floats(-1.0, 10.0))
value = st.one_of(st.floats(-1e6, 1e6), st.sampled_from([np.nan, np.inf, -np.inf, 1e308, -1e308]))


@settings(max_examples=150, deadline=None)
@given(st.sampled_from(["fr3", "fr3-period", "sim"]), st.lists(st.tuples(dts, st.lists(value, min_size=7, max_size=7),
       st.lists(value, min_size=7, max_size=7), st.lists(st.floats(-1.2, 1.2), min_size=7, max_size=7)),
       min_size=1, max_size=6))
def test_the_limiter_never_makes_a_non_finite_command(which, ticks):
    """Any dt (0, negative, tiny, huge, non-finite), any layers' velocity and measured q (at, past and far past the
    limits, non-finite), in any order: every command finite, inside the velocity limits."""
    limits = SIM if which == "sim" else FR3
    lim = Limiter(json.loads(json.dumps(limits_config(limits))), franka.PERIOD_S if which == "fr3-period" else None)
    n = len(limits["qd_max"])
    for dt, v, q, frac in ticks:
        q = np.where(np.abs(frac[:n]) <= 1.1, limits["q_min"] + (np.array(frac[:n]) + 1) / 2 *
                     (np.where(np.isfinite(limits["q_max"]), limits["q_max"], 1) -
                      np.where(np.isfinite(limits["q_min"]), limits["q_min"], -1)), np.array(q[:n]))
        out = lim(np.array(v[:n]), q, dt)
        assert np.isfinite(out).all() and np.isfinite(lim.acc).all(), (dt, v, q, out)
        assert (np.abs(out) <= limits["qd_max"] + 1e-9).all()


class Scripted:
    """pylibfranka's `Robot` and its active control as a script: the robot's clock from `times` (s; then on at 1 ms a
    state), the arm following each command exactly (dq = the last command), or stuck moving at `stuck` rad/s once
    the ramp begins; `written`: every command sent."""

    def __init__(self, times=(), stuck=None, reflex_at=None):
        self.times, self.stuck, self.written, self.k = list(times), stuck, [], 0
        self.reflex_at = reflex_at  # the read that raises libfranka's ControlException (the robot's own reflex)
        self.q, self.dq, self.stopped = np.array(franka.Q_MIN + franka.Q_MAX) / 2, np.zeros(7), 0

    def start_joint_velocity_control(self, mode):
        return self

    def readOnce(self):
        if self.k == self.reflex_at:
            self.k += 1
            raise pylibfranka.ControlException("libfranka: Move command aborted: motion aborted by reflex! "
                                             "[\"joint_velocity_violation\"]")
        t = self.times[self.k] if self.k < len(self.times) else (self.times[-1] if self.times else 0.0) + \
            (self.k - len(self.times) + 1) * 1e-3
        self.k += 1
        self.q = self.q + self.dq * 1e-3
        rs = SimpleNamespace(time=SimpleNamespace(to_sec=lambda: t), q=self.q.tolist(), dq=self.dq.tolist(),
                             control_command_success_rate=1.0)
        return rs, SimpleNamespace(to_sec=lambda: 1e-3)

    def writeOnce(self, cmd):
        self.written.append((np.array(cmd.dq), cmd.motion_finished))
        ramping = self.stuck is not None and len(self.written) > 1 and not np.array(cmd.dq).any()
        self.dq = np.full(7, self.stuck) if ramping or (self.stuck is not None and self.dq.any() and
                                                       np.abs(self.dq).max() == self.stuck) else np.array(cmd.dq)

    def stop(self):
        self.stopped += 1

    def read_once(self):
        """The state stream outside a motion: after `stop`, the robot's own stop brakes every joint at 10 rad/s^2."""
        if self.stopped:
            self.dq = np.sign(self.dq) * np.maximum(np.abs(self.dq) - 10.0 * 1e-3, 0.0)
        return self.readOnce()[0]


class Swing:
    """The command source: the base joint at 0.3 rad/s."""

    spec, stale_s, refused, intrusion = "swing", None, 0, None

    def start(self, q0):
        pass

    def __call__(self, t, q):
        return SWING

    def age(self):
        return 0.0


class Layers:
    """The layers doing nothing (the plan goes to the limiter as it is)."""

    defensiveness, last_f = None, 0.0

    def __init__(self):
        self.last, self.info = np.zeros(7), TickInfo()

    def tick(self, t, q, readings, planned, dt, qdot=None):
        return np.array(planned, float)


class Source:
    frame_period_s = 0.01

    def __init__(self):
        self.seq = 0

    def newest(self):
        self.seq += 1
        return loop.Readings(0.0, np.zeros(1), self.seq, {0: 0.0})


class Kept:
    """A recorder that keeps every tick."""

    def __init__(self):
        self.ticks = []

    def put(self, tick):
        self.ticks.append(tick)


def fr3_runtime(robot, seconds=None, faults=None):
    drv = FrankaDriver("scripted", realtime=False, rate_limited=False, robot=robot, faults=faults)
    rec = Kept()
    rt = Runtime(drv, Source(), Layers(), Swing(), np.zeros(1, bool), np.ones(1), rec, seconds=seconds,
                 limiter=Limiter(limits_config(drv.limits()), drv.period_s))
    return rt, rec


def test_the_printed_stopping_bound_is_detection_response_and_braking_by_hand():
    """`monitor.stopping`, what `skinsafe run` prints at start as its worst stopping distance: one taxel 0.5 m from a
    joint at 2 rad/s braking at 10 rad/s^2 (0.2 s, 0.2 rad), a kind detected within one 2 ms period, the robot's
    response 2 periods: 0.206 s and 0.5 x (2 x 0.006 + 0.2) = 0.106 m; a jerk limit of 100 rad/s^3 adds
    2 x 10 / 100 = 0.2 s at full speed (0.4 rad more: 0.306 m)."""
    from skinsafe.core.runtime.monitor import Kind, Timing, stopping

    J = np.zeros((2, 6, 2))
    J[0, 0, 0], J[1, 1, 0], J[1, 1, 1] = 0.5, 0.1, 0.1  # taxel 0 the furthest; joint 1 at rest
    tm = Timing(0.002, 0.01, 0.05)
    t, d = stopping(tm, J, np.array([2.0, 0.0]), np.array([10.0, 10.0]))[Kind.STACK_LATCH]
    assert np.isclose(t, 0.206) and np.isclose(d, 0.106)
    t, d = stopping(tm, J, np.array([2.0, 0.0]), np.array([10.0, 10.0]), np.array([100.0, 100.0]))[Kind.STACK_LATCH]
    assert np.isclose(t, 0.406) and np.isclose(d, 0.306)
    t, _ = stopping(tm, J, np.array([2.0, 0.0]), np.array([10.0, 10.0]))[Kind.BOARD_SILENT]
    assert np.isclose(t, 0.05 + 2 * 0.002 + 0.005 + 0.004 + 0.2)  # silence + a board's hand-off, then the same


def test_a_repeated_fr3_timestamp_sends_no_nan_and_the_robot_clock_names_the_stop():
    """The robot's clock repeats once at 30 ms (the watchdog lets one through: no NaN, the arm goes on), then stays at
    60 ms: robot-frozen names it, and the ramp after it goes out and is recorded until the arm rests."""
    times = [k * 1e-3 for k in range(1, 31)] + [0.030] + [k * 1e-3 for k in range(31, 61)] + [0.060] * 3
    robot = Scripted(times)
    rt, rec = fr3_runtime(robot)
    out = rt.run(settle_s=0.0)
    sent = np.array([w for w, _ in robot.written])
    assert np.isfinite(sent).all() and sent[:, 0].max() > 0.2  # it moved, never a NaN
    assert out.watchdog == "robot-frozen" and out.exit_code == 1 and out.state == "protective_stop", out.reason
    assert robot.written[-1][1] and not robot.written[-1][0].any() and robot.stopped == 1  # ramped, then finished
    assert len(rec.ticks) == len(robot.written)  # every command sent is a tick of the record, the ramp's too
    np.testing.assert_array_equal(np.array([k.command for k in rec.ticks]), sent)
    after = [k for k in rec.ticks if not k.ticked]
    assert len(after) > 20 and all(k.stop == out.reason for k in after) and rt.ticks + len(after) == len(sent)
    s = out.stopping
    assert s["stop_time_ms"] > 20 and s["speed_at_onset"] > 0.2 and len(s["q_path"]) > 30  # onset -> rest


def test_a_ramp_that_never_brings_the_arm_to_rest_changes_the_exit_code():
    """The run ends as planned (--seconds) but the arm keeps moving after its ramp: the ramp's failure is a fault
    during the stop, named, exit 4, not 0."""
    robot = Scripted(stuck=0.3)
    rt, _ = fr3_runtime(robot, seconds=0.05)
    out = rt.run(settle_s=0.0)
    assert out.kind == "end" and out.exit_code == 4, out
    assert "while stopping: fr3: the stop's ramp did not bring the arm to rest" in out.reason
    assert out.during_stop and out.stopping["stop_time_ms"] is None and "not at rest" in out.stopping["why"]


def test_a_driver_that_lost_the_robot_records_its_own_stop_to_rest():
    """The FR3 driver stops talking to the robot (robot-die) while the base swings at 0.3 rad/s: nothing more is
    sent; the robot's own stop (braking at 10 rad/s^2 here) is watched on its state stream and recorded until the arm
    rests (flagged nothing-sent, the last command sent), and the stop measured from the fault's onset."""
    robot = Scripted()
    plan = FaultPlan((Injection("robot-die", 0.2),))
    rt, rec = fr3_runtime(robot, faults=plan)
    plan.start()
    out = rt.run(settle_s=0.0)
    assert out.watchdog == "driver" and out.exit_code == 1 and "stopped talking" in out.reason, out.reason
    assert out.onset_mono == plan.onsets["robot-die"] and robot.stopped == 1 and rt.driver.stats["rest_observed"]
    assert out.onset_mono <= rt.driver.stats["zero_mono"]  # the robot's own stop asked after the onset: the bench times it
    after = [k for k in rec.ticks if not k.ticked]
    # 0.3 rad/s less 0.01 a state until below 0.02: 28 states
    assert len(after) == 28 and all(k.flags == ("stop", "nothing-sent") for k in after)
    np.testing.assert_array_equal(after[-1].command, robot.written[-1][0])  # what was last sent, nothing since
    assert len(robot.written) == rt.ticks and np.abs(after[-1].qd).max() < 0.02
    s = out.stopping
    # onset -> rest: 29 states on the robot's clock, less the host time from the last tick's start to the onset
    assert s["speed_at_onset"] == pytest.approx(0.3) and 0 < s["stop_time_ms"] <= 29.0
    assert len(s["q_path"]) == 29  # the onset's state, then the 28 watched


def test_an_fr3_exception_reaches_the_monitor_with_its_onset():
    """libfranka raises (the robot's reflex) at the 101st read while the base swings: the driver reports it, typed
    `driver` with the instant it met it, before it ends the motion; the monitor names it, and the robot's own stop is
    watched to rest on its state stream (recorded as nothing sent: the last command stays the last one sent)."""
    robot = Scripted(reflex_at=100)
    rt, rec = fr3_runtime(robot)
    before = time.monotonic()
    out = rt.run(settle_s=0.0)
    assert out.watchdog == "driver" and out.exit_code == 1 and out.kind == "driver", out.reason
    assert out.reason.startswith("fr3: the robot stopped the motion: libfranka: Move command aborted")
    assert before < out.onset_mono <= out.detected_mono and robot.stopped == 1 and rt.ticks == 100
    after = [k for k in rec.ticks if not k.ticked]  # its own stop watched to rest, nothing sent
    assert len(after) == 28 and all(k.flags == ("stop", "nothing-sent") for k in after)
    np.testing.assert_array_equal(rec.ticks[-1].command, robot.written[-1][0])
    assert out.stopping["stop_time_ms"] is not None and rt.driver.stats["rest_observed"]


def test_a_driver_fault_reaches_the_monitor_with_its_onset(ur5):
    """The simulation dies at 0.2 s: the driver reports it (kind driver, its onset the failure's instant) before it
    stops; the monitor decided it then, the driver's return came after."""
    drv, rt = loop._runtime(ur5, faults=SimFaults(die_at=0.2))
    out = rt.run(settle_s=0.0)
    assert out.watchdog == "driver" and out.exit_code == 1 and out.state == "protective_stop", out.reason
    assert out.onset_mono == drv.stats.fault_mono and out.detected_mono <= drv.stats.zero_mono
    assert "physics stopped at t = 0.200 s (injected)" in out.reason


def test_the_sim_stop_is_recorded_until_the_arm_rests(ur5):
    """--seconds ends a run mid-retraction: the stop's ramp and the hold after it go to the record, tick by tick,
    until the arm rests; every command of the ramp within the acceleration limit of the one before, the hold zero."""
    drv, rt = loop._runtime(ur5, seconds=0.26)
    rt.recorder = rec = Kept()
    out = rt.run(settle_s=0.0)
    after = [k for k in rec.ticks if not k.ticked]
    ramp = np.array([k.command for k in after[:drv.stats.ramp_ticks]])
    step = drv.limits()["qdd_max"] * drv.period_s
    assert out.exit_code == 0 and drv.stats.ramp_ticks > 0 and all(not k.command.any() for k in after[len(ramp):])
    assert np.all(np.abs(np.diff(np.vstack([ramp, np.zeros(len(step))]), axis=0)) <= step + 1e-12), out.reason
    assert np.abs(after[-1].qd).max() <= 1e-3 and [k.index for k in rec.ticks] == list(range(1, len(rec.ticks) + 1))
    assert out.stopping["stop_time_ms"] is not None and out.stopping["stop_time_ms"] >= 0


@pytest.mark.parametrize("speed", [0.25, 1.0])
def test_the_sim_stop_decelerates_within_the_braking_model(ur5, tmp_path, speed):
    """The shoulder pan swept at `speed` x its velocity limit (1: the fastest the limiter allows), the robot's state
    going NaN at 0.5 s: the stop ramps the command from the arm's speed to zero at 15 rad/s^2 (its ramp's length says
    so) and its measured time and furthest taxel's travel to rest stay within the printed bounds' braking model, as
    the fault bench computes it (`over_model`; the servos holding the measured pose instead took 92 ms against the
    model's 64 at 0.25)."""
    from skinsafe.core.app.runtime_faults import _Stopping
    from skinsafe.core.bench.runtime import write_waypoints
    from skinsafe.core.robot.kinematics import TaxelKinematics
    from skinsafe.core.runtime.commands import Trajectory
    from skinsafe.core.runtime.layers import build_stack
    from skinsafe.core.runtime.limiter import MARGIN
    from skinsafe.core.runtime.loop import warm_up
    from skinsafe.core.runtime.monitor import Timing
    from skinsafe.core.sim.robot_driver import SimDriver

    robot, design = ur5
    drv = SimDriver(design, robot, None, 0.002, realtime=False, faults=SimFaults(nan_at=0.5))
    lim = drv.limits()
    stack = build_stack(design, robot.model, lim["qd_max"], lim["qdd_max"], drv.period_s)
    warm_up(stack, robot.home, design.taxels.thresholds["force"], drv.period_s)
    end = robot.home + np.eye(6)[0] * speed * lim["qd_max"][0] * (1 - MARGIN)
    sweep = write_waypoints(tmp_path / "sweep.csv", drv.joint_names, [0.0, 1.0, 2.0], [robot.home, end, end])
    rt = Runtime(drv, loop.SimReadings(drv), stack, Trajectory(sweep, drv.joint_names, lim),
                 np.zeros(design.n_taxels, bool), design.taxels.thresholds["force"], seconds=3.0)
    out = rt.run(settle_s=0.0)
    st = out.stopping
    kin = TaxelKinematics(robot.model, design)
    the = _Stopping(drv.joint_names, lim, kin.jacobians_of(np.arange(kin.n), robot.home)[0], Timing(0.002, 0.002, 0.004))
    the.kin = kin
    model_ms, model_mm = the.model(out.watchdog, st["qd_peak"], 0.0, np.asarray(st["q_path"][0]))
    mm = float(np.nanmax(the.travel(st["q_path"])) * 1e3)
    assert out.watchdog == "robot-nonfinite" and st["speed_at_onset"] > 0.85 * speed * np.pi, out.reason
    assert drv.stats.ramp_ticks == pytest.approx(st["speed_at_onset"] / 15.0 / drv.period_s, abs=2)
    assert 0.6 * model_ms < st["stop_time_ms"] <= model_ms and 0.5 * model_mm < mm <= model_mm, (st, model_ms, mm)
    assert drv.stats.rest_qd <= 1e-3


def test_a_slow_writer_drops_telemetry_never_a_tick(tmp_path):
    """300 ticks of 16k taxels each, put as fast as the loop can, behind a queue of 2: the forces of most are dropped
    and counted; every tick's joint state, command and tick message is in the record, the stop's last."""
    n, k = 16384, 300
    rec = Recorder(tmp_path / "r.mcap", [f"j{i}" for i in range(7)], {}, queue_size=2)
    for i in range(k):
        last = i == k - 1
        rec.put(Tick(t=i * 1e-3, q=np.zeros(7), qd=np.zeros(7), command=np.zeros(7) if last else np.full(7, i * 1e-3),
                     force=np.full(n, float(i)), force_new=True, reading_seq=float(i), ticked=not last,
                     stop="stopped" if last else "", flags=("stop",) if last else (), index=i + 1, ns=10**6 * (i + 1)))
    out = rec.close({"reason": "stopped", "kind": "fault", "dropped": rec.dropped})
    assert out["dropped"] > 0 and "path" in out
    with open(out["path"], "rb") as f:
        msgs = [(c.topic, m.data) for _, c, m in make_reader(f).iter_messages(log_time_order=False)]
    ticks = list(read_record(out["path"])[1])
    assert [x.index for x in ticks] == list(range(1, k + 1)) and not ticks[-1].ticked
    assert sum(t == "/skinsafe/command" for t, _ in msgs) == k
    assert sum(x.force is not None for x in ticks) == sum(t == "/skinsafe/forces" for t, _ in msgs) == k - out["dropped"]
    assert msgs[-1][0] == "/diagnostics"


class BrakingLayers:
    """The layers as built; from 0.1 s their info says they braked on the TDM's output (as SafetyStack does on a
    non-finite strategy output)."""

    def __init__(self, inner):
        object.__setattr__(self, "inner", inner)

    def __getattr__(self, name):
        return getattr(self.inner, name)

    def __setattr__(self, name, value):
        setattr(self.inner, name, value)

    def tick(self, t, *args, **kw):
        v = self.inner.tick(t, *args, **kw)
        if t >= 0.1:
            self.inner.info.flags = ("nonfinite:tdm", "nonfinite")
        return v


def test_a_layers_brake_on_a_non_finite_model_output_latches(ur5):
    """The layers' own brake (nonfinite:tdm / nonfinite:potential) is a stop the monitor names, not a silent tick."""
    drv, rt = loop._runtime(ur5)
    rt.stack = BrakingLayers(rt.stack)
    out = rt.run(settle_s=0.0)
    assert out.watchdog == "stack-nonfinite" and "braked on a non-finite output (tdm)" in out.reason, out.reason
    assert 0.1 <= drv.stats.stop_t <= 0.1 + 2 * drv.period_s + 1e-9


@pytest.mark.parametrize("bad, message", [
    ({"qdd_max": np.array([10.0, 10, -1, 10, 10, 10, 10])}, "qdd_max[2] is -1.0; give each joint's positive finite"),
    ({"qd_max": np.full(7, np.inf)}, "qd_max[0] is inf"), ({"q_min": franka.Q_MAX}, "joint 0's q_min 2.7437 is not below"),
    ({"qd_max": np.ones(6)}, "qd_max has 6 values, q_min 7"), ({"qd_bounds": "ur5"}, "qd_bounds 'ur5' is not one of"),
    ({"qdd_max": None}, "qdd_max missing")])
def test_a_drivers_limits_are_validated_once_naming_the_fix(bad, message):
    """JointLimits: the FR3 driver's own record; a dict (the sim's) validated at the runtime's boundary; bad limits
    refused in one line naming the joint."""
    good = FrankaDriver("scripted", realtime=False, robot=Scripted()).limits()
    assert isinstance(good, JointLimits) and good.n == 7 and not good.qd_max.flags.writeable
    assert JointLimits.of(dict(good)).qd_bounds == "fr3" and limits_config(good)["qd_bounds"] == "fr3"
    with pytest.raises(ValueError, match=r"^joint limits: .*") as e:
        JointLimits.of({**dict(good), **bad})
    assert message in str(e.value) and "\n" not in str(e.value)


class PushingLayers(BrakingLayers):
    """The layers as built (their pool, flags and no-push rows), the plan sent instead of their retraction: the arm
    drives on into what it touched."""

    def tick(self, t, q, readings, planned, dt, qdot=None):
        self.inner.tick(t, q, readings, planned, dt, qdot=qdot)
        return np.array(planned, float)


def test_pushing_into_a_contact_beyond_braking_latches(ur5, tmp_path):
    """The shoulder pan drives the forearm into a sprung post and the retraction is not obeyed: once the taxel is
    pushed 2 mm past what braking from its speed into the post allows, the monitor latches the stop (a clean
    retraction of the same contact pushes it 1.2 mm in all, franky-sim's jitter under a hand 0.02 mm)."""
    from skinsafe.core.runtime.commands import Trajectory
    from skinsafe.core.runtime.layers import build_stack
    from skinsafe.core.runtime.loop import warm_up
    from skinsafe.core.sim.robot_driver import Contact, SimDriver

    robot, design = ur5
    drv = SimDriver(design, robot, None, 0.002, Contact("post", joint=0, gap=0.01), realtime=False)
    lim = drv.limits()
    stack = build_stack(design, robot.model, lim["qd_max"], lim["qdd_max"], drv.period_s)
    warm_up(stack, robot.home, design.taxels.thresholds["force"], drv.period_s)
    traj = Trajectory(Path(__file__).resolve().parents[2] / "examples" / "ur5_pan.csv", drv.joint_names, lim)
    rt = Runtime(drv, loop.SimReadings(drv), PushingLayers(stack), traj, np.zeros(design.n_taxels, bool),
                 design.taxels.thresholds["force"], seconds=2.0)
    out = rt.run(settle_s=0.0)
    assert out.watchdog == "stack-latch" and "pushed a contacted taxel" in out.reason, out.reason
    assert 2.0 < rt.push_mm_max < 4.0 and out.exit_code == 1
