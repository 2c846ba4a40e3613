"""`skinsafe emulate`, `deploy`, `stream` and `bench serial` end to end (emulator in its own process)."""
import hashlib
import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from skinsafe.core.app.cli import main
from skinsafe.core.skin.taxel_map import save
from skinsafe.hardware.board_config import board_configs
from skinsafe.hardware.emulator import flash_path
from skinsafe.hardware.flat_design import flat_design

SKINSAFE = str(Path(sys.executable).with_name("skinsafe"))


@pytest.fixture
def emulated(tmp_path):
    """A 2-board map saved to skin.json, and `skinsafe emulate --map` running with a link folder."""
    d = flat_design(96, 2)
    save(d, tmp_path / "skin.json")
    f = np.full((4, 48), 0.5)
    f[:, 7] = 9.0  # channel 7 of every board is pressed harder than the 5 N threshold
    np.save(tmp_path / "replay.npy", f)
    proc = subprocess.Popen([SKINSAFE, "emulate", "--map", str(tmp_path / "skin.json"), "--flash-dir",
                             str(tmp_path / "flash"), "--link-dir", str(tmp_path / "links"),
                             "--replay", str(tmp_path / "replay.npy"), "--baud", "1000000"],
                            stdout=subprocess.PIPE, text=True)
    lines = [proc.stdout.readline().strip() for _ in range(3)]
    assert lines[2] == "ready", lines
    yield d, tmp_path, lines
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(10) == 0
    proc.stdout.close()
    assert not any((tmp_path / "links").iterdir())  # links removed on exit


def test_emulate_deploy_stream_cli(emulated, capsys):
    d, tmp, lines = emulated
    assert lines[0].startswith(f"board {d.boards[0].uid:#x} /dev/pts/")
    find = ["--all", "--no-system-ports", "--glob", str(tmp / "links" / "board-*")]
    skin = str(tmp / "skin.json")
    assert main(["deploy", skin, *find, "--dry-run"]) == 0
    out = capsys.readouterr().out
    assert out.count("would-update [untouched] (none ->") == 2 and "channels +48 -0 ~0" in out
    assert not (tmp / "flash").exists() or not any((tmp / "flash").iterdir())
    assert main(["deploy", skin, *find]) == 0
    out = capsys.readouterr().out
    assert out.count(": updated [committed] (none -> ") == 2 and "deployed 2 of 2 boards; 0 failed" in out
    for cfg in board_configs(d):
        assert hashlib.sha256(flash_path(tmp / "flash", cfg.uid).read_bytes()).digest() == cfg.sha256
    port1 = os.readlink(tmp / "links" / f"board-{d.boards[1].uid:016x}")
    assert main(["deploy", skin, "--port", port1, "--board", "board0"]) == 1
    assert ": refused [untouched]: " in capsys.readouterr().out
    assert main(["stream", skin, *find, "--seconds", "1.0", "--rate", "50"]) == 0
    out = capsys.readouterr().out
    ids = [i for line in out.splitlines() if "DANGER" in line
           for i in json.loads(line[line.index("["):line.index("]") + 1])]
    assert sorted(ids) == [7, (1 << 16) + 7] and "(max 9.0 N)" in out  # channel 7 of board (module) 0 and 1, once each
    done = out.strip().splitlines()[-1]
    assert done.startswith("done: ") and done.endswith(" 0 lost, 0 corrupt, 0 resynced, 2 danger events")
    per_board = [line for line in out.splitlines() if "stopped; received" in line]
    assert len(per_board) == 2 and all("lost 0, corrupt 0, resynced 0 of" in line for line in per_board)


def test_deploy_cli_errors(tmp_path, capsys):
    assert main(["deploy", str(tmp_path / "missing.json"), "--port", "/dev/null"]) == 2
    assert "file not found" in capsys.readouterr().err
    save(flat_design(8, 1), tmp_path / "skin.json")
    assert main(["deploy", str(tmp_path / "skin.json")]) == 2
    assert "give --port PORT" in capsys.readouterr().err
    assert main(["deploy", str(tmp_path / "skin.json"), "--port", str(tmp_path / "nope")]) == 1
    out = capsys.readouterr().out
    # the map's board gets its line, naming the port and why (issue 26: "1 other problems" and no board named)
    assert "board 0 'board0' uid 0x5c1a0000: missing [untouched]: not found; 1 of 1 ports gave no board: " in out
    assert "nope (link: " in out and "cannot open the serial port" in out and "other problems" not in out
    assert main(["deploy", str(tmp_path / "skin.json"), "--all", "--no-system-ports", "--glob", str(tmp_path / "x*")]) == 1
    out = capsys.readouterr().out
    assert "board 0 'board0' uid 0x5c1a0000: missing [untouched]: no serial port to probe" in out


def test_bench_serial_rows(capsys):
    assert main(["bench", "serial", "--json", "--taxels", "256", "--boards", "2", "--rate", "40",
                 "--repeat", "1", "--baud", "4000000"]) == 0
    rows = json.loads(capsys.readouterr().out)
    assert [r["verify"] for r in rows] == ["readback", "hash"]
    row, hashed = rows
    assert row["n_taxels"] == 256 and row["boards"] == 2
    # hash verify saves the read back: about half the bytes
    assert 0.4 < hashed["wire_bytes"] / row["wire_bytes"] < 0.6
    assert row["deploy_s"] > 0 and row["decode_x_wire"] > 0
    # 2 boards x 128 channels x 12 B, each way, plus framing: the wire time follows from the bytes
    assert row["wire_bytes"] > 2 * 2 * 128 * 12
    assert row["wire_s"] == pytest.approx(row["wire_bytes"] / 2 * 10 / 4e6, rel=0.05)


def test_bench_serial_fault_storm_rows(capsys):
    assert main(["bench", "serial", "--faults", "--json", "--rounds", "2", "--boards-per-round", "6",
                 "--kills", "2", "--early-interrupts", "3", "--seed", "3"]) == 0
    (row,) = json.loads(capsys.readouterr().out)
    assert row["board_deploys"] == 12 and row["emulator_kills"] >= 2
    assert sum(row[k] for k in ("updated", "unchanged", "refused", "failed", "cancelled", "missing",
                                "would-update")) == 12
    assert row["stream_runs"] == 1 and row["early_interrupts"] == 3
    for k in ("mixed_configs", "wrong_states", "tracebacks", "bad_exit_codes", "boards_without_report",
              "not_found_without_reason", "emulator_hangs", "updated_not_in_flash", "hashless_commits_accepted",
              "lying_config_len_accepted", "dry_run_writes", "hung_commands", "left_streaming", "link_lost_unnamed",
              "replays_counted_as_lost", "replays_unnamed", "foreign_accepted", "start_answer_lost_failed",
              "incompatible_streamed", "stream_tracebacks", "stream_bad_exit_codes", "early_interrupt_tracebacks",
              "early_interrupt_bad_exit"):
        assert row[k] == 0, k
    assert row["not_found"] == row["missing"] and 0 < row["emulator_kill_max_s"] < 5
