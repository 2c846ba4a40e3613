"""`skinsafe bench serial --faults`, the streaming half: the real `skinsafe stream` against boards with the faults
a safety runtime must survive, and Ctrl-C while the command starts.

Each round starts one emulator process of 4 boards that stream 32 channels at 200 Hz for 1 s. In a
stream round every board draws one fault of STREAM_FAULTS (replayed older frames, frames of another
uid, both, every stream-start answer lost, the cable pulled after 100 frames, or none); in a refusal round
one board is already streaming (another host left it so) or runs firmware 2.0.0. A quarter of the
rounds get Ctrl-C at a random moment of the stream. Then each board is asked whether it still
streams, and each board's last line is read:

- left_streaming: boards still streaming after the command ended (the one left streaming by an
  earlier host, and a pulled cable, excepted);
- link_lost_unnamed: pulled cables whose board line does not say "link lost" (a board stopped before its
  100th frame, by Ctrl-C or another board's pulled cable, had not lost it yet);
- replays_counted_as_lost: boards replaying old frames on an otherwise clean link whose line counts
  frames lost; replays_unnamed: their lines (of boards that sent SURE frames) not naming the replayed
  frames dropped;
- foreign_accepted: boards whose link carried another uid's frames (SURE frames or more) with no line
  refusing them;
- start_answer_lost_failed: rounds a board whose start answers were lost (it did start) made fail;
- incompatible_streamed: refusal rounds that did not end with exit 1 naming the board and why;
- stream_tracebacks, stream_bad_exit_codes, hung_commands (runs killed after HANG_S).

`early_interrupts` runs of `skinsafe stream` get SIGINT at times spread over its first 0.4 s:
early_interrupt_tracebacks counts tracebacks through skinsafe's own source, early_interrupt_bad_exit
exit codes other than 130 (or the signal's, before Python installs its handler) among the others,
and early_interrupt_in_python_startup the interrupts that landed before skinsafe's first line ran
(Python's interpreter start, its site packages, finding the package): Python prints those itself.
"""
from __future__ import annotations

import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from skinsafe.core.skin.taxel_map import save
from skinsafe.core.system import SKINSAFE
from skinsafe.hardware import protocol as P
from skinsafe.hardware.board_config import board_configs
from skinsafe.hardware.client import BoardClient, BoardError
from skinsafe.hardware.emulator import EmulatorProcess, flash_path
from skinsafe.hardware.flat_design import flat_design

SOURCE = [Path(P.__file__).resolve().parents[1] / d for d in ("core", "hardware", "exporters", "addon")]
STREAM_FAULTS = ["", "old_frames=0.1", "foreign_frames=0.1", "lost_start_answers=10", "unplug_after=100",
                 "old_frames=0.1,foreign_frames=0.1"]
SURE = 100  # frames after which a board with a 10% fault has shown it (but for 0.9^100 = 3e-5)
REFUSALS = ["streaming=100", "firmware=2.0.0"]
KEYS = ["stream_runs", "stream_interrupted", "left_streaming", "link_lost_unnamed", "replays_counted_as_lost",
        "replays_unnamed", "foreign_accepted", "start_answer_lost_failed", "incompatible_streamed",
        "stream_tracebacks", "stream_bad_exit_codes", "hung_commands", "early_interrupts",
        "early_interrupt_tracebacks", "early_interrupt_bad_exit", "early_interrupt_in_python_startup"]
HANG_S = 60.0  # a command still running after this long is killed and counted as hung
BOARDS, RATE, SECONDS = 4, 200, 1.0
LINE = re.compile(r"board (\d+) '[^']*' uid \S+ on \S+: (.*?); received (\d+), lost (\d+), corrupt (\d+)")


def traceback_kind(text: str) -> str | None:
    """"ours": a traceback through skinsafe's source; "python": one before skinsafe's first line ran
    (Python's own start-up, its site packages, finding the package); None: no traceback."""
    if "Traceback" not in text:
        return None
    return "ours" if any(f'File "{d}/' in text for d in SOURCE) else "python"


def run(cmd: list[str], counts: dict, interrupt_after: float | None = None,
        after_line: str | None = None) -> tuple[int, str, str]:
    """Run a command (SIGINT `interrupt_after` s after it printed `after_line` on stderr, or after it started);
    a run still going after HANG_S is killed and counted in hung_commands."""
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    head = ""
    if interrupt_after is not None:
        while after_line is not None and after_line not in head:
            line = proc.stderr.readline()
            if not line:
                break
            head += line
        time.sleep(interrupt_after)
        proc.send_signal(signal.SIGINT)
    out, err = finish(proc, counts)
    return proc.returncode, out, head + err


def finish(proc: subprocess.Popen, counts: dict) -> tuple[str, str]:
    """Wait for a command's output; one still running after HANG_S is killed and counted in hung_commands."""
    try:
        return proc.communicate(timeout=HANG_S)
    except subprocess.TimeoutExpired:
        proc.kill()
        counts["hung_commands"] += 1
        return proc.communicate()


def stream_round(k: int, rng: np.random.Generator, tmp: Path, counts: dict) -> None:
    before = {key: counts[key] for key in KEYS[2:12]}
    design = flat_design(32 * BOARDS, BOARDS)
    save(design, tmp / "skin.json")
    for cfg in board_configs(design):  # every board runs the map, as after a deploy (firmware 2 included)
        flash_path(tmp / "flash", cfg.uid).parent.mkdir(exist_ok=True)
        flash_path(tmp / "flash", cfg.uid).write_bytes(cfg.to_bytes())
    refusal = rng.random() < 0.25
    faults = [str(rng.choice(STREAM_FAULTS)) for _ in design.boards]
    if refusal:
        faults = [""] * BOARDS
        faults[int(rng.integers(BOARDS))] = str(rng.choice(REFUSALS))
    interrupt = rng.uniform(0.0, SECONDS) if rng.random() < 0.25 else None
    links = tmp / "links"
    with EmulatorProcess([(b.uid, 32, f) for b, f in zip(design.boards, faults)], tmp / "flash", "--link-dir",
                         str(links), "--seed", str(k)) as em:
        code, out, err = run([SKINSAFE, "stream", str(tmp / "skin.json"), "--all", "--no-system-ports", "--glob",
                              str(links / "board-*"), "--rate", str(RATE), "--seconds", str(SECONDS), "--timeout",
                              "0.1", "--retries", "2"], counts, interrupt, "streaming at")
        still = {}
        for b, f in zip(design.boards, faults):
            if "unplug" not in f and "streaming" not in f:
                try:
                    with BoardClient(em.ports[b.uid], timeout=0.2) as c:
                        still[b.id] = bool(c.identify().flags & P.FLAG_STREAMING)
                except BoardError:
                    still[b.id] = True  # it does not answer: its state is not known to be safe
    counts["stream_runs"] += 1
    counts["stream_interrupted"] += interrupt is not None
    counts["left_streaming"] += sum(still.values())
    counts["stream_tracebacks"] += traceback_kind(out + err) is not None
    lines = {int(m[1]): m for m in map(LINE.match, out.splitlines()) if m}
    unplugged = any("unplug" in f for f in faults)
    allowed = {1} if refusal else ({0, 1} if unplugged else {0})
    if interrupt is not None:
        allowed = allowed | {130, -signal.SIGINT} - {0}  # (the stream may have ended by itself: a pulled cable)
    counts["stream_bad_exit_codes"] += code not in allowed
    for b, f in zip(design.boards, faults):
        m, text = lines.get(b.id), next((x for x in out.splitlines() if x.startswith(f"board {b.id} '")), "")
        if "unplug" in f:  # (a stream stopped before its 100th frame ended before the cable was pulled)
            counts["link_lost_unnamed"] += m is None or "link lost" not in m[2] and int(m[3]) >= 100
        if "old_frames" in f:
            counts["replays_counted_as_lost"] += m is not None and int(m[4]) > 0
            counts["replays_unnamed"] += m is not None and int(m[3]) >= SURE and "replayed" not in text
        if "foreign_frames" in f:
            counts["foreign_accepted"] += m is not None and int(m[3]) >= SURE and "frames from uid" not in text
        if "lost_start_answers" in f:
            counts["start_answer_lost_failed"] += m is None or m[2] != "stopped" and "stream-start" in err
        if f in REFUSALS:
            why = "already streaming" if "streaming" in f else "firmware 2.0.0 is not supported"
            named = any(f"board '{b.name}'" in x and why in x for x in err.splitlines())
            counts["incompatible_streamed"] += not (code == 1 and named)
    wrong = [key for key, v in before.items() if counts[key] != v]
    if wrong:  # keep the evidence of anything that went wrong
        print(f"stream round {k}: {', '.join(wrong)}; exit {code}, interrupt {interrupt}, faults {faults}\n{out}\n{err}",
              file=sys.stderr)


def early_interrupts(n: int, rng: np.random.Generator, tmp: Path, counts: dict) -> None:
    """`skinsafe stream` with SIGINT at times spread evenly over its first 0.4 s (imports, discovery, start)."""
    design = flat_design(64, 2)
    save(design, tmp / "skin.json")
    for cfg in board_configs(design):
        flash_path(tmp / "flash", cfg.uid).parent.mkdir(exist_ok=True)
        flash_path(tmp / "flash", cfg.uid).write_bytes(cfg.to_bytes())
    with EmulatorProcess([(b.uid, 32) for b in design.boards], tmp / "flash", "--link-dir", str(tmp / "links")):
        for k in range(n):
            code, out, err = run([SKINSAFE, "stream", str(tmp / "skin.json"), "--all", "--no-system-ports", "--glob",
                                  str(tmp / "links" / "board-*"), "--seconds", "2"], counts,
                                 (k + rng.random()) * 0.4 / n)
            kind = traceback_kind(out + err)
            counts["early_interrupts"] += 1
            counts["early_interrupt_tracebacks"] += kind == "ours"
            counts["early_interrupt_in_python_startup"] += kind == "python"
            counts["early_interrupt_bad_exit"] += kind is None and code not in (130, -signal.SIGINT)
            if kind == "ours" or kind is None and code not in (130, -signal.SIGINT):
                print(f"early interrupt {k}: exit {code}\n{out}\n{err}", file=sys.stderr)
