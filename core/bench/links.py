"""`skinsafe bench runtime --links`: how late a host's serial input arrives, pseudo-terminals against pipes.

Four links, each a writer thread sending a 2 KiB frame (a 1,024-channel board's) every 10 ms (100 Hz)
stamped with the host's clock, and one reader taking all four: through pseudo-terminals (the emulated
boards' links; a USB serial port takes the same path in the kernel: a tty's flip buffer handed to the
line discipline by a kernel worker) and through pipes (no tty, no worker). The reader waits with
`poll` (what a tty reader usually does) or an edge-triggered `epoll` (what the boards' reader does). Both
ends run at real-time priority where the system allows it; the reader reads what FIONREAD says is there (a read of
an empty tty, too, waits for the kernel's pending tty work). Per row: the delivery delay (p50, p99, max,
frames later than 20 ms: 2 frame periods at 100 Hz) and the reader's longest time between passes (a
tty's poll waits for the kernel's pending tty work: n_tty_poll -> tty_buffer_flush_work).
"""
from __future__ import annotations

import fcntl
import os
import select
import struct
import termios
import threading
import time
import tty

import numpy as np

FRAME = 2048
LINKS = 4


def _links(kind: str) -> list[tuple[int, int]]:
    """(write fd, read fd) per link."""
    out = []
    for _ in range(LINKS):
        if kind == "pty":
            master, slave = os.openpty()
            tty.setraw(slave)
            out.append((master, slave))
        else:
            r, w = os.pipe()
            out.append((w, r))
    return out


def measure(kind: str, wait: str, seconds: float, rate: float = 100.0) -> dict:
    """One row: `kind` pty | pipe, `wait` poll | epoll, `seconds` of frames at `rate` per link."""
    links = _links(kind)
    for _, r in links:
        os.set_blocking(r, False)
    delays, gaps = [], []
    stop = threading.Event()

    def writer(fd: int, phase: float) -> None:
        nxt = time.monotonic() + phase
        while not stop.is_set():
            nxt += 1.0 / rate
            time.sleep(max(0.0, nxt - time.monotonic()))
            os.write(fd, struct.pack("<d", time.monotonic()) + bytes(FRAME - 8))

    def reader() -> None:
        bufs = {r: b"" for _, r in links}
        if wait == "epoll":
            ep = select.epoll()
            for r in bufs:
                ep.register(r, select.EPOLLIN | select.EPOLLET)
        else:
            po = select.poll()
            for r in bufs:
                po.register(r, select.POLLIN)
        last = time.monotonic()
        while not stop.is_set():
            (ep.poll(0.01) if wait == "epoll" else po.poll(10))
            now = time.monotonic()
            gaps.append(now - last)
            last = now
            for r in bufs:
                waiting = struct.unpack("i", fcntl.ioctl(r, termios.FIONREAD, b"\0\0\0\0"))[0]
                if waiting:  # (a read of an empty tty waits for the pending tty work, as its poll does)
                    bufs[r] += os.read(r, waiting)
                while len(bufs[r]) >= FRAME:
                    delays.append(now - struct.unpack_from("<d", bufs[r])[0])
                    bufs[r] = bufs[r][FRAME:]
        if wait == "epoll":
            ep.close()

    threads = [threading.Thread(target=reader)] + [threading.Thread(target=writer, args=(w, k / (LINKS * rate)))
                                                   for k, (w, _) in enumerate(links)]
    for t in threads:
        t.start()
    time.sleep(seconds)
    stop.set()
    for t in threads:
        t.join()
    for fds in links:
        for fd in fds:
            os.close(fd)
    d, g = np.array(delays) * 1e3, np.array(gaps) * 1e3
    return {"link": kind, "wait": wait, "frames": len(d), "seconds": seconds,
            "delay_ms_p50": round(float(np.median(d)), 3), "delay_ms_p99": round(float(np.percentile(d, 99)), 2),
            "delay_ms_max": round(float(d.max()), 1), "over_20ms": int((d > 20).sum()),
            "reader_gap_ms_max": round(float(g.max()), 1), "load": round(os.getloadavg()[0], 1)}


def rows(seconds: float, realtime: bool = True) -> list[dict]:
    """pty/pipe x poll/epoll, one after another (each `seconds`), at real-time priority where allowed."""
    if realtime:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(10))
        except (AttributeError, PermissionError, OSError):
            pass
    return [measure(kind, wait, seconds) for kind in ("pty", "pipe") for wait in ("poll", "epoll")]
