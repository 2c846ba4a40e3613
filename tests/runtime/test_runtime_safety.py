"""The safety monitor decides every stop from a typed fault at its source: the boards' reader's death seen from its
pidfd after a stall used up the old one-shot check, steadily late frames judged by the board's own clock, the robot's
own clock frozen or going back (while a host counter still counts, as the FR3 driver's does), a retraction's end
under --after-contact hold latches the stop; faults injected at their source (the layers' command, the retraction's
QP solve, a reading) named from the tick they take effect in; consecutive overruns on the robot's own clock (never
the host's lateness); the one command limiter after the layers."""
import json
import socket
import time

import numpy as np
import pytest
import test_runtime_closed_loop as closed_loop
import test_runtime_loop as loop

from skinsafe.core.runtime.limiter import Limiter, limits_config
from skinsafe.core.runtime.monitor import Kind, Monitor, Timing, bounds
from skinsafe.core.runtime.protocol import StopRobot
from skinsafe.core.runtime.teleop import NO_KEY, Teleop, datagram, now_us
from skinsafe.core.sim.robot_driver import SimFaults, SimState
from skinsafe.hardware.skin_reader import KINDS

skin, ur5 = closed_loop.skin, loop.ur5  # their fixtures
messages, run, _runtime = closed_loop.messages, closed_loop.run, loop._runtime
# `skinsafe run`s (SCHED_FIFO, core 0, timed watchdogs): one at a time (conftest.realtime_host); the in-process runtimes
# (`_runtime`: the sim unpaced, every watchdog on its own clock) need no slot
REALTIME = pytest.mark.xdist_group("realtime")
SLOT = pytest.mark.usefixtures("realtime_host")


def _stopped_by(p, s, record, kind: str):
    assert p.returncode == 1, p.stderr
    assert s["watchdog"] == kind and s["state"] == "protective_stop", s["reason"]
    assert s["world"]["zero_mono"] > s["detected_mono"] > 0  # zero went out after the decision, in that tick
    stop = [m for t, m in messages(record) if t == "/diagnostics"][-1].status[0]
    assert stop.name == "skinsafe/watchdog" and stop.message == s["reason"]


@REALTIME
@SLOT
def test_reader_death_after_a_settle_stall_is_named(skin, tmp_path):
    """The reader stalls (SIGSTOP) while the boards settle (named, let pass), then is killed while the robot moves:
    its pidfd names the death, whatever --link-latency (0.5 s here) a board's silence waits."""
    p, s, record = run(skin, tmp_path, "--inject", "reader-stall@0", "--inject", "reader-kill@1.2", seconds=3.0)
    _stopped_by(p, s, record, "reader-died")
    assert "the boards' reader ended (exit code -9)" in s["reason"]
    assert s["injected"]["reader-kill"] < s["world"]["zero_mono"]


# a reader stalled while the robot moves (SIGSTOP): tests/runtime/test_fault_bench.py (reader-stall, named
# reader-stalled within its bound, latched, the record readable)


@REALTIME
@SLOT
def test_late_but_steady_frames_stop_the_robot(skin, tmp_path):
    """From 0.3 s on a board's frames arrive ever later but never more than 1.5 frame periods apart: no silence by
    arrival; by the board's own clock they are late."""
    p, s, record = run(skin, tmp_path, "--inject", "frame-lag@0.3", seconds=3.0)
    _stopped_by(p, s, record, "board-late")
    assert "late by the board's own clock" in s["reason"] and "board 'board0'" in s["reason"]
    # the onset measured on the link proxy's frames (the newest one passed to the host older than the silence,
    # 2 frame periods at 100 Hz + the link latency) comes before the zero, within the kind's bound
    onset, bound = s["injected"]["frame-lag"], bounds(Timing(s["period_s"], 0.01, 0.02 + closed_loop.LINK_LATENCY))
    assert 0 < s["world"]["zero_mono"] - onset <= bound[Kind.BOARD_LATE]


@pytest.mark.parametrize("fault, kind", [("clock_freeze_at", "robot-frozen"), ("clock_back_at", "robot-clock-back")])
def test_the_robot_watchdog_watches_the_robots_own_clock(ur5, fault, kind):
    """The state's sequence number still counts every read (as the FR3 driver's host counter does); its clock froze
    or went back: the robot's clock names it, within the bound."""
    drv, rt = _runtime(ur5, faults=SimFaults(**{fault: 0.2}))
    out = rt.run(settle_s=0.0)
    assert out.watchdog == kind and out.exit_code == 1 and out.state == "protective_stop", out.reason
    stop_t = drv.stats.stop_t
    assert 0.2 <= stop_t <= 0.2 + bounds(Timing(0.002, 0.002, 0.004))[Kind(kind)] + 1e-9


def test_after_contact_hold_latches_after_the_retraction(ur5):
    drv, rt = _runtime(ur5, seconds=3.0)
    rt.monitor = Monitor("hold")
    out = rt.run(settle_s=0.0)
    assert out.watchdog == "after-contact" and out.exit_code == 1, out.reason
    assert drv.stats.reaction_t is not None and drv.stats.stop_t > drv.stats.reaction_t


def test_every_kind_the_reader_names_is_a_monitor_kind():
    assert {Kind(k) for k in KINDS} <= set(Kind) and Kind("reader-died") and Kind("reader-stalled")


def test_the_limiter_stops_short_of_a_joint_limit_and_keeps_acceleration():
    """Joint 0 is 0.02 rad below its limit: it may approach at most sqrt(2 qdd_max 0.02) = 0.4 rad/s, however fast the
    layers ask; joint 1 (no limit, JSON None) is held to its velocity limit, reached at its acceleration limit; the
    record's JSON of the limits rebuilds the same limiter."""
    limits = {"q_min": np.array([-1.0, -np.inf]), "q_max": np.array([1.0, np.inf]), "qd_max": np.array([2.0, 1.0]),
              "qdd_max": np.array([4.0, 100.0])}
    lim = Limiter(json.loads(json.dumps(limits_config(limits))))
    q = np.array([0.98, 0.0])
    out = [lim(np.array([5.0, 5.0]), q, 0.01) for _ in range(30)]
    assert out[0] == pytest.approx([0.04, 1.0])  # 4 rad/s^2 for 10 ms; joint 1 at once (100 rad/s^2)
    assert out[-1] == pytest.approx([0.4, 1.0]) and lim.changed == 30
    assert lim(np.array([-0.5, 0.0]), np.array([1.0, 0.0]), 0.01) == pytest.approx([0.36, 0.0])  # braking at 4


def test_a_non_finite_robot_state_or_teleop_target_is_typed(ur5):
    """A NaN in the measured q names the robot; a teleop datagram with a NaN target (real UDP) names the command
    source; each stops the tick it arrives in, before the layers tick."""
    robot, design = ur5
    drv, rt = _runtime(ur5)
    q = robot.home.copy()
    q[2] = np.nan
    with pytest.raises(StopRobot, match="non-finite q"):
        rt.control(SimState(0.0, q, np.zeros(6), 0))
    assert rt.monitor.fault.kind is Kind.ROBOT_NONFINITE and rt.ticks == 0
    drv, rt = _runtime(ur5)
    rt.command = Teleop("127.0.0.1:0", drv.joint_names, drv.limits())
    rt.stale_s = None
    rt.control(SimState(0.0, robot.home.copy(), np.zeros(6), 0))  # the robot moves (what queued before: dropped)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as out:
        out.sendto(datagram([np.nan] + [0.0] * 5, NO_KEY, now_us()), ("127.0.0.1", rt.command.port))
        time.sleep(0.05)
        with pytest.raises(StopRobot, match="non-finite joint target"):
            rt.control(SimState(0.002, robot.home.copy(), np.zeros(6), 1))
    rt.command.close()
    assert rt.monitor.fault.kind is Kind.COMMAND_BAD and rt.ticks == 1


@REALTIME
@SLOT
@pytest.mark.parametrize("fault, kind, extra", [("stack-qp-fail", "stack-latch", ("--contact", "poke:at=0.4"))])
# stack-nan and reading-nan: tests/runtime/test_fault_bench.py (named, within their bounds, the record readable) and
# tests/runtime/test_stopping.py (no non-finite command can be sent)
def test_stack_and_reading_faults_are_named_from_their_source(skin, tmp_path, fault, kind, extra):
    """From 0.2 s after the hand-over the layers' tick returns NaN, the retraction's QP solver reports failure (first
    at the poke's retraction, its contact at 0.5 s), or the readings source's frames carry a NaN: named as such,
    stopped at the tick that met it (decided after the onset, before the zero), no non-finite command recorded."""
    p, s, record = run(skin, tmp_path, "--inject", f"{fault}@0.2", *extra, seconds=3.0)
    _stopped_by(p, s, record, kind)
    onset = s["injected"][fault]
    assert onset <= s["detected_mono"] < s["world"]["zero_mono"], s
    cmd = np.array([m.velocity for t, m in messages(record) if t == "/skinsafe/command"])
    assert len(cmd) > 50 and np.isfinite(cmd).all()
    if fault == "stack-qp-fail":  # the poke's retraction was the first QP solve after 0.2 s: the stop came after it
        assert "QP solve failed" in s["reason"] and s["t"] >= s["world"]["onset_t"] >= 0.4, s
    if fault == "reading-nan":
        assert "non-finite reading on 1 taxel(s)" in s["reason"]


@REALTIME
@SLOT
def test_consecutive_overruns_on_the_robots_clock_stop_it(skin, tmp_path):
    """From 0.3 s the sim's state clock advances 3 periods a tick (states missed): the third overrun in a row stops the
    robot, its onset the first one's start; --overruns 0 lets the same run end as planned, counting them."""
    p, s, record = run(skin, tmp_path, "--inject", "sim-overrun@0.3", seconds=1.0)
    _stopped_by(p, s, record, "overrun")
    assert "3 consecutive overruns" in s["reason"] and s["overrun_run_max"] == s["overrun_ticks"] == 3
    assert s["world"]["fault_mono"] <= s["onset_mono"] < s["detected_mono"]
    assert 0.3 + 2 * 0.002 - 1e-9 <= s["world"]["stop_t"] <= 0.3 + 3 * 0.002 + 1e-9  # the sim's clock at the third
    p, s, _ = run(skin, tmp_path, "--inject", "sim-overrun@0.3", "--overruns", "0", seconds=1.0)
    assert p.returncode == 0 and s["kind"] == "end" and s["overrun_ticks"] == s["overrun_run_max"] > 50, p.stderr


def test_a_slow_host_never_makes_the_sim_overrun(ur5):
    """The sim steps one period per tick on its own clock, however late the host's ticks are (here every tick takes
    3 periods): the host's lateness is counted (the driver's overruns), the robot's clock shows no missed state."""
    drv, rt = _runtime(ur5, seconds=0.1)
    drv.realtime = True
    tick = rt.stack.tick

    def slow(*args, **kw):
        time.sleep(3 * drv.period_s)
        return tick(*args, **kw)
    rt.stack.tick = slow
    out = rt.run(settle_s=0.0)
    assert out.kind == "end" and rt.overrun_ticks == 0 and drv.stats.overruns > 40, out.reason
    drv, rt = _runtime(ur5, faults=SimFaults(overrun_at=0.1), seconds=0.3)
    rt.overruns = 5  # --overruns 5: the fifth in a row stops
    out = rt.run(settle_s=0.0)
    assert out.watchdog == "overrun" and rt.overrun_run_max == 5, out.reason
    assert 0.1 + 4 * 0.002 - 1e-9 <= drv.stats.stop_t <= 0.1 + 5 * 0.002 + 1e-9  # the fifth tick from the first overrun's
