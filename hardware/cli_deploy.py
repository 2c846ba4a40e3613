"""`skinsafe deploy skin.json --port PORT | --all`: push each board's part of the map, commit, read back, compare."""
from __future__ import annotations

import sys

from tqdm import tqdm

from skinsafe.core.skin.model import DesignError, SkinDesign
from skinsafe.core.skin.taxel_map import load
from skinsafe.hardware.board_config import board_configs
from skinsafe.hardware.deploy import BoardReport, candidate_ports, deploy, discover, plan


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
    p.add_argument("--retries", type=int, default=4, help="re-sends of a request on timeout or CRC error")


def add_arguments(p) -> None:
    add_port_arguments(p)
    p.add_argument("--board", help="with one --port: deploy this board (id or name) there, checked by uid")
    p.add_argument("--dry-run", action="store_true", help="only show what would change on each board")
    p.add_argument("--force", action="store_true", help="push even when a board already runs this config")
    p.add_argument("--verify", choices=["readback", "hash"], default="readback",
                   help="readback: read the config back and hash it here (default); hash: the board hashes its flash")


def find_ports(design: SkinDesign, args) -> tuple[dict[int, str], list[str], list[str]]:
    """Board id -> port for the boards found (matched by uid), problems (failures) and notes."""
    if not args.all and not args.port:
        raise DesignError("give --port PORT (repeatable) or --all to find the boards")
    if getattr(args, "board", None):
        if len(args.port) != 1 or args.all:
            raise DesignError("--board needs exactly one --port and no --all")
        b = next((b for b in design.boards if args.board in (str(b.id), b.name)), None)
        if b is None:
            raise DesignError(f"--board {args.board!r} is not a board of the map; "
                              f"use one of {[b.name for b in design.boards]}")
        return {b.id: args.port[0]}, [], []
    candidates = candidate_ports(args.glob, not args.no_system_ports) if args.all else args.port
    found = discover(candidates, timeout=args.timeout, baud=args.baud)
    p = plan(design, found)
    strangers = [f"{port}: board uid {uid:#x} is not in the map; it was left alone" for uid, port in p.strangers.items()]
    if args.all:  # other boards on the bus are fine; a board of the map that is not there is not
        return p.ports, [f"board {b.id} '{b.name}' uid {b.uid:#x}: not found on any port" for b in p.missing], strangers
    answered = {port for port, _ in found.values()}
    problems = [f"{port}: no board answered" for port in args.port if port not in answered]
    return p.ports, problems + strangers, []  # a port given by hand holding a stranger is a mistake


def run(args) -> int:
    try:
        design = load(args.map)
        configs = board_configs(design)
        ports, problems, notes = find_ports(design, args)
    except DesignError as e:
        print(f"skinsafe deploy: {e}", file=sys.stderr)
        return 2
    bar = tqdm(total=len(ports), desc="deploy", unit="board", file=sys.stderr, disable=None)

    def done(rep: BoardReport) -> None:
        bar.update(1)

    reports = deploy(design, ports, args.dry_run, args.force, configs, on_done=done, verify=args.verify,
                     baud=args.baud, timeout=args.timeout, retries=args.retries)
    bar.close()
    for rep in reports:
        print(rep.line())
    for msg in notes:
        print(f"note: {msg}")
    for msg in problems:
        print(f"problem: {msg}")
    failed = [r for r in reports if not r.ok]
    verb = "would deploy" if args.dry_run else "deployed"
    print(f"{verb} {len(reports) - len(failed)} of {len(design.boards)} boards; "
          f"{len(failed)} failed, {len(problems)} other problems")
    return 1 if failed or problems else 0
