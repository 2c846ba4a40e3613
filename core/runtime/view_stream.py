"""The live view stream: the runtime's newest tick for viewers (the web page, Blender), over TCP, off the loop.

A publisher thread (`ViewPublisher`) reads the newest tick at `rate_hz` (30) and sends it to every
connected viewer. A viewer that has not taken the last message yet (its socket buffer full) misses the
ticks until it has: frames are dropped, per viewer and counted, never queued. stdlib + numpy only:
Blender's add-on reads it too.

`skinsafe run --view` runs the publisher in its own process, fed through shared memory
(core/runtime/view_share.py).

Wire format (every message; little-endian):

    b"SKV1" | u32 header_len | u32 blob_len | header: UTF-8 JSON | blob

- the first message on a connection, header `{"kind": "hello", "n_taxels": N, "joint_names": [...],
  "boards": {"<uid>": "<name>"}, "map": path, "map_sha256": hex, "period_s": s, "source": "run" | "record"
  | "experiment", "board_period_s": s between a board's frames (0: unknown)}`, blob: the N taxel ids (int64) in the map's order;
- then one per published tick, header `{"kind": "frame", "seq": k, "t": robot clock s, "q": [...],
  "command": [...], "planned": [...] | null, "retracting": bool, "pool": [taxel index, ...] (highest
  priority first), "potential": f, "speed_factor": |command| / |planned|, "flags": [...], "stop": reason
  or "", "board_age_ms": {"<uid>": ms}, "frames_lost": n}`, blob: the N taxel forces (float32, newtons;
  NaN where a taxel has no fresh reading).

`ViewClient` connects, and `poll()` (never blocks) returns the newest complete frame received since
the last call, dropping older ones: the reader keeps up however slowly it draws.
"""
from __future__ import annotations

import json
import math
import selectors
import socket
import struct
import threading
import time

import numpy as np

MAGIC = b"SKV1"
HEAD = struct.Struct("<4sII")
MAX_HEADER = 1 << 20  # bytes: a header longer than this is no view stream
DEFAULT_PORT = 8790


class StreamError(ValueError):
    """Bytes that are not a view stream, or a lost connection: one line naming what."""


def encode(header: dict, blob: bytes = b"") -> bytes:
    h = json.dumps(header, separators=(",", ":"), allow_nan=True).encode()
    return HEAD.pack(MAGIC, len(h), len(blob)) + h + blob


def _floats(x) -> list | None:
    return None if x is None else [float(v) for v in x]


def hello(n_taxels: int, ids, joint_names, boards: dict, map_path: str = "", map_sha256: str = "",
          period_s: float = 0.0, source: str = "run", board_period_s: float = 0.0) -> bytes:
    return encode({"kind": "hello", "n_taxels": int(n_taxels), "joint_names": list(joint_names),
                   "boards": {str(k): str(v) for k, v in boards.items()}, "map": str(map_path),
                   "map_sha256": map_sha256, "period_s": float(period_s), "source": source,
                   "board_period_s": float(board_period_s)},
                  np.ascontiguousarray(ids, "<i8").tobytes())


def frame_header(seq: int, f) -> dict:
    """A `Tick`'s frame header (module docstring)."""
    ages = f.board_age_s or {}
    return {"kind": "frame", "seq": seq, "t": float(f.t), "q": _floats(f.q), "command": _floats(f.command),
            "planned": _floats(f.planned), "retracting": bool(f.retracting),
            "pool": [] if f.pool_taxels is None else [int(i) for i in f.pool_taxels],
            "potential": float(f.potential), "speed_factor": float(f.speed_factor), "flags": list(f.flags),
            "stop": f.stop, "board_age_ms": {str(k): round(v * 1e3, 3) for k, v in ages.items()},
            "frames_lost": int(f.frames_lost)}


def frame_message(seq: int, f) -> bytes:
    """One `Tick` as a stream message."""
    n = len(f.force) if f.force is not None else 0
    force = np.full(n, np.nan, "<f4") if f.force is None else np.asarray(f.force, "<f4")
    return encode(frame_header(seq, f), force.tobytes())


def decode(buf: bytearray) -> tuple[list[tuple[dict, bytes]], int]:
    """The complete messages at the start of `buf` and how many bytes they took."""
    out, at = [], 0
    while len(buf) - at >= HEAD.size:
        magic, hl, bl = HEAD.unpack_from(buf, at)
        if magic != MAGIC or hl > MAX_HEADER:
            raise StreamError(f"not a skinsafe view stream (magic {bytes(magic)!r}); is this the port of "
                              "`skinsafe run --view` or `skinsafe view --publish`?")
        end = at + HEAD.size + hl + bl
        if len(buf) < end:
            break
        header = json.loads(bytes(buf[at + HEAD.size:at + HEAD.size + hl]))
        out.append((header, bytes(buf[end - bl:end])))
        at = end
    return out, at


class ViewPublisher:
    """Publishes the newest frame of `latest()` (a tap's `Frame`, or an encoded message: `SharedFrames.newest`) to
    every viewer connected to (host, port).

    `hello_message` is sent to each viewer first (see `hello`). Port 0 picks a free one (`address`)."""

    def __init__(self, latest, hello_message: bytes, host: str = "127.0.0.1", port: int = DEFAULT_PORT,
                 rate_hz: float = 30.0):
        if not (math.isfinite(rate_hz) and 0 < rate_hz <= 1000):
            raise ValueError(f"view rate {rate_hz} Hz: give 0 < rate <= 1000")
        self.latest, self.hello, self.period = latest, hello_message, 1.0 / rate_hz
        self.server = socket.create_server((host, port), reuse_port=False)
        self.server.setblocking(False)
        self.address = self.server.getsockname()[:2]
        self.sel = selectors.DefaultSelector()
        self.sel.register(self.server, selectors.EVENT_READ)
        self.pending: dict[socket.socket, memoryview] = {}
        self.sent = self.dropped = self.viewers = 0
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._work, name="view-publisher", daemon=True)
        self.thread.start()

    def close(self) -> dict:
        self._stop.set()
        self.thread.join(2.0)
        for s in list(self.pending):
            s.close()
        self.server.close()
        self.sel.close()
        return {"sent": self.sent, "dropped": self.dropped, "viewers": self.viewers}

    def _work(self) -> None:
        last, seq, due = None, 0, time.monotonic()
        while not self._stop.is_set():
            for key, events in self.sel.select(max(0.0, due - time.monotonic())):
                if key.fileobj is self.server:
                    self._accept()
                elif events & selectors.EVENT_WRITE:
                    self._flush(key.fileobj)
                else:  # a viewer sends nothing: readable means it hung up
                    self._drop(key.fileobj)
            if time.monotonic() < due:
                continue
            due = max(due + self.period, time.monotonic() - self.period)
            if not self.pending:  # nobody to send it to: not even read (SharedFrames: the loop stops copying)
                continue
            f = self.latest()
            if f is None or f is last:
                continue
            last, seq = f, seq + 1
            msg = memoryview(f if isinstance(f, bytes) else frame_message(seq, f))
            for s, left in list(self.pending.items()):
                if len(left):  # still sending an older frame: this one is dropped for it
                    self.dropped += 1
                    continue
                self.pending[s] = msg
                self._flush(s)

    def _accept(self) -> None:
        try:
            s, _ = self.server.accept()
        except OSError:
            return
        s.setblocking(False)
        s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.pending[s] = memoryview(self.hello)
        self.viewers += 1
        self.sel.register(s, selectors.EVENT_READ)
        self._flush(s)

    def _flush(self, s) -> None:
        left = self.pending.get(s)
        if left is None:
            return
        try:
            n = s.send(left) if len(left) else 0
        except BlockingIOError:
            n = 0
        except OSError:
            return self._drop(s)
        self.pending[s] = left = left[n:]
        if n:
            self.sent += not len(left)
        self.sel.modify(s, selectors.EVENT_READ | (selectors.EVENT_WRITE if len(left) else 0))

    def _drop(self, s) -> None:
        self.pending.pop(s, None)
        try:
            self.sel.unregister(s)
        except (KeyError, ValueError):
            pass
        s.close()


class ViewClient:
    """A viewer's end: `poll()` never blocks and returns the newest frame (header, forces) or None."""

    def __init__(self, host: str, port: int, timeout_s: float = 5.0):
        try:
            self.sock = socket.create_connection((host, port), timeout=timeout_s)
        except OSError as e:
            raise StreamError(f"cannot connect to the view stream at {host}:{port} ({e.strerror or e}); start "
                              "`skinsafe run ... --view` or `skinsafe view FILE.mcap --publish` first") from None
        self.sock.setblocking(False)
        self.buf = bytearray()
        self.hello: dict | None = None
        self.ids: np.ndarray | None = None
        self.frames = self.skipped = 0
        self.closed = False
        deadline = time.monotonic() + timeout_s
        while self.hello is None:  # the hello comes first, at once
            if time.monotonic() > deadline:
                self.close()
                raise StreamError(f"{host}:{port}: no hello within {timeout_s:g} s; not a skinsafe view stream")
            self.poll()
            if self.closed:
                raise StreamError(f"{host}:{port}: the stream closed before its hello")
            time.sleep(0.01)

    def poll(self) -> tuple[dict, np.ndarray] | None:
        while not self.closed:
            try:
                chunk = self.sock.recv(1 << 20)
            except (BlockingIOError, InterruptedError):
                break
            except OSError:
                chunk = b""
            if not chunk:
                self.closed = True
                break
            self.buf += chunk
        messages, used = decode(self.buf)
        del self.buf[:used]
        newest = None
        for header, blob in messages:
            if header.get("kind") == "hello":
                self.hello, self.ids = header, np.frombuffer(blob, "<i8")
            elif header.get("kind") == "frame":
                if newest is not None:
                    self.skipped += 1
                newest = (header, np.frombuffer(blob, "<f4").astype(float))
                self.frames += 1
        return newest

    def close(self) -> None:
        self.closed = True
        self.sock.close()
