"""`skinsafe stream skin.json --port PORT | --all`: readings mapped to taxels, danger events, lost/corrupt counts."""
from __future__ import annotations

import sys
import time

import numpy as np

from skinsafe.core.safety.events import danger_events
from skinsafe.core.skin.model import DesignError
from skinsafe.core.skin.taxel_map import load
from skinsafe.hardware.cli_deploy import add_port_arguments, find_ports
from skinsafe.hardware.client import BoardError
from skinsafe.hardware.stream import SkinStream, StreamUpdate


def add_arguments(p) -> None:
    add_port_arguments(p)
    p.add_argument("--rate", type=int, default=100, help="frames per second per board")
    p.add_argument("--seconds", type=float, default=None, help="stop after this long (default: until Ctrl-C)")
    p.add_argument("--no-verify", action="store_true", help="stream even if a board runs another config")


class DangerPrinter:
    """Prints taxels entering danger (core.events.danger_events on each poll's peak) and a status line per second."""

    def __init__(self, design, out=sys.stdout):
        self.ids, self.thresholds, self.out = design.taxels.ids, design.taxels.thresholds, out
        self.active = np.zeros(design.n_taxels, bool)
        self.t0 = self.last = time.monotonic()
        self.events = 0

    def __call__(self, u: StreamUpdate) -> None:
        d = danger_events({"force": u.peak}, {"force": self.thresholds["force"]})
        new = d & ~self.active
        self.active = d | (self.active & np.isnan(u.peak))  # taxels without a new frame keep their state
        if new.any():
            self.events += int(new.sum())
            ids = self.ids[new]
            print(f"{u.t - self.t0:8.3f} s  DANGER {len(ids)} taxels {ids[:8].tolist()}"
                  f"{' ...' if len(ids) > 8 else ''} (max {np.nanmax(u.peak[new]):.1f} N)", file=self.out)
        if u.t - self.last >= 1.0:
            self.last = u.t
            print(f"{u.t - self.t0:8.3f} s  frames {sum(v[0] for v in u.per_board.values())}  lost {u.lost}  "
                  f"corrupt {u.corrupt}  in danger {int(self.active.sum())}", file=self.out, flush=True)


def run(args) -> int:
    try:
        design = load(args.map)
        ports, problems, notes = find_ports(design, args)
    except DesignError as e:
        print(f"skinsafe stream: {e}", file=sys.stderr)
        return 2
    for msg in notes + problems:
        print(f"{'note' if msg in notes else 'problem'}: {msg}", file=sys.stderr)
    if not ports:
        print("skinsafe stream: no board of the map was found", file=sys.stderr)
        return 1
    printer = DangerPrinter(design)
    try:
        with SkinStream(design, ports, args.rate, verify=not args.no_verify,
                        baud=args.baud, timeout=args.timeout, retries=args.retries) as stream:
            stream.run(printer, args.seconds)
            u = stream.poll(0.0)
    except BoardError as e:
        print(f"skinsafe stream: {e}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 0
    print(f"done: {sum(v[0] for v in u.per_board.values())} frames, {u.lost} lost, {u.corrupt} corrupt, "
          f"{printer.events} danger events")
    return 0
