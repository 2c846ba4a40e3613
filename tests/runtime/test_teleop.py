"""Teleop from the leader alone (core/runtime/teleop.py): a second sender's forged, replayed, jumped or unsigned
datagrams never change the target the robot tracks, each is counted and named; a leader with another key is
refused with the reason; the key file; binding beyond loopback without a key is refused; hypothesis over a
datagram's bytes; and the hijack end to end (`skinsafe run` on the sim, a leader and an intruder over UDP)."""
import json
import os
import select
import socket
import struct
import threading

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from skinsafe.core.runtime.commands import CommandError, command_source
from skinsafe.core.runtime.protocol import StopRobot
from skinsafe.core.runtime.rosbag2 import record_file
from skinsafe.core.runtime.teleop import (
    MAGIC,
    NO_KEY,
    Refusal,
    Teleop,
    datagram,
    load_key,
    make_key,
    now_us,
)

JOINTS = ["j0", "j1", "j2"]
LIMITS = {"q_min": np.full(3, -2.0), "q_max": np.full(3, 2.0), "qd_max": np.full(3, 1.0), "qdd_max": np.full(3, 10.0)}
T0 = 1_700_000_000_000_000  # µs: the receiver's wall clock in the unit tests (its seam)


class Rig:
    """A Teleop with a key and a fixed wall clock, a leader's socket and an intruder's, on loopback."""

    def __init__(self, key, **kw):
        self.now = T0
        self.src = Teleop("127.0.0.1:0", JOINTS, LIMITS, stale_s=0.1, key=key, clock_us=lambda: self.now, **kw)
        self.to = ("127.0.0.1", self.src.port)
        self.leader, self.intruder = (socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(2))
        for s in (self.leader, self.intruder):
            s.bind(("127.0.0.1", 0))

    def name(self, s) -> str:
        return f"127.0.0.1:{s.getsockname()[1]}"

    def send(self, s, data: bytes):
        """One datagram from `s`, then a tick that reads it: the target the robot tracks after it."""
        s.sendto(data, self.to)
        assert select.select([self.src.sock], [], [], 1.0)[0]
        self.src(0.0, np.zeros(3))
        return None if self.src.target is None else self.src.target.copy()

    def close(self):
        for s in (self.leader, self.intruder, self.src):
            s.close()


@pytest.fixture
def key(tmp_path):
    return make_key(tmp_path / "leader.key")


def test_an_intruder_never_moves_the_robot_and_is_named(key):
    rig = Rig(key)
    try:
        lead = np.array([0.1, -0.2, 0.3])
        first = datagram(lead, key, T0)
        assert rig.send(rig.leader, first) == pytest.approx(lead)  # pinned: the first valid sender
        assert rig.src.leader_name == rig.name(rig.leader) and rig.src.pinned == "first datagram"
        bad = [0.4, 0.0, 0.0]  # the hijacker's shoulder target
        other = make_key(rig.src.key.path + ".other")
        attempts = [datagram(bad, other, T0 + 1),  # forged: another key
                    first,  # replayed: the leader's own datagram, captured
                    datagram(bad, key, T0 + 2**30),  # jumped: 2^30 µs ahead, even with the right key
                    datagram(bad, NO_KEY, T0 + 3)]  # unsigned
        for k, data in enumerate(attempts, start=1):
            assert rig.send(rig.intruder, data) == pytest.approx(lead)  # the target never changes
            s = rig.src.senders[rig.name(rig.intruder)]
            assert rig.src.refused == s.datagrams == k and s.why is Refusal.NOT_LEADER
        # from the leader's own address: a replay, a jump within the clock's skew, one off the clock, a forgery
        for data, why in ((first, Refusal.REPLAYED), (datagram(bad, key, T0 + 800_000), Refusal.JUMPED),
                          (datagram(bad, key, T0 + 2**30), Refusal.CLOCK), (datagram(bad, other, T0 + 5), Refusal.FORGED),
                          (b"SKT2" + bytes(10), Refusal.MALFORMED)):
            n = rig.src.refused
            assert rig.send(rig.leader, data) == pytest.approx(lead) and rig.src.refused == n + 1
            assert rig.src.senders[rig.name(rig.leader)].why is Refusal.REPLAYED  # its first refusal, counted on
        assert rig.src.senders[rig.name(rig.leader)].datagrams == 5 and rig.src.accepted == 1
        rig.now += 10_000
        assert rig.send(rig.leader, datagram(lead + 0.01, key, T0 + 10_000)) == pytest.approx(lead + 0.01)
        i = rig.src.intrusion  # 3 refused within 1 s: the intruder's first is the onset
        assert i is not None and i.onset == rig.src.senders[rig.name(rig.intruder)].first
        assert rig.name(rig.intruder) in i.message and "not the leader" in i.message
        assert f"the leader is {rig.name(rig.leader)}" in i.message
        summary = rig.src.summary()
        assert summary["key_id"] == key.key_id and key.secret.hex() not in json.dumps(summary)
        assert {s["address"]: s["datagrams"] for s in summary["senders"]} == {rig.name(rig.intruder): 4,
                                                                               rig.name(rig.leader): 5}
    finally:
        rig.close()


def test_what_queued_before_the_robot_moved_is_dropped_unread(key):
    """A leader streams while the run is wired (seconds: pre-flight, warm-up); at the start that backlog, stale by
    then, is dropped, not refused (it would read as an intruder, its stamps off the clock)."""
    rig = Rig(key)
    try:
        for k in range(5):
            rig.leader.sendto(datagram([0.1, 0.1, 0.1], key, T0 - 5_000_000 + k), rig.to)
        assert select.select([rig.src.sock], [], [], 1.0)[0]
        rig.src.start(np.zeros(3))
        assert (rig.src.dropped, rig.src.refused, rig.src.accepted) == (5, 0, 0)
        assert rig.send(rig.leader, datagram([0.2, 0.2, 0.2], key, T0)) == pytest.approx([0.2] * 3)
    finally:
        rig.close()


def test_a_leader_with_another_key_is_refused_with_the_reason(key, tmp_path):
    rig = Rig(key)
    try:
        wrong = make_key(tmp_path / "wrong.key")
        for k in range(3):
            assert rig.send(rig.leader, datagram([0.1, 0.1, 0.1], wrong, T0 + k)) is None
        assert rig.src.accepted == 0 and rig.src.leader_name == ""  # never pinned by a datagram that fails
        msg = rig.src.intrusion.message
        assert "another key" in msg and key.key_id in msg and rig.name(rig.leader) in msg and "fails authentication" in msg
    finally:
        rig.close()


def test_a_given_leader_pins_its_address(key):
    rig = Rig(key, leader="127.0.0.1")  # a host alone: its first valid datagram pins the port too
    try:
        assert rig.src.pinned == "given"
        assert rig.send(rig.intruder, datagram([0.1, 0.1, 0.1], key, T0)) is not None  # from that host: the leader
        assert rig.send(rig.leader, datagram([0.2, 0.2, 0.2], key, T0 + 1)) == pytest.approx([0.1] * 3)
        assert rig.src.senders[rig.name(rig.leader)].why is Refusal.NOT_LEADER
    finally:
        rig.close()
    with pytest.raises(CommandError, match="HOST or HOST:PORT"):
        Teleop("127.0.0.1:0", JOINTS, LIMITS, key=key, leader="127.0.0.1:99999")


def test_listening_beyond_loopback_needs_a_key_and_the_key_file_is_private(key, tmp_path):
    with pytest.raises(CommandError, match="without a key lets anyone who reaches the port drive the robot"):
        command_source("teleop:0.0.0.0:0", JOINTS, LIMITS)
    command_source("teleop:0.0.0.0:0", JOINTS, LIMITS, key=key).close()
    with pytest.raises(CommandError, match="--teleop-key and --teleop-leader are for --command teleop"):
        command_source("hold", JOINTS, LIMITS, key=key)
    path = tmp_path / "leader.key"
    assert os.stat(path).st_mode & 0o777 == 0o600 and load_key(path) == key
    assert key.secret.hex() not in repr(key) and len(key.key_id) == 16
    with pytest.raises(CommandError, match="exists; .* --force"):
        make_key(path)
    assert make_key(path, force=True).secret != key.secret
    os.chmod(path, 0o644)
    with pytest.raises(CommandError, match="others may read it .*`chmod 600"):
        load_key(path)
    bad = tmp_path / "bad.key"
    bad.write_text('{"schema_version": 9, "kind": "skinsafe-teleop-key", "key": "00"}')
    os.chmod(bad, 0o600)
    with pytest.raises(CommandError, match="schema_version 9"):
        load_key(bad)
    with pytest.raises(CommandError, match="skinsafe teleop-key"):
        load_key(tmp_path / "missing.key")


def test_teleop_key_command_prints_the_id_never_the_key(tmp_path, capsys):
    from skinsafe.core.app.cli import main

    assert main(["teleop-key", str(tmp_path / "k.key")]) == 0
    out = capsys.readouterr().out
    key = load_key(tmp_path / "k.key")
    assert key.key_id in out and key.secret.hex() not in out
    assert main(["teleop-key", str(tmp_path / "k.key")]) == 2 and "--force" in capsys.readouterr().err


@pytest.fixture(scope="module")
def fuzzed():
    from skinsafe.core.runtime.teleop import TeleopKey

    rig = Rig(TeleopKey("hypothesis", bytes(range(32))))
    rig.send(rig.leader, datagram([0.5, -0.5, 1.0], rig.src.key, T0))
    yield rig
    rig.close()


@settings(max_examples=150, deadline=None)
@given(magic=st.sampled_from([MAGIC, b"SKT1", b"\0\0\0\0"]),
       stamp=st.one_of(st.integers(0, 2**64 - 1), st.integers(T0 - 2_000_000, T0 + 2_000_000)),
       count=st.sampled_from([None, None, 0, 2, 4]),
       values=st.lists(st.floats(allow_nan=True, allow_infinity=True), min_size=2, max_size=4),
       sign=st.sampled_from(["key", "key", "none", "garbage"]), cut=st.sampled_from([0, 0, -3, -1, 1, 8]),
       from_leader=st.booleans(), raw=st.binary(max_size=120))
def test_no_datagram_moves_the_robot_off_the_leaders_target(fuzzed, magic, stamp, count, values, sign, cut,
                                                            from_leader, raw):
    """Whatever arrives (a datagram's magic, stamp, joint count, values finite or not, length, tag; or any bytes),
    from the leader's address or another: the target the robot tracks is the last valid one the leader sent; a
    non-finite target in a valid datagram stops the robot and never becomes the target."""
    import hashlib
    import hmac

    rig = fuzzed
    count = len(values) if count is None else count
    body = struct.pack("<4sQH", magic, stamp, count) + np.asarray(values, "<f8").tobytes()
    body = body[:len(body) + cut] if cut < 0 else body + bytes(cut)
    tag = {"key": hmac.new(rig.src.key.secret, body, hashlib.sha256).digest(), "none": b"", "garbage": raw[:32]}[sign]
    for data in (body + tag, raw):
        before, newest = rig.src.target.copy(), rig.src.stamp
        valid = (data is not raw and from_leader and sign == "key" and magic == MAGIC and cut == 0
                 and count == len(values) == 3 and abs(stamp - T0) <= 1e6 and newest < stamp <= newest + rig.src.jump_us)
        stopped = False
        try:
            after = rig.send(rig.leader if from_leader else rig.intruder, data)
        except StopRobot:
            stopped, after = True, rig.src.target
        finite = bool(np.isfinite(values).all())
        assert stopped == (valid and not finite)
        assert np.array_equal(after, np.clip(values, -2, 2) if valid and finite else before)


# -- end to end: the hijack of the issue, on `skinsafe run` ---------------------------------------------------------

@pytest.mark.xdist_group("realtime")
@pytest.mark.usefixtures("realtime_host")
def test_the_hijack_fails_the_leader_keeps_the_arm_and_the_intruder_is_named(tmp_path):
    """A leader holds the UR5's home at 100 Hz with the key; 0.3 s after the robot moves, a second process sends the
    shoulder to +0.4 rad at 100 Hz (stamps 2^30 µs ahead, unsigned; another key; the leader's datagram replayed).
    Today's code followed the second sender. Now: the planned command stays the leader's (the arm at home), the run
    stops for `command-intruder` naming the intruder, in the report, the stats and the record."""
    import test_runtime_closed_loop as closed_loop

    from skinsafe.core.design.sample import make_sample_design
    from skinsafe.core.robot.models import build_ur5
    from skinsafe.core.runtime.leader import stream
    from skinsafe.core.skin.taxel_map import save

    skin = tmp_path / "skin.json"
    save(make_sample_design("ur5"), skin)
    key = make_key(tmp_path / "leader.key")
    home = build_ur5().home
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    stop, to = threading.Event(), ("127.0.0.1", port)
    leader = threading.Thread(target=stream, args=(to, np.array([0.0, 1.0]), np.stack([home, home]), stop, 100.0, key),
                              daemon=True)
    leader.start()
    intruder = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    intruder.bind(("127.0.0.1", 0))
    bad = home + np.array([0.4, 0, 0, 0, 0, 0])
    captured = datagram(home, key, now_us())
    other = make_key(tmp_path / "other.key")

    def hijack():
        for k in range(100):
            if stop.wait(0.01):
                return
            data = (datagram(bad, NO_KEY, now_us() + 2**30), datagram(bad, other, now_us()), captured)[k % 3]
            intruder.sendto(data, to)

    try:
        p, s, record = closed_loop.run(skin, tmp_path, "--teleop-key", key.path, command=f"teleop:{port}", seconds=3.0,
                                       when_moving=lambda proc: threading.Timer(0.3, hijack).start())
    finally:
        stop.set()
        intruder.close()
    assert p.returncode == 1, p.stderr
    assert s["watchdog"] == "command-intruder" and s["state"] == "protective_stop", s["reason"]
    senders = {x["address"]: x for x in s["teleop"]["senders"]}
    assert len(senders) == 1 and s["teleop"]["accepted"] > 20 and s["teleop"]["key_id"] == key.key_id
    (name, tally), = senders.items()
    assert name != s["teleop"]["leader"] and tally["why"] == "not the leader" and tally["datagrams"] >= 3
    assert name in s["reason"] and name in p.stderr and s["world"]["zero_mono"] - s["onset_mono"] < 0.1
    msgs = closed_loop.messages(record)
    planned = np.array([m.velocity for t, m in msgs if t == "/skinsafe/planned"])
    q = np.array([m.position for t, m in msgs if t == "/joint_states"])
    assert np.abs(planned).max() < 0.02 and np.abs(q[:, 0] - home[0]).max() < 0.005  # the leader's: home
    stop_diag = [m for t, m in msgs if t == "/diagnostics"][-1].status[0]
    values = dict((v.key, v.value) for v in stop_diag.values)
    assert name in stop_diag.message and name in values["teleop"]
    from mcap.reader import make_reader

    with open(record_file(record), "rb") as f:
        config = json.loads(next(m for m in make_reader(f).iter_metadata() if m.name == "skinsafe").metadata["config"])
    assert config["teleop"] == {"leader": "", "key": key.path, "key_id": key.key_id}
    assert key.secret.hex() not in record_file(record).read_bytes().decode(errors="replace")
