"""Stream readings from the boards into taxel order, decoded to newtons by the shared FSR model.

Decoding is vectorised: a board's frames are joined and viewed as one structured array, ADC counts
go through a 65,536-entry table built once from `FSRModel.decode` (the same numbers as calling
it), and the mapped channels land in their taxel rows. Each board's counter starts at 0 with the
stream and its stop answer says how many frames it sent, so every frame sent is counted once:
received, corrupt (its CRC failed) or lost (never arrived), before the first good frame and after
the last one included.
"""
from __future__ import annotations

import select
import time
from dataclasses import dataclass, field
from typing import Callable, NamedTuple

import numpy as np

from skinsafe.core.skin.model import SkinDesign
from skinsafe.hardware.board_config import board_configs, channel_rows, default_sensor
from skinsafe.hardware.client import BITS_PER_BYTE, BoardClient, BoardError
from skinsafe.hardware.protocol import FrameRun, stream_frame_bytes


def decode_table(decode: Callable | None = None) -> np.ndarray:
    """(65536,) newtons for every possible uint16 count, from `decode` (default: FSRModel().decode)."""
    decode = decode or default_sensor().decode
    return np.asarray(decode(np.arange(65536, dtype=np.uint16)), dtype=np.float64)


def frame_dtype(n_channels: int) -> np.dtype:
    return np.dtype([("t_us", "<u8"), ("sample", "<u4"), ("n", "<u2"), ("over", "<u2"),
                     ("counts", "<u2", (n_channels,))])


def decode_frames(frames: list, n_channels: int, channels: np.ndarray, table: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Stream frames (Frame or FrameRun) of one board -> (sample counters (F,), forces (F, len(channels)) in N).

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
    return rec["sample"], table[counts]


def achievable_hz(baud: int, n_channels: int) -> float:
    """Stream frames per second a UART link at `baud` (8N1) carries for a board of `n_channels`."""
    return baud / (BITS_PER_BYTE * stream_frame_bytes(n_channels))


class BoardStats(NamedTuple):
    """A board's stream so far; every frame the board sent is counted once in received, lost or corrupt
    (corrupt: failed its CRC; lost: never arrived), resynced counts the parser's resynchronisations."""

    received: int
    lost: int
    corrupt: int
    resynced: int


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

    def count(self, samples: np.ndarray) -> None:
        """Account for received sample counters; the counter starts at 0 with the stream and wraps at 2^32,
        so frames before the first good one (and between two good ones) count as sent."""
        seq = samples.astype(np.int64)
        prev = -1 if self.last_sample is None else self.last_sample
        self.sent += int((np.diff(np.concatenate([[prev], seq])) & 0xFFFFFFFF).sum())
        self.last_sample = int(seq[-1])
        self.frames += len(seq)

    def end(self, counter: int) -> None:
        """The stop answer (the board's next counter): frames after the last good one count as sent too."""
        prev = -1 if self.last_sample is None else self.last_sample
        self.sent += (counter - prev - 1) & 0xFFFFFFFF
        self.last_sample = (counter - 1) & 0xFFFFFFFF

    def stats(self) -> BoardStats:
        p = self.client.parser
        missing = max(0, self.sent - self.frames)
        corrupt = min(p.crc_errors - self.crc0 + self.malformed, missing)
        return BoardStats(self.frames, missing - corrupt, corrupt, p.resyncs - self.resync0)


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


class SkinStream:
    """Readings of all boards of a design, in the design's taxel order.

    `ports` maps board id -> serial port. On opening, each board's identity and active config hash
    are checked against the map (a board running another map would put readings on wrong taxels).
    Starting is all or nothing: a board that fails to start stops the boards already started.
    """

    def __init__(self, design: SkinDesign, ports: dict[int, str], rate_hz: int = 100,
                 decode: Callable | None = None, verify: bool = True, **client_kw):
        if not 1 <= int(rate_hz) <= 65535:
            raise ValueError(f"stream rate {rate_hz} Hz: the protocol carries 1..65535 Hz")
        self.design, self.rate_hz = design, int(rate_hz)
        self.table = decode_table(decode)
        n = design.n_taxels
        self.force = np.full(n, np.nan)
        self.boards: list[BoardState] = []
        expected = {c.board_id: c.sha256 for c in board_configs(design)} if verify else {}
        try:
            for b in design.boards:
                if b.id not in ports:
                    continue
                c = BoardClient(ports[b.id], **client_kw)
                self.boards.append(BoardState(b.id, b.uid, c, b.capacity, *self._map(b)))
                info = c.identify()
                if info.uid != b.uid or info.n_channels != b.capacity:
                    raise BoardError(f"{c.port}: board uid {info.uid:#x} with {info.n_channels} channels, the map's "
                                     f"board '{b.name}' is uid {b.uid:#x} with {b.capacity}; check the port",
                                     kind="incompatible")
                if verify and info.config_hash != expected[b.id]:
                    raise BoardError(f"{c.port}: board '{b.name}' runs another config than this map "
                                     f"({info.config_hash.hex()[:8]} vs {expected[b.id].hex()[:8]}); "
                                     "run `skinsafe deploy` first", kind="incompatible")
                if self.rate_hz > info.max_rate_hz:
                    raise BoardError(f"{c.port}: board '{b.name}' streams at most {info.max_rate_hz} Hz, asked "
                                     f"{self.rate_hz}; lower --rate", kind="incompatible")
        except BaseException:
            self.close()
            raise

    def _map(self, board) -> tuple[np.ndarray, np.ndarray]:
        rows = channel_rows(self.design, board)
        return self.design.taxels.channel[rows].astype(np.int64), rows

    def start(self) -> None:
        """Start every board; if one fails, stop those already started and raise its BoardError."""
        for s in self.boards:
            s.crc0, s.resync0 = s.client.parser.crc_errors, s.client.parser.resyncs
            try:
                s.client.start_stream(self.rate_hz)
            except BoardError:
                self.stop()
                raise
            s.started = True

    def stop(self) -> dict[int, str]:
        """Stop every started board and account for its last frames; board id -> problem for those that
        did not confirm (their stop is not certain)."""
        problems = {}
        for s in self.boards:
            if not s.started or s.stopped:
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
        """Read and decode everything the boards sent since the last poll."""
        peak = np.full(self.design.n_taxels, np.nan)
        frames = 0
        per_board = {}
        if max_wait > 0 and not any(s.client.ser.in_waiting for s in self.boards):
            select.select([s.client.ser.fileno() for s in self.boards], [], [], max_wait)
        for s in self.boards:
            got = s.client.read_stream(0.0)
            size = frame_dtype(s.n_channels).itemsize
            bad = [f for f in got if (f.payloads.shape[1] if isinstance(f, FrameRun) else len(f.payload)) != size]
            if bad:  # a frame with a valid CRC but the wrong size for this board: the firmware is wrong
                s.malformed += sum(len(f.seqs) if isinstance(f, FrameRun) else 1 for f in bad)
                got = [f for f in got if not any(f is b for b in bad)]
            if got:
                samples, forces = decode_frames(got, s.n_channels, s.channels, self.table)
                s.count(samples)
                self.force[s.rows] = forces[-1]
                peak[s.rows] = forces.max(axis=0)
                frames += len(samples)
            per_board[s.board_id] = s.stats()
        total = [sum(v[k] for v in per_board.values()) for k in (1, 2, 3)]
        return StreamUpdate(time.monotonic(), self.force, peak, frames, *total, per_board)

    def run(self, callback: Callable[[StreamUpdate], object], seconds: float | None = None,
            period_s: float = 0.01) -> None:
        """Poll (waiting up to `period_s` for data) and hand each update to `callback`, until `seconds` pass
        or the callback returns False."""
        end = None if seconds is None else time.monotonic() + seconds
        while end is None or time.monotonic() < end:
            if callback(self.poll(period_s)) is False:
                return
