"""Runtime pieces without a robot: the force feed's seqlock across processes, command sources (trajectory
CSV validation, teleop over real UDP), the record's CDR encoders against mcap-ros2-support, the
pre-flight's taxel health policy."""
import io
import socket
import subprocess
import sys
import time

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from mcap.reader import make_reader
from mcap_ros2.writer import Writer as Ros2Writer

from skinsafe.core.runtime import ros2_msgs as msgs
from skinsafe.core.runtime.commands import CommandError, Trajectory, read_trajectory
from skinsafe.core.runtime.protocol import StopRobot
from skinsafe.core.runtime.record_read import decode_float64_array
from skinsafe.core.runtime.teleop import NO_KEY, Refusal, Teleop, datagram, now_us
from skinsafe.core.skin.force_feed import FeedError, ForceFeed
from skinsafe.hardware.skin_source import classify

JOINTS = ["j0", "j1", "j2"]
LIMITS = {"q_min": np.full(3, -2.0), "q_max": np.full(3, 2.0), "qd_max": np.full(3, 1.0), "qdd_max": np.full(3, 10.0)}


def test_feed_reads_are_never_torn_across_processes():
    n = 20_000
    with ForceFeed.create(None, n) as feed:
        writer = subprocess.Popen([sys.executable, "-c", (
            "import numpy as np, sys; from skinsafe.core.skin.force_feed import ForceFeed\n"
            f"f = ForceFeed.attach('{feed.name}')\n"
            f"for k in range(1, 3001): f.write(np.full({n}, float(k)), k * 0.001)\n"
            "f.close()")])
        seen = set()
        while writer.poll() is None or len(seen) < 2:
            seq, t, x = feed.read()
            assert x.min() == x.max() == seq and t == pytest.approx(seq * 0.001)  # one write, whole
            seen.add(seq)
            if writer.poll() is not None:
                break
        assert writer.wait() == 0 and len(seen) > 1
        idx = np.array([5, 7])
        assert feed.read(idx)[2].tolist() == [3000.0, 3000.0]
    with pytest.raises(FeedError, match="does not exist"):
        ForceFeed.attach(feed.name)


def _csv(tmp_path, text):
    p = tmp_path / "traj.csv"
    p.write_text(text)
    return p


@pytest.mark.parametrize("text, match", [
    ("time,j0,j1,j2\n0,0,0,0\n1,0,0,0\n", "first column"),
    ("t,j0,j1\n0,0,0\n1,0,0\n", r"missing \['j2'\]"),
    ("t,j0,j1,j2\n0,0,0,0\n1,0,x,0\n", "row 3, column 'j1'"),
    ("t,j0,j1,j2\n0,0,0,0\n1,0,nan,0\n", "not finite"),
    ("t,j0,j1,j2\n0,0,0,0\n1,0,0,0\n1,0,0,0\n", "row 4: t = 1.0 does not increase"),
    ("t,j0,j1,j2\n0,0,0,0\n1,0,0,2.5\n", "row 3, joint 'j2': 2.5000 is above"),
    ("t,j0,j1,j2\n0,0,0,0\n0.5,0,0.9,0\n", "rows 2-3, joint 'j1': 1.800 rad/s"),
    ("t,j0,j1,j2\n0,0,0,0\n", "at least two"),
])
def test_bad_trajectories_are_refused_naming_row_and_column(tmp_path, text, match):
    with pytest.raises(CommandError, match=match):
        read_trajectory(_csv(tmp_path, text), JOINTS, LIMITS)


def test_trajectory_tracks_then_holds_its_last_row(tmp_path):
    src = Trajectory(_csv(tmp_path, "# a comment\nt,j2,j0,j1\n0,0,0,0\n1,0.5,0.2,0\n"), JOINTS, LIMITS)
    q = np.zeros(3)
    v = src(0.5, q)  # on the path: feed-forward rate plus the error term, in the robot's joint order
    assert v == pytest.approx([0.2 + 3 * 0.1, 0.0, 0.5 + 3 * 0.15])  # error clipped at 0.15
    assert src(5.0, np.array([0.2, 0.0, 0.5])) == pytest.approx(np.zeros(3))
    assert src.duration == 1.0


def test_teleop_over_udp_tracks_rejects_and_goes_stale():
    src = Teleop("127.0.0.1:0", JOINTS, LIMITS, stale_s=0.05)
    out = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        q = np.zeros(3)
        assert src(0.0, q).tolist() == [0, 0, 0] and src.age() == 0.0  # nothing before the first datagram
        addr = ("127.0.0.1", src.port)
        t = now_us()
        out.sendto(datagram([0.1, -0.05, 9.0], NO_KEY, t), addr)
        out.sendto(b"SKT2garbage", addr)
        out.sendto(datagram([0.1, 0.2], NO_KEY, t + 1), addr)
        time.sleep(0.05)
        v = src(0.0, q)
        assert v == pytest.approx([0.3, -0.15, 0.45])  # 3 x error, clipped at 0.15; target clipped to q_max
        assert src.accepted == 1 and src.refused == 2 and src.intrusion is None
        assert src.senders[f"127.0.0.1:{out.getsockname()[1]}"].why is Refusal.MALFORMED
        out.sendto(datagram([0.0, 0.0, 0.0], NO_KEY, t - 1), addr)  # older: refused (the third within 1 s)
        time.sleep(0.02)
        assert src(0.0, q) == pytest.approx(v) and src.intrusion is not None
        time.sleep(0.06)
        assert src.age() > src.stale_s
        out.sendto(datagram([np.nan, 0, 0], NO_KEY, now_us()), addr)
        time.sleep(0.02)
        with pytest.raises(StopRobot, match="non-finite"):
            src(0.0, q)
    finally:
        out.close()
        src.close()


def _reference(name, msg) -> bytes:
    buf = io.BytesIO()
    w = Ros2Writer(buf)
    schema = w.register_msgdef(name, msgs.schema(name))
    w.write_message("/x", schema, msg, log_time=1)
    w.finish()
    buf.seek(0)
    return next(iter(make_reader(buf).iter_messages()))[2].data


@settings(max_examples=30, deadline=None)
@given(t=st.floats(0, 1e5), n=st.integers(0, 9), names=st.lists(st.text("abcxyz_", min_size=1, max_size=9), max_size=8),
       seed=st.integers(0, 2 ** 31))
def test_cdr_encoders_equal_mcap_ros2_support(t, n, names, seed):
    rng = np.random.default_rng(seed)
    pos, vel = rng.normal(size=len(names)), rng.normal(size=len(names))
    sec = int(np.floor(t))
    stamp = {"sec": sec, "nanosec": min(int(round((t - sec) * 1e9)), 999_999_999)}
    ref = _reference("sensor_msgs/msg/JointState", {"header": {"stamp": stamp, "frame_id": ""}, "name": names,
                                                    "position": pos.tolist(), "velocity": vel.tolist(), "effort": []})
    assert msgs.JointStateEncoder(names)(t, pos, vel) == ref
    x = rng.normal(size=n)
    data = _reference("std_msgs/msg/Float64MultiArray", {"layout": {"dim": [], "data_offset": 0}, "data": x.tolist()})
    assert decode_float64_array(data).tolist() == x.tolist()  # records of versions 1 and 2
    status = [(nm, k % 3, nm * 2, [(nm, str(k))] * k) for k, nm in enumerate(names)]
    ref = _reference("diagnostic_msgs/msg/DiagnosticArray", {"header": {"stamp": stamp, "frame_id": ""}, "status": [
        {"level": lv, "name": nm, "message": m, "hardware_id": "skinsafe",
         "values": [{"key": a, "value": b} for a, b in v]} for nm, lv, m, v in status]})
    assert msgs.diagnostics(t, status) == ref
    header = {"stamp": stamp, "frame_id": ""}
    assert msgs.taxel_forces(t, x) == _reference("skinsafe_msgs/msg/TaxelForces", {"header": header, "force": x.tolist()})
    assert msgs.tick(t, 1e-3, 7.0, n, n % 2 == 1) == _reference("skinsafe_msgs/msg/Tick", {
        "header": header, "t": t, "dt": 1e-3, "reading_seq": 7.0, "index": n, "ticked": n % 2 == 1})
    poses = rng.normal(size=(n, 7))  # x y z, qw qx qy qz
    assert msgs.pose_array(t, "world", poses) == _reference("geometry_msgs/msg/PoseArray", {
        "header": header | {"frame_id": "world"}, "poses": [
            {"position": dict(zip("xyz", p[:3])), "orientation": dict(zip("wxyz", p[3:]))} for p in poses.tolist()]})


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2 ** 31), frames=st.integers(2, 60), n=st.integers(8, 300))
def test_health_policy_finds_exactly_the_faulty_taxels(seed, frames, n):
    rng = np.random.default_rng(seed)
    th = rng.uniform(1.0, 5.0, n)
    x = np.zeros((frames, n))
    live = rng.random(n) < 0.3  # preloaded cells with ADC noise below the noise limit: healthy
    x[:, live] = rng.uniform(0.1, 0.5, live.sum()) * th[live] + rng.uniform(0, 0.2, (frames, live.sum())) * th[live]
    kinds = rng.choice(["ok", "dead", "stuck", "noisy", "pressed", "saturated"], n, p=[0.6, 0.08, 0.08, 0.08, 0.08, 0.08])
    x[:, kinds == "dead"] = np.nan
    x[:, kinds == "stuck"] = rng.uniform(0.1, 0.9, (kinds == "stuck").sum()) * th[kinds == "stuck"]
    noisy = kinds == "noisy"
    x[:, noisy] = rng.uniform(0, 1, (frames, noisy.sum())) * th[noisy]
    x[0, noisy], x[1, noisy] = 0.0, th[noisy] * 0.9  # spread 0.9 x threshold
    pressed = kinds == "pressed"
    x[:, pressed] = th[pressed] * 1.5 + rng.uniform(0, 0.05, (frames, pressed.sum())) * th[pressed]
    x[0, pressed] -= 0.01
    x[:, kinds == "saturated"] = 34.0
    base, found = classify(x, th, 34.0, 0.25)
    assert np.array_equal(found["dead"], kinds == "dead")
    assert np.array_equal(found["stuck"], (kinds == "stuck") | (kinds == "saturated"))
    assert np.array_equal(found["noisy"], noisy)
    assert np.array_equal(found["pressed"], pressed)
    ok = kinds == "ok"
    assert np.allclose(base[ok], np.median(x[:, ok], axis=0))


@pytest.mark.xdist_group("realtime")  # reads the machine-wide PM QoS target, which a running `skinsafe run` holds at 0
@pytest.mark.usefixtures("realtime_host")
def test_while_the_robot_moves_idle_cores_are_kept_awake_then_released():
    import os

    from skinsafe.core.realtime import loop_priority

    def target() -> int:  # the kernel's CPU latency target (PM QoS), us
        with open("/dev/cpu_dma_latency", "rb") as f:
            return int.from_bytes(f.read(4), sys.byteorder)
    if not os.access("/dev/cpu_dma_latency", os.R_OK | os.W_OK):
        pytest.skip("/dev/cpu_dma_latency is not open to this user (the run goes on without it)")
    before = target()
    with loop_priority("normal priority"):
        assert target() == before  # only a real-time run asks
    try:
        with loop_priority("real-time priority SCHED_FIFO 10"):
            assert target() == 0
    except PermissionError:
        pytest.skip("real-time priority not allowed here")
    assert target() == before > 0


@pytest.mark.parametrize("argv, message", [
    (["--period", "0"], "--period 0.0: give the sim's control period, 0.0002..0.05 s"),
    (["--period", "nan"], "--period nan"),
    (["--alpha", "-0.1"], "--alpha -0.1: RetractionParams: 'alpha' is -0.1; it must be a finite number >= 0"),
    (["--alpha", "inf"], "--alpha inf"),
    (["--tare-frames", "1"], "--tare-frames 1: give 2..10000"),
    (["--tare-frames", "99999999999"], "--tare-frames 99999999999: give 2..10000"),  # the reader ran out of memory
    (["--baud", "99999999999"], "--baud 99999999999: give 1..12000000 bit/s"),  # pyserial's OverflowError
    (["--robot", "fr3", "--host", "127.0.0.1", "--feed", "f", "--after-contact", "always-resume"],
     "--after-contact always-resume resumes the plan after every retraction, flagged or not: refused on a hardware"),
])
def test_run_refuses_bad_numbers_in_one_line_before_anything_starts(tmp_path, capsys, argv, message):
    from skinsafe.core.app.cli import main
    from skinsafe.core.design.sample import make_sample_design
    from skinsafe.core.skin.taxel_map import save

    save(make_sample_design("ur5"), tmp_path / "skin.json")
    assert main(["run", str(tmp_path / "skin.json"), "--boards", "emulate", "--command", "hold", *argv]) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err and len(err.strip().splitlines()) == 1, err
