"""`skinsafe run` end to end on one machine: MuJoCo contacts -> shared-memory feed -> emulated boards on
pseudo-terminals (their own process) -> serial -> host decode -> the layers -> the sim driver; every
watchdog, Ctrl-C, the pre-flight's refusals, the record (read by mcap-ros2-support) and its replay.
Boards stream at 100 Hz with a link latency of 0.5 s allowed (a board is silent after 20 + 500 ms): on the
shared test machine the kernel holds the pseudo-terminals' input for tens to hundreds of ms at a time
(README "Running a robot")."""
import json
import re
import signal
import socket
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
from cli_run import start_run
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from skinsafe.core.design.sample import make_sample_design
from skinsafe.core.robot.models import build_ur5
from skinsafe.core.runtime.leader import stream
from skinsafe.core.runtime.monitor import Kind
from skinsafe.core.runtime.ros2_topics import TOPICS as ROS2_TOPICS
from skinsafe.core.runtime.rosbag2 import record_file
from skinsafe.core.runtime.run_config import RunConfig
from skinsafe.core.skin.taxel_map import save

LINK_LATENCY = 0.5  # s: the host's serial input may be this late before a board is named silent
# SCHED_FIFO loop pinned to core 0, timed watchdogs: one at a time (conftest.realtime_host)
pytestmark = [pytest.mark.xdist_group("realtime"), pytest.mark.usefixtures("realtime_host")]
TOPICS = {"/joint_states", "/skinsafe/command", "/skinsafe/planned", "/skinsafe/forces", "/skinsafe/tick",
          "/skinsafe/state", "/diagnostics", *ROS2_TOPICS}


@pytest.fixture(scope="module")
def skin(tmp_path_factory):
    path = tmp_path_factory.mktemp("run") / "skin.json"
    save(make_sample_design("ur5"), path)
    return path


def skinsafe(*args, timeout=60, **kw):
    return subprocess.run([sys.executable, "-m", "skinsafe.core.app.cli", *map(str, args)], capture_output=True,
                          text=True, timeout=timeout, **kw)


def run(skin, tmp_path, *extra, command="hold", seconds=1.5, when_moving=None, record=True):
    """`skinsafe run` with the emulated boards; `when_moving(proc)` is called once the robot moves; `record` False: no
    `--record` (its writer process costs ~2-5 CPU s a run), for a test that reads none."""
    stats, path = tmp_path / "stats.json", tmp_path / "run"
    args = ["run", skin, "--robot", "sim", "--boards", "emulate", "--command", command, "--link-latency", LINK_LATENCY, "--allow-link-latency", "--tare-frames", 10,
            "--seconds", seconds, *(["--record", path] if record else []), "--stats", stats, *extra]
    code, out, err = start_run(args, when_moving)
    p = subprocess.CompletedProcess(args, code, out, err)
    return p, (json.loads(stats.read_text()) if stats.exists() else None), path if record else None


def messages(record):
    """Every message of a record (its folder's MCAP), decoded by mcap-ros2-support (the ROS 2 reader)."""
    with open(record_file(record), "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        return [(c.topic, m) for _, c, _, m in reader.iter_decoded_messages(log_time_order=False)]


def test_a_poke_is_retracted_and_the_record_replays_exactly(skin, tmp_path):
    p, s, record = run(skin, tmp_path, "--contact", "poke:at=0.4", seconds=1.6)
    assert p.returncode == 0, p.stderr
    worst = re.search(r"worst stopping distance (\d+) mm in (\d+) ms \(`([a-z-]+)`", p.stderr)  # printed at start
    assert worst and int(worst[1]) > 0 and int(worst[2]) > 0 and worst[3] in {k.value for k in Kind}
    w = s["world"]
    assert w["onset_t"] is not None and w["reaction_t"] is not None and w["peak_N"] > 2.0  # above the 2 N threshold
    assert 2.0 < w["first_peak_N"] <= w["peak_N"]  # the first contact's peak: one of the run's
    lat, wait = np.array(s["latency_ms_all"]), np.array(s["latency_wait_ms_all"])
    assert len(lat) == s["latency_samples"] > 0 and (0 <= wait).all() and (wait < lat).all()  # a part, before the tick
    at = np.array(s["latency_tick_all"])  # each latency's tick: one at most per tick, in order, within the run
    assert len(at) == len(lat) and (np.diff(at) > 0).all() and 0 < at[0] and at[-1] < s["ticks"]
    assert 0 < s["start_mono"] < time.monotonic() - 1.6  # the first tick's start: the run lasted 1.6 s after it
    msgs = messages(record)
    assert {t for t, _ in msgs} == TOPICS
    times = np.array([m.header.stamp.sec + m.header.stamp.nanosec * 1e-9 for t, m in msgs if t == "/skinsafe/command"])
    cmd = np.array([m.velocity for t, m in msgs if t == "/skinsafe/command"])
    assert np.abs(cmd[times < w["onset_t"]]).max() == 0.0  # hold: still until the poke
    assert np.abs(cmd[times > w["onset_t"]]).max() > 0.05  # then the retraction
    taxels = [m for t, m in msgs if t == "/skinsafe/forces"]
    assert len(taxels[0].force) == s["taxels"] and max(max(m.force) for m in taxels) > 2.0
    layers = [m for t, m in msgs if t == "/skinsafe/state"]
    assert len(layers) == len(cmd)  # one per tick
    on = [x for x in layers if x.retracting]
    assert on and all(len(x.pool_taxels) >= 1 for x in on)  # the retraction names its taxels
    assert not any(x.retracting for x, tt in zip(layers, times) if tt < w["onset_t"])
    r = skinsafe("replay", record, "--json")
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert out["ticks"] == s["ticks"] and out["complete"] and out["max_abs_diff"] <= 1e-12
    with open(record_file(record), "rb") as f:  # the record holds the run's configuration as given
        config = json.loads(next(m for m in make_reader(f).iter_metadata() if m.name == "skinsafe").metadata["config"])
    cfg = RunConfig.from_json(config["run"])
    assert (cfg.contact, cfg.seconds, cfg.record, cfg.link_latency) == ("poke:at=0.4", 1.6, str(record), LINK_LATENCY)


def test_a_trajectory_into_the_post_is_turned_back(skin, tmp_path):
    home = build_ur5().home
    t = np.linspace(0, 2, 21)
    q = np.repeat(home[None], len(t), 0)
    q[:, 0] += 0.2 * t  # the post stands in the way of joint 0 turning positive
    csv = tmp_path / "traj.csv"
    joints = ["shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint", "wrist_1_joint", "wrist_2_joint", "wrist_3_joint"]
    csv.write_text("t," + ",".join(joints) + "\n" + "\n".join(",".join(map(str, [a, *b])) for a, b in zip(t, q)))
    p, s, record = run(skin, tmp_path, "--contact", "post:joint=0,gap=0.01", command=f"trajectory:{csv}", seconds=1.5)
    # the contact at speed flags the retraction's first ticks infeasible: once it has turned the arm back
    # the monitor latches a protective stop instead of resuming the plan into the post
    assert p.returncode == 1 and s["watchdog"] == "stack-latch" and s["state"] == "protective_stop", p.stderr
    w = s["world"]
    assert w["onset_t"] is not None and w["reaction_t"] is not None and w["stop_t"] > w["reaction_t"]
    msgs = messages(record)
    planned = np.array([m.velocity[0] for t, m in msgs if t == "/skinsafe/planned"])
    sent = np.array([m.velocity[0] for t, m in msgs if t == "/skinsafe/command"])
    assert planned.min() >= 0 and sent.min() < -0.01  # the plan pushes on; the layers pulled the arm back


def _teleop(port: int, stop: threading.Event):
    """Leader-arm datagrams at 100 Hz (the UR5's home pose) until `stop`."""
    home = build_ur5().home
    stream(("127.0.0.1", port), np.array([0.0, 1.0]), np.stack([home, home]), stop)


@pytest.mark.parametrize("inject, reason, kind, named", [
    ("board-unplug@0.3:1", "board 'board1' (uid 0x5c1a0001): link lost", "fault", "link-lost"),
    ("frame-delay@0.3", "silent for", "fault", "board-silent"),
    ("crc-storm@0.3", "CRC storm", "fault", "crc-storm"),
    ("sim-die@0.3", "sim: the simulation failed", "driver", "driver"),
    # frame-replay, foreign-uid and sim-freeze: tests/runtime/test_fault_bench.py (named as injected, latched, within
    # their bounds, the record readable)
    ("teleop-silent@0.3", "command: teleop:127.0.0.1:", "fault", "command-stale"),
])
def test_every_watchdog_stops_the_robot_naming_why(skin, tmp_path, inject, reason, kind, named):
    extra, command, stop, moving = [], "hold", threading.Event(), None
    if inject.startswith("teleop"):  # the operator's leader arm goes quiet 0.3 s after the robot moves
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.bind(("127.0.0.1", 0))
            port = s.getsockname()[1]
        command = f"teleop:{port}"
        threading.Thread(target=_teleop, args=(port, stop), daemon=True).start()
        moving = lambda proc: threading.Timer(0.3, stop.set).start()  # noqa: E731
    else:
        extra = ["--inject", inject]
    try:
        p, s, record = run(skin, tmp_path, *extra, command=command, seconds=3.0, when_moving=moving)
    finally:
        stop.set()
    assert p.returncode == 1, p.stderr
    assert reason in s["reason"] and s["kind"] == kind and reason in p.stderr
    assert s["watchdog"] == named and s["state"] == "protective_stop"  # the monitor's typed fault, latched
    w = s["world"]
    assert w["zero_mono"] - s["detected_mono"] < 2 * s["period_s"]  # zero velocity within 2 periods of detection
    assert w["rest_qd"] < 1e-2 or kind == "driver"  # the robot's own stop ended at rest (a dead sim has no arm)
    msgs = messages(record)
    last_cmd = [m for t, m in msgs if t == "/skinsafe/command"][-1]
    assert list(last_cmd.velocity) == [0.0] * 6 or kind == "driver"
    stop_diag = [m for t, m in msgs if t == "/diagnostics"][-1].status[0]
    assert stop_diag.name == "skinsafe/watchdog" and stop_diag.level == 2 and reason in stop_diag.message


def test_ctrl_c_stops_the_robot_first_then_reports_and_exits_130(skin, tmp_path):
    p, s, record = run(skin, tmp_path, "--contact", "poke:at=0.2", seconds=30,
                       when_moving=lambda proc: threading.Timer(0.6, proc.send_signal, (signal.SIGINT,)).start())
    assert p.returncode == 130, p.stderr
    assert "STOPPED by the operator" in p.stderr and "SIGINT" in p.stderr
    assert s["kind"] == "operator" and s["world"]["zero_mono"] - s["detected_mono"] < 2 * s["period_s"]
    assert s["world"]["rest_qd"] < 1e-2 and s["t"] < 5  # the robot's own stop ended at rest, long before --seconds
    msgs = messages(record)
    assert list([m for t, m in msgs if t == "/skinsafe/command"][-1].velocity) == [0.0] * 6
    assert "interrupted by the operator" in [m for t, m in msgs if t == "/diagnostics"][-1].status[0].message


def test_preflight_names_faulty_taxels_and_refuses_beyond_the_limit(skin, tmp_path):
    p, s, _ = run(skin, tmp_path, "--taxel-fault", "stuck:10", "--taxel-fault", "noisy:20", seconds=0.3,
                  record=False)
    assert p.returncode == 0, p.stderr
    assert s["preflight"]["stuck"] == [10] and s["preflight"]["noisy"] == [20] and s["preflight"]["excluded"] == 2
    assert "stuck [10], noisy [20]" in p.stderr
    (tmp_path / "refused").mkdir()
    p, s, _ = run(skin, tmp_path / "refused", "--taxel-fault", "stuck:10", "--max-excluded", "0", seconds=0.3,
                  record=False)
    assert p.returncode == 3 and "pre-flight refused" in p.stderr and "stuck 1" in p.stderr and "[10]" in p.stderr
    assert s is None  # the robot never moved


def test_preflight_refuses_a_board_running_another_map(skin, tmp_path):
    from skinsafe.core.skin.taxel_map import load
    from skinsafe.hardware.deploy import deploy
    from skinsafe.hardware.emulator import EmulatorProcess

    design = load(skin)
    other = load(skin)
    other.taxels.thresholds["force"][:] = 3.0  # another map: the boards' configs differ
    with EmulatorProcess([], tmp_path / "flash", "--map", str(skin)) as em:
        ports = {b.id: em.ports[b.uid] for b in design.boards}
        assert all(r.ok for r in deploy(other, ports))
        p = skinsafe("run", skin, "--boards", *ports.values(), "--command", "hold", "--seconds", 0.2)
    assert p.returncode == 3, p.stderr
    assert "pre-flight refused" in p.stderr and "board 'board0' runs another config than this map" in p.stderr
