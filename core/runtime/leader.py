"""A stand-in leader arm: plays a trajectory forth and back as signed teleop datagrams (core/runtime/teleop.py).

`skinsafe teleop-send FILE.csv --to [HOST:]PORT --key KEY` is the command (core/app/teleop_send.py); this is
its loop, also what the tests and the fault bench lead with. The targets are the trajectory's positions
interpolated at the host's clock, played forward to the end, then backward, and again, at `rate` datagrams
per second, each stamped with the wall clock (`Stamper`) and signed with the key. What a real leader arm (the
paper's teleoperation) would send.
"""
from __future__ import annotations

import socket
import threading
import time

import numpy as np

from skinsafe.core.runtime.teleop import NO_KEY, Stamper, TeleopKey, datagram


def stream(address: tuple[str, int], times: np.ndarray, targets: np.ndarray, stop: threading.Event,
           rate: float = 100.0, key: TeleopKey = NO_KEY, sock: socket.socket | None = None) -> int:
    """Send `targets` (T, n) at `times` (T,) forth and back to `address` until `stop`, signed with `key`, from
    `sock` (default: a fresh UDP socket, closed at the end); the datagrams sent."""
    period, span, k = 1.0 / rate, float(times[-1]), 0
    stamp = Stamper()
    t0 = time.monotonic()
    out = sock or socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        while not stop.is_set():
            s = (time.monotonic() - t0) % (2 * span) if span > 0 else 0.0
            s = s if s <= span else 2 * span - s
            try:
                out.sendto(datagram([np.interp(s, times, q) for q in targets.T], key, stamp()), address)
            except ConnectionRefusedError:  # the run is not listening (yet, or any more): an ICMP echo
                pass
            k += 1
            stop.wait(period)
    finally:
        if sock is None:
            out.close()
    return k
