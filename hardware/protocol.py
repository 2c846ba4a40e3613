"""The skinsafe board wire protocol (see PROTOCOL.md): frames, message types, payload layouts.

A frame is a 16-byte header (sync word, protocol version, type, sequence, board uid, payload
length), a CRC-16 over the header, the payload and a CRC-32 over everything before it. The
parser resynchronises after garbage by scanning for the sync word and checking both CRCs.
"""
from __future__ import annotations

import binascii
import struct
import zlib
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

PROTOCOL_VERSION = 1
FIRMWARE_MAJOR = 1  # hosts talk to firmware whose major version equals this
SYNC = b"\xa5\x5a"
HEADER = struct.Struct("<2sBBHQH")  # sync, version, type, seq, uid, payload length
HEADER_CRC = struct.Struct("<H")
CRC32 = struct.Struct("<I")
_HEAD_AND_CRC = struct.Struct("<2sBBHQHH")
HEADER_SIZE = HEADER.size + HEADER_CRC.size  # 18
OVERHEAD = HEADER_SIZE + CRC32.size  # 22
MAX_PAYLOAD = 65535  # what the 16-bit length field can say; receivers bound it tighter (max_payload)
BROADCAST_UID = 0  # only identify may be broadcast
MIN_CHUNK = 16  # a board must accept config chunks (and reads) of at least this many bytes
MAX_SHORT_PAYLOAD = 255  # largest payload of a frame before identify: identify answer, error answers
MAX_ERROR_TEXT = 200  # bytes of ASCII message after an error status
RESPONSE_DEADLINE_S = 0.2  # a board answers within this after a request's last byte (plus the answer's wire time)

# message types; a response has the request's type | RESPONSE and echoes its sequence number
IDENTIFY = 0x01
CONFIG_BEGIN = 0x02
CONFIG_CHUNK = 0x03
CONFIG_COMMIT = 0x04
CONFIG_READ = 0x05
STREAM_START = 0x06
STREAM_STOP = 0x07
SET_PARAMS = 0x08
RESET = 0x09
CONFIG_VERIFY = 0x0A
STREAM_DATA = 0x40  # unsolicited, board -> host
RESPONSE = 0x80
COMMANDS = {IDENTIFY: "identify", CONFIG_BEGIN: "config-begin", CONFIG_CHUNK: "config-chunk",
            CONFIG_COMMIT: "config-commit", CONFIG_READ: "config-read", STREAM_START: "stream-start",
            STREAM_STOP: "stream-stop", SET_PARAMS: "set-params", RESET: "reset",
            CONFIG_VERIFY: "config-verify"}

# status codes (first payload byte of every response)
OK = 0
STATUS = {
    OK: "ok", 1: "malformed request", 2: "no config transfer in progress", 3: "chunk outside the declared length",
    4: "transfer incomplete", 5: "hash mismatch", 6: "config rejected", 7: "flash write failed",
    8: "unknown command", 9: "bad parameter", 10: "not allowed while streaming",
}
E_MALFORMED, E_NO_TRANSFER, E_RANGE, E_INCOMPLETE, E_HASH, E_CONFIG, E_FLASH, E_UNKNOWN, E_PARAM, E_STREAMING = \
    range(1, 11)
# requests a streaming board still serves; the others get E_STREAMING
WHILE_STREAMING = frozenset({IDENTIFY, STREAM_START, STREAM_STOP, SET_PARAMS, RESET})

# capability bits reported by identify
CAP_FORCE, CAP_TEMPERATURE, CAP_CLASSIFIER, CAP_SET_PARAMS, CAP_READBACK = 1, 2, 4, 8, 16

# payload layouts (little-endian)
IDENTIFY_RESP = struct.Struct("<BBBBHHIHH32sI")  # see Identity
BEGIN_REQ = struct.Struct("<I32s")  # total length, sha256 of the whole config
CHUNK_REQ = struct.Struct("<I")  # offset, then the data
CHUNK_RESP = struct.Struct("<I")  # next expected offset
COMMIT_REQ = struct.Struct("<32s")
READ_REQ = struct.Struct("<IH")  # offset, length
READ_RESP = struct.Struct("<I")  # offset, then the data
START_REQ = struct.Struct("<H")  # rate in Hz
STOP_RESP = struct.Struct("<I")  # frames sent since the stream started (the next sample counter)
PARAMS_REQ = struct.Struct("<HH")  # first channel, count, then count x (threshold u16, gain u16 Q8.8)
STREAM_HEAD = struct.Struct("<QIHH")  # timestamp us, sample counter, n channels, n channels over threshold
FLAG_STREAMING, FLAG_CONFIG_VALID, FLAG_PARAMS_CHANGED = 1, 2, 4
MAX_CHANNELS = (MAX_PAYLOAD - STREAM_HEAD.size) // 2  # a stream frame carries every channel
MAX_CHUNK = MAX_PAYLOAD - 1 - READ_RESP.size  # a read answer carries status, offset and the chunk


def board_max_payload(max_chunk: int, n_channels: int) -> int:
    """Largest payload a board with this identity sends (the host's bound on a length header)."""
    return max(MAX_SHORT_PAYLOAD, 1 + READ_RESP.size + max_chunk, STREAM_HEAD.size + 2 * n_channels)


def host_max_payload(max_chunk: int, n_channels: int) -> int:
    """Largest request payload a board with this identity accepts (the board's bound on a length header)."""
    return max(MAX_SHORT_PAYLOAD, CHUNK_REQ.size + max_chunk, PARAMS_REQ.size + 4 * n_channels)


CONFIG_HEADER_BYTES, CONFIG_ENTRY_BYTES = 24, 12  # the board config's layout (PROTOCOL.md "Board config")


def max_config_bytes(n_channels: int) -> int:
    """The largest config a board of `n_channels` holds: the header and one entry per channel."""
    return CONFIG_HEADER_BYTES + CONFIG_ENTRY_BYTES * n_channels


def stream_frame_bytes(n_channels: int) -> int:
    """Bytes on the wire of one stream frame of a board with `n_channels`."""
    return OVERHEAD + STREAM_HEAD.size + 2 * n_channels


class ProtocolError(Exception):
    """The peer spoke the protocol wrongly (bad version, malformed payload, error status)."""


class Frame(NamedTuple):
    version: int
    type: int
    seq: int
    uid: int
    payload: bytes


def encode_frame(msg_type: int, seq: int, uid: int, payload: bytes = b"", version: int = PROTOCOL_VERSION) -> bytes:
    """One frame on the wire: header, header CRC-16, payload, CRC-32."""
    if len(payload) > MAX_PAYLOAD:
        raise ValueError(f"payload of {len(payload)} bytes exceeds the protocol maximum {MAX_PAYLOAD}")
    head = HEADER.pack(SYNC, version, msg_type, seq & 0xFFFF, uid, len(payload))
    body = head + HEADER_CRC.pack(crc16(head)) + payload
    return body + CRC32.pack(zlib.crc32(body))


def crc16(data: bytes) -> int:
    """CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, no reflection, no final xor)."""
    return binascii.crc_hqx(data, 0xFFFF)


class FrameParser:
    """Incremental frame parser: feed it any bytes, get whole valid frames back; never raises.

    Counts `crc_errors` (a valid header whose payload CRC failed), `bytes_skipped` (garbage
    between frames, including frames with a damaged header) and `resyncs` (runs of skipped bytes).
    `max_payload` bounds the length header (PROTOCOL.md "Length bound"): a larger one is garbage. With `runs`, consecutive stream
    frames of one board come back as one FrameRun (payloads as rows of one array) instead of
    one Frame each: the fast path for decoding thousands of frames a second.
    """

    def __init__(self, max_payload: int = MAX_PAYLOAD, runs: bool = False):
        self.buf = bytearray()
        self.runs = runs
        self.max_payload = max_payload
        self.crc_errors = 0
        self.bytes_skipped = 0
        self.resyncs = 0  # runs of discarded bytes: each one a resynchronisation
        self.frames = 0
        self._skipping = False

    def _skip(self, n: int) -> None:
        if n > 0:
            self.bytes_skipped += n
            self.resyncs += not self._skipping
            self._skipping = True

    def feed(self, data: bytes) -> list:
        buf = self.buf
        buf += data
        out: list[Frame] = []
        pos, n = 0, len(buf)
        find, head, crc32, crc_hqx, new = buf.find, _HEAD_AND_CRC.unpack_from, zlib.crc32, binascii.crc_hqx, tuple.__new__
        with memoryview(buf) as mv:
            while True:
                i = find(SYNC, pos)
                if i < 0:
                    keep = n - 1 if n and buf[-1] == SYNC[0] else n  # a sync word may straddle two reads
                    self._skip(keep - pos)
                    pos = max(pos, keep)
                    break
                self._skip(i - pos)
                pos = i
                if n - i < HEADER_SIZE:
                    break
                _, version, msg_type, seq, uid, length, hcrc = head(buf, i)
                if crc_hqx(mv[i:i + HEADER.size], 0xFFFF) != hcrc or length > self.max_payload:
                    self._skip(1)
                    pos = i + 1
                    continue
                end = i + HEADER_SIZE + length
                if n < end + CRC32.size:
                    break
                if crc32(mv[i:end]) != CRC32.unpack_from(buf, end)[0]:
                    self.crc_errors += 1
                    self._skip(1)
                    pos = i + 1
                    continue
                out.append(new(Frame, (version, msg_type, seq, uid, bytes(mv[i + HEADER_SIZE:end]))))
                self._skipping = False
                pos = end + CRC32.size
                if msg_type == STREAM_DATA and n - pos >= 2 * (pos - i):
                    pos = self._run(buf, mv, i, pos, out)
        del buf[:pos]
        self.frames += len(out)
        return out

    def _run(self, buf: bytearray, mv: memoryview, first: int, pos: int, out: list) -> int:
        """Fast path for stream frames following the one at `first` with its size, type and uid.

        Headers are checked all at once with numpy: CRC-16 is affine, so a header differing from
        the checked one only in its sequence bytes has that header's CRC xor the zero-init CRC of
        the difference. Then the CRC-32 of each frame; returns where the run ends.
        """
        size = pos - first
        k = (len(buf) - pos) // size
        rows = np.frombuffer(mv, np.uint8, k * size, pos).reshape(k, size)
        ref = np.frombuffer(mv, np.uint8, HEADER_SIZE, first)
        want = (int(ref[16]) | int(ref[17]) << 8) ^ _SEQ_LO[rows[:, 4] ^ ref[4]] ^ _SEQ_HI[rows[:, 5] ^ ref[5]]
        same = ((rows[:, :4] == ref[:4]).all(axis=1) & (rows[:, 6:HEADER.size] == ref[6:HEADER.size]).all(axis=1)
                & (want == (rows[:, 16] | rows[:, 17].astype(np.uint16) << 8)))
        k = k if same.all() else int(same.argmin())
        crc32, m, p, body = zlib.crc32, 0, pos, size - CRC32.size
        for crc in rows[:k, body:].copy().view("<u4").ravel().tolist():
            if crc32(mv[p:p + body]) != crc:
                break  # the general loop resynchronises from here
            m, p = m + 1, p + size
        if m:
            version, msg_type, _, uid, _ = out[-1]
            run = FrameRun(version, msg_type, rows[:m, 4:6].copy().view("<u2").ravel(), uid,
                           rows[:m, HEADER_SIZE:body].copy())
            if self.runs:
                out.append(run)
            else:
                out.extend(run.frames())
            self.frames += m - 1 if self.runs else 0  # feed() counts each item of `out` once
        del rows, ref  # release the buffer export before the caller trims it
        return p


def _seq_crc_table(offset: int) -> np.ndarray:
    """Zero-init CRC-16 of a header that is all zeros but byte `offset` (0..255)."""
    return np.array([binascii.crc_hqx(bytes(offset) + bytes([b]) + bytes(HEADER.size - offset - 1), 0)
                     for b in range(256)], dtype=np.uint16)


_SEQ_LO, _SEQ_HI = _seq_crc_table(4), _seq_crc_table(5)


class FrameRun(NamedTuple):
    """Consecutive equal-size stream frames of one board, as the parser returns them with `runs=True`:
    `seqs` (k,) and `payloads` (k, L) uint8, one row per frame."""

    version: int
    type: int
    seqs: np.ndarray
    uid: int
    payloads: np.ndarray

    def frames(self) -> list[Frame]:
        return [Frame(self.version, self.type, int(q), self.uid, p.tobytes()) for q, p in zip(self.seqs, self.payloads)]


def expand(items: list) -> list[Frame]:
    """Frames and FrameRuns as a flat list of Frames."""
    return [f for x in items for f in (x.frames() if isinstance(x, FrameRun) else [x])]


@dataclass(frozen=True)
class Identity:
    """What a board says about itself (identify response)."""

    uid: int
    protocol: int
    firmware: tuple[int, int, int]
    n_channels: int
    max_chunk: int
    capabilities: int
    max_rate_hz: int
    flags: int
    config_hash: bytes  # sha256 of the active config, zeros when none
    config_length: int

    def pack(self) -> bytes:
        return IDENTIFY_RESP.pack(self.protocol, *self.firmware, self.n_channels, self.max_chunk, self.capabilities,
                                  self.max_rate_hz, self.flags, self.config_hash, self.config_length)

    @classmethod
    def unpack(cls, uid: int, data: bytes) -> "Identity":
        if len(data) < IDENTIFY_RESP.size:
            raise ProtocolError(f"identify response of {len(data)} bytes, expected {IDENTIFY_RESP.size}")
        p, a, b, c, n, chunk, caps, rate, flags, h, length = IDENTIFY_RESP.unpack_from(data)
        return cls(uid, p, (a, b, c), n, chunk, caps, rate, flags, h, length)

    @property
    def firmware_str(self) -> str:
        return ".".join(map(str, self.firmware))


def response(status: int, data: bytes = b"") -> bytes:
    """A response payload: status byte, then data (or an ASCII message when status != OK)."""
    return bytes([status]) + data


def error_text(payload: bytes) -> str:
    """Human text of an error response payload."""
    code = payload[0] if payload else E_MALFORMED
    detail = payload[1:].decode("ascii", "replace")
    return STATUS.get(code, f"status {code}") + (f": {detail}" if detail else "")
