"""`skinsafe run --robot fr3` against franky-sim (a MuJoCo server of the libfranka protocol) in its own process and
environment (`make franky-sim`), a hand reaching into the arm in its world, the skin's readings from its contacts
through emulated boards over pseudo-terminals: three processes, two protocols (serial, libfranka), no shortcut.
One franky-sim world serves the module (the last test kills it); the driver's own stops run on it too."""
import faulthandler
import json
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import mujoco
import numpy as np
import pytest
from cli_run import start_run
from hypothesis import given, settings
from hypothesis import strategies as st
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from skinsafe.core.app.cli import main as skinsafe
from skinsafe.core.bench.runtime import write_still, write_waypoints
from skinsafe.core.runtime.rosbag2 import record_file
from skinsafe.core.sim.franky_world import INITIAL_Q, MISSED_LIMIT, WorldProcess, franky_python, hand_in_reach
from skinsafe.core.skin import taxel_map
from skinsafe.hardware import franka
from skinsafe.hardware.franka import FrankaDriver, rate_limit

ROOT = Path(__file__).resolve().parents[2]
SWING = np.array([0.3, 0, 0, 0, 0, 0, 0])  # rad/s of the base joint
LINK_LATENCY = 0.5  # s: the shared test machine's kernel holds serial input this late at times (README)
# one world, in order (the last test kills it); SCHED_FIFO (conftest.realtime_host)
pytestmark = [pytest.mark.xdist_group("realtime"), pytest.mark.usefixtures("realtime_host")]
HANG_S = 120  # s: no test here takes half of it
# where a hung test's stacks go (tests/conftest.py prints them; xdist drops a worker's stderr)
HANG_LOG = Path(os.environ.get("SKINSAFE_HANG_LOG") or Path(tempfile.gettempdir()) / "skinsafe-hangs.txt")


@pytest.fixture(autouse=True)
def no_hang(request):
    """pylibfranka's readOnce waits for the robot's next state holding the interpreter lock, so a world that stops
    sending states would hang the suite where no Python timeout can act: faulthandler's watchdog (a C thread, no
    lock needed) dumps every thread's stack to HANG_LOG and ends the process instead, a failure that names where it
    stood."""
    with HANG_LOG.open("a") as log:
        log.write(f"{time.strftime('%F %T')} {request.node.nodeid}\n")
        log.flush()
        faulthandler.dump_traceback_later(HANG_S, exit=True, file=log)
        yield
        faulthandler.cancel_dump_traceback_later()


@pytest.fixture(scope="module")
def fr3_map(tmp_path_factory):
    """A skin designed on franky-sim's own FR3 MJCF (mesh directory pointed at meshes/)."""
    subprocess.run(["make", "-s", "franky-sim"], cwd=ROOT, check=True)
    d = tmp_path_factory.mktemp("fr3")
    subprocess.run([str(franky_python()), "-m", "skinsafe.core.sim.franky_world", "mjcf", str(d / "fr3.xml")],
                   check=True, capture_output=True)
    assert skinsafe(["design", str(d / "fr3.xml"), "--bodies", "fr3_link5,fr3_link6", "--out",
                     str(d / "skin.json")]) == 0
    return d / "skin.json"


@pytest.fixture(scope="module")
def world(fr3_map):
    """franky-sim's FR3 with a hand that reaches into the arm at rest on skin, 0.5 s into every motion, then
    every `Hand.period` s; at real-time priority where allowed, as the robot's own controller runs."""
    with WorldProcess(fr3_map, fr3_map.parent / "world.json", hand=hand_in_reach(str(fr3_map), INITIAL_Q),
                      realtime=True) as w:
        yield w


def run_fr3(fr3_map, world, tmp_path, seconds, when_moving=None, swing=False):
    """`skinsafe run --robot fr3` holding franky-sim's start pose (the arm goes back after each retraction), or
    with `swing` turning the base joint away from it at 0.2 rad/s: moving before the hand comes (0.5 s), so a stop
    asked then ramps a free arm to rest (one asked in the hand's push would measure the hand)."""
    still = (write_waypoints(tmp_path / "swing.csv", franka.JOINT_NAMES, (0.0, 2.0), (INITIAL_Q, INITIAL_Q + 0.4 * np.eye(7)[0]))
             if swing else write_still(tmp_path / "still.csv", franka.JOINT_NAMES, INITIAL_Q))
    stats, record = tmp_path / "stats.json", tmp_path / "run"
    args = ["run", fr3_map, "--robot", "fr3", "--host", world.host, "--boards", "emulate", "--feed", world.feed,
            "--command", f"trajectory:{still}", "--seconds", seconds, "--link-latency", LINK_LATENCY, "--allow-link-latency", "--allow-non-realtime",
            "--tare-frames", 20, "--record", record, "--stats", stats,
            "--after-contact", "always-resume"]  # the hand comes back every Hand.period s; a retraction it flags
    # infeasible would latch a protective stop under the default (tests/runtime/test_runtime_closed_loop.py's post)
    code, _, err = start_run(args, when_moving, timeout=120)
    assert stats.exists(), f"exit {code}: {err}"
    return code, err, json.loads(stats.read_text()), record


def topics(record):
    """topic -> [(the robot's clock at its tick, message)] of a record, decoded by mcap-ros2-support (the ROS 2
    reader); a tick's messages share their log time, its joint state holds the robot's clock."""
    out, clock = {}, {}
    with open(record_file(record), "rb") as f:
        for _, channel, raw, m in make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages(
                log_time_order=False):
            if channel.topic == "/joint_states":
                clock[raw.log_time] = m.header.stamp.sec + m.header.stamp.nanosec * 1e-9
            out.setdefault(channel.topic, []).append((raw.log_time, m))
    return {k: [(clock.get(ns), m) for ns, m in v] for k, v in out.items()}


def test_fr3_run_senses_the_hand_retracts_and_replays(fr3_map, world, tmp_path):
    """The hand reaches the skin: the boards' frames show it, the stack turns the held pose into a retraction, the
    arm's measured joint velocity follows it, the robot's clock was kept (no communication-constraint stop), and
    the record replays exactly."""
    code, err, s, record = run_fr3(fr3_map, world, tmp_path, seconds=2.0)
    assert code == 0 and s["kind"] == "end", err  # a communication-constraint stop would be the driver's (exit 1)
    assert s["loop_hz_robot_p50"] == pytest.approx(1000, rel=1e-3) and s["world"]["success_rate_min"] > 0.5
    m = topics(record)
    threshold = float(taxel_map.load(fr3_map).taxels.thresholds["force"].min())
    felt = [t for t, msg in m["/skinsafe/forces"] if max(msg.force) > threshold]
    assert felt, "the skin never sensed the hand"
    cmd = np.array([msg.velocity for t, msg in m["/skinsafe/command"]])
    ct = np.array([t for t, _ in m["/skinsafe/command"]])
    assert np.abs(cmd[ct < felt[0]]).max() < 0.05  # holding the pose until the hand came
    retract = np.flatnonzero((ct >= felt[0]) & (np.linalg.norm(cmd, axis=1) > 0.05))
    assert len(retract), "the stack did not retract"
    js = {t: np.array(msg.velocity) for t, msg in m["/joint_states"]}
    follows = [t for t, v in zip(ct[retract], cmd[retract]) if js[t] @ v > 0.5 * np.linalg.norm(v) * np.linalg.norm(js[t])
               and np.linalg.norm(js[t]) > 0.02]
    assert follows, "the measured joint velocity never followed the retraction"
    # what the record holds is what was sent: the one limiter's output, inside the FR3's acceleration and jerk
    # limits (the stack's own output steps its acceleration at a contact), sent unchanged:
    # per command, one robot cycle each (libfranka's limitRate rule: a state the host skipped on a stall does not
    # widen the step); the last command is the stop's zero, the driver ramps from the one before it
    acc = np.diff(cmd[:-1], axis=0) / franka.PERIOD_S
    jerk = np.diff(acc, axis=0) / franka.PERIOD_S
    assert (np.abs(acc) <= franka.QDD_MAX + 1e-6).all()
    assert (np.abs(jerk) <= franka.QDDD_MAX + 1e-3).all() and np.abs(jerk).max() > 100  # it had work to do
    assert s["world"]["rate_limited_ticks"] == 0
    r = subprocess.run([sys.executable, "-m", "skinsafe.core.app.cli", "replay", str(record), "--json"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert out["complete"] and out["ticks"] == s["ticks"] and out["max_abs_diff"] <= 1e-12


def test_fr3_ctrl_c_stops_the_robot_first_then_exits_130(fr3_map, world, tmp_path):
    code, err, s, record = run_fr3(fr3_map, world, tmp_path, seconds=30, swing=True, when_moving=lambda proc: threading.Timer(
        0.3, proc.send_signal, (signal.SIGINT,)).start())
    assert code == 130, err
    assert "STOPPED by the operator" in err and "SIGINT" in err
    assert s["kind"] == "operator" and s["t"] < 10  # long before --seconds
    assert s["world"]["ramp_ticks"] > 0 and s["world"]["rest_qd"] < 0.05  # ramped to rest, then the robot's stop
    m = topics(record)
    assert list(m["/skinsafe/command"][-1][1].velocity) == [0.0] * 7
    assert "interrupted by the operator" in m["/diagnostics"][-1][1].status[0].message


def test_fr3_ctrl_c_twice_stops_once_and_keeps_the_record(fr3_map, world, tmp_path):
    """Two SIGINTs 10 ms apart while the arm moves: the second only sets the same flag (it used to raise
    KeyboardInterrupt through the ramp: no stop reason, no report, the record lost as .part)."""
    def twice(proc):
        for at in (0.3, 0.31):
            threading.Timer(at, proc.send_signal, (signal.SIGINT,)).start()
    code, err, s, record = run_fr3(fr3_map, world, tmp_path, seconds=30, swing=True, when_moving=twice)
    assert code == 130, err
    assert "STOPPED by the operator" in err and s["kind"] == "operator" and s["watchdog"] == "operator"
    assert s["world"]["ramp_ticks"] > 0 and s["world"]["rest_qd"] < 0.05
    assert record.exists() and not record.with_suffix(".mcap.part").exists()
    m = topics(record)
    assert list(m["/skinsafe/command"][-1][1].velocity) == [0.0] * 7
    assert "interrupted by the operator (SIGINT)" == m["/diagnostics"][-1][1].status[0].message


def test_fr3_a_stop_asked_before_the_motion_is_honoured(driver):
    """A Ctrl-C between the signal handler's install and the driver's start: the arm never starts."""
    driver.stop("interrupted by the operator (SIGINT)")
    calls = []
    assert driver.run(lambda s: calls.append(s) or np.zeros(7)) == "interrupted by the operator (SIGINT)"
    assert not calls
    assert driver.run(lambda s: None) == "control ended the motion"  # honoured once: the next run starts


def test_fr3_limits_match_the_robot_model(fr3_map):
    model = mujoco.MjModel.from_xml_path(str(fr3_map.parent / "fr3.xml"))
    ranges = np.array([model.joint(n).range for n in franka.JOINT_NAMES])
    np.testing.assert_allclose(ranges[:, 0], franka.Q_MIN)
    np.testing.assert_allclose(ranges[:, 1], franka.Q_MAX)
    assert (franka.QD_MAX > 2.5).all() and (franka.QDD_MAX == 10).all()


@settings(max_examples=200, deadline=None)
@given(st.lists(st.floats(-50, 50), min_size=7, max_size=7), st.lists(st.floats(-1, 1), min_size=7, max_size=7),
       st.lists(st.floats(-1, 1), min_size=7, max_size=7))
def test_fr3_rate_limit_keeps_velocity_acceleration_and_jerk(cmd, v_frac, a_frac):
    """From any state inside the limits, any command (even far outside them) moves within them."""
    v0 = np.array(v_frac) * franka.QD_MAX * 0.99
    a0 = np.array(a_frac) * franka.QDD_MAX * 0.99
    v, a = v0, a0
    for _ in range(5):
        v1, a1 = rate_limit(np.array(cmd), v, a)
        assert (np.abs(v1) <= franka.QD_MAX + 1e-9).all()
        assert (np.abs(a1) <= franka.QDD_MAX + 1e-9).all()
        assert (np.abs(a1 - a) <= franka.QDDD_MAX * franka.PERIOD_S + 1e-9).all()
        np.testing.assert_allclose(v1, v + a1 * franka.PERIOD_S, atol=1e-12)
        v, a = v1, a1


def test_fr3_rate_limit_reaches_a_reachable_command():
    v, a = np.zeros(7), np.zeros(7)
    for _ in range(100):
        v, a = rate_limit(SWING, v, a)
    np.testing.assert_allclose(v, SWING, atol=0.011)


@pytest.fixture
def driver(world):
    d = FrankaDriver(world.host)
    yield d
    d.close()


def test_fr3_stops_are_named_and_ramp_to_zero(driver):
    states = []

    def swing(s):
        states.append(s)
        return SWING if s.t - states[0].t < 0.3 else -SWING  # out and back: the next test finds the arm at home

    threading.Timer(0.5, driver.stop, args=("operator pressed stop",)).start()
    assert driver.run(swing) == "operator pressed stop"
    assert driver.stats["ramp_ticks"] > 0 and driver.stats["rest_qd"] < 0.05  # the ramp brought the arm to rest
    assert max(abs(s.qd[0]) for s in states) > 0.1  # it had been moving
    first = []
    assert driver.run(lambda s: first.append(s)) == "control ended the motion"
    assert np.abs(first[0].qd).max() < 0.02  # at rest when the next motion starts

    def refuse(s):
        raise RuntimeError("command source silent for 0.2 s")
    assert driver.run(refuse) == "command source silent for 0.2 s"
    reason = driver.run(lambda s: np.full(7, np.nan))
    assert reason.startswith("fr3: control returned (7,)") and "7 finite values" in reason
    assert "7 finite values" in driver.run(lambda s: np.zeros(6))


def test_fr3_missed_cycles_trip_the_communication_constraint(driver):
    n = []

    def slow_once(s):
        n.append(1)
        if len(n) == 100:
            time.sleep(0.05)  # 50 cycles without a command, MISSED_LIMIT stop the arm
        return np.zeros(7)

    reason = driver.run(slow_once)
    assert MISSED_LIMIT < 50
    assert reason.startswith("fr3: the robot stopped the motion") and "communication_constraints_violation" in reason
    assert driver.run(lambda s: None) == "control ended the motion"  # the next motion starts again


def test_fr3_unreachable_host_is_one_line():
    with pytest.raises(franka.FrankaError, match=r"fr3: cannot connect to 127\.0\.0\.254: .*FCI"):
        FrankaDriver("127.0.0.254")


def test_a_world_left_running_stops_itself_and_removes_its_force_feed(fr3_map, tmp_path):
    """A `with WorldProcess` left without `stop()` (the fault bench's way) asks the world to stop: it exits 0 and
    removes its shared memory itself (killed, the memory was left to the resource tracker, with a leak warning)."""
    with WorldProcess(fr3_map, tmp_path / "world.json") as w:
        feed = w.feed
    assert w.proc.returncode == 0
    assert not (Path("/dev/shm") / feed).exists()


def test_fr3_robot_gone_is_named(world, driver):
    """Last: it kills the module's world."""
    n = []

    def kill_at_50(s):
        n.append(1)
        if len(n) == 50:
            world.kill()
        return np.zeros(7)

    reason = driver.run(kill_at_50)
    assert reason.startswith("fr3: communication with the robot lost"), reason
