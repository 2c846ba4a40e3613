"""One emulated interface board on a pseudo-terminal: link faults, flash file, protocol handler, stream clock.

Each board owns a pty (`os.openpty`); the host opens the slave path with pyserial like
`/dev/ttyUSB0`. Flash is a file written atomically on commit. Faults (dropped bytes, flipped bits,
delays, a reset in the middle of a transfer, truncated answers, a wrong firmware or protocol version;
and the firmware and wiring faults a host must survive: replayed older frames, frames of another
board, lost stream-start answers, an unplugged cable, a board left streaming, a commit answer
without its hash, a lost flash write, a lying config length) are injected on the emulated link,
each board from its own seed. At `baud`, the board paces its link
at 10 bits per byte (8N1), so a pty takes as long as a real UART would. `NotABoard` is a device on a
pty that answers text, as a modem or a GPS receiver on the same USB hub would.
"""
from __future__ import annotations

import collections
import hashlib
import os
import select
import threading
import time
import tty
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from skinsafe.core.skin.files import atomic_write
from skinsafe.core.skin.model import DesignError
from skinsafe.hardware import protocol as P
from skinsafe.hardware.board_config import GAIN_ONE, BoardConfig, default_sensor

BITS_PER_BYTE = 10  # 8N1: start + 8 data + stop


@dataclass
class Faults:
    """Link and board faults; probabilities are per byte, in both directions."""

    drop: float = 0.0
    flip: float = 0.0
    delay_s: float = 0.0  # added before a response ...
    delay_p: float = 1.0  # ... with this probability
    reset_at_chunk: int | None = None  # reboot (no answer) when the k-th config chunk arrives (1-based) ...
    resets: int = 1  # ... this many times (-1: on every transfer)
    malformed: float = 0.0  # probability an answer is cut short at a random byte (framed and CRC'd correctly)
    seed: int = 0  # the run seed; each board draws from its own stream derived from it and its uid
    old_frames: float = 0.0  # probability a stream frame is followed by a re-send of an older one (its old counter)
    foreign_frames: float = 0.0  # probability a stream frame is followed by one of another board (FOREIGN_BIT uid)
    lost_start_answers: int = 0  # the first K stream-start answers are lost (the board starts all the same)
    unplug_after: int = 0  # the cable is pulled after this many stream frames (the pty closes); 0: never
    streaming: int = 0  # the board boots streaming at this rate, Hz (a host started it and went away); 0: idle
    hashless_commit: bool = False  # a commit is answered "ok" without the committed config's hash
    flash_write_lost: bool = False  # the flash write is silently lost: RAM runs the new config, flash keeps the old
    config_len: int | None = None  # identify reports this config length; reads past the config return erased 0xFF


FOREIGN_BIT = 1 << 40  # a foreign frame's uid: the board's own with this bit flipped


def board_seed(run_seed: int, uid: int) -> np.random.SeedSequence:
    """A board's own fault seed: one run seed, independent streams per board (independent of board order)."""
    return np.random.SeedSequence([run_seed, uid & 0xFFFFFFFF, uid >> 32])


@dataclass
class BoardSpec:
    uid: int
    n_channels: int
    firmware: tuple[int, int, int] = (1, 0, 0)
    protocol: int = P.PROTOCOL_VERSION
    max_chunk: int = 1024
    max_rate_hz: int = 2000
    faults: Faults = field(default_factory=Faults)


class EmulatedBoard:
    """One board: a pty, a flash file, a protocol handler and a streaming clock."""

    BOOT_S = 0.05
    OVERRUN_S = 0.5  # how long a full link may block a send before the rest of the frame is dropped

    def __init__(self, spec: BoardSpec, flash_path: str | Path, baud: int | None = None,
                 replay: np.ndarray | None = None, encode=None, feed=None):
        self.spec, self.flash_path, self.baud = spec, Path(flash_path), baud
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)
        os.set_blocking(self.master, False)
        self.port = os.ttyname(self.slave)
        self.rng = np.random.default_rng(board_seed(spec.faults.seed, spec.uid))
        self.encode = encode or default_sensor().encode
        self.replay = replay
        self.feed = feed  # () -> (n_channels,) forces in N, e.g. from a simulation's ForceFeed
        self.resets_left = spec.faults.resets
        self.chunks_seen = 0
        self.tx_dropped = 0
        self.start_answers_lost = 0
        self.sent_frames: collections.deque[bytes] = collections.deque(maxlen=16)  # for old_frames
        self.foreign_sample = 0
        self.closed = False
        self._boot()
        if spec.faults.streaming:  # left streaming by an earlier host
            self.streaming, self.rate, self.next_tick = True, spec.faults.streaming, time.monotonic()

    # -- state -------------------------------------------------------------------------------
    def _boot(self) -> None:
        self.boots = getattr(self, "boots", -1) + 1
        self.parser = P.FrameParser(P.host_max_payload(self.spec.max_chunk, self.spec.n_channels))
        self.streaming, self.rate, self.sample = False, 0, 0
        self.staging = None
        self.t0 = time.monotonic()
        self.wire_rx = self.wire_tx = 0.0
        self.config_bytes, self.config = b"", None
        if self.flash_path.exists():
            data = self.flash_path.read_bytes()
            try:
                cfg = BoardConfig.from_bytes(data, str(self.flash_path))
            except DesignError:
                cfg = None  # an unreadable flash boots without a config, as does one for another board
            if cfg is not None and (cfg.uid, cfg.capacity) == (self.spec.uid, self.spec.n_channels):
                self.config, self.config_bytes = cfg, data
        self._params_from_config()

    def _params_from_config(self) -> None:
        n = self.spec.n_channels
        self.threshold = np.full(n, 65535, np.int64)
        self.gain = np.full(n, GAIN_ONE, np.int64)  # Q8.8
        self.params_changed = False
        if self.config is not None:
            e = self.config.entries
            on = (e["flags"] & 1).astype(bool)
            self.threshold[e["channel"][on]] = e["threshold"][on]
            self.gain[e["channel"]] = e["gain"]

    @property
    def config_hash(self) -> bytes:
        return hashlib.sha256(self.config_bytes).digest() if self.config is not None else bytes(32)

    def identity(self) -> P.Identity:
        flags = (P.FLAG_STREAMING * self.streaming | P.FLAG_CONFIG_VALID * (self.config is not None)
                 | P.FLAG_PARAMS_CHANGED * self.params_changed)
        length = self.spec.faults.config_len
        return P.Identity(self.spec.uid, self.spec.protocol, self.spec.firmware, self.spec.n_channels,
                          self.spec.max_chunk, P.CAP_FORCE | P.CAP_SET_PARAMS | P.CAP_READBACK,
                          self.spec.max_rate_hz, flags, self.config_hash,
                          len(self.config_bytes) if length is None else length)

    # -- link --------------------------------------------------------------------------------
    def _wire(self, data: bytes) -> bytes:
        f = self.spec.faults
        if not (f.drop or f.flip) or not data:
            return data
        a = np.frombuffer(data, np.uint8).copy()
        flip = self.rng.random(a.size) < f.flip
        a[flip] ^= (1 << self.rng.integers(0, 8, int(flip.sum()))).astype(np.uint8)
        return a[self.rng.random(a.size) >= f.drop].tobytes()

    def _pace(self, clock: str, n: int) -> None:
        if not self.baud:
            return
        now = time.monotonic()
        t = max(now, getattr(self, clock)) + n * BITS_PER_BYTE / self.baud
        setattr(self, clock, t)
        if t > now:
            time.sleep(t - now)

    def send(self, frame: bytes) -> None:
        self._pace("wire_tx", len(frame))
        data = memoryview(self._wire(frame))
        deadline = time.monotonic() + self.OVERRUN_S
        while data:
            try:
                data = data[os.write(self.master, data):]
            except BlockingIOError:  # a slow host holds the board back (USB flow control); a gone one loses data
                if time.monotonic() > deadline:
                    self.tx_dropped += len(data)
                    return
                select.select([], [self.master], [], 0.01)

    # -- protocol ----------------------------------------------------------------------------
    def receive(self, data: bytes) -> None:
        self._pace("wire_rx", len(data))
        boots = self.boots
        for frame in self.parser.feed(self._wire(data)):
            if self.boots != boots:  # the rest of the read arrived while the board rebooted
                return
            out = self.handle(frame)
            if out is None:
                continue
            f = self.spec.faults
            if f.delay_s and (f.delay_p >= 1 or self.rng.random() < f.delay_p):
                time.sleep(f.delay_s)
            if f.malformed and out and self.rng.random() < f.malformed:
                out = out[:int(self.rng.integers(0, len(out)))]
            if frame.type == P.CONFIG_COMMIT and f.hashless_commit and out[:1] == bytes([P.OK]):
                out = out[:1]
            if frame.type == P.STREAM_START and self.start_answers_lost < f.lost_start_answers:
                self.start_answers_lost += 1
                continue
            self.send(P.encode_frame(frame.type | P.RESPONSE, frame.seq, self.spec.uid, out, self.spec.protocol))
            if frame.type == P.RESET:
                self.reboot()

    def handle(self, frame: P.Frame) -> bytes | None:
        """The answer payload to a request (None: no answer), by the rules of PROTOCOL.md."""
        if frame.type & P.RESPONSE or frame.uid not in (P.BROADCAST_UID, self.spec.uid):
            return None
        if frame.uid == P.BROADCAST_UID and frame.type != P.IDENTIFY:
            return None  # only identify may be broadcast
        if frame.version != self.spec.protocol:
            return b""  # another version: not interpreted; the empty answer in our version tells the host ours
        handler = self.HANDLERS.get(frame.type)
        if handler is None:
            return P.response(P.E_UNKNOWN, b"%d" % frame.type)
        if self.streaming and frame.type not in P.WHILE_STREAMING:
            return P.response(P.E_STREAMING, b"stop the stream first")
        try:
            return handler(self, frame.payload)
        except Exception as e:  # a malformed request must never kill the board
            return P.response(P.E_MALFORMED, str(e).encode("ascii", "replace")[:P.MAX_ERROR_TEXT])

    def reboot(self) -> None:
        time.sleep(self.BOOT_S)
        while True:  # bytes arriving while the board boots are lost
            try:
                if not os.read(self.master, 65536):
                    break
            except (BlockingIOError, OSError):
                break
        self._boot()

    def _identify(self, _: bytes) -> bytes:
        return P.response(P.OK, self.identity().pack())

    def _begin(self, p: bytes) -> bytes:
        total, digest = P.BEGIN_REQ.unpack(p)
        limit = P.max_config_bytes(self.spec.n_channels)
        if total > limit:
            return P.response(P.E_RANGE, b"config of %d bytes exceeds this board's %d" % (total, limit))
        self.staging, self.staging_hash, self.next = bytearray(total), digest, 0
        return P.response(P.OK)

    def _chunk(self, p: bytes) -> bytes | None:
        if self.staging is None:
            return P.response(P.E_NO_TRANSFER)
        self.chunks_seen += 1
        f = self.spec.faults
        if f.reset_at_chunk == self.chunks_seen and self.resets_left != 0:
            self.resets_left -= 1
            self.chunks_seen = 0 if self.resets_left else self.chunks_seen
            self.reboot()
            return None
        (offset,) = P.CHUNK_REQ.unpack_from(p)
        data = p[P.CHUNK_REQ.size:]
        if offset > self.next or offset + len(data) > len(self.staging) or len(data) > self.spec.max_chunk:
            return P.response(P.E_RANGE, b"offset %d len %d (next %d of %d)" % (offset, len(data), self.next,
                                                                                 len(self.staging)))
        self.staging[offset:offset + len(data)] = data
        self.next = max(self.next, offset + len(data))
        return P.response(P.OK, P.CHUNK_RESP.pack(self.next))

    def _commit(self, p: bytes) -> bytes:
        (digest,) = P.COMMIT_REQ.unpack(p)
        if self.staging is None:  # a retried commit whose answer was lost
            return P.response(P.OK, digest) if digest == self.config_hash else P.response(P.E_NO_TRANSFER)
        data, self.staging = bytes(self.staging), None
        if self.next < len(data):
            return P.response(P.E_INCOMPLETE, b"%d of %d bytes" % (self.next, len(data)))
        if hashlib.sha256(data).digest() != digest or digest != self.staging_hash:
            return P.response(P.E_HASH)
        try:
            cfg = BoardConfig.from_bytes(data, "staged config")
        except DesignError as e:
            return P.response(P.E_CONFIG, str(e).encode()[:P.MAX_ERROR_TEXT])
        if cfg.uid != self.spec.uid or cfg.capacity != self.spec.n_channels:
            return P.response(P.E_CONFIG, b"config for uid %#x with %d channels; this board is %#x with %d"
                              % (cfg.uid, cfg.capacity, self.spec.uid, self.spec.n_channels))
        try:
            if not self.spec.faults.flash_write_lost:
                atomic_write(self.flash_path, data)
        except OSError as e:
            return P.response(P.E_FLASH, str(e).encode()[:P.MAX_ERROR_TEXT])
        self.config, self.config_bytes = cfg, data
        self._params_from_config()
        return P.response(P.OK, digest)

    def _verify(self, _: bytes) -> bytes:
        try:
            data = self.flash_path.read_bytes()
        except FileNotFoundError:
            return P.response(P.E_FLASH, b"flash is empty")
        return P.response(P.OK, hashlib.sha256(data).digest())

    def _read(self, p: bytes) -> bytes:
        """The active config's bytes as stored in flash (not the RAM copy the board runs)."""
        offset, length = P.READ_REQ.unpack(p)
        if len(p) != P.READ_REQ.size or length > self.spec.max_chunk:
            return P.response(P.E_PARAM, b"read of %d bytes exceeds max chunk %d" % (length, self.spec.max_chunk))
        try:
            flash = self.flash_path.read_bytes() if self.config is not None else b""
        except OSError as e:
            return P.response(P.E_FLASH, str(e).encode()[:P.MAX_ERROR_TEXT])
        total = self.identity().config_length  # past the stored bytes, up to what identify said: erased flash
        erased = max(0, min(offset + length, total) - max(offset, len(flash)))
        return P.response(P.OK, P.READ_RESP.pack(offset) + flash[offset:offset + length] + b"\xff" * erased)

    def _start(self, p: bytes) -> bytes:
        (rate,) = P.START_REQ.unpack(p)
        if not 1 <= rate <= self.spec.max_rate_hz:
            return P.response(P.E_PARAM, b"rate %d Hz outside 1..%d" % (rate, self.spec.max_rate_hz))
        if not self.streaming:  # a start while streaming (a re-send) only sets the rate: the counter runs on
            self.sample, self.next_tick = 0, time.monotonic()
        self.streaming, self.rate = True, rate
        return P.response(P.OK)

    def _stop(self, _: bytes) -> bytes:
        self.streaming = False  # a re-sent stop answers the same count
        return P.response(P.OK, P.STOP_RESP.pack(self.sample & 0xFFFFFFFF))

    def _params(self, p: bytes) -> bytes:
        first, count = P.PARAMS_REQ.unpack_from(p)
        if first + count > self.spec.n_channels or len(p) != P.PARAMS_REQ.size + 4 * count:
            return P.response(P.E_PARAM, b"channels %d..%d of %d" % (first, first + count, self.spec.n_channels))
        v = np.frombuffer(p, "<u2", 2 * count, P.PARAMS_REQ.size).reshape(count, 2)
        self.threshold[first:first + count] = v[:, 0]
        self.gain[first:first + count] = v[:, 1]
        self.params_changed = True
        return P.response(P.OK)

    def _reset(self, _: bytes) -> bytes:
        return P.response(P.OK)

    HANDLERS = {P.IDENTIFY: _identify, P.CONFIG_BEGIN: _begin, P.CONFIG_CHUNK: _chunk, P.CONFIG_COMMIT: _commit,
                P.CONFIG_READ: _read, P.STREAM_START: _start, P.STREAM_STOP: _stop, P.SET_PARAMS: _params,
                P.RESET: _reset, P.CONFIG_VERIFY: _verify}

    # -- streaming ---------------------------------------------------------------------------
    def forces(self, t: float) -> np.ndarray | None:
        """Synthetic forces (N): a 12 N press sweeping across the channels once a second, a replay, or the feed
        (None: the feed has no complete sample)."""
        n = self.spec.n_channels
        if self.feed is not None:
            return self.feed()
        if self.replay is not None:
            return self.replay[self.sample % len(self.replay)]
        c = np.arange(n)
        centre = (t % 1.0) * n
        return 12.0 * np.exp(-0.5 * ((c - centre) / max(1.0, n / 64)) ** 2)

    def stream_frame(self) -> bytes | None:
        """The next stream frame, or None when there is no sample to send (the feed's writer is stuck)."""
        t = time.monotonic() - self.t0
        forces = self.forces(t)
        if forces is None:
            return None
        raw = np.asarray(self.encode(forces), np.int64)
        counts = np.minimum((raw * self.gain) >> 8, 65535).astype("<u2")  # gain Q8.8, rounded down
        over = int((counts > self.threshold).sum())
        sample = self.sample & 0xFFFFFFFF
        head = P.STREAM_HEAD.pack(int(t * 1e6), sample, len(counts), over)
        self.sample += 1
        return P.encode_frame(P.STREAM_DATA, sample, self.spec.uid, head + counts.tobytes(), self.spec.protocol)

    def _stream_faults(self, frame: bytes) -> list[bytes]:
        """What goes on the wire for one stream frame: the frame, then maybe an older one again, and maybe a
        frame of another board (every channel at full scale: a phantom press wherever it is taken for ours)."""
        f, out = self.spec.faults, [frame]
        if f.old_frames and len(self.sent_frames) > 1 and self.rng.random() < f.old_frames:
            out.append(self.sent_frames[int(self.rng.integers(0, len(self.sent_frames) - 1))])
        self.sent_frames.append(frame)
        if f.foreign_frames and self.rng.random() < f.foreign_frames:
            n = self.spec.n_channels
            head = P.STREAM_HEAD.pack(0, self.foreign_sample & 0xFFFFFFFF, n, n)
            out.append(P.encode_frame(P.STREAM_DATA, self.foreign_sample, self.spec.uid ^ FOREIGN_BIT,
                                      head + np.full(n, 65535, "<u2").tobytes(), self.spec.protocol))
            self.foreign_sample += 1
        return out

    def run(self, stop: threading.Event) -> None:
        while not stop.is_set():
            now = time.monotonic()
            wait = 0.05 if not self.streaming else max(0.0, self.next_tick - now)
            if select.select([self.master], [], [], wait)[0]:
                try:
                    data = os.read(self.master, 65536)
                except (BlockingIOError, OSError):
                    data = b""
                if data:
                    self.receive(data)
            if self.streaming and time.monotonic() >= self.next_tick:
                frame = self.stream_frame()
                for frame in self._stream_faults(frame) if frame is not None else []:
                    self.send(frame)
                self.next_tick = max(self.next_tick + 1.0 / self.rate, time.monotonic() - 1.0 / self.rate)
                if self.spec.faults.unplug_after and self.sample >= self.spec.faults.unplug_after:
                    self.close()  # the cable is pulled: the host's end of the pty hangs up
                    return

    def close(self) -> None:
        if not self.closed:
            self.closed = True
            os.close(self.master)
            os.close(self.slave)


def flash_path(flash_dir: str | Path, uid: int) -> Path:
    """The flash file of board `uid` in `flash_dir`."""
    return Path(flash_dir) / f"board-{uid:016x}.flash"




class NotABoard:
    """A device on a pty that is not a board: it answers anything with a line of NMEA text (a GPS receiver)."""

    LINE = b"$GPGGA,123519,4807.038,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,*47\r\n"

    def __init__(self):
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)
        os.set_blocking(self.master, False)
        self.port = os.ttyname(self.slave)

    def run(self, stop: threading.Event) -> None:
        while not stop.is_set():
            if select.select([self.master], [], [], 0.05)[0]:
                try:
                    if os.read(self.master, 65536):
                        os.write(self.master, self.LINE)
                except (BlockingIOError, OSError):
                    pass

    def close(self) -> None:
        os.close(self.master)
        os.close(self.slave)
