"""Stream readings from the boards into taxel order, decoded to newtons by the shared FSR model.

Decoding is vectorised: a board's frames are joined and viewed as one structured array, ADC counts
go through a 65,536-entry table built once from `FSRModel.decode` (the same numbers as calling
it), and the mapped channels land in their taxel rows. Each board's counter starts at 0 with the
stream and its stop answer says how many frames it sent, so every frame sent is counted once:
received, corrupt (its CRC failed) or lost (never arrived), before the first good frame and after
the last one included. A frame whose counter is not ahead of the last one taken (a replay, a frame
out of order) or is ahead of what the board can have sent since its start is dropped and counted as
`replayed`, never as loss; frames of another uid are refused (`foreign`); a link that fails marks
its board lost. Each is named in `StreamUpdate.faults`; the other boards stream on.
"""
from __future__ import annotations

import select
import time
from dataclasses import dataclass, field
from typing import Callable, NamedTuple

import numpy as np

from skinsafe.core.skin.model import SkinDesign
from skinsafe.hardware import protocol as P
from skinsafe.hardware.board_config import board_configs, channel_rows, default_sensor
from skinsafe.hardware.client import BITS_PER_BYTE, BoardClient, BoardError, identity_problem
from skinsafe.hardware.protocol import FrameRun, stream_frame_bytes


def decode_table(decode: Callable | None = None) -> np.ndarray:
    """(65536,) newtons for every possible uint16 count, from `decode` (default: FSRModel().decode)."""
    decode = decode or default_sensor().decode
    return np.asarray(decode(np.arange(65536, dtype=np.uint16)), dtype=np.float64)


def frame_dtype(n_channels: int) -> np.dtype:
    return np.dtype([("t_us", "<u8"), ("sample", "<u4"), ("n", "<u2"), ("over", "<u2"),
                     ("counts", "<u2", (n_channels,))])


def decode_frames(frames: list, n_channels: int, channels: np.ndarray, table: np.ndarray, stamps: bool = False
                  ) -> tuple[np.ndarray, ...]:
    """Stream frames (Frame or FrameRun) of one board -> (sample counters (F,), forces (F, len(channels)) in N)
    and, with `stamps`, the board's clock at each frame (F,), s.

    Frames of the wrong size (a board with another channel count) raise ValueError.
    """
    dt = frame_dtype(n_channels)
    parts = [f.payloads if isinstance(f, FrameRun) else np.frombuffer(f.payload, np.uint8)[None] for f in frames]
    bad = next((p.shape[1] for p in parts if p.shape[1] != dt.itemsize), None)
    if bad is not None:
        raise ValueError(f"stream frame of {bad} bytes, expected {dt.itemsize} for {n_channels} channels")
    rec = (parts[0] if len(parts) == 1 else np.concatenate(parts)).view(dt)[:, 0]
    counts = rec["counts"]
    if len(channels) != n_channels or (channels != np.arange(n_channels)).any():
        counts = counts[:, channels]
    return (rec["sample"], table[counts]) + ((rec["t_us"] * 1e-6,) if stamps else ())


def achievable_hz(baud: int, n_channels: int) -> float:
    """Stream frames per second a UART link at `baud` (8N1) carries for a board of `n_channels`."""
    return baud / (BITS_PER_BYTE * stream_frame_bytes(n_channels))


class BoardStats(NamedTuple):
    """A board's stream so far; every frame the board sent is counted once in received, lost or corrupt
    (corrupt: failed its CRC; lost: never arrived), resynced counts the parser's resynchronisations;
    replayed: frames dropped for a counter not ahead of the last one (or ahead of the board's clock);
    foreign: frames of other uids refused on this board's link."""

    received: int
    lost: int
    corrupt: int
    resynced: int
    replayed: int = 0
    foreign: int = 0


class StreamFault(NamedTuple):
    """A named stream fault: `kind` is "link lost", "replayed" (frames dropped for their counter) or
    "foreign uid" (frames of another board refused); `text` names the board, its port and what happened."""

    board_id: int
    kind: str
    text: str

    def __str__(self) -> str:
        return self.text


COUNTER = 1 << 32  # the sample counter wraps here
CLOCK_SLACK = 1.01, 0.05  # a board's counter may run this much (factor, seconds) ahead of the host's clock


@dataclass
class BoardState:
    board_id: int
    uid: int
    client: BoardClient
    n_channels: int
    channels: np.ndarray  # mapped channels on the board
    rows: np.ndarray  # their taxel rows in the design
    last_sample: int | None = None  # the last sample counter received (u32)
    sent: int = 0  # frames the board sent, as far as known (unwrapped last counter + 1, or the stop answer)
    frames: int = 0
    crc0: int = 0  # parser counters when the stream started
    resync0: int = 0
    started: bool = False
    stopped: bool = False
    end_counter: int | None = None  # the stop answer, until the frames before it are read
    malformed: int = 0  # frames with a valid CRC but the wrong size (counted as corrupt)
    rate_hz: int = 0  # the stream's rate; with t_start it bounds how far the counter can be
    t_start: float | None = None  # host clock when the start was first sent
    start_sent: bool = False  # a start went out (it may have taken effect even if its answer was lost)
    replayed: int = 0  # frames dropped: counter not ahead of the last one taken, or ahead of the board's clock
    lost_link: str | None = None  # why the link is gone (the board reads NaN from then on)
    last_counter: int | None = None  # the last dropped counter, for the fault's text
    foreign_named: dict = field(default_factory=dict)  # uid -> refused frames already named in a fault

    def count(self, samples: np.ndarray, now: float | None = None) -> np.ndarray:
        """Account for received sample counters; returns which frames to take (bool per frame).

        The counter starts at 0 with the stream and wraps at 2^32: each is unwrapped to the nearest value
        around the last one taken, so frames before the first good one (and between two good ones) count as
        sent. A frame not ahead of the last one taken (a replay, out of order) is dropped, and so is one
        ahead of what the board can have sent by `now` at `rate_hz` since `t_start` (when both are known);
        both count as `replayed`, never as sent or lost."""
        last = self.sent - 1  # the last counter taken, unwrapped (-1: none yet)
        if len(samples) == 1 and now is None:  # a reader's usual pass: one frame, in plain integers
            c = int(samples[0])
            step = (c - last) % COUNTER
            u = last + (step - COUNTER if step >= COUNTER // 2 else step)
            if u > last:
                self.sent, self.last_sample, self.frames = u + 1, c, self.frames + 1
            else:
                self.replayed, self.last_counter = self.replayed + 1, c
            return np.array([u > last])
        step = (samples.astype(np.int64) - last) % COUNTER
        u = last + np.where(step >= COUNTER // 2, step - COUNTER, step)
        take = np.ones(len(u), bool)
        if now is not None and self.rate_hz and self.t_start is not None:
            take &= u <= self.rate_hz * ((now - self.t_start) * CLOCK_SLACK[0] + CLOCK_SLACK[1])
        ahead = np.maximum.accumulate(np.where(take, u, last))  # the highest counter taken up to each frame
        take &= u > np.concatenate([[last], ahead[:-1]])
        n = int(take.sum())
        if n < len(u):
            self.replayed += len(u) - n
            self.last_counter = int(samples[~take][-1])
        if n:
            self.sent = int(u[take][-1]) + 1
            self.last_sample = int(samples[take][-1])
            self.frames += n
        return take

    def end(self, counter: int) -> None:
        """The stop answer (the board's next counter): frames after the last good one count as sent too
        (a stop answer behind the frames taken changes nothing)."""
        step = (counter - self.sent) % COUNTER
        if step < COUNTER // 2:
            self.sent += step
            self.last_sample = (counter - 1) % COUNTER

    def stats(self) -> BoardStats:
        p = self.client.parser
        missing = max(0, self.sent - self.frames)
        corrupt = min(p.crc_errors - self.crc0 + self.malformed, missing)
        return BoardStats(self.frames, missing - corrupt, corrupt, p.resyncs - self.resync0, self.replayed,
                          sum(self.client.foreign.values()))


@dataclass
class StreamUpdate:
    """What arrived since the previous poll. `force` holds the latest reading per taxel (NaN: none yet;
    the stream's live array, copy it to keep), `peak` the largest over every frame of this poll (NaN:
    no frame), so no contact between polls is missed."""

    t: float
    force: np.ndarray
    peak: np.ndarray
    frames: int
    lost: int
    corrupt: int
    resynced: int = 0
    per_board: dict = field(default_factory=dict)  # board id -> BoardStats totals
    faults: list[StreamFault] = field(default_factory=list)  # since the previous poll


class SkinStream:
    """Readings of all boards of a design, in the design's taxel order.

    `ports` maps board id -> serial port. On opening, each board's identity (uid, firmware major,
    channels) and active config hash are checked against the map (a board running another map would
    put readings on wrong taxels), and a board already streaming is refused (its counter and rate are
    another host's), or with `restart` stopped first. Starting is all or nothing: a board that fails
    to start, and every board already started, is sent a stop.
    """

    def __init__(self, design: SkinDesign, ports: dict[int, str], rate_hz: int = 100,
                 decode: Callable | None = None, verify: bool = True, restart: bool = False, **client_kw):
        if not 1 <= int(rate_hz) <= 65535:
            raise ValueError(f"stream rate {rate_hz} Hz: the protocol carries 1..65535 Hz")
        self.design, self.rate_hz = design, int(rate_hz)
        self.table = decode_table(decode)
        n = design.n_taxels
        self.force = np.full(n, np.nan)
        self.boards: list[BoardState] = []
        expected = {c.board_id: c.sha256 for c in board_configs(design)} if verify else {}
        problems: list[BoardError] = []
        try:
            for b in design.boards:
                if b.id not in ports:
                    continue
                try:
                    c = BoardClient(ports[b.id], **client_kw)
                    self.boards.append(BoardState(b.id, b.uid, c, b.capacity, *self._map(b)))
                    self._check(c, b, expected.get(b.id), restart)
                except BoardError as e:
                    if e.kind == "cancelled":
                        raise
                    problems.append(e)  # every board is checked, so each refusal is named at once
            if problems:
                raise BoardError("\n".join(map(str, problems)), kind=problems[0].kind, uid=problems[0].uid)
        except BaseException:
            self.close()
            raise

    def _check(self, c: BoardClient, b, expected: bytes | None, restart: bool) -> None:
        """Refuse (BoardError) a board that is not the map's, runs another config, cannot stream at the rate,
        or is already streaming (unless `restart`: then it is stopped)."""
        info = c.identify()
        why = identity_problem(info, b)
        if why:
            raise BoardError(f"{c.port}: board '{b.name}' refused: {why}", kind="incompatible", uid=info.uid)
        if info.flags & P.FLAG_STREAMING and restart:
            c.stop_stream()
        elif info.flags & P.FLAG_STREAMING:
            raise BoardError(f"{c.port}: board '{b.name}' uid {b.uid:#x} is already streaming (another program "
                             "reads it, or a host ended without stopping it); stop that, reset the board, or "
                             "restart it (`skinsafe stream --restart`)", kind="incompatible", uid=info.uid)
        if expected is not None and info.config_hash != expected:
            raise BoardError(f"{c.port}: board '{b.name}' runs another config than this map "
                             f"({info.config_hash.hex()[:8]} vs {expected.hex()[:8]}); run `skinsafe deploy` first",
                             kind="incompatible", uid=info.uid)
        if self.rate_hz > info.max_rate_hz:
            raise BoardError(f"{c.port}: board '{b.name}' streams at most {info.max_rate_hz} Hz, asked "
                             f"{self.rate_hz}; lower --rate", kind="incompatible", uid=info.uid)

    def _map(self, board) -> tuple[np.ndarray, np.ndarray]:
        rows = channel_rows(self.design, board)
        return self.design.taxels.channel[rows].astype(np.int64), rows

    def start(self) -> None:
        """Start every board; if one fails, stop it and those already started, and raise its BoardError."""
        for s in self.boards:
            s.crc0, s.resync0 = s.client.parser.crc_errors, s.client.parser.resyncs
            s.rate_hz, s.t_start, s.start_sent = self.rate_hz, time.monotonic(), True
            try:
                s.client.start_stream(self.rate_hz)
            except BoardError:
                self.stop()  # the failed one too: its start may have taken effect with its answer lost
                raise
            s.started = True

    def stop(self) -> dict[int, str]:
        """Stop every board a start was sent to and account for its last frames; board id -> problem for
        those that did not confirm (their stop is not certain)."""
        problems = {}
        for s in self.boards:
            if not s.start_sent or s.stopped:
                continue
            if s.lost_link:
                problems[s.board_id] = s.lost_link
                continue
            s.client.cancel = None  # a stop is sent even after Ctrl-C
            try:
                s.end_counter = s.client.stop_stream()
                s.stopped = True
            except BoardError as e:
                problems[s.board_id] = str(e)
        self.poll(0.0)  # the frames sent before the stop answers
        for s in self.boards:
            if s.end_counter is not None:
                s.end(s.end_counter)
                s.end_counter = None
        return problems

    def close(self) -> None:
        for s in self.boards:
            s.client.close()

    def __enter__(self) -> "SkinStream":
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        try:
            self.stop()
        finally:
            self.close()

    def poll(self, max_wait: float = 0.01) -> StreamUpdate:
        """Read and decode everything the boards sent since the last poll. Never raises for a board's link:
        a board whose link fails is named in `faults` and reads NaN from then on."""
        peak = np.full(self.design.n_taxels, np.nan)
        frames = 0
        per_board, faults = {}, []
        live = [s for s in self.boards if not s.lost_link]
        if max_wait > 0 and live:
            select.select([s.client.ser.fileno() for s in live], [], [], max_wait)
        for s in self.boards:
            before = s.stats()
            if not s.lost_link:
                try:
                    got = s.client.read_stream(0.0)
                except BoardError as e:
                    s.lost_link, got = str(e), []
                    self.force[s.rows] = np.nan
                    faults.append(StreamFault(s.board_id, "link lost",
                                              f"{self._name(s)}: {s.lost_link.split(': ', 1)[-1]}"))
                frames += self._take(s, got, time.monotonic(), peak)  # after the read: every frame was sent by then
            per_board[s.board_id] = st = s.stats()
            if st.replayed > before.replayed:
                faults.append(StreamFault(s.board_id, "replayed", f"{self._name(s)}: {st.replayed - before.replayed} "
                                          f"replayed or out-of-order frames dropped (counter {s.last_counter}, "
                                          f"last taken {s.last_sample})"))
            for uid, n in s.client.foreign.items():
                if n > s.foreign_named.get(uid, 0):
                    faults.append(StreamFault(s.board_id, "foreign uid", f"{self._name(s)}: "
                                              f"{n - s.foreign_named.get(uid, 0)} frames from uid {uid:#x} refused "
                                              "(another board on this link?)"))
                    s.foreign_named[uid] = n
        total = [sum(v[k] for v in per_board.values()) for k in (1, 2, 3)]
        return StreamUpdate(time.monotonic(), self.force, peak, frames, *total, per_board, faults)

    def _name(self, s: BoardState) -> str:
        return f"board {s.board_id} uid {s.uid:#x} on {s.client.port}"

    def _take(self, s: BoardState, got: list, now: float, peak: np.ndarray) -> int:
        """Decode one board's frames into `force` and `peak`; frames of the wrong size count as corrupt,
        replayed ones are dropped. Returns the frames taken."""
        size = frame_dtype(s.n_channels).itemsize
        bad = [f for f in got if (f.payloads.shape[1] if isinstance(f, FrameRun) else len(f.payload)) != size]
        if bad:  # a frame with a valid CRC but the wrong size for this board: the firmware is wrong
            s.malformed += sum(len(f.seqs) if isinstance(f, FrameRun) else 1 for f in bad)
            got = [f for f in got if not any(f is b for b in bad)]
        if not got:
            return 0
        samples, forces = decode_frames(got, s.n_channels, s.channels, self.table)
        take = s.count(samples, now)
        if not take.any():
            return 0
        forces = forces[take]
        self.force[s.rows] = forces[-1]
        peak[s.rows] = forces.max(axis=0)
        return len(forces)

    def run(self, callback: Callable[[StreamUpdate], object], seconds: float | None = None,
            period_s: float = 0.01) -> None:
        """Poll (waiting up to `period_s` for data) and hand each update to `callback`, until `seconds` pass
        or the callback returns False."""
        end = None if seconds is None else time.monotonic() + seconds
        while end is None or time.monotonic() < end:
            if callback(self.poll(period_s)) is False:
                return
