"""`skinsafe teleop-send FILE.csv --to [HOST:]PORT [--key KEY] [--rate 100] [--seconds S]`: a stand-in leader arm.

Plays a trajectory CSV (core/runtime/commands.py; its columns in the robot's joint order:
`examples/ur5_pan.csv` is the UR5's) forth and back as signed teleop datagrams (core/runtime/teleop.py) to
where `skinsafe run --command teleop:` listens, at `--rate` datagrams per second until `--seconds` or
SIGINT/SIGTERM. `--key` is the run's `--teleop-key` file; without one the datagrams are only accepted by a run
listening on loopback without a key. Exit 0 when it stopped, 2 bad input.
"""
from __future__ import annotations

import math
import signal
import sys
import threading

import numpy as np

from skinsafe.core.runtime.commands import CommandError, read_trajectory
from skinsafe.core.runtime.leader import stream
from skinsafe.core.runtime.teleop import NO_KEY, load_key


def add_arguments(p) -> None:
    p.add_argument("csv", help="trajectory CSV, its columns in the robot's joint order")
    p.add_argument("--to", required=True, metavar="[HOST:]PORT", help="where `skinsafe run --command teleop:` listens "
                   "(host default 127.0.0.1)")
    p.add_argument("--key", metavar="FILE", help="the run's --teleop-key file (`skinsafe teleop-key FILE` makes one)")
    p.add_argument("--rate", type=float, default=100.0, help="datagrams per second (default 100)")
    p.add_argument("--seconds", type=float, help="stop after this long (default: until SIGINT/SIGTERM)")


def run(args) -> int:
    host, _, port = args.to.rpartition(":")
    try:
        if not port.isdigit() or not 0 < int(port) < 65536:
            raise CommandError(f"--to {args.to}: give [HOST:]PORT, a port 1..65535")
        if not (math.isfinite(args.rate) and args.rate > 0):
            raise CommandError(f"--rate {args.rate}: give a positive number of datagrams per second")
        if args.seconds is not None and not (math.isfinite(args.seconds) and args.seconds > 0):
            raise CommandError(f"--seconds {args.seconds}: give a positive duration")
        key = load_key(args.key) if args.key else NO_KEY
        with open(args.csv) as f:
            lines = [ln for ln in f if ln.strip() and not ln.lstrip().startswith("#")]
        joints = [c.strip() for c in lines[0].split(",")[1:]] if lines else []
        inf = np.full(len(joints), np.inf)
        times, targets = read_trajectory(args.csv, joints, {"q_min": -inf, "q_max": inf, "qd_max": inf})
    except (OSError, UnicodeDecodeError) as e:
        print(f"skinsafe teleop-send: {args.csv}: cannot read it ({e})", file=sys.stderr)
        return 2
    except CommandError as e:
        print(f"skinsafe teleop-send: {e}", file=sys.stderr)
        return 2
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    if args.seconds is not None:
        timer = threading.Timer(args.seconds, stop.set)
        timer.daemon = True
        timer.start()
    where = f"{host or '127.0.0.1'}:{port}"
    print(f"skinsafe teleop-send: {len(joints)} joint targets to {where} at {args.rate:g} Hz, "
          f"{'signed with key id ' + key.key_id if key.secret else 'unsigned (loopback only)'}", file=sys.stderr)
    sent = stream((host or "127.0.0.1", int(port)), times, targets, stop, args.rate, key)
    print(f"skinsafe teleop-send: sent {sent} datagrams to {where}", file=sys.stderr)
    return 0
