"""`skinsafe bench serial --faults`: a fault storm through the real `skinsafe deploy` and `skinsafe stream` CLIs.

Each deploy round starts one emulator process whose boards each draw one fault of FAULTS (byte loss,
bit flips, late answers, resets mid-transfer, truncated answers, another firmware or protocol
version, the smallest chunk size, a commit answer without its hash, a flash write lost under the RAM
copy, a config length larger than the board can hold), plus a device that is not a board and
sometimes a second process with a duplicate uid; boards start fresh or with an old config.
`skinsafe deploy --all` (in a fifth of the rounds `--dry-run`) runs as a subprocess; some rounds get
Ctrl-C, some lose their emulator (SIGTERM) at a random moment. Then every board's flash is checked
against its report: mixed_configs counts flashes holding neither the old nor the new config,
wrong_states reports whose state contradicts the flash (boards whose flash write was lost excepted:
they run what their flash does not hold), not_found_without_reason "missing" lines that do not name
the board's port and why it was skipped, updated_not_in_flash boards reported updated (verified)
whose flash does not hold the new config, hashless_commits_accepted boards reported updated whose
commit answer had no hash, lying_config_len_accepted boards reporting an impossible config length
that were not refused for it, dry_run_writes flashes a dry run changed, hung_commands runs killed
after 60 s. A second loop signals `emulator_kills` emulators (SIGTERM and SIGINT alternately,
boards streaming or in a delay) and times how long each took to end. The stream storm and the early
Ctrl-C loop are in core/bench/stream_faults.py.
"""
from __future__ import annotations

import hashlib
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from skinsafe.core.bench import stream_faults as streams
from skinsafe.core.skin.taxel_map import save
from skinsafe.core.system import SKINSAFE
from skinsafe.hardware.board_config import board_configs
from skinsafe.hardware.client import BoardClient, BoardError
from skinsafe.hardware.emulator import EmulatorProcess, flash_path
from skinsafe.hardware.flat_design import flat_design

FAULTS = ["drop=0.002", "flip=0.002", "delay=0.3,delay_p=0.3", "reset_at_chunk=2", "reset_at_chunk=2,resets=-1",
          "malformed=0.05", "firmware=2.0.0", "protocol=2", "max_chunk=16", "drop=0.01", "hashless_commit=1",
          "flash_write_lost=1", "config_len=4294967295"]
ANOMALIES = ("mixed_configs", "wrong_states", "tracebacks", "bad_exit_codes", "boards_without_report",
             "not_found_without_reason", "updated_not_in_flash", "hashless_commits_accepted",
             "lying_config_len_accepted", "dry_run_writes", "hung_commands")


def add_arguments(p) -> None:
    p.add_argument("--faults", action="store_true", help="run the fault storm instead of the speed benchmark")
    p.add_argument("--rounds", type=int, default=100,
                   help="fault storm: deploy rounds (and a quarter as many stream rounds); --rounds 8 for a quick run")
    p.add_argument("--boards-per-round", type=int, default=10, help="fault storm: boards of the map per round")
    p.add_argument("--kills", type=int, default=None,
                   help="fault storm: emulators stopped by a signal and timed (default: 2 per deploy round)")
    p.add_argument("--early-interrupts", type=int, default=None,
                   help="fault storm: `skinsafe stream` runs sent Ctrl-C within their first 0.4 s (default: 2 per "
                        "5 deploy rounds)")
    p.add_argument("--seed", type=int, default=0)


def storm_round(k: int, n_boards: int, rng: np.random.Generator, tmp: Path, counts: dict) -> None:
    old, new = flat_design(32 * n_boards, n_boards, 3.0), flat_design(32 * n_boards, n_boards, 6.0)
    save(new, tmp / "skin.json")
    olds, news = {c.uid: c.sha256 for c in board_configs(old)}, {c.uid: c.sha256 for c in board_configs(new)}
    flash = tmp / "flash"
    flash.mkdir()
    initial = {}
    for cfg in board_configs(old):
        initial[cfg.uid] = cfg.sha256 if rng.random() < 0.7 else None  # the others are fresh boards
        if initial[cfg.uid]:
            flash_path(flash, cfg.uid).write_bytes(cfg.to_bytes())
    faults = [str(rng.choice(FAULTS)) for _ in new.boards]
    specs = [(b.uid, 32, f if "max_chunk" in f else ",".join(filter(None, [f, "max_chunk=64"])))  # 7 chunks each
             for b, f in zip(new.boards, faults)]
    links = tmp / "links"
    dup = rng.random() < 0.2
    interrupt, kill = rng.random() < 0.25, rng.random() < 0.15
    kill = kill and not interrupt
    dry = rng.random() < 0.2
    with EmulatorProcess(specs, flash, "--link-dir", str(links), "--not-a-board", "1", "--seed", str(k)) as em, \
            EmulatorProcess([(new.boards[0].uid, 32)] if dup else [], tmp / "dup",
                            *([] if dup else ["--board", "0x99:8"]), "--link-dir", str(links / "dup")):
        cmd = [SKINSAFE, "deploy", str(tmp / "skin.json"), "--all", "--no-system-ports", "--glob",
               str(links / "board-*"), "--glob", str(links / "dup" / "board-*"), "--timeout", "0.1", "--retries", "3",
               *(["--dry-run"] if dry else [])]
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        if interrupt or kill:
            proc.stderr.readline()
            time.sleep(rng.uniform(0, 0.5))
            if interrupt:
                proc.send_signal(signal.SIGINT)
            else:
                counts["emulator_kill_max_s"] = max(counts["emulator_kill_max_s"], em.signal(signal.SIGTERM))
                counts["emulator_kills"] += 1
        out, err = streams.finish(proc, counts)
    before = {key: counts.get(key, 0) for key in ANOMALIES}
    counts["tracebacks"] += ("Traceback" in out + err)
    counts["interrupted_deploys"] += interrupt
    counts["dry_runs"] += dry
    counts["interrupt_exit_130"] += interrupt and proc.returncode == 130
    # -SIGINT: the signal came after the report, while Python shut down (its handlers are reset to the
    # default then); the shell shows 130 as for an exit code of 130
    late = proc.returncode == -signal.SIGINT and out.rstrip()[-200:].rsplit("\n", 1)[-1].startswith(("deployed", "would"))
    counts["bad_exit_codes"] += proc.returncode not in ((130, 0, 1) if interrupt else (0, 1)) and not late
    for b, f in zip(new.boards, faults):
        counts["board_deploys"] += 1
        line = next((x for x in out.splitlines() if x.startswith(f"board {b.id} '")), None)
        if line is None:
            counts["lying_config_len_accepted"] += "config_len" in f  # (a run that read on until killed)
            counts["boards_without_report"] += 1
            continue
        status, state = line.split(": ", 1)[1].split(" [")[0], line.split("[")[1].split("]")[0]
        counts[status] = counts.get(status, 0) + 1
        dup_port = f"{links / 'dup'}/" in line  # deployed to the duplicate (its twin never answered): its flash
        path = flash_path(tmp / "dup" if dup_port else flash, b.uid)
        running = hashlib.sha256(path.read_bytes()).digest() if path.exists() else None
        counts["mixed_configs"] += running not in (olds[b.uid], news[b.uid], None)
        first = None if dup_port else initial[b.uid]
        want = {"committed": news[b.uid], "untouched": first, "rolled back": first}
        counts["wrong_states"] += state in want and running != want[state] and "flash_write_lost" not in f
        counts["updated_not_in_flash"] += status == "updated" and running != news[b.uid]
        counts["hashless_commits_accepted"] += status == "updated" and "hashless" in f
        counts["dry_run_writes"] += dry and running != first
        # a length no board of its channels holds: the board is refused for it (or deployed to neither as a
        # duplicate), never deployed to or read from
        counts["lying_config_len_accepted"] += "config_len" in f and not dup_port and status in (
            "updated", "unchanged", "would-update")
        if status == "missing":
            counts["not_found"] += 1
            port = f"board-{b.uid:016x}"
            counts["not_found_without_reason"] += not (f"{port} (" in line or f"uid {b.uid:#x} answers on" in line)
    if any(counts.get(key, 0) != v for key, v in before.items()):  # keep the evidence of anything that went wrong
        print(f"round {k}: exit {proc.returncode}, interrupt {interrupt}, kill {kill}, dry run {dry}, faults {specs}"
              f"\n{out}\n{err}", file=sys.stderr)


def kill_loop(n: int, tmp: Path, counts: dict) -> None:
    """Start an emulator (a board streaming at 2 kHz, one answering late), signal it, time its end."""
    times = []
    for k in tqdm(range(n), desc="emulator kills", file=sys.stderr, disable=None):
        with EmulatorProcess([(0x10, 64), (0x20, 64, "delay=0.3")], tmp) as em:
            try:
                with BoardClient(em.ports[0x10]) as c:
                    c.identify()
                    c.start_stream(2000)
            except BoardError:
                pass
            times.append(em.signal(signal.SIGTERM if k % 2 else signal.SIGINT))
    counts["emulator_kills"] += n
    counts["emulator_kill_median_s"] = float(np.median(times)) if times else 0.0
    counts["emulator_kill_max_s"] = max([counts["emulator_kill_max_s"], *times])
    counts["emulator_hangs"] = sum(t > 1.0 for t in times)


def rows(args) -> list[dict]:
    rng = np.random.default_rng(args.seed)
    keys = ["board_deploys", "updated", "unchanged", "refused", "failed", "cancelled", "missing", "would-update",
            "mixed_configs", "wrong_states", "tracebacks", "bad_exit_codes", "boards_without_report", "not_found",
            "not_found_without_reason", "interrupted_deploys", "interrupt_exit_130", "dry_runs", *ANOMALIES[6:10],
            "emulator_kills", "emulator_kill_median_s", "emulator_kill_max_s", "emulator_hangs"]
    counts = dict.fromkeys(keys + streams.KEYS, 0)
    counts["emulator_kill_max_s"] = 0.0
    t0 = time.monotonic()
    for k in tqdm(range(args.rounds), desc="deploy storm", file=sys.stderr, disable=None):
        with tempfile.TemporaryDirectory() as tmp:
            storm_round(k, args.boards_per_round, rng, Path(tmp), counts)
    for k in tqdm(range(max(1, args.rounds // 4)), desc="stream storm", file=sys.stderr, disable=None):
        with tempfile.TemporaryDirectory() as tmp:
            streams.stream_round(k, rng, Path(tmp), counts)
    with tempfile.TemporaryDirectory() as tmp:
        early = max(1, args.rounds * 2 // 5) if args.early_interrupts is None else args.early_interrupts
        streams.early_interrupts(early, rng, Path(tmp), counts)
    with tempfile.TemporaryDirectory() as tmp:
        kill_loop(2 * args.rounds if args.kills is None else args.kills, Path(tmp), counts)
    return [{"rounds": args.rounds, **{k: counts[k] for k in keys + streams.KEYS}, "seconds": time.monotonic() - t0}]
