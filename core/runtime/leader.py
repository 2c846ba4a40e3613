"""A stand-in leader arm: streams `teleop:PORT` datagrams that play a trajectory CSV forth and back.

    python -m skinsafe.core.runtime.leader FILE.csv --to [HOST:]PORT [--rate 100] [--seconds S]

The CSV is a trajectory file (core/runtime/commands.py) whose columns are in the robot's joint order
(`examples/ur5_pan.csv` is the UR5's); the targets are its positions interpolated at the host's clock,
played forward to the end, then backward, and again, at `--rate` datagrams per second until
`--seconds` or SIGINT/SIGTERM. What a real leader arm (the paper's teleoperation) would send.
"""
from __future__ import annotations

import argparse
import signal
import socket
import sys
import threading
import time

import numpy as np

from skinsafe.core.runtime.commands import CommandError, read_trajectory, teleop_datagram


def stream(address: tuple[str, int], times: np.ndarray, targets: np.ndarray, stop: threading.Event,
           rate: float = 100.0) -> int:
    """Send `targets` (T, n) at `times` (T,) forth and back to `address` until `stop`; the datagrams sent."""
    period, span, k = 1.0 / rate, float(times[-1]), 0
    t0 = time.monotonic()
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as out:
        while not stop.is_set():
            s = (time.monotonic() - t0) % (2 * span) if span > 0 else 0.0
            s = s if s <= span else 2 * span - s
            out.sendto(teleop_datagram(k, [np.interp(s, times, q) for q in targets.T]), address)
            k += 1
            stop.wait(period)
    return k


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m skinsafe.core.runtime.leader", description=__doc__.split("\n")[0])
    p.add_argument("csv", help="trajectory CSV, its columns in the robot's joint order")
    p.add_argument("--to", required=True, metavar="[HOST:]PORT", help="where `skinsafe run --command teleop:` listens")
    p.add_argument("--rate", type=float, default=100.0, help="datagrams per second (default 100)")
    p.add_argument("--seconds", type=float, help="stop after this long (default: until SIGINT/SIGTERM)")
    args = p.parse_args(argv)
    host, _, port = args.to.rpartition(":")
    if not port.isdigit() or not 0 < int(port) < 65536 or not args.rate > 0:
        p.error(f"--to {args.to} --rate {args.rate}: give [HOST:]PORT (a port 1..65535) and a positive rate")
    try:
        with open(args.csv) as f:
            lines = [ln for ln in f if ln.strip() and not ln.lstrip().startswith("#")]
        joints = [c.strip() for c in lines[0].split(",")[1:]] if lines else []
        inf = np.full(len(joints), np.inf)
        times, targets = read_trajectory(args.csv, joints, {"q_min": -inf, "q_max": inf, "qd_max": inf})
    except (OSError, UnicodeDecodeError, CommandError) as e:
        p.error(str(e))
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    if args.seconds is not None:
        threading.Timer(args.seconds, stop.set).start()
    sent = stream((host or "127.0.0.1", int(port)), times, targets, stop, args.rate)
    print(f"leader: sent {sent} datagrams of {len(joints)} joint targets to {host or '127.0.0.1'}:{port}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
