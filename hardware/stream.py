"""Stream readings from the boards into taxel order, decoded to newtons by the shared FSR model.

Decoding is vectorised: a board's frames are joined and viewed as one structured array, ADC counts
go through a 65,536-entry table built once from `FSRModel.decode` (the same numbers as calling
it), and the mapped channels land in their taxel rows. Lost frames are found from gaps in the
boards' sample counters; corrupt frames are those whose CRC failed.
"""
from __future__ import annotations

import select
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from skinsafe.core.skin.model import SkinDesign
from skinsafe.hardware.board_config import board_configs, channel_rows, default_sensor
from skinsafe.hardware.client import BoardClient, BoardError
from skinsafe.hardware.protocol import FrameRun


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


@dataclass
class BoardState:
    board_id: int
    uid: int
    client: BoardClient
    n_channels: int
    channels: np.ndarray  # mapped channels on the board
    rows: np.ndarray  # their taxel rows in the design
    last_sample: int | None = None
    frames: int = 0
    lost: int = 0


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
    per_board: dict = field(default_factory=dict)  # board id -> (frames, lost, corrupt) totals


class SkinStream:
    """Readings of all boards of a design, in the design's taxel order.

    `ports` maps board id -> serial port. On start, each board's identity and active config hash
    are checked against the map (a board running another map would put readings on wrong taxels).
    """

    def __init__(self, design: SkinDesign, ports: dict[int, str], rate_hz: int = 100,
                 decode: Callable | None = None, verify: bool = True, **client_kw):
        self.design, self.rate_hz = design, rate_hz
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
                                     f"board '{b.name}' is uid {b.uid:#x} with {b.capacity}; check the port")
                if verify and info.config_hash != expected[b.id]:
                    raise BoardError(f"{c.port}: board '{b.name}' runs another config than this map "
                                     f"({info.config_hash.hex()[:8]} vs {expected[b.id].hex()[:8]}); "
                                     "run `skinsafe deploy` first")
                c.uid = b.uid
        except BaseException:
            self.close()
            raise

    def _map(self, board) -> tuple[np.ndarray, np.ndarray]:
        rows = channel_rows(self.design, board)
        return self.design.taxels.channel[rows].astype(np.int64), rows

    def start(self) -> None:
        for s in self.boards:
            s.client.start_stream(self.rate_hz)

    def stop(self) -> None:
        for s in self.boards:
            try:
                s.client.stop_stream()
            except BoardError:
                pass  # a board that stopped answering is not streaming to us any more

    def close(self) -> None:
        for s in self.boards:
            s.client.close()

    def __enter__(self) -> "SkinStream":
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop()
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
            if got:
                samples, forces = decode_frames(got, s.n_channels, s.channels, self.table)
                s.lost += self._lost(s, samples)
                s.frames += len(samples)
                self.force[s.rows] = forces[-1]
                peak[s.rows] = forces.max(axis=0)
                frames += len(samples)
            per_board[s.board_id] = (s.frames, s.lost, s.client.parser.crc_errors)
        lost = sum(v[1] for v in per_board.values())
        corrupt = sum(v[2] for v in per_board.values())
        return StreamUpdate(time.monotonic(), self.force, peak, frames, lost, corrupt, per_board)

    @staticmethod
    def _lost(s: BoardState, samples: np.ndarray) -> int:
        seq = samples.astype(np.int64)
        if s.last_sample is not None:
            seq = np.concatenate([[s.last_sample], seq])
        s.last_sample = int(seq[-1])
        d = np.diff(seq)
        return int(np.where(d > 0, d - 1, 0).sum())  # a counter that goes back: the board restarted (or wrapped)

    def run(self, callback: Callable[[StreamUpdate], object], seconds: float | None = None,
            period_s: float = 0.01) -> None:
        """Poll (waiting up to `period_s` for data) and hand each update to `callback`, until `seconds` pass
        or the callback returns False."""
        end = None if seconds is None else time.monotonic() + seconds
        while end is None or time.monotonic() < end:
            if callback(self.poll(period_s)) is False:
                return

