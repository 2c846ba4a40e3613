"""The boards as the runtime's readings source: the pre-flight (map check, tare, taxel health), then the
newest reading of every taxel and every link fault named, from a reader in its own process.

Pre-flight, before the robot may move (robot still, nothing touching the skin):
1. every board's active config must be the one MAP gives it (`SkinStream` refuses naming the board);
2. tare: `tare_frames` frames of every board; per taxel baseline = the median;
3. health over those frames, per taxel (the policy; README "Running a robot"):
   - dead: not one finite reading -> excluded;
   - stuck: the same non-zero reading in every frame (a live cell under load shows ADC noise), or
     at the sensor's saturation -> excluded;
   - noisy: spread (max - min) above `noise_fraction` x its threshold -> excluded (it would raise
     false danger events);
   - pressed: baseline at or above its threshold while not stuck -> refused (something touches the
     skin; a tare would blind that taxel);
   - taxels disabled in the map are excluded too. More than `max_excluded` (fraction) excluded -> refused.
   Excluded taxels read NaN; the runtime feeds them to the layers as 0 N (they never trigger).

Running, `newest()` never waits: the boards' reader (hardware/skin_reader.py, its own process at the
loop's priority) decodes each board's frames (its own counter and uid checked first) into the latest
force per taxel (tared, clipped at 0) in shared memory. Faults come typed, (kind, source, text, onset),
kind a core/runtime/monitor.py `Kind` value: a board silent for more than `silent_periods` frame
periods (+ `link_latency`), or late by its own clock beyond that (its taxels read NaN until it is on
time again), a CRC storm (`crc_storm` failed frames within a second), frames from another uid, a
frame counter that went back (a replayed or stale frame, or a board reset), the link lost (NaN);
the reader itself not running for as long as a board may be silent (`reader-stalled`, on every call
while it lasts), or dead: its process's pidfd and its pipe's hang-up are polled on every call
(`reader-died`, whatever `link_latency` is), never inferred from its silence.
"""
from __future__ import annotations

import os
import select
import subprocess
import sys
import time
from dataclasses import dataclass
from multiprocessing.connection import Connection

import numpy as np

from skinsafe.core.skin.force_feed import ForceFeed
from skinsafe.core.skin.model import SkinDesign
from skinsafe.hardware.client import BoardError

START_S = 30.0  # the reader's start (its imports) may take this long on a loaded machine, besides the tare
CLOSE_S = 5.0  # the reader's stop of the boards, and its settling after a silence


class PreflightRefused(Exception):
    """The robot may not move: one line naming the board or taxels and the fix."""


@dataclass
class Readings:
    t: float  # host time.monotonic() when the newest complete frame was read
    force: np.ndarray  # (N,) N after tare; NaN: no fresh data (silent board) or excluded
    seq: int  # increments with every frame decoded
    board_age_s: dict[int, float]  # board uid -> s since its last frame
    faults: list[tuple]  # (kind, source, text, onset or None) named since the last call
    frames_lost: int




def classify(frames: np.ndarray, threshold: np.ndarray, saturation: float, noise_fraction: float
             ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """(baseline (N,), {"dead"|"stuck"|"noisy"|"pressed": bool (N,)}) over tare frames (F, N)."""
    finite = np.isfinite(frames)
    dead = ~finite.any(axis=0)
    f = np.where(finite, frames, np.nan)
    with np.errstate(all="ignore"):
        lo, hi = np.nanmin(np.where(dead, 0, f), axis=0), np.nanmax(np.where(dead, 0, f), axis=0)
        base = np.where(dead, 0.0, np.nanmedian(np.where(dead, 0, f), axis=0))
    stuck = ~dead & (((hi == lo) & (base > 0)) | (base >= saturation))
    noisy = ~dead & ~stuck & (hi - lo > noise_fraction * threshold)
    pressed = ~dead & ~stuck & ~noisy & (base >= threshold)
    return base, {"dead": dead, "stuck": stuck, "noisy": noisy, "pressed": pressed}


def ending_status(pid: int) -> int | None:
    """The exit status (as `Popen.returncode` gives it) of a process that is ending but not yet reapable: the kernel
    sets it (/proc/PID/stat, field 52) before it closes the process's files, so a pipe's hang-up can be named at
    once; None when there is none to read (still running, gone, or ending with status 0)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            status = int(f.read().rsplit(")", 1)[1].split()[49])
    except (OSError, IndexError, ValueError):
        return None
    return -(status & 0x7F) if status & 0x7F else (status >> 8) or None


class SkinSource:
    """Readings of a design's boards on `ports` (board id -> port), streamed at `rate_hz`; the pre-flight and the
    reading run in the boards' reader process (module docstring)."""

    def __init__(self, design: SkinDesign, ports: dict[int, str], rate_hz: int = 100, noise_fraction: float = 0.25,
                 max_excluded: float = 0.02, silent_periods: float = 2.0, crc_storm: int = 5,
                 link_latency: float = 0.0, faults=None, **client_kw):
        """`faults`: a run's fault plan (core/runtime/fault_plan.py): from its `reading-nan` on, every frame read
        carries a NaN on the first taxel not excluded (its onset: the first such frame's read time)."""
        missing = [b.name for b in design.boards if b.id not in ports]
        if missing:
            raise PreflightRefused(f"no port for board(s) {', '.join(missing)} of the map; give every board's port "
                                   "(or --boards emulate)")
        self.design, self.ports, self.faults = design, ports, faults
        self.n_taxels = design.n_taxels
        self.frame_period_s = 1.0 / int(rate_hz)
        self.silence_s = silent_periods * self.frame_period_s + link_latency  # a board is silent after this long
        self.excluded = ~np.asarray(design.taxels.enabled, bool)
        self.summary: dict = {}  # the reader's, once closed: frames lost, the link's delays, the silences
        self._cfg = {"design": design, "ports": ports, "rate_hz": int(rate_hz), "noise_fraction": noise_fraction,
                     "max_excluded": max_excluded, "silent_periods": silent_periods, "link_latency": link_latency,
                     "crc_storm": crc_storm, "client_kw": client_kw}
        self._proc = self._rx = self._tx = self._state = self._beat = None
        self._uids: list[int] = []
        self._faults: list[tuple] = []
        self._pidfd: int | None = None
        self._gone = select.poll()  # the reader's pidfd (readable once it ended) and its pipe's hang-up

    # -- pre-flight ----------------------------------------------------------------------------
    def preflight(self, map_hash: bytes, tare_frames: int = 100) -> dict:
        """Start the reader, which checks, starts and tares the boards; the report (PreflightRefused or BoardError
        when it refuses)."""
        if tare_frames < 2:
            raise PreflightRefused(f"tare over {tare_frames} frames: give at least 2 (e.g. 100)")
        nb = len(self.design.boards)
        self._state = ForceFeed.create(None, 1 + nb + self.n_taxels)
        self._beat = ForceFeed.create(None, 1)
        down_r, down_w = os.pipe()
        up_r, up_w = os.pipe()
        try:
            self._proc = subprocess.Popen([sys.executable, "-m", "skinsafe.hardware.skin_reader", str(down_r), str(up_w)],
                                          pass_fds=(down_r, up_w), stdin=subprocess.DEVNULL)
        finally:
            os.close(down_r)
            os.close(up_w)
        self._tx, self._rx = Connection(down_w, readable=False), Connection(up_r, writable=False)
        self._pidfd = os.pidfd_open(self._proc.pid)
        self._gone.register(self._pidfd, select.POLLIN)
        self._gone.register(self._rx.fileno(), 0)  # POLLHUP only: every writer of the pipe closed
        try:
            self._tx.send({**self._cfg, "map_hash": map_hash, "tare_frames": tare_frames, "state": self._state.name,
                           "beat": self._beat.name})
        except OSError:
            pass  # it ended at once: the answer names it
        msg = self._answer(START_S + max(2.0, 5 * tare_frames * self.frame_period_s))
        if msg[0] == "refused":
            raise PreflightRefused(msg[1])
        if msg[0] == "board-error":
            raise BoardError(msg[1], kind=msg[2])
        _, report, self.excluded = msg
        self._uids = [b.uid for b in self.design.boards if b.id in self.ports]  # the reader's order (SkinStream's)
        return report

    def _answer(self, timeout: float):
        """The reader's next message; PreflightRefused naming why when it ends or stays silent instead."""
        deadline, ended = time.monotonic() + timeout, False
        while not ended and time.monotonic() < deadline:
            if self._rx.poll(0.1):
                try:
                    return self._rx.recv()
                except EOFError:
                    ended = True
            ended = ended or self._proc.poll() is not None
        code = self._proc.poll()
        if ended and code is None:  # its pipe closed on its way out: the exit code follows
            try:
                code = self._proc.wait(timeout=1.0)
            except subprocess.TimeoutExpired:
                code = ending_status(self._proc.pid)
        why = (f"ended with exit code {code}" if code is not None else "ended (its pipe closed)") if ended else \
            f"did not answer within {timeout:.0f} s"
        raise PreflightRefused(f"the boards' reader {why} before the pre-flight finished; run it again, or check the "
                               "serial ports")

    # -- running -------------------------------------------------------------------------------
    def start(self) -> None:
        """The reader runs from the end of the pre-flight on: nothing to start (faults since then are reported)."""
        if self._state is None or self._proc is None:
            raise RuntimeError("SkinSource.start before preflight: run the pre-flight first")

    @property
    def pid(self) -> int | None:
        """The boards' reader's process id (None before the pre-flight or after close)."""
        return self._proc.pid if self._proc is not None else None

    def newest(self) -> Readings:
        """The reader's newest readings (from shared memory: never waits), and the faults named since the last call."""
        seq, t, v = self._state.read()
        beat = float(self._beat.read()[2][0])
        now = time.monotonic()
        nb = len(self._uids)
        faults = self._take_faults()
        if self._gone.poll(0):
            code = self._proc.poll()
            code = ending_status(self._proc.pid) if code is None else code
            how = f"exit code {code}" if code is not None else "its pipe closed"
            faults.insert(0, ("reader-died", "skin", f"the boards' reader ended ({how})", None))
        elif now - beat > self.silence_s:
            faults.append(("reader-stalled", "skin", f"the boards' reader was silent for {(now - beat) * 1e3:.1f} ms, "
                           f"more than a board may be ({self.silence_s * 1e3:.1f} ms): the host is overloaded",
                           beat + self.silence_s))
        ages = {uid: now - a for uid, a in zip(self._uids, v[1:1 + nb])}
        force = v[1 + nb:]
        if self.faults is not None and self.faults.due("reading-nan", t):
            force = force.copy()
            force[np.flatnonzero(~self.excluded)[0]] = np.nan
        return Readings(t, force, seq, ages, faults, int(v[0]))

    def _take_faults(self) -> list[str]:
        try:
            while self._rx.poll(0):
                msg = self._rx.recv()
                if msg[0] == "fault":
                    self._faults.append(tuple(msg[1:]))
        except (EOFError, OSError):
            pass  # the reader ended: its pidfd names it
        out, self._faults = self._faults, []
        return out

    def frames_lost(self) -> int:
        if "frames_lost" in self.summary:
            return self.summary["frames_lost"]
        return int(self._state.read()[2][0]) if self._state is not None else 0

    def close(self) -> dict:
        """Stop the reader and the boards; board id -> problem for those whose stop was not confirmed. The reader's
        summary (frames lost, the link's delays, what each silence was) is in `summary`."""
        problems = {}
        if self._proc is not None:
            try:
                self._tx.send("stop")
                deadline = time.monotonic() + CLOSE_S
                while time.monotonic() < deadline and self._rx.poll(max(0.0, deadline - time.monotonic())):
                    msg = self._rx.recv()
                    if msg[0] == "closed":
                        self.summary = msg[1]
                        problems = self.summary.pop("problems")
                        break
                    if msg[0] == "fault":
                        self._faults.append(tuple(msg[1:]))
            except (EOFError, OSError):
                pass
            try:
                self._proc.wait(CLOSE_S)
            except subprocess.TimeoutExpired:
                self._proc.kill()
                self._proc.wait()
                problems = problems or {-1: "the boards' reader did not stop; the boards may still stream"}
            for c in (self._tx, self._rx):
                c.close()
            os.close(self._pidfd)
            self._gone = select.poll()
            self._proc = self._pidfd = None
        for feed in (self._state, self._beat):
            if feed is not None:
                feed.close()
        self._state = self._beat = None
        return problems
