"""The boards' reader, in a process of its own: pre-flight, then every board's frames decoded into the
newest tared force per taxel, published in shared memory for the safety loop (`SkinSource`).

Its own process, because the loop's process cannot promise a reader thread the interpreter: a robot
library may keep the interpreter lock while it waits for the robot (pylibfranka's `readOnce` and
motion start do; measured: beside the FR3 driver a reader thread went 33-42 ms without running,
and each of 5 runs stopped on a false board silence within 80 ms of the motion's start). Here
nothing shares the interpreter with the reader; it inherits the loop's real-time priority.

    python -m skinsafe.hardware.skin_reader FROM_FD TO_FD   (started by `SkinSource`, not by hand)

Protocol (multiprocessing `Connection`s over two pipes): the parent sends the configuration; the
reader answers ("report", report, excluded) or ("refused", text) / ("board-error", text, kind); then
("fault", kind, source, text, onset) for each named fault while it runs (kind: one of `KINDS`, the runtime
monitor's fault kinds; onset: host monotonic time the fault began, or None); "stop" from the parent (or its pipe closing)
stops the boards, answered by ("closed", summary). Shared memory (two `ForceFeed`s, seqlocks):
`state` = [frames lost, each board's last frame (host monotonic time), the (N,) forces] with the
newest frame's host time as its stamp, written whenever frames arrive; `beat` = [the reader's last
pass], written every pass, so the loop sees a reader that stopped running.

Silence is judged here, after every pass has read all the kernel delivered (the reader's own wake-ups
never count): a board with no frame for `silent_periods` frame periods plus `link_latency` is named
silent and its taxels read NaN; so are a lost link's, and a board's whose frames are late by its own clock
(host read time - board stamp - the least such delay seen) beyond the same bound, however steadily they
arrive; every frame of a burst is checked. When its frames come again, their own clock (the board's time
stamps) tells who was silent: frames the board sent before it was named, arriving late, mean the
host's serial input stalled; none mean the board was (`summary["silences"]`).
"""
from __future__ import annotations

import gc
import select
import signal
import sys
import time
from collections import deque
from dataclasses import dataclass, field
from multiprocessing.connection import Connection

import numpy as np

from skinsafe.core.skin.force_feed import ForceFeed
from skinsafe.hardware.client import BoardError
from skinsafe.hardware.protocol import FrameRun
from skinsafe.hardware.skin_source import PreflightRefused, classify
from skinsafe.hardware.stream import SkinStream, decode_frames, frame_dtype

HALF_RANGE = 1 << 31
# the faults this reader names (core/runtime/monitor.py Kind values; hardware cannot import it)
KINDS = ("link-lost", "board-silent", "board-late", "counter-back", "foreign-uid", "crc-storm")
SETTLE_S = 0.5  # after a silence, how long the stop waits for the board's late frames (to say who was silent)


@dataclass
class _Board:
    uid: int
    name: str
    rows: np.ndarray
    index: int  # its slot in the published state
    arrived: float = 0.0  # host time of its last good frame
    crc: deque = field(default_factory=deque)
    crc_seen: int = 0
    dead: str = ""  # why the link is gone
    excluded: np.ndarray | None = None  # of its rows, those the health policy excluded
    baseline: np.ndarray | None = None  # of its rows, the tare's baseline
    silent_at: float = 0.0  # host time it was named silent (0: it is not)
    offset: float = np.inf  # least (host read time - board stamp): the board clock's offset plus the least delay
    lags: deque = field(default_factory=lambda: deque(maxlen=100_000))  # per read: host read time - board stamps, s
    silence: dict | None = None  # the open silence: what its next frames tell
    late: bool = False  # its newest frames are late by its own clock (taxels NaN until they are on time again)
    sent: float = -np.inf  # host time its newest good frame was sent, by its own clock (stamp + offset)


class BoardsReader:
    """Pre-flight and reading of a design's boards on `ports` (board id -> port) at `rate_hz`."""

    def __init__(self, design, ports: dict[int, str], rate_hz: int, noise_fraction: float, max_excluded: float,
                 silent_periods: float, link_latency: float, crc_storm: int, client_kw: dict):
        self.design, self.ports, self.rate_hz, self.client_kw = design, ports, int(rate_hz), client_kw
        self.noise_fraction, self.max_excluded = noise_fraction, max_excluded
        self.silent_periods, self.link_latency, self.crc_storm = silent_periods, link_latency, crc_storm
        self.frame_period_s = 1.0 / self.rate_hz
        self.silence_s = silent_periods * self.frame_period_s + link_latency
        # the newest frame's age by the board's own clock that names it late between arrivals: half a frame period
        # over the silence, so that a plain silence (its last frame came with the usual delay) is named silent
        self.stale_s = self.silence_s + self.frame_period_s / 2
        self.n_taxels = design.n_taxels
        self.stream: SkinStream | None = None
        self.baseline = np.zeros(self.n_taxels)
        self.excluded = ~np.asarray(design.taxels.enabled, bool)
        self.boards: dict[int, _Board] = {}
        self._faults: list[tuple] = []
        self._named: set[str] = set()
        self.silences: list[dict] = []
        self.gaps: deque = deque(maxlen=1_000_000)  # s between the reader's passes (its own wake-ups)
        self.held: deque = deque(maxlen=1_000_000)  # s from the newest frame's arrival to its readings' publication
        self.t_newest = 0.0  # host time of the newest frame
        self._epoll = None
        self._rx_registered = False
        self._lost = False  # a link was lost this pass (its taxels went NaN: publish)
        self.running = False  # lateness is judged from the run on (the tare learns each board's least delay)

    # -- pre-flight ----------------------------------------------------------------------------
    def preflight(self, map_hash: bytes, tare_frames: int) -> dict:
        """Check, start and tare the boards; the report (refuses with PreflightRefused or BoardError)."""
        from skinsafe.hardware.board_config import default_sensor

        self.stream = SkinStream(self.design, self.ports, self.rate_hz, verify=True, **self.client_kw)
        by_id = {b.id: b for b in self.design.boards}
        self.boards = {s.board_id: _Board(s.uid, by_id[s.board_id].name, s.rows, k)
                       for k, s in enumerate(self.stream.boards)}
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
            b.excluded, b.baseline = np.flatnonzero(self.excluded[b.rows]), self.baseline[b.rows]
        self.vec = np.zeros(1 + len(self.boards) + self.n_taxels)  # the published state (module docstring)
        self.arrived, self.force = self.vec[1:1 + len(self.boards)], self.vec[1 + len(self.boards):]
        self.force[:] = np.where(self.excluded, np.nan, np.maximum(frames[-1] - self.baseline, 0.0))
        for b in self.boards.values():
            b.lags.clear()  # the tare's frames waited for the whole tare: they say nothing of the link
        return report

    def _body(self, i: int) -> str:
        return self.design.bodies[int(self.design.taxels.body[i])]

    def _tare(self, n: int) -> np.ndarray:
        """(n, N) readings: frame k of every board in row k."""
        out = np.full((n, self.n_taxels), np.nan)
        got = dict.fromkeys(self.boards, 0)
        wait = max(2.0, 5 * n * self.frame_period_s)
        deadline = time.monotonic() + wait
        while min(got.values()) < n:
            if time.monotonic() > deadline:
                slow = [self.boards[b].name for b, k in got.items() if k < n]
                raise PreflightRefused(f"board(s) {', '.join(slow)} sent fewer than {n} frames in {wait:.1f} s; "
                                       "check their links")
            for bid, forces in self._read(self.frame_period_s):
                take = min(n - got[bid], len(forces))
                out[got[bid]:got[bid] + take, self.boards[bid].rows] = forces[:take]
                got[bid] += take
            faults = self._take_faults()
            if faults:
                raise PreflightRefused(f"during the tare: {faults[0][2]}")
        return out

    # -- running -------------------------------------------------------------------------------
    def run(self, rx: Connection, tx: Connection, state: ForceFeed, beat: ForceFeed) -> None:
        """Read, publish and name faults until the parent says stop (or its pipe closes); no collector pass over
        everything imported holds a frame up (`gc.freeze`)."""
        gc.freeze()
        self.t_newest = time.monotonic()
        self.running = True
        self._publish(state)
        last = self.t_newest
        while True:
            now = time.monotonic()
            self.gaps.append(now - last)
            last = now
            beat.write(np.array([now]), now)
            due = [min(b.arrived + self.silence_s, np.inf if b.late else b.sent + self.stale_s) - now
                   for b in self.boards.values() if not (b.dead or b.silent_at)]
            wait = min([self.frame_period_s, *due])
            got = self._read(max(wait, 1e-4), rx)
            now = time.monotonic()
            for bid, forces in got:
                b = self.boards[bid]
                if b.late:  # stale by the board's own clock: fail safe
                    self.force[b.rows] = np.nan
                    continue
                f = forces[-1] - b.baseline
                np.maximum(f, 0.0, out=f)
                f[b.excluded] = np.nan
                self.force[b.rows] = f
            named = self._silent(now) | self._stale(now) or self._lost
            self._lost = False
            for fault in self._take_faults():  # before the readings they explain (a silent board's NaN): the loop
                tx.send(("fault", *fault))  # that reads those finds its name waiting
            if got or named:
                self.t_newest = max([self.boards[b].arrived for b, _ in got], default=self.t_newest)
                self._publish(state)
                if got:
                    self.held.append(time.monotonic() - self.t_newest)
            if rx.poll(0):
                try:
                    if rx.recv() == "stop":
                        return
                except EOFError:
                    return

    def _silent(self, now: float) -> bool:
        """Name every board with no frame for longer than `silence_s` (once per silence); its taxels read NaN.
        True when one was named."""
        named = False
        for b in self.boards.values():
            if b.dead or b.silent_at or now - b.arrived <= self.silence_s:
                continue
            b.silent_at = now
            self.force[b.rows] = np.nan
            corrupt = sum(c > b.arrived for c in b.crc)
            allowance = f" + {self.link_latency * 1e3:g} ms link latency" if self.link_latency else ""
            b.silence = {"board": b.name, "silent_ms": round((now - b.arrived) * 1e3, 1), "named": now,
                         "last": b.arrived, "cause": "nothing came before the stop"}
            self._fault("crc-storm" if corrupt else "board-silent", b, f"silent for {(now - b.arrived) * 1e3:.1f} ms, more than "
                        f"{self.silent_periods:g} frame periods ({self.silent_periods * self.frame_period_s * 1e3:.1f} "
                        f"ms){allowance}"
                        + (f"; {corrupt} corrupt frames since its last good one (a CRC storm)" if corrupt else ""),
                        b.arrived + self.frame_period_s, again=True)
            self.silences.append(b.silence)
            named = True
        return named

    def _stale(self, now: float) -> bool:
        """Name every board whose newest frame, by its own clock, is older than `stale_s` while frames still arrive
        (late frames a little apart never go silent by arrival); its taxels read NaN until one comes on time."""
        named = False
        for b in self.boards.values():
            if b.dead or b.silent_at or b.late or b.silence is not None or now - b.sent <= self.stale_s:
                continue
            b.late = True
            self.force[b.rows] = np.nan
            self._fault("board-late", b, f"late by the board's own clock: its newest frame is {(now - b.sent) * 1e3:.1f} "
                        f"ms old (the last arrived {(now - b.arrived) * 1e3:.1f} ms ago), more than "
                        f"{self.silence_s * 1e3:.1f} ms (frames arriving steadily but stale)", b.sent + self.silence_s,
                        again=True)
            named = True
        return named

    def _publish(self, state: ForceFeed) -> None:
        self.vec[0] = self.frames_lost()
        for b in self.boards.values():
            self.arrived[b.index] = b.arrived
        state.write(self.vec, self.t_newest)

    def settle(self, rx: Connection | None = None) -> None:
        """After a named silence, read on (up to SETTLE_S) until each silent board's frames tell who was silent."""
        end = time.monotonic() + SETTLE_S
        while any(b.silence is not None for b in self.boards.values() if not b.dead) and time.monotonic() < end:
            self._read(self.frame_period_s)

    def close(self) -> dict:
        """Stop the boards; the summary: board id -> problem for stops not confirmed, frames lost, the link's delays."""
        problems = {}
        if self._epoll is not None:
            self._epoll.close()
        if self.stream is not None:
            try:
                problems = self.stream.stop()
            except (BoardError, OSError) as e:
                problems = {-1: str(e)}
            finally:
                self.stream.close()
        return {"problems": problems, "frames_lost": self.frames_lost(), **self.stats()}

    def stats(self) -> dict:
        """How late the boards' frames reached this reader (host read time against the board's own clock, over
        the least such delay of each board: the link's and the kernel's delay, not the reader's), and how long
        the reader itself went between passes."""
        lags = [np.concatenate(b.lags) - b.offset for b in self.boards.values() if b.lags]
        lag = np.concatenate(lags) * 1e3 if lags else np.zeros(0)
        gaps = np.array(self.gaps) * 1e3
        held = np.array(self.held) * 1e3

        def pct(a, p):
            return round(float(np.percentile(a, p)), 2) if len(a) else None
        return {"frame_delay_ms_p50": pct(lag, 50), "frame_delay_ms_p99": pct(lag, 99), "frame_delay_ms_max": pct(lag, 100),
                "frames_over_silence": int((lag > self.silence_s * 1e3 - self.frame_period_s * 1e3).sum()),
                "reader_gap_ms_p99": pct(gaps, 99), "reader_gap_ms_max": pct(gaps, 100),
                "publish_ms_p50": pct(held, 50), "publish_ms_p99": pct(held, 99), "publish_ms_max": pct(held, 100),
                "silences_host": sum(x["cause"].startswith("host") for x in self.silences),
                "silences_board": sum(x["cause"].startswith("board") for x in self.silences),
                "silences": self.silences[:20]}

    def frames_lost(self) -> int:
        return sum(s.stats().lost for s in self.stream.boards) if self.stream is not None else 0

    def _fault(self, kind: str, b: _Board, text: str, onset: float | None = None, again: bool = False) -> None:
        """Name a fault of board `b` to the loop, each text once (a CRC storm or a foreign uid is seen on every pass),
        or every time with `again` (each silence is news: one named before the robot moved, which the loop lets
        pass, must not hide a later one of the same length)."""
        text = f"board '{b.name}' (uid {b.uid:#x}): {text}"
        if again or text not in self._named:
            self._named.add(text)
            self._faults.append((kind, f"board '{b.name}'", text, onset))

    def _take_faults(self) -> list[tuple]:
        out, self._faults = self._faults, []
        return out

    def _read(self, wait: float, rx: Connection | None = None) -> list[tuple[int, np.ndarray]]:
        """Wait up to `wait` for data (or a word from the parent), then read the boards that have some (every board
        when the wait timed out): [(board id, forces (F, rows))] of good frames.

        The wait is an edge-triggered epoll, registered once: a tty's own poll (select, poll, level-triggered
        epoll) waits, when no input is there, for the kernel's pending tty work to finish (n_tty_poll ->
        tty_buffer_flush_work), which a loaded machine runs tens to hundreds of ms late: the reader would
        stall with it, unable to name a silence or to stop."""
        if self._epoll is None:
            self._epoll = select.epoll()
            for s in self.stream.boards:
                self._epoll.register(s.client.ser.fileno(), select.EPOLLIN | select.EPOLLET)
        if rx is not None and not self._rx_registered:
            self._epoll.register(rx.fileno(), select.EPOLLIN | select.EPOLLET)
            self._rx_registered = True
        try:
            events = dict(self._epoll.poll(wait))
        except OSError:
            events = {}
        # the boards the wait says have news (each is drained, so an edge comes with its next bytes); after a wait
        # that ended with none, every board (its bytes cannot be missed either way)
        ready = [s for s in self.stream.boards if s.client.ser.fileno() in events] or self.stream.boards
        out = []
        for s in (s for s in ready if not self.boards[s.board_id].dead):
            b = self.boards[s.board_id]
            try:
                if events.get(s.client.ser.fileno(), 0) & (select.EPOLLHUP | select.EPOLLERR):
                    raise OSError("the port hung up: cable pulled or board powered off")
                frames = s.client.read_stream(0.0)
            except (BoardError, OSError) as e:
                b.dead = f"link lost ({e})"
                self._fault("link-lost", b, b.dead, time.monotonic())
                self.force[b.rows] = np.nan  # fail safe: never its last forces
                self._lost = True
                self._epoll.unregister(s.client.ser.fileno())
                continue
            now = time.monotonic()
            self._crc_storm(s, b, now)
            self._refused(s, b)
            if not frames:
                continue
            frames = self._own(s, b, frames)
            if frames:
                samples, forces, stamps = decode_frames(frames, s.n_channels, s.channels, self.stream.table, stamps=True)
                keep = self._in_order(s, b, samples)
                if keep.any():
                    s.count(samples[keep])
                    self._arrived(b, now, stamps[keep])
                    out.append((s.board_id, forces[keep]))
        return out

    def _arrived(self, b: _Board, now: float, stamps: np.ndarray) -> None:
        """A board's frames read at `now`: its last arrival, the link's delays, and what they say of an open silence."""
        lag = now - stamps
        b.lags.append(lag)
        b.offset = min(b.offset, float(lag.min()))
        b.arrived = now
        b.sent = max(b.sent, float(stamps[-1]) + b.offset)
        if self.running:
            self._late(b, lag - b.offset, stamps)
        if b.silence is not None:  # the first frames since the board was named silent
            sent = stamps + b.offset  # when the board sent them, on this host's clock (at the least delay)
            early = sent[sent < b.silence["named"]]
            b.silence["cause"] = (f"host: the board sent its frames on time; they reached the host up to "
                                  f"{(now - early.min()) * 1e3:.0f} ms late (the link or the host's serial input held "
                                  "them)" if len(early) else
                                  f"board: it sent nothing for {(sent[0] - b.silence['last']) * 1e3:.0f} ms")
            b.silence.pop("named"), b.silence.pop("last")
            b.silence = None
            b.silent_at = 0.0

    def _late(self, b: _Board, late: np.ndarray, stamps: np.ndarray) -> None:
        """Every frame of a burst judged by the board's own clock: one later than a board may be silent names the
        board late (once per episode; a silence already named says it), and while its newest frame is, its taxels
        read NaN."""
        over = late > self.silence_s
        if over.any() and not b.late and b.silence is None:
            k = int(np.argmax(over))
            self._fault("board-late", b, f"a frame {late.max() * 1e3:.1f} ms late by the board's own clock, more than "
                        f"{self.silence_s * 1e3:.1f} ms (frames arriving steadily but stale)",
                        float(stamps[k]) + b.offset + self.silence_s, again=True)
        b.late = bool(over[-1])

    def _own(self, s, b: _Board, frames: list) -> list:
        """Frames of this board of the right size; others named (another uid) or counted (wrong size)."""
        size = frame_dtype(s.n_channels).itemsize
        good = []
        for f in frames:
            if f.uid != b.uid:
                self._fault("foreign-uid", b, f"frames from another uid {f.uid:#x} on its port", time.monotonic())
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
                    self._fault("counter-back", b, f"frame counter went back from {prev} to {c} (a replayed or stale "
                                "frame, or the board reset)", time.monotonic())
                    continue
            prev = c
        return keep

    def _refused(self, s, b: _Board) -> None:
        """Frames the client or the stream refused themselves (another uid, a counter not ahead), where they count them."""
        foreign = getattr(s.client, "foreign", None) or {}
        if foreign:
            uid = next(iter(foreign))
            self._fault("foreign-uid", b, f"frames from another uid {uid:#x} on its port", time.monotonic())
        if getattr(s, "replayed", 0):
            self._fault("counter-back", b, "frame counter went back (a replayed or stale frame, or the board reset)",
                        time.monotonic())

    def _crc_storm(self, s, b: _Board, now: float) -> None:
        errors = s.client.parser.crc_errors
        new, b.crc_seen = errors - b.crc_seen, errors
        b.crc.extend([now] * max(0, new))
        while b.crc and now - b.crc[0] > 1.0:
            b.crc.popleft()
        if len(b.crc) >= self.crc_storm:
            self._fault("crc-storm", b, f"CRC storm ({len(b.crc)} corrupt frames within 1 s); "
                        "check the cable and its shielding")


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    rx, tx = Connection(int(argv[0]), writable=False), Connection(int(argv[1]), readable=False)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the loop's: it stops the robot, then this reader
    cfg = rx.recv()
    reader = BoardsReader(cfg["design"], cfg["ports"], cfg["rate_hz"], cfg["noise_fraction"], cfg["max_excluded"],
                          cfg["silent_periods"], cfg["link_latency"], cfg["crc_storm"], cfg["client_kw"])
    state = beat = None
    try:
        try:
            report = reader.preflight(cfg["map_hash"], cfg["tare_frames"])
        except PreflightRefused as e:
            tx.send(("refused", str(e)))
            return 0
        except BoardError as e:
            tx.send(("board-error", str(e), e.kind))
            return 0
        state, beat = ForceFeed.attach(cfg["state"]), ForceFeed.attach(cfg["beat"])
        tx.send(("report", report, reader.excluded))
        reader.run(rx, tx, state, beat)
        reader.settle()
    finally:
        summary = reader.close()
        for feed in (state, beat):
            if feed is not None:
                feed.close()
    try:
        tx.send(("closed", summary))
    except OSError:  # the parent is gone
        pass
    return 0


if __name__ == "__main__":
    sys.exit(main())
