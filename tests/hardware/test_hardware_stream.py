"""Streaming from emulated boards over ptys: decoded newtons per taxel, danger events, loss and corruption counts."""
import time

import numpy as np
import pytest

from skinsafe.core.bench.serial_link import decode_all, decode_loop, stream_bytes
from skinsafe.core.safety.events import danger_events
from skinsafe.core.sim.sensor_model import FSRModel
from skinsafe.hardware import protocol as P
from skinsafe.hardware.board_config import channel_rows
from skinsafe.hardware.client import BoardClient, BoardError
from skinsafe.hardware.deploy import deploy
from skinsafe.hardware.emulator import EmulatorProcess
from skinsafe.hardware.flat_design import flat_design
from skinsafe.hardware.stream import SkinStream, decode_frames, decode_table

THRESHOLD = 5.0


def _replay(tmp_path, n_channels, frames=7):
    """Forces (frames, channels): frame k presses channels k*3 .. k*3+2 at 8 N, the rest at 1 N."""
    f = np.full((frames, n_channels), 1.0)
    for k in range(frames):
        f[k, 3 * k:3 * k + 3] = 8.0
    path = tmp_path / "replay.npy"
    np.save(path, f)
    return f, path


def test_decode_table_matches_fsr_model_exactly():
    fsr = FSRModel()
    table = decode_table(fsr.decode)
    counts = np.random.default_rng(0).integers(0, 65536, (50, 64)).astype(np.uint16)
    wire = b"".join(P.encode_frame(P.STREAM_DATA, k, 9, P.STREAM_HEAD.pack(0, k, 64, 0) + c.astype("<u2").tobytes())
                    for k, c in enumerate(counts))
    items = P.FrameParser(runs=True).feed(wire)
    assert [type(x).__name__ for x in items] == ["Frame", "FrameRun"] and len(items[1].seqs) == 49
    samples, forces = decode_frames(items, 64, np.array([5, 1, 63]), table)
    assert samples.tolist() == list(range(50))
    assert np.array_equal(forces, fsr.decode(counts[:, [5, 1, 63]]))
    frames = P.expand(items)
    short = P.Frame(*frames[1][:4], frames[1].payload[:-2])
    with pytest.raises(ValueError, match="frame of 142 bytes, expected 144 for 64 channels"):
        decode_frames([frames[0], short], 64, np.arange(64), table)
    d = flat_design(96, 3)
    wires = stream_bytes(d, 5)
    assert np.array_equal(decode_all(d, wires, table), decode_loop(d, wires, fsr.decode, 5))


def test_stream_maps_readings_to_taxels_and_flags_danger(tmp_path):
    d = flat_design(64, 2, THRESHOLD)  # boards of 32 channels
    forces, replay = _replay(tmp_path, 32)
    fsr = FSRModel()
    with EmulatorProcess([(b.uid, b.capacity) for b in d.boards], tmp_path, "--replay", str(replay)) as em:
        ports = {b.id: em.ports[b.uid] for b in d.boards}
        assert all(r.status == "updated" for r in deploy(d, ports))
        with SkinStream(d, ports, rate_hz=200) as stream:
            seen, dangers = 0, set()
            deadline = time.monotonic() + 20
            while seen < 30 and time.monotonic() < deadline:
                u = stream.poll(0.05)
                seen += u.frames
                d_now = danger_events({"force": u.peak}, d.taxels.thresholds)
                dangers |= set(d.taxels.ids[d_now].tolist())
                for s in stream.boards:
                    if s.last_sample is None:
                        continue
                    want = fsr.decode(fsr.encode(forces[s.last_sample % len(forces)]))[s.channels]
                    assert np.array_equal(u.force[s.rows], want)
            assert seen >= 30 and u.lost == 0 and u.corrupt == 0
        # every pressed channel on both boards crossed the threshold, and nothing else did
        assert dangers == {(b << 16) + c for b in range(2) for c in range(21)}  # module b (one per board), index c


def test_stream_counts_corrupt_and_lost_frames(tmp_path):
    d = flat_design(128, 1, THRESHOLD)
    with EmulatorProcess([(d.boards[0].uid, 128)], tmp_path / "a") as clean, \
            EmulatorProcess([(d.boards[0].uid, 128)], tmp_path / "b", "--flip", "0.0003", "--seed", "1") as noisy:
        assert deploy(d, {0: clean.ports[d.boards[0].uid]})[0].ok
        assert deploy(d, {0: noisy.ports[d.boards[0].uid]}, timeout=0.1, retries=8)[0].ok
        with SkinStream(d, {0: noisy.ports[d.boards[0].uid]}, rate_hz=1000, timeout=0.1, retries=8) as stream:
            frames = lost = corrupt = 0
            deadline = time.monotonic() + 20
            while frames < 600 and time.monotonic() < deadline:
                u = stream.poll(0.05)
                frames += u.frames
            lost, corrupt = u.lost, u.corrupt
        b = stream.boards[0]
        st = b.stats()
        assert b.stopped and st.received == b.frames >= frames
    # every frame the board sent (its stop answer) is received, corrupt or lost, exactly once
    assert st.received + st.lost + st.corrupt == b.sent
    # a 294-byte frame survives 0.0003 flips per byte ~92% of the time; a flip in the 18-byte header
    # (about 6% of damaged frames) loses it without a CRC error
    assert corrupt > 5 and lost < corrupt and st.resynced >= corrupt
    assert lost + corrupt < 0.3 * frames


def test_set_params_gain_and_reset_over_the_wire(tmp_path):
    d = flat_design(16, 1, THRESHOLD)
    forces, replay = _replay(tmp_path, 16, frames=1)  # channels 0-2 at 8 N, the rest 1 N
    fsr = FSRModel()
    with EmulatorProcess([(d.boards[0].uid, 16)], tmp_path, "--replay", str(replay)) as em:
        port = em.ports[d.boards[0].uid]
        assert deploy(d, {0: port})[0].ok
        with BoardClient(port) as c:
            c.identify()
            c.set_params(3, [0] * 2, [512] * 2)  # channels 3, 4: gain 2, threshold 0
            info = c.identify()
            assert info.flags & P.FLAG_PARAMS_CHANGED
            c.start_stream(100)
            got = []
            while not got:
                got = c.read_stream(0.1)
            last = P.expand(got)[-1].payload
            head = P.STREAM_HEAD.unpack_from(last)
            counts = np.frombuffer(last, "<u2", 16, P.STREAM_HEAD.size)
            base = fsr.encode(forces[0])
            assert counts[3] == 2 * base[3] and counts[5] == base[5] and counts[0] == base[0]
            assert head[3] == 5  # over threshold on the board: channels 0-2 (8 N > 5 N) and 3-4 (threshold 0)
            with pytest.raises(BoardError, match="refused set-params: bad parameter"):
                c.set_params(15, [0] * 2, [256] * 2)
            c.reset()
            time.sleep(0.2)
            c.read_stream(0.05)
            info = c.identify()
            assert not info.flags & P.FLAG_STREAMING and not info.flags & P.FLAG_PARAMS_CHANGED
            assert not c.read_stream(0.1)  # the reset stopped streaming


def test_stream_refuses_a_board_running_another_map(tmp_path):
    d = flat_design(32, 1, THRESHOLD)
    with EmulatorProcess([(d.boards[0].uid, 32)], tmp_path) as em:
        port = em.ports[d.boards[0].uid]
        with pytest.raises(BoardError, match="runs another config than this map"):
            SkinStream(d, {0: port})
        assert deploy(d, {0: port})[0].ok
        other = flat_design(32, 1, THRESHOLD + 1)
        with pytest.raises(BoardError, match="run `skinsafe deploy` first"):
            SkinStream(other, {0: port})
        SkinStream(d, {0: port}).close()
        assert channel_rows(d, d.boards[0]).tolist() == list(range(32))


def test_every_frame_sent_counted_once_including_before_the_first_and_after_the_last():
    from skinsafe.hardware.stream import BoardState
    s = BoardState(0, 1, None, 4, np.arange(4), np.arange(4))
    s.count(np.array([2, 3, 4, 7, 8], np.uint32))  # 0 and 1 lost before the first good frame, 5 and 6 between
    assert (s.sent, s.frames) == (9, 5)
    s.count(np.array([11], np.uint32))  # 9 and 10 went missing between two polls
    assert (s.sent, s.frames) == (12, 6)
    s.end(15)  # the stop answer: 15 frames sent, so 12..14 were lost after the last good one
    assert (s.sent, s.frames) == (15, 6)
    w = BoardState(0, 1, None, 4, np.arange(4), np.arange(4), last_sample=2 ** 32 - 3, sent=2 ** 32 - 2)
    w.count(np.array([2 ** 32 - 1, 1], np.uint32))  # the u32 counter wraps: 2^32-2 and 0 missing
    assert w.sent == 2 ** 32 + 2 and w.frames == 2
    quiet = BoardState(0, 1, None, 4, np.arange(4), np.arange(4))
    quiet.end(7)  # nothing arrived at all: all 7 frames were lost
    assert (quiet.sent, quiet.frames) == (7, 0)


def test_a_stream_frame_of_the_wrong_size_counts_as_corrupt_not_a_crash(tmp_path):
    d = flat_design(32, 1, THRESHOLD)
    with EmulatorProcess([(d.boards[0].uid, 32)], tmp_path) as em:
        port = em.ports[d.boards[0].uid]
        assert deploy(d, {0: port})[0].ok
        stream = SkinStream(d, {0: port}, 100)
        s = stream.boards[0]
        s.client.stream.append(P.Frame(1, P.STREAM_DATA, 0, s.uid, bytes(10)))  # as if a buggy board sent it
        s.sent = 1
        u = stream.poll(0.0)
        assert s.malformed == 1 and u.corrupt == 1 and u.frames == 0
        stream.close()
