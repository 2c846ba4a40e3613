"""`skinsafe deploy skin.json --port PORT | --all`: push each board's part of the map, commit, read back, compare.

Ends with one line per board of the map (status and state: untouched, committed, rolled back or
unknown) and a summary, never a traceback. Exit codes (EXIT_CODES): 0 every board runs the map;
1 a board failed, was refused or not found; 2 bad input (map, options); 130 Ctrl-C; 143 SIGTERM.
"""
from __future__ import annotations

import math
import sys

from tqdm import tqdm

from skinsafe.core.skin.model import DesignError, SkinDesign
from skinsafe.core.skin.taxel_map import load
from skinsafe.hardware.board_config import board_configs
from skinsafe.hardware.client import baud_problem
from skinsafe.hardware.deploy import BoardReport, candidate_ports, deploy, discover, missing_reports, plan
from skinsafe.hardware.interrupt import Interrupt, for_command

EXIT_CODES = {0: "every board runs the map", 1: "a board failed, was refused or was not found",
              2: "bad input (map file, options)", 130: "interrupted by Ctrl-C (SIGINT)",
              143: "interrupted by SIGTERM"}
MAX_RETRIES = 20


def add_port_arguments(p) -> None:
    p.add_argument("map", help="taxel map (JSON) to deploy")
    p.add_argument("--port", action="append", default=[], help="serial port of a board; repeatable")
    p.add_argument("--all", action="store_true",
                   help="find the boards on every serial port (serial.tools.list_ports plus --glob) by unique id")
    p.add_argument("--glob", action="append", default=[], metavar="PATTERN",
                   help="more ports to probe with --all, e.g. an emulator's --link-dir: '/tmp/boards/board-*'")
    p.add_argument("--no-system-ports", action="store_true", help="with --all, probe only the --glob ports")
    p.add_argument("--baud", type=int, default=1_000_000, help="link speed (default 1000000)")
    p.add_argument("--timeout", type=float, default=0.25, help="seconds to wait for an answer, on top of wire time")
    p.add_argument("--retries", type=int, default=4,
                   help=f"re-sends of a request on timeout or CRC error, 0..{MAX_RETRIES} (discovery too)")
    p.epilog = "exit codes: " + "; ".join(f"{k} {v}" for k, v in EXIT_CODES.items())


def add_arguments(p) -> None:
    add_port_arguments(p)
    p.add_argument("--board", help="with one --port: deploy this board (id or name) there, checked by uid")
    p.add_argument("--dry-run", action="store_true", help="only show what would change on each board")
    p.add_argument("--force", action="store_true", help="push even when a board already runs this config")
    p.add_argument("--verify", choices=["readback", "hash"], default="readback",
                   help="readback: read the config back and hash it here (default); hash: the board hashes its flash")


def check_link_options(args) -> None:
    """Options checked before any I/O (DesignError: exit 2 with the message)."""
    if not 0 <= args.retries <= MAX_RETRIES:
        raise DesignError(f"--retries {args.retries}: give 0..{MAX_RETRIES}")
    if not (math.isfinite(args.timeout) and 0 < args.timeout <= 60):
        raise DesignError(f"--timeout {args.timeout}: give seconds in (0, 60]")
    if baud_problem(args.baud):
        raise DesignError(baud_problem(args.baud))


def find_ports(design: SkinDesign, args, cancel=None
               ) -> tuple[dict[int, str], list[BoardReport], list[str], list[str]]:
    """Board id -> port for the boards found (matched by uid), reports of the map's boards not found (each with
    the reason), notes (--all: ports skipped, boards not in the map) and problems (--port: given ports holding a
    board not in the map, or no board while every board of the map was found)."""
    if not args.all and not args.port:
        raise DesignError("give --port PORT (repeatable) or --all to find the boards")
    if getattr(args, "board", None):
        if len(args.port) != 1 or args.all:
            raise DesignError("--board needs exactly one --port and no --all")
        b = next((b for b in design.boards if args.board in (str(b.id), b.name)), None)
        if b is None:
            raise DesignError(f"--board {args.board!r} is not a board of the map; "
                              f"use one of {[b.name for b in design.boards]}")
        return {b.id: args.port[0]}, [], [], []
    candidates = candidate_ports(args.glob, not args.no_system_ports) if args.all else args.port
    found = discover(candidates, timeout=args.timeout, retries=args.retries, baud=args.baud, cancel=cancel)
    p = plan(design, found)
    strangers = [f"{port}: board uid {uid:#x} is not in the map; it was left alone" for uid, port in p.strangers.items()]
    skipped = [f"{port}: no board ({why})" for port, why in sorted(found.skipped.items())]
    missing = missing_reports(design, p)  # each names the ports that gave no board, and why
    if args.all:  # other devices on the bus are fine; a board of the map that is not there is not
        return p.ports, missing, strangers + skipped, []
    # a port given by hand without a board of the map is a mistake: named in the missing boards' lines, or
    # on its own line when every board was found elsewhere
    return p.ports, missing, [], strangers + ([] if missing else skipped)


def run(args) -> int:
    with for_command() as stop:
        try:
            check_link_options(args)
            design = load(args.map)
            configs = board_configs(design)
            ports, missing, notes, problems = find_ports(design, args, stop)
        except DesignError as e:
            print(f"skinsafe deploy: {e}", file=sys.stderr)
            return 2
        print(f"skinsafe deploy: {len(ports)} of {len(design.boards)} boards found; "
              f"{'checking' if args.dry_run else 'deploying'} (Ctrl-C stops cleanly)", file=sys.stderr, flush=True)
        bar = tqdm(total=len(ports), desc="deploy", unit="board", file=sys.stderr, disable=None)
        reports = [] if stop.requested else deploy(
            design, ports, args.dry_run, args.force, configs, on_done=lambda _: bar.update(1), verify=args.verify,
            cancel=stop, baud=args.baud, timeout=args.timeout, retries=args.retries)
        bar.close()
        if stop.requested:  # boards the interrupt kept us from reaching
            done = {r.board.id for r in reports + missing}
            reports += [BoardReport(b, ports.get(b.id), "cancelled", f"interrupted by {stop.name} before it was "
                                    "reached", new_hash=c.sha256, kind="cancelled")
                        for b, c in zip(design.boards, configs) if b.id not in done]
        reports = sorted(reports + missing, key=lambda r: r.board.id)
        return report(design, reports, notes, problems, args.dry_run, stop)


def report(design, reports: list[BoardReport], notes: list[str], problems: list[str], dry_run: bool,
           stop: Interrupt) -> int:
    """Print one line per board, the notes, problems and a summary; the exit code."""
    for rep in reports:
        print(rep.line())
    for msg in notes:
        print(f"note: {msg}")
    for msg in problems:
        print(f"problem: {msg}")
    failed = [r for r in reports if not r.ok]
    states = {s: sum(r.state == s for r in reports) for s in ("untouched", "committed", "rolled back", "unknown")}
    verb = "would deploy" if dry_run else "deployed"
    states = ", ".join(f"{k} {v}" for k, v in states.items() if v)
    print(f"{verb} {len(reports) - len(failed)} of {len(design.boards)} boards; {len(failed)} failed or not found"
          + (f", {len(problems)} port problems (the 'problem:' lines)" if problems else "")
          + (f"; boards {states}" if states else "")
          + (f"; interrupted by {stop.name}" if stop.requested else ""), flush=True)
    if stop.requested:
        return stop.exit_code
    return 1 if failed or problems else 0
