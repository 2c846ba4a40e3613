"""The boards as the runtime's readings source: pre-flight (map check, tare, taxel health), then a
reader thread that keeps the newest reading of every taxel and names every link fault.

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

Running, `newest()` never waits: the reader thread decodes each board's frames (its own counter and
uid checked first) into the latest force per taxel (tared, clipped at 0). Faults named once each:
a board silent for more than `silent_periods` frame periods (its taxels read NaN until it speaks
again), a CRC storm (`crc_storm` failed frames within a second), frames from another uid, a frame
counter that went back (a replayed or stale frame, or a board reset), the link lost.
"""
from __future__ import annotations

import select
import threading
import time
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from skinsafe.core.skin.model import SkinDesign
from skinsafe.hardware.client import BoardError
from skinsafe.hardware.protocol import FrameRun
from skinsafe.hardware.stream import SkinStream, decode_frames, frame_dtype

HALF_RANGE = 1 << 31


class PreflightRefused(Exception):
    """The robot may not move: one line naming the board or taxels and the fix."""


@dataclass
class Readings:
    t: float  # host time.monotonic() when the newest complete frame was read
    force: np.ndarray  # (N,) N after tare; NaN: no fresh data (silent board) or excluded
    seq: int  # increments with every frame decoded
    board_age_s: dict[int, float]  # board uid -> s since its last frame
    faults: list[str]  # named faults since the last call
    frames_lost: int


@dataclass
class _Board:
    uid: int
    name: str
    rows: np.ndarray
    arrived: float = 0.0
    crc: deque = field(default_factory=deque)
    crc_seen: int = 0
    dead: str = ""  # why the link is gone
    excluded: np.ndarray | None = None  # of its rows, those the health policy excluded


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


class SkinSource:
    """Readings of a design's boards on `ports` (board id -> port), streamed at `rate_hz`."""

    def __init__(self, design: SkinDesign, ports: dict[int, str], rate_hz: int = 500, noise_fraction: float = 0.25,
                 max_excluded: float = 0.02, silent_periods: float = 2.0, crc_storm: int = 5, **client_kw):
        missing = [b.name for b in design.boards if b.id not in ports]
        if missing:
            raise PreflightRefused(f"no port for board(s) {', '.join(missing)} of the map; give every board's port "
                                   "(or --boards emulate)")
        self.design, self.ports, self.rate_hz, self.client_kw = design, ports, int(rate_hz), client_kw
        self.noise_fraction, self.max_excluded = noise_fraction, max_excluded
        self.silent_periods, self.crc_storm = silent_periods, crc_storm
        self.n_taxels = design.n_taxels
        self.frame_period_s = 1.0 / self.rate_hz
        self.stream: SkinStream | None = None
        self.baseline = np.zeros(self.n_taxels)
        self.excluded = ~np.asarray(design.taxels.enabled, bool)
        self._force = np.full(self.n_taxels, np.nan)
        self._pub = None
        self._faults: list[str] = []
        self._named: set[str] = set()
        self._lock = threading.Lock()
        self._run = threading.Event()
        self._thread = None
        self._seq = 0

    # -- pre-flight ----------------------------------------------------------------------------
    def preflight(self, map_hash: bytes, tare_frames: int = 100) -> dict:
        """Check, start and tare the boards; returns the report (refuses with PreflightRefused or BoardError)."""
        from skinsafe.hardware.board_config import default_sensor

        if tare_frames < 2:
            raise PreflightRefused(f"tare over {tare_frames} frames: give at least 2 (e.g. 100)")
        self.stream = SkinStream(self.design, self.ports, self.rate_hz, verify=True, **self.client_kw)
        by_id = {b.id: b for b in self.design.boards}
        self.boards = {s.board_id: _Board(s.uid, by_id[s.board_id].name, s.rows) for s in self.stream.boards}
        self.stream.start()
        for s in self.stream.boards:
            self.boards[s.board_id].crc_seen = s.client.parser.crc_errors
        frames = self._tare(tare_frames)
        th = np.asarray(self.design.taxels.thresholds["force"], float)
        base, found = classify(frames, th, default_sensor().max_force, self.noise_fraction)
        names = self.design.taxels.ids
        report = {"map_hash": map_hash.hex(), "tare_frames": tare_frames,
                  "boards": {b.name: {"uid": b.uid, "config": "matches the map"} for b in self.boards.values()}}
        if found["pressed"].any():
            i = np.flatnonzero(found["pressed"])
            raise PreflightRefused(f"{len(i)} taxel(s) read at or above their threshold at rest (taxel "
                                   f"{int(names[i[0]])} on '{self._body(i[0])}': {base[i[0]]:.2f} N): something touches "
                                   "the skin; clear it and start again")
        disabled = self.excluded.copy()
        for k in ("dead", "stuck", "noisy"):
            report[k] = [int(x) for x in names[found[k] & ~disabled]]
        self.excluded = disabled | found["dead"] | found["stuck"] | found["noisy"]
        frac = float(self.excluded[~disabled].mean()) if (~disabled).any() else 0.0
        report.update(excluded=int(self.excluded.sum()), disabled_in_map=int(disabled.sum()), excluded_fraction=frac)
        if frac > self.max_excluded:
            raise PreflightRefused(f"{frac:.1%} of the enabled taxels are dead, stuck or noisy (dead "
                                   f"{len(report['dead'])}, stuck {len(report['stuck'])}, noisy {len(report['noisy'])}; "
                                   f"first: {(report['dead'] + report['stuck'] + report['noisy'])[:8]}), more than the "
                                   f"{self.max_excluded:.1%} allowed: repair the skin or disable them in the map")
        self.baseline = np.where(self.excluded, 0.0, base)
        report["baseline_max_N"] = float(self.baseline.max()) if len(self.baseline) else 0.0
        for b in self.boards.values():
            b.excluded = self.excluded[b.rows]
        self._force = np.where(self.excluded, np.nan, np.maximum(frames[-1] - self.baseline, 0.0))
        self._publish(time.monotonic())
        self._run.set()  # from here on the reader keeps every link drained
        self._thread = threading.Thread(target=self._reader, name="skin-reader", daemon=True)
        self._thread.start()
        return report

    def _body(self, i: int) -> str:
        return self.design.bodies[int(self.design.taxels.body[i])]

    def _tare(self, n: int) -> np.ndarray:
        """(n, N) readings: frame k of every board in row k."""
        out = np.full((n, self.n_taxels), np.nan)
        got = dict.fromkeys(self.boards, 0)
        deadline = time.monotonic() + max(2.0, 5 * n * self.frame_period_s)
        while min(got.values()) < n:
            if time.monotonic() > deadline:
                slow = [self.boards[b].name for b, k in got.items() if k < n]
                raise PreflightRefused(f"board(s) {', '.join(slow)} sent fewer than {n} frames in "
                                       f"{max(2.0, 5 * n * self.frame_period_s):.1f} s; check their links")
            for bid, forces in self._read(self.frame_period_s):
                take = min(n - got[bid], len(forces))
                out[got[bid]:got[bid] + take, self.boards[bid].rows] = forces[:take]
                got[bid] += take
            faults = self._take_faults()
            if faults:
                raise PreflightRefused(f"during the tare: {faults[0]}")
        return out

    # -- running -------------------------------------------------------------------------------
    def start(self) -> None:
        """The reader runs from the end of the pre-flight on: nothing to start (faults since then are reported)."""
        if self._thread is None:
            raise RuntimeError("SkinSource.start before preflight: run the pre-flight first")

    def newest(self) -> Readings:
        t, force, seq, arrived, lost = self._pub
        now = time.monotonic()
        ages = {self.boards[b].uid: now - a for b, a in arrived.items()}
        limit = self.silent_periods * self.frame_period_s
        stale = [b for b, a in arrived.items() if now - a > limit]
        faults = self._take_faults()
        if stale:
            force = force.copy()
            for b in stale:
                x = self.boards[b]
                force[x.rows] = np.nan
                if not x.dead:  # a dead link was named once already
                    corrupt = sum(c > arrived[b] for c in list(x.crc))
                    faults.append(f"board '{x.name}' (uid {x.uid:#x}): silent for {(now - arrived[b]) * 1e3:.1f} ms, "
                                  f"more than {self.silent_periods:g} frame periods ({limit * 1e3:.1f} ms)"
                                  + (f"; {corrupt} corrupt frames since its last good one (a CRC storm)" if corrupt else ""))
        return Readings(t, force, seq, ages, faults, lost)

    def close(self) -> dict:
        """Stop the reader and the boards; board id -> problem for those whose stop was not confirmed."""
        self._run.clear()
        if self._thread is not None:
            self._thread.join(1.0)
        problems = {}
        if self.stream is not None:
            try:
                problems = self.stream.stop()
            except (BoardError, OSError) as e:
                problems = {-1: str(e)}
            finally:
                self.stream.close()
        return problems

    def frames_lost(self) -> int:
        return sum(s.stats().lost for s in self.stream.boards) if self.stream is not None else 0

    def _reader(self) -> None:
        while self._run.is_set():
            got = self._read(self.frame_period_s)
            if got:
                for bid, forces in got:
                    b = self.boards[bid]
                    self._force[b.rows] = np.where(b.excluded, np.nan, np.maximum(forces[-1] - self.baseline[b.rows], 0.0))
                self._publish(max(self.boards[b].arrived for b, _ in got))

    def _publish(self, t: float) -> None:
        self._seq += 1
        self._pub = (t, self._force.copy(), self._seq, {b: x.arrived for b, x in self.boards.items()},
                     self.frames_lost())

    def _fault(self, text: str) -> None:
        with self._lock:
            if text not in self._named:
                self._named.add(text)
                self._faults.append(text)

    def _take_faults(self) -> list[str]:
        with self._lock:
            out, self._faults = self._faults, []
        return out

    def _read(self, wait: float) -> list[tuple[int, np.ndarray]]:
        """Wait up to `wait` for data, then read every board: [(board id, forces (F, rows))] of good frames."""
        live = [s for s in self.stream.boards if not self.boards[s.board_id].dead]
        poll = select.poll()
        for s in live:
            poll.register(s.client.ser.fileno(), select.POLLIN | select.POLLHUP | select.POLLERR)
        try:
            events = dict(poll.poll(wait * 1e3))
        except (OSError, ValueError):
            events = {}
        out = []
        for s in live:
            b = self.boards[s.board_id]
            try:
                if events.get(s.client.ser.fileno(), 0) & (select.POLLHUP | select.POLLERR):
                    raise OSError("the port hung up: cable pulled or board powered off")
                frames = s.client.read_stream(0.0)
            except (BoardError, OSError) as e:
                b.dead = f"board '{b.name}' (uid {b.uid:#x}): link lost ({e})"
                self._fault(b.dead)
                continue
            now = time.monotonic()
            self._crc_storm(s, b, now)
            self._refused(s, b)
            if not frames:
                continue
            frames = self._own(s, b, frames)
            if frames:
                samples, forces = decode_frames(frames, s.n_channels, s.channels, self.stream.table)
                keep = self._in_order(s, b, samples)
                if keep.any():
                    s.count(samples[keep])
                    b.arrived = now
                    out.append((s.board_id, forces[keep]))
        return out

    def _own(self, s, b: _Board, frames: list) -> list:
        """Frames of this board of the right size; others named (another uid) or counted (wrong size)."""
        size = frame_dtype(s.n_channels).itemsize
        good = []
        for f in frames:
            if f.uid != b.uid:
                self._fault(f"board '{b.name}' (uid {b.uid:#x}): frames from another uid {f.uid:#x} on its port")
            elif (f.payloads.shape[1] if isinstance(f, FrameRun) else len(f.payload)) != size:
                s.malformed += len(f.seqs) if isinstance(f, FrameRun) else 1
            else:
                good.append(f)
        return good

    def _in_order(self, s, b: _Board, samples: np.ndarray) -> np.ndarray:
        """Mask of frames whose counter moves forward; a counter that goes back is named."""
        prev = -1 if s.last_sample is None else s.last_sample
        keep = np.ones(len(samples), bool)
        for k, c in enumerate(samples.astype(np.int64)):
            step = (c - prev) & 0xFFFFFFFF
            if s.last_sample is not None or k:
                if step == 0 or step >= HALF_RANGE:
                    keep[k] = False
                    self._fault(f"board '{b.name}' (uid {b.uid:#x}): frame counter went back from {prev} to {c} "
                                "(a replayed or stale frame, or the board reset)")
                    continue
            prev = c
        return keep

    def _refused(self, s, b: _Board) -> None:
        """Frames the client or the stream refused themselves (another uid, a counter not ahead), where they count them."""
        foreign = getattr(s.client, "foreign", None) or {}
        if foreign:
            uid = next(iter(foreign))
            self._fault(f"board '{b.name}' (uid {b.uid:#x}): frames from another uid {uid:#x} on its port")
        if getattr(s, "replayed", 0):
            self._fault(f"board '{b.name}' (uid {b.uid:#x}): frame counter went back (a replayed or stale frame, "
                        "or the board reset)")

    def _crc_storm(self, s, b: _Board, now: float) -> None:
        errors = s.client.parser.crc_errors
        new, b.crc_seen = errors - b.crc_seen, errors
        b.crc.extend([now] * max(0, new))
        while b.crc and now - b.crc[0] > 1.0:
            b.crc.popleft()
        if len(b.crc) >= self.crc_storm:
            self._fault(f"board '{b.name}' (uid {b.uid:#x}): CRC storm ({len(b.crc)} corrupt frames within 1 s); "
                        "check the cable and its shielding")
