"""The serial layer under the faults a safety runtime must survive (issue 27), each against emulated boards
on real ptys: a pulled cable, lost stream-start answers, replayed and foreign frames, a board left
streaming or on firmware 2, a lying config length, a commit answer without its hash, a flash write
lost under a RAM copy, Ctrl-C while the command starts; and deploy naming every board it did not reach."""
import hashlib
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from skinsafe.core.app.cli import main
from skinsafe.core.bench.stream_faults import traceback_kind
from skinsafe.core.sim.sensor_model import FSRModel
from skinsafe.core.skin.taxel_map import save
from skinsafe.hardware import protocol as P
from skinsafe.hardware.board_config import board_configs
from skinsafe.hardware.client import BoardClient, BoardError
from skinsafe.hardware.deploy import deploy
from skinsafe.hardware.emulated_board import FOREIGN_BIT, BoardSpec, EmulatedBoard, Faults
from skinsafe.hardware.emulator import EmulatorProcess, flash_path
from skinsafe.hardware.flat_design import flat_design
from skinsafe.hardware.stream import COUNTER, BoardState, SkinStream

SKINSAFE = str(Path(sys.executable).with_name("skinsafe"))


def _flashed(tmp_path, d):
    """Flash files holding the map's configs (as after a deploy), so boards of any firmware run the map."""
    folder = tmp_path / "flash"
    folder.mkdir(exist_ok=True)
    for cfg in board_configs(d):
        flash_path(folder, cfg.uid).write_bytes(cfg.to_bytes())
    return folder


def _streaming(port) -> bool:
    with BoardClient(port) as c:
        return bool(c.identify().flags & P.FLAG_STREAMING)


def test_a_pulled_cable_mid_stream_names_the_board_and_ends_with_exit_1(tmp_path, capsys):
    d = flat_design(64, 2)
    save(d, tmp_path / "skin.json")
    boards = [(d.boards[0].uid, 32), (d.boards[1].uid, 32, "unplug_after=40")]
    with EmulatorProcess(boards, _flashed(tmp_path, d)) as em:
        ports = [em.ports[b.uid] for b in d.boards]
        code = main(["stream", str(tmp_path / "skin.json"), "--port", ports[0], "--port", ports[1], "--rate", "100",
                     "--seconds", "10"])
        assert not _streaming(ports[0])  # the other board was stopped
    out, err = capsys.readouterr()
    assert code == 1 and "Traceback" not in err and "choose a folder" not in err, err
    lines = {int(x.split()[1]): x for x in out.splitlines() if x.startswith("board ")}
    assert f"on {ports[1]}: link lost; received " in lines[1]
    assert re.search(r"received (\d+), lost 0, corrupt 0, resynced 0 of \1 frames sent", lines[1]), lines[1]
    assert 30 <= int(re.search(r"received (\d+)", lines[1])[1]) <= 40  # the board sent 40; a hang-up drops what was in flight
    assert f"on {ports[0]}: stopped; received " in lines[0]
    assert f"board {d.boards[1].uid:#x} on {ports[1]}: link lost (" in err  # named, with the port
    assert "FAULT board 1 uid" in out and out.count("link lost") >= 2


def test_a_lost_stream_start_answer_is_recovered_and_a_failed_start_leaves_no_board_streaming(tmp_path):
    d = flat_design(64, 2)
    boards = [(d.boards[0].uid, 32), (d.boards[1].uid, 32, "lost_start_answers=50")]
    with EmulatorProcess(boards, _flashed(tmp_path, d)) as em:
        ports = {b.id: em.ports[b.uid] for b in d.boards}
        # every answer to board 1's start is lost: identify shows it streaming, so the start took effect
        with SkinStream(d, ports, 100, timeout=0.05, retries=2) as stream:
            assert stream.boards[1].client.start_answer_lost and not stream.boards[0].client.start_answer_lost
            frames = 0
            deadline = time.monotonic() + 10
            while frames < 20 and time.monotonic() < deadline:
                frames += stream.poll(0.05).frames
        assert frames >= 20 and all(s.stopped for s in stream.boards)
        assert not any(_streaming(p) for p in ports.values())

        class CtrlCAfter:  # Ctrl-C arrives while the start's answer is awaited: the start went out, its answer not
            name, calls = "SIGINT", 0

            @property
            def requested(self):
                self.calls += 1
                return self.calls > 1

        stream = SkinStream(d, {1: ports[1]}, 100, timeout=0.05, retries=2)
        stream.boards[0].client.cancel = CtrlCAfter()
        with pytest.raises(BoardError, match="stream-start not sent: interrupted"):
            stream.start()
        stream.close()
        assert stream.boards[0].stopped and not _streaming(ports[1])  # its start took effect; it was stopped all the same


def test_replayed_and_out_of_order_counters_are_dropped_never_counted_as_loss():
    s = BoardState(0, 1, None, 4, np.arange(4), np.arange(4))
    take = s.count(np.array([0, 1, 2, 3, 1, 4, 2, 2, 5], np.uint32))
    assert take.tolist() == [True] * 4 + [False, True, False, False, True]
    assert (s.sent, s.frames, s.replayed, s.last_sample, s.last_counter) == (6, 6, 3, 5, 2)
    assert not s.count(np.array([5, 0], np.uint32)).any() and (s.sent, s.replayed) == (6, 5)
    # across the wrap at 2^32: an older counter just below the wrap is a replay, not 2^32 frames lost
    w = BoardState(0, 1, None, 4, np.arange(4), np.arange(4), last_sample=COUNTER - 2, sent=COUNTER - 1)
    assert w.count(np.array([COUNTER - 1, 0, COUNTER - 3, 1], np.uint32)).tolist() == [True, True, False, True]
    assert (w.sent, w.frames, w.replayed) == (COUNTER + 2, 3, 1)
    # a counter ahead of what the board can have sent at its rate since the start is dropped too
    c = BoardState(0, 1, None, 4, np.arange(4), np.arange(4), rate_hz=100, t_start=10.0)
    assert c.count(np.array([0, 1, 5000, 2], np.uint32), now=11.0).tolist() == [True, True, False, True]
    assert (c.sent, c.replayed) == (3, 1)
    assert c.count(np.array([106], np.uint32), now=11.0).tolist() == [True]  # 100 Hz x 1.01 s + 5 frames: possible
    c.end(110)  # the stop answer
    assert (c.sent, c.frames, c.last_sample) == (110, 4, 109)


def test_replayed_and_foreign_frames_never_reach_a_taxel(tmp_path):
    d = flat_design(32, 1)
    forces = np.full((5, 32), 1.0)
    forces[np.arange(5), np.arange(5)] = 8.0  # frame k presses channel k
    np.save(tmp_path / "replay.npy", forces)
    fsr = FSRModel()
    seen = fsr.decode(fsr.encode(forces))
    with EmulatorProcess([(d.boards[0].uid, 32, "old_frames=0.3,foreign_frames=0.3")], _flashed(tmp_path, d),
                         "--replay", str(tmp_path / "replay.npy"), "--seed", "4") as em:
        with SkinStream(d, {0: em.ports[d.boards[0].uid]}, 200) as stream:
            kinds, frames = set(), 0
            s = stream.boards[0]
            deadline = time.monotonic() + 15
            while (frames < 150 or len(kinds) < 2) and time.monotonic() < deadline:
                u = stream.poll(0.02)
                frames += u.frames
                kinds |= {f.kind for f in u.faults}
                if s.last_sample is not None:  # the newest reading is the newest counter taken, never an older one
                    assert np.array_equal(u.force, seen[s.last_sample % 5])
                assert np.nanmax(u.peak, initial=0) <= seen.max()  # a foreign frame is full scale everywhere
    st = s.stats()
    assert kinds == {"replayed", "foreign uid"} and st.replayed > 10 and st.foreign > 10
    assert s.client.foreign.keys() == {d.boards[0].uid ^ FOREIGN_BIT}
    # every frame the board sent (its stop answer) is received, corrupt or lost once; replays are none of them
    # (on a clean link nothing is lost, bar a host stalled past the link's buffer on a loaded machine)
    assert st.received + st.lost + st.corrupt == s.sent and st.corrupt == 0 and st.lost < 0.05 * s.sent


def test_stream_refuses_a_board_already_streaming_or_on_firmware_2_naming_each(tmp_path, capsys):
    d = flat_design(96, 3)
    save(d, tmp_path / "skin.json")
    boards = [(d.boards[0].uid, 32), (d.boards[1].uid, 32, "streaming=100"), (d.boards[2].uid, 32, "firmware=2.0.0")]
    with EmulatorProcess(boards, _flashed(tmp_path, d)) as em:
        ports = [em.ports[b.uid] for b in d.boards]
        argv = ["stream", str(tmp_path / "skin.json"), *sum((["--port", p] for p in ports), []), "--seconds", "0.5"]
        assert main(argv) == 1
        err = capsys.readouterr().err.splitlines()
        assert any(f"{ports[1]}: board 'board1' uid {d.boards[1].uid:#x} is already streaming" in x for x in err), err
        assert any(f"{ports[2]}: board 'board2' refused: firmware 2.0.0 is not supported" in x for x in err), err
        assert not _streaming(ports[0]) and _streaming(ports[1])  # nothing started; the other host's stream untouched
        # --restart stops the streaming board and starts it afresh: its counter from 0, nothing counted lost
        time.sleep(0.3)
        assert main(argv[:2] + ["--port", ports[1], "--seconds", "0.5", "--restart"]) == 1  # board 0, 2 not found
        out = capsys.readouterr().out
        line = next(x for x in out.splitlines() if x.startswith("board 1 "))
        assert re.search(r"stopped; received (\d+), lost 0, corrupt 0, resynced 0 of \1 frames sent", line), line
        assert not _streaming(ports[1])


def test_a_lying_config_length_is_refused_and_dry_run_ends(tmp_path):
    d = flat_design(32, 1)
    save(d, tmp_path / "skin.json")
    with EmulatorProcess([(d.boards[0].uid, 32, "config_len=4294967295")], _flashed(tmp_path, d)) as em:
        port = em.ports[d.boards[0].uid]
        t0 = time.monotonic()
        r = subprocess.run([SKINSAFE, "deploy", str(tmp_path / "skin.json"), "--port", port, "--dry-run"],
                           capture_output=True, text=True, timeout=60)
    assert time.monotonic() - t0 < 30 and r.returncode == 1 and "Traceback" not in r.stderr
    line = next(x for x in r.stdout.splitlines() if x.startswith("board 0 "))
    assert ": missing [untouched]: " in line and f"{port} (malformed: " in line
    assert "bytes 49-52 (config_len) say 4294967295, a board of 32 channels holds at most 408" in line


def test_a_commit_answer_without_its_hash_is_malformed(tmp_path):
    d = flat_design(32, 1)
    with EmulatorProcess([(d.boards[0].uid, 32, "hashless_commit=1")], tmp_path) as em:
        (rep,) = deploy(d, {0: em.ports[d.boards[0].uid]})
    assert rep.status == "failed" and rep.kind == "malformed"
    assert "sent a malformed config-commit answer: 1 bytes, byte 1 onwards missing" in rep.message
    assert rep.state == "committed" and rep.active_hash == board_configs(d)[0].sha256  # asked after: it committed


@pytest.mark.parametrize("verify", ["readback", "hash"])
def test_a_flash_write_lost_under_the_ram_copy_is_caught_by_either_verify(tmp_path, verify):
    d = flat_design(32, 1)
    old = flat_design(32, 1, threshold=3.0)
    folder = _flashed(tmp_path, old)
    with EmulatorProcess([(d.boards[0].uid, 32, "flash_write_lost=1")], folder) as em:
        (rep,) = deploy(d, {0: em.ports[d.boards[0].uid]}, verify=verify)
    assert rep.status == "failed" and "the config in the board's flash differs from the one sent" in rep.message
    assert hashlib.sha256(flash_path(folder, d.boards[0].uid).read_bytes()).digest() == board_configs(old)[0].sha256


def test_the_emulated_read_returns_flash_not_ram(tmp_path):
    d = flat_design(32, 1)
    cfg = board_configs(d)[0]
    board = EmulatedBoard(BoardSpec(cfg.uid, 32, faults=Faults()), tmp_path / "flash")
    try:
        begin = P.BEGIN_REQ.pack(len(cfg.to_bytes()), cfg.sha256)
        assert board.handle(P.Frame(1, P.CONFIG_BEGIN, 1, cfg.uid, begin))[0] == P.OK
        data = cfg.to_bytes()
        assert board.handle(P.Frame(1, P.CONFIG_CHUNK, 2, cfg.uid, P.CHUNK_REQ.pack(0) + data))[0] == P.OK
        assert board.handle(P.Frame(1, P.CONFIG_COMMIT, 3, cfg.uid, cfg.sha256))[1:] == cfg.sha256
        rotten = bytearray(data)
        rotten[-1] ^= 0x40  # a flash cell flips after the commit; the board runs its RAM copy
        (tmp_path / "flash").write_bytes(rotten)
        got = board.handle(P.Frame(1, P.CONFIG_READ, 4, cfg.uid, P.READ_REQ.pack(0, 1024)))
        assert got[1 + P.READ_RESP.size:] == bytes(rotten) and board.config_hash == cfg.sha256
    finally:
        board.close()


def test_ctrl_c_from_the_commands_first_line_ends_with_one_line_never_a_traceback(tmp_path):
    # the CLI module sets its quiet Ctrl-C hook before it imports anything but sys, and imports nothing but
    # signal after it: nothing else loads before main installs its handler
    import ast

    import skinsafe.core.app.cli as cli
    body = ast.parse(Path(cli.__file__).read_text()).body
    imports = [(k, a.name) for k, n in enumerate(body) if isinstance(n, ast.Import) for a in n.names]
    imports += [(k, n.module) for k, n in enumerate(body) if isinstance(n, ast.ImportFrom)]
    hook = next(k for k, n in enumerate(body) if isinstance(n, ast.If) and "excepthook" in ast.unparse(n))
    assert sorted(name for k, name in imports if k < hook) == ["__future__", "sys"]
    assert [name for k, name in imports if k > hook] == ["signal"]
    save(flat_design(8, 1), tmp_path / "skin.json")
    ours = []
    for k in range(12):  # Ctrl-C while the command imports, parses its options and opens the port
        proc = subprocess.Popen([SKINSAFE, "deploy", str(tmp_path / "skin.json"), "--port", "/dev/null"],
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        time.sleep(0.06 + 0.02 * k)
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=30)
        if traceback_kind(err) == "ours":  # (one before skinsafe's first line runs is Python's own)
            ours.append(err)
    assert not ours, ours[0]


def test_deploy_names_every_board_it_did_not_reach_and_why(tmp_path, capsys):
    d = flat_design(64, 2)
    save(d, tmp_path / "skin.json")
    with EmulatorProcess([(d.boards[0].uid, 32)], tmp_path / "flash") as em:
        bad = str(tmp_path / "nope")
        assert main(["deploy", str(tmp_path / "skin.json"), "--port", em.ports[d.boards[0].uid], "--port", bad]) == 1
    out = capsys.readouterr().out.splitlines()
    assert out[0].startswith("board 0 'board0'") and ": updated [committed]" in out[0]
    assert out[1].startswith(f"board 1 'board1' uid {d.boards[1].uid:#x}: missing [untouched]: not found; ")
    assert f"{bad} (link: " in out[1] and "cannot open the serial port" in out[1]
    assert out[2] == "deployed 1 of 2 boards; 1 failed or not found; boards untouched 1, committed 1"
    assert not any("problem" in x for x in out)  # the port's trouble is said once, in the board's line


@pytest.mark.parametrize("period, silence, rate", [(0.02, 0.04, 0.5), (0.01, 0.52, 0.5), (0.001, 0.002, 0.1)])
def test_a_frame_lags_onset_is_when_the_newest_frame_the_host_has_is_older_than_the_silence(period, silence, rate):
    """The proxy's onset of a frame-lag, from the frames it passed (read from the board, written to the host), against
    a brute-force scan of the host's newest frame's age on a fine clock."""
    from skinsafe.hardware.link_faults import _Link

    start = 1.0
    n = int((3 * silence / rate + 10 * period) / period)
    reads = start - 5 * period + period * (np.arange(n) + np.random.default_rng(0).uniform(-0.2, 0.2, n))  # jitter
    writes = np.where(reads < start, reads, reads + (reads - start) * rate)
    link = object.__new__(_Link)  # its bookkeeping only: no ports
    link.onset, link.silence_s, link.fault, link.passed = None, silence, ("frame-lag", start), []
    for r, w in zip(reads, writes):  # written in order, as the proxy flushes them
        link.passed.append((r, w))
        link._lag_onset()
    clock = np.arange(start, writes[-1], 1e-6)
    newest = reads[np.searchsorted(writes, clock, side="right") - 1]  # the newest frame the host has at each instant
    expected = clock[np.argmax(clock - newest > silence)]
    assert link.onset == pytest.approx(expected, abs=2e-6)
    assert link.onset > start + silence  # a ramp: nothing is stale at its start
