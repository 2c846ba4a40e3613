"""Operator faults through the real CLI against emulators on ptys: Ctrl-C, devices that are not boards,
duplicate uids, other protocol versions, malformed answers, bad options, emulator shutdown on signals."""
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
from skinsafe.core.skin.taxel_map import save
from skinsafe.hardware.board_config import board_configs
from skinsafe.hardware.emulator import EmulatorProcess, flash_path
from skinsafe.hardware.flat_design import flat_design

SKINSAFE = str(Path(sys.executable).with_name("skinsafe"))


def _lines(out: str, d) -> dict[int, str]:
    return {b.id: next(x for x in out.splitlines() if x.startswith(f"board {b.id} '")) for b in d.boards}


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_ctrl_c_at_a_random_point_of_a_multi_board_deploy(tmp_path, seed):
    old, new = flat_design(1024, 4, 3.0), flat_design(1024, 4, 6.0)  # 4 boards of 256 channels
    save(new, tmp_path / "skin.json")
    for cfg in board_configs(old):
        flash_path(tmp_path / "flash", cfg.uid).parent.mkdir(exist_ok=True)
        flash_path(tmp_path / "flash", cfg.uid).write_bytes(cfg.to_bytes())
    links = tmp_path / "links"
    with EmulatorProcess([(b.uid, b.capacity) for b in new.boards], tmp_path / "flash", "--baud", "115200",
                         "--link-dir", str(links)):
        proc = subprocess.Popen([SKINSAFE, "deploy", str(tmp_path / "skin.json"), "--all", "--no-system-ports",
                                 "--glob", str(links / "board-*"), "--baud", "115200"],
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        assert "deploying" in proc.stderr.readline()
        time.sleep(np.random.default_rng(seed).uniform(0.0, 0.8))  # a whole deploy takes about 0.9 s here
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=30)
    # -2: the signal came after the report, while Python shut down (the shell shows 130 all the same)
    assert "Traceback" not in err and proc.returncode in (130, 0, -2), err
    assert out.splitlines()[-1].startswith("deployed ")
    lines = _lines(out, new)
    olds, news = {c.uid: c.sha256 for c in board_configs(old)}, {c.uid: c.sha256 for c in board_configs(new)}
    for b in new.boards:
        running = hashlib.sha256(flash_path(tmp_path / "flash", b.uid).read_bytes()).digest()
        assert running in (olds[b.uid], news[b.uid])  # never a mix
        state = lines[b.id].split("[")[1].split("]")[0]
        if state in ("untouched", "rolled back"):
            assert running == olds[b.uid], lines[b.id]
        elif state == "committed":
            assert running == news[b.uid], lines[b.id]
        else:
            assert state == "unknown" and "old or the new config" in lines[b.id]
    if proc.returncode == 130:
        assert "interrupted by SIGINT" in out.splitlines()[-1]


def test_discovery_says_why_each_port_was_skipped(tmp_path, capsys):
    d = flat_design(128, 4)
    save(d, tmp_path / "skin.json")
    uid = [b.uid for b in d.boards]
    boards = [(uid[0], 32), (uid[1], 32, "protocol=2"), (uid[2], 32), (uid[3], 32, "protocol=2"), (0x77, 32),
              (0x5C1A0099, 32, "malformed=1")]
    with EmulatorProcess(boards, tmp_path / "a", "--not-a-board", "1", "--link-dir", str(tmp_path / "links")), \
            EmulatorProcess([(uid[2], 32), (uid[3], 32)], tmp_path / "b", "--link-dir", str(tmp_path / "links2")):
        argv = ["deploy", str(tmp_path / "skin.json"), "--all", "--no-system-ports", "--glob",
                str(tmp_path / "links" / "board-*"), "--glob", str(tmp_path / "links2" / "board-*"),
                "--timeout", "0.05", "--retries", "1"]
        assert main(argv) == 1
    out = capsys.readouterr().out
    lines = _lines(out, d)
    assert ": updated [committed]" in lines[0]
    assert ": missing [untouched]" in lines[1] and "version: " in lines[1] and "speaks protocol version 2" in lines[1]
    assert ": missing [untouched]" in lines[2] and f"uid {uid[2]:#x} answers on 2 ports" in lines[2]
    # one uid on two ports, one of them speaking another version: still a duplicate, deployed to neither
    assert ": missing [untouched]" in lines[3] and f"uid {uid[3]:#x} answers on 2 ports" in lines[3]
    assert not flash_path(tmp_path / "b", uid[3]).exists()
    other = next(x for x in out.splitlines() if "board-other-0: no board" in x)
    assert "not-a-board: " in other and "none of them a skinsafe frame" in other and "2 tries" in other
    assert "board uid 0x77 is not in the map; it was left alone" in out
    bad = next(x for x in out.splitlines() if "board-000000005c1a0099: no board" in x)
    assert "malformed: " in bad and "sent a malformed identify answer: " in bad and "byte " in bad
    assert f"board-{uid[2]:016x}: no board (duplicate uid" in out
    assert not flash_path(tmp_path / "a", uid[1]).exists() and not flash_path(tmp_path / "a", uid[2]).exists()


def test_malformed_answer_mid_deploy_names_board_and_byte(tmp_path, capsys):
    d = flat_design(64, 1)
    save(d, tmp_path / "skin.json")
    with EmulatorProcess([(d.boards[0].uid, 64, "malformed=0.3,max_chunk=64")], tmp_path, "--seed", "5") as em:
        port = em.ports[d.boards[0].uid]
        codes = [main(["deploy", str(tmp_path / "skin.json"), "--port", port, "--force"]) for _ in range(4)]
    out = capsys.readouterr().out
    assert 1 in codes and "Traceback" not in out
    bad = [x for x in out.splitlines() if x.startswith("board 0") and "failed" in x]
    assert bad and all(f"board {d.boards[0].uid:#x} sent a malformed " in x and "byte " in x for x in bad)
    running = hashlib.sha256(flash_path(tmp_path, d.boards[0].uid).read_bytes()).digest() \
        if flash_path(tmp_path, d.boards[0].uid).exists() else None
    assert running in (None, board_configs(d)[0].sha256)


@pytest.mark.parametrize("argv, message", [
    (["stream", "{map}", "--port", "/dev/null", "--rate", "70000"], "--rate 70000: give frames per second"),
    (["stream", "{map}", "--port", "/dev/null", "--rate", "-1"], "--rate -1"),
    (["deploy", "{map}", "--port", "/dev/null", "--retries", "-2"], "--retries -2: give 0..20"),
    (["deploy", "{map}", "--port", "/dev/null", "--timeout", "nan"], "--timeout nan"),
    (["deploy", "{map}", "--port", "/dev/null", "--baud", "99999999999"], "--baud 99999999999: give 1..12000000"),
    (["stream", "{map}", "--port", "/dev/null", "--baud", "0"], "--baud 0: give 1..12000000"),
])
def test_bad_options_refused_before_any_io(tmp_path, capsys, argv, message):
    save(flat_design(8, 1), tmp_path / "skin.json")
    assert main([a.format(map=tmp_path / "skin.json") for a in argv]) == 2
    assert message in capsys.readouterr().err


def test_stream_rate_warned_and_failed_start_stops_the_started_boards(tmp_path, capsys):
    d = flat_design(512, 2)  # 256 channels: a 550-byte frame, 181.8 frames/s at 1 Mbaud
    save(d, tmp_path / "skin.json")
    boards = [(d.boards[0].uid, 256, "max_rate_hz=4000"), (d.boards[1].uid, 256)]
    with EmulatorProcess(boards, tmp_path, "--link-dir", str(tmp_path / "links")) as em:
        ports = [em.ports[b.uid] for b in d.boards]
        assert main(["deploy", str(tmp_path / "skin.json"), "--port", ports[0], "--port", ports[1]]) == 0
        capsys.readouterr()
        # board 1 refuses 3000 Hz (its maximum is 2000): board 0 was checked first and is never left streaming
        assert main(["stream", str(tmp_path / "skin.json"), "--port", ports[0], "--port", ports[1],
                     "--rate", "3000", "--seconds", "0.2"]) == 1
        err = capsys.readouterr().err
        assert "at 1000000 baud the link carries at most 181 frames/s, asked 3000" in err
        assert "streams at most 2000 Hz, asked 3000" in err
        from skinsafe.hardware.client import BoardClient, BoardError
        from skinsafe.hardware.stream import SkinStream
        stream = SkinStream(d, {0: ports[0], 1: ports[1]}, 100)
        stream.rate_hz = 3000  # as a board whose identify promised more than it does: board 0 starts, board 1 refuses
        with pytest.raises(BoardError, match="refused stream-start: bad parameter"):
            stream.start()
        assert stream.boards[0].started and stream.boards[0].stopped and not stream.boards[1].started
        stream.close()
        for p in ports:
            with BoardClient(p) as c:
                assert not c.identify().flags & 1  # nobody left streaming


def test_ctrl_c_stops_a_stream_with_every_frame_accounted(tmp_path):
    d = flat_design(128, 2)
    save(d, tmp_path / "skin.json")
    with EmulatorProcess([(b.uid, b.capacity) for b in d.boards], tmp_path / "flash", "--link-dir",
                         str(tmp_path / "links")) as em:
        assert main(["deploy", str(tmp_path / "skin.json"), *sum((["--port", p] for p in em.ports.values()), [])]) == 0
        proc = subprocess.Popen([SKINSAFE, "stream", str(tmp_path / "skin.json"), "--all", "--no-system-ports",
                                 "--glob", str(tmp_path / "links" / "board-*"), "--rate", "500"],
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        assert "2 boards streaming at 500 Hz" in proc.stderr.readline()
        time.sleep(0.3)
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=30)
    assert proc.returncode == 130 and "Traceback" not in err, err
    lines = [x for x in out.splitlines() if x.startswith("board ")]
    assert len(lines) == 2
    for line in lines:  # a clean link: every frame the board says it sent was received, none before or after lost
        got = re.search(r"stopped; received (\d+), lost 0, corrupt 0, resynced 0 of (\d+) frames sent", line)
        assert got and int(got[1]) == int(got[2]) > 50, line
    assert out.splitlines()[-1].endswith("interrupted by SIGINT")


def test_emulator_ends_by_itself_on_sigterm_and_sigint(tmp_path):
    """20 tries here (the bench does 200 and times them): boards streaming, answering with delays, or idle;
    every emulator ends by itself with exit 0 (`signal` kills one still running after 5 s and returns inf)."""
    worst = 0.0
    for k in range(20):
        with EmulatorProcess([(0x10 + k, 64), (0x40 + k, 64, "delay=0.3")], tmp_path) as em:
            from skinsafe.hardware.client import BoardClient
            with BoardClient(em.ports[0x10 + k]) as c:
                c.identify()
                c.start_stream(2000)
            worst = max(worst, em.signal(signal.SIGTERM if k % 2 else signal.SIGINT))
            assert em.proc.returncode == 0
    assert worst < float("inf")


@pytest.mark.parametrize("extra, message", [
    (["--max-chunk", "8"], "max chunk 8 outside 16..65530"),
    (["--board", "0x5:8:drop=2"], "drop 2.0 is a probability; give 0..1"),
    (["--board", "0x5:8:colour=red"], "give UID:CHANNELS[:KEY=VALUE,...]"),
    (["--delay", "nan"], "delay nan s: give 0..60 s"),  # a NaN delay once passed the `< 0` check
    (["--seed", "-1"], "--seed -1, --not-a-board 0: give numbers >= 0"),  # was numpy's traceback
    (["--protocol", "256"], "protocol 256: give 0..255"),
    (["--max-rate", "-1"], "max rate -1 Hz: give 1..65535"),
    (["--reset-at-chunk", "0"], "reset-at-chunk 0: give the chunk, 1 or more"),
    (["--baud", "99999999999"], "--baud 99999999999: give 1..12000000 bit/s"),
])
def test_emulator_refuses_options_that_cannot_work(tmp_path, extra, message):
    r = subprocess.run([sys.executable, "-m", "skinsafe.hardware.emulator", "--flash-dir", str(tmp_path),
                        "--board", "0x1:8", *extra], capture_output=True, text=True, timeout=30)
    assert r.returncode == 1 and message in r.stderr and "Traceback" not in r.stderr
