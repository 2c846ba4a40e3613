"""A board's part of the taxel map: channel -> taxel id, threshold (ADC counts), gain; canonical bytes + hash.

Layout (little-endian, PROTOCOL.md "Board config"): a 24-byte header (magic b"SKCF", format
version, entry count, board uid, channel capacity, reserved, board id) and one 12-byte entry per
mapped channel, sorted by channel (channel, flags, threshold counts, gain Q8.8, taxel id).
"""
from __future__ import annotations

import hashlib
import struct
from dataclasses import dataclass
from typing import Callable

import numpy as np

from skinsafe.core.skin.model import Board, DesignError, SkinDesign

MAGIC = b"SKCF"
FORMAT_VERSION = 1
HEADER = struct.Struct("<4sHHQHHI")
ENTRY = np.dtype([("channel", "<u2"), ("flags", "<u2"), ("threshold", "<u2"), ("gain", "<u2"), ("taxel_id", "<u4")])
FLAG_ENABLED = 1
GAIN_ONE = 256  # Q8.8


def default_sensor():
    """The FSR model shared by simulation and hardware (counts <-> newtons)."""
    from skinsafe.core.sim.sensor_model import FSRModel
    return FSRModel()


@dataclass(frozen=True)
class BoardConfig:
    """One board's configuration; `entries` is a structured array of dtype ENTRY sorted by channel."""

    uid: int
    board_id: int
    capacity: int
    entries: np.ndarray
    taxel_index: np.ndarray | None = None  # (n,) row of each entry in the design's taxels (host side only)

    def to_bytes(self) -> bytes:
        head = HEADER.pack(MAGIC, FORMAT_VERSION, len(self.entries), self.uid, self.capacity, 0, self.board_id)
        return head + self.entries.astype(ENTRY, copy=False).tobytes()

    @property
    def sha256(self) -> bytes:
        return hashlib.sha256(self.to_bytes()).digest()

    @property
    def channels(self) -> np.ndarray:
        return self.entries["channel"].astype(np.int64)

    @classmethod
    def from_bytes(cls, data: bytes, source: str = "board config") -> "BoardConfig":
        """Parse and check canonical bytes (the board runs this before committing to flash)."""
        if len(data) < HEADER.size:
            raise DesignError(f"{source}: {len(data)} bytes, shorter than the {HEADER.size}-byte header")
        magic, version, n, uid, capacity, _, board_id = HEADER.unpack_from(data)
        if magic != MAGIC:
            raise DesignError(f"{source}: magic {magic!r} is not {MAGIC!r}; this is not a skinsafe board config")
        if version != FORMAT_VERSION:
            raise DesignError(f"{source}: format version {version}, this reader knows {FORMAT_VERSION}; "
                              "deploy with a matching skinsafe")
        if len(data) != HEADER.size + n * ENTRY.itemsize:
            raise DesignError(f"{source}: {len(data)} bytes, expected {HEADER.size + n * ENTRY.itemsize} "
                              f"for {n} entries")
        entries = np.frombuffer(data, ENTRY, n, HEADER.size).copy()
        ch = entries["channel"].astype(np.int64)
        if n and ((np.diff(ch) <= 0).any() or ch[-1] >= capacity):
            raise DesignError(f"{source}: channels must be strictly increasing and below the capacity {capacity}")
        return cls(uid, board_id, capacity, entries)


def channel_rows(design: SkinDesign, board: Board) -> np.ndarray:
    """Rows of the design's taxels on `board`, sorted by channel (the order of the config's entries)."""
    rows = np.flatnonzero(design.taxels.board == board.id)
    return rows[np.argsort(design.taxels.channel[rows], kind="stable")]


def board_config(design: SkinDesign, board: Board, encode: Callable | None = None,
                 gains: np.ndarray | None = None) -> BoardConfig:
    """The config of one board of a (validated) design; thresholds in N become ADC counts via `encode`."""
    t = design.taxels
    rows = channel_rows(design, board)
    ids = t.ids[rows]
    if ids.size and (ids.min() < 0 or ids.max() > np.iinfo(np.uint32).max):
        bad = int(ids[(ids < 0) | (ids > np.iinfo(np.uint32).max)][0])
        raise DesignError(f"board {board.id} '{board.name}': taxel id {bad} does not fit the board's 32-bit id field; "
                          "renumber taxels to 0..4294967295")
    encode = encode or default_sensor().encode
    thr = np.asarray(encode(t.thresholds["force"][rows]))
    g = np.ones(len(rows)) if gains is None else np.asarray(gains, float)[rows]
    q = np.round(g * GAIN_ONE)  # Q8.8, round half to even (PROTOCOL.md "Gain")
    if not (np.isfinite(q) & (q >= 1) & (q <= 65535)).all():
        raise DesignError(f"board {board.id} '{board.name}': gains must round to 1/256 .. 65535/256 in Q8.8")
    entries = np.zeros(len(rows), ENTRY)
    entries["channel"] = t.channel[rows]
    entries["flags"] = np.where(t.enabled[rows], FLAG_ENABLED, 0)
    entries["threshold"] = np.clip(thr, 0, 65535)
    entries["gain"] = q
    entries["taxel_id"] = ids
    return BoardConfig(board.uid, board.id, board.capacity, entries, rows)


def board_configs(design: SkinDesign, encode: Callable | None = None, gains: np.ndarray | None = None,
                  ) -> list[BoardConfig]:
    """Configs of every board of a design (validated first), in the design's board order."""
    design.validate()
    encode = encode or default_sensor().encode
    return [board_config(design, b, encode, gains) for b in design.boards]


def diff(old: BoardConfig | None, new: BoardConfig) -> dict:
    """What a deploy would change: channels added, removed, re-mapped, re-thresholded or re-gained."""
    if old is None:
        return {"added": len(new.entries), "removed": 0, "changed": 0}
    a = {int(e["channel"]): e for e in old.entries}
    b = {int(e["channel"]): e for e in new.entries}
    changed = sum(1 for c in a.keys() & b.keys() if a[c].tobytes() != b[c].tobytes())
    return {"added": len(b.keys() - a.keys()), "removed": len(a.keys() - b.keys()), "changed": changed}
