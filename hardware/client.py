"""Host side of the board protocol over pyserial: requests with retries and back-off, config transfer, streaming."""
from __future__ import annotations

import collections
import os
import select
import time

import numpy as np
import serial

from skinsafe.hardware import protocol as P

BITS_PER_BYTE = 10  # 8N1
MAX_BAUD = 12_000_000  # the fastest USB-serial bridges (FT232H); above it a port refuses or overflows


def baud_problem(baud: int) -> str | None:
    """Why `--baud` cannot be a link speed (the line to print), or None."""
    return None if 0 < baud <= MAX_BAUD else f"--baud {baud}: give 1..{MAX_BAUD} bit/s, e.g. 1000000"


class BoardError(Exception):
    """A board refused a request, stopped answering, answered malformed, or speaks another protocol.

    `kind` says which, for reports: refused, timeout, not-a-board, version, malformed, link, cancelled, incompatible.
    """

    def __init__(self, message: str, status: int | None = None, kind: str = "refused", uid: int | None = None):
        super().__init__(message)
        self.status, self.kind, self.uid = status, kind, uid  # uid: the board's, where its frames said it


def identity_problem(info: P.Identity, board) -> str | None:
    """Why the map's `board` (with .name, .uid, .capacity) must not be used through the board that answered
    identify: another uid, firmware major or channel count. None if it may."""
    if info.uid != board.uid:
        return (f"the port holds board uid {info.uid:#x}, the map's board '{board.name}' is uid {board.uid:#x}; "
                "connect the right board or use --all to match boards by uid")
    if info.firmware[0] != P.FIRMWARE_MAJOR:
        return (f"firmware {info.firmware_str} is not supported (this host needs {P.FIRMWARE_MAJOR}.x); "
                "update the board firmware")
    if info.n_channels != board.capacity:
        return (f"the board has {info.n_channels} channels, the map's board '{board.name}' has capacity "
                f"{board.capacity}; fix the board's capacity in the design or connect the right board")
    return None


class BoardClient:
    """One serial link to one board.

    `timeout` is the wait for an answer on top of the wire time of request and answer at `baud`;
    failed requests (timeout, CRC error) are re-sent up to `retries` times, sleeping
    `backoff * 2**k` seconds before the k-th retry (PROTOCOL.md "Re-sending"). `cancel` (an
    Interrupt) stops before the next request and ends a request's re-sends. Once identify named the
    board, frames of any other uid are refused (counted by uid in `foreign`); a failing link raises
    BoardError(kind="link") naming the board and the port.
    """

    def __init__(self, port: str, baud: int = 1_000_000, timeout: float = 0.25, retries: int = 4,
                 backoff: float = 0.01, uid: int = P.BROADCAST_UID, cancel=None):
        self.port, self.baud, self.timeout, self.retries, self.backoff, self.uid, self.cancel = \
            port, baud, timeout, retries, backoff, uid, cancel
        try:
            self.ser = serial.Serial(port, baud, timeout=0.005, write_timeout=2.0)
            self.ser.reset_input_buffer()
        except (serial.SerialException, OSError, ValueError, OverflowError) as e:
            raise BoardError(f"{port}: cannot open the serial port ({e}); check the path and permissions",
                             kind="link") from None
        self.parser = P.FrameParser(P.MAX_SHORT_PAYLOAD, runs=True)  # widened by identify
        self.stream = collections.deque(maxlen=100_000)
        self.seq = int.from_bytes(os.urandom(2), "little")  # a stale answer to an earlier session cannot match
        self.tx_bytes = self.rx_bytes = self.resent = 0
        self.max_chunk = P.MIN_CHUNK
        self.last_uid = uid
        self.committed = False  # a commit of this client was acknowledged
        self.info: P.Identity | None = None  # the last identify answer
        self.foreign: collections.Counter = collections.Counter()  # uid -> frames refused from it
        self.start_answer_lost = False  # a stream start whose answers were lost was confirmed by identify

    def close(self) -> None:
        self.ser.close()

    def __enter__(self) -> "BoardClient":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def wire_s(self) -> float:
        """Time the bytes sent plus received so far need on a real UART at `baud` (requests wait for answers)."""
        return (self.tx_bytes + self.rx_bytes) * BITS_PER_BYTE / self.baud

    # -- transport ---------------------------------------------------------------------------
    def link_lost(self, e: Exception) -> BoardError:
        """The error for a link that failed under a read, write or poll (a cable pulled, a board powered off)."""
        who = f"board {self.uid:#x} on {self.port}" if self.uid != P.BROADCAST_UID else self.port
        return BoardError(f"{who}: link lost ({e}); check the cable and the board's power", kind="link",
                          uid=self.uid if self.uid != P.BROADCAST_UID else None)

    def waiting(self) -> int:
        """Bytes waiting to be read; BoardError(kind="link") when the link is gone."""
        try:
            return self.ser.in_waiting
        except (serial.SerialException, OSError) as e:
            raise self.link_lost(e) from None

    def _read(self) -> list[P.Frame]:
        try:
            data = self.ser.read(self.waiting() or 1)
        except (serial.SerialException, OSError) as e:
            raise self.link_lost(e) from None
        self.rx_bytes += len(data)
        frames = []
        for f in self.parser.feed(data) if data else ():
            if f.version != P.PROTOCOL_VERSION:
                raise BoardError(f"{self.port}: board {f.uid:#x} speaks protocol version {f.version}, this host "
                                 f"speaks {P.PROTOCOL_VERSION}; update the board firmware or skinsafe", kind="version",
                                 uid=f.uid)
            if self.uid != P.BROADCAST_UID and f.uid != self.uid:  # another board on this link: never its data
                self.foreign[f.uid] += len(f.seqs) if isinstance(f, P.FrameRun) else 1
            elif f.type == P.STREAM_DATA:
                self.stream.append(f)
            else:
                frames.append(f)
        return frames

    def _malformed(self, uid: int, name: str, detail: str) -> BoardError:
        return BoardError(f"{self.port}: board {uid:#x} sent a malformed {name} answer: {detail}; "
                          "check the board firmware against hardware/PROTOCOL.md", kind="malformed", uid=uid)

    def request(self, msg_type: int, payload: bytes = b"", size: int = 0) -> bytes:
        """Send a command and return the data of its OK answer (at least `size` bytes);
        raise BoardError on refusal, silence, a malformed answer or cancellation."""
        name = P.COMMANDS.get(msg_type, hex(msg_type))
        why, kind = "no answer", "timeout"
        for attempt in range(self.retries + 1):
            if self.cancel is not None and self.cancel.requested:
                raise BoardError(f"{self.port}: {name} not sent: interrupted by {self.cancel.name}", kind="cancelled")
            if attempt:
                self.resent += 1
                self.parser.buf.clear()  # a half frame left by a lost byte would swallow the next answer
                time.sleep(min(self.backoff * 2 ** (attempt - 1), 1.0))
            self.seq = (self.seq + 1) & 0xFFFF
            frame = P.encode_frame(msg_type, self.seq, self.uid, payload)
            try:
                self.ser.write(frame)
            except (serial.SerialException, OSError) as e:
                raise self.link_lost(e) from None
            self.tx_bytes += len(frame)
            wire = (len(frame) + self.parser.max_payload + P.OVERHEAD) * BITS_PER_BYTE / self.baud
            deadline = time.monotonic() + self.timeout + wire
            crc = self.parser.crc_errors
            while time.monotonic() < deadline:
                match = [f for f in self._read() if f.type == msg_type | P.RESPONSE and f.seq == self.seq]
                if match:
                    return self._answer(match[0], name, size)
                if self.parser.crc_errors != crc:
                    why, kind = "CRC error", "timeout"
                    break
            else:
                if self.rx_bytes and not self.parser.frames:
                    why, kind = f"{self.rx_bytes} bytes came back, none of them a skinsafe frame", "not-a-board"
                else:
                    why, kind = "timeout", "timeout"
        raise BoardError(f"{self.port}: {name} failed after {self.retries + 1} tries ({why}); "
                         "check the cable, the port and that the board is powered", kind=kind)

    def _answer(self, f: P.Frame, name: str, size: int) -> bytes:
        p = f.payload
        if not p:
            raise self._malformed(f.uid, name, "empty payload, byte 0 (the status) missing")
        if p[0] not in P.STATUS:
            raise self._malformed(f.uid, name, f"byte 0 (the status) is {p[0]:#04x}, not a protocol status")
        self.last_uid = f.uid
        if p[0] != P.OK:
            raise BoardError(f"{self.port}: board {f.uid:#x} refused {name}: {P.error_text(p)}", p[0], uid=f.uid)
        if len(p) - 1 < size:
            raise self._malformed(f.uid, name, f"{len(p)} bytes, byte {len(p)} onwards missing "
                                  f"(expected status + {size} bytes)")
        return p[1:]

    # -- commands ----------------------------------------------------------------------------
    def identify(self) -> P.Identity:
        """Who is on this port; sizes config chunks to what the board accepts, bounds the frame length
        it may send, and (if this client was broadcasting) addresses that board from now on."""
        data = self.request(P.IDENTIFY, size=P.IDENTIFY_RESP.size)
        info = P.Identity.unpack(self.last_uid, data)
        if info.protocol != P.PROTOCOL_VERSION:
            raise self._malformed(info.uid, "identify", f"byte 1 (protocol) is {info.protocol}, the frame said "
                                  f"{P.PROTOCOL_VERSION}")
        if not P.MIN_CHUNK <= info.max_chunk <= P.MAX_CHUNK:
            raise BoardError(f"{self.port}: board {info.uid:#x} accepts chunks of {info.max_chunk} bytes, the protocol "
                             f"needs {P.MIN_CHUNK}..{P.MAX_CHUNK}; update the board firmware", kind="incompatible")
        if info.n_channels > P.MAX_CHANNELS:
            raise BoardError(f"{self.port}: board {info.uid:#x} reports {info.n_channels} channels, the protocol "
                             f"carries at most {P.MAX_CHANNELS}; update the board firmware", kind="incompatible")
        if info.config_length > P.max_config_bytes(info.n_channels):
            raise self._malformed(info.uid, "identify", f"bytes 49-52 (config_len) say {info.config_length}, a board "
                                  f"of {info.n_channels} channels holds at most {P.max_config_bytes(info.n_channels)}")
        self.info = info
        self.max_chunk = info.max_chunk
        self.parser.max_payload = P.board_max_payload(info.max_chunk, info.n_channels)
        if self.uid == P.BROADCAST_UID:
            self.uid = info.uid
        return info

    def write_config(self, data: bytes, digest: bytes, restarts: int = 2) -> None:
        """Begin, send every chunk, commit. A board that lost the transfer (it reset) gets it again from the start."""
        for attempt in range(restarts + 1):
            try:
                self.request(P.CONFIG_BEGIN, P.BEGIN_REQ.pack(len(data), digest))
                step = self.max_chunk
                for off in range(0, len(data), step):
                    nxt = P.CHUNK_RESP.unpack_from(self.request(P.CONFIG_CHUNK, P.CHUNK_REQ.pack(off) + data[off:off + step],
                                                                P.CHUNK_RESP.size))[0]
                    if nxt != min(off + step, len(data)):
                        raise BoardError(f"{self.port}: board acknowledged up to byte {nxt}, sent up to {off + step}",
                                         P.E_RANGE)
                answer = self.request(P.CONFIG_COMMIT, P.COMMIT_REQ.pack(digest), P.COMMIT_REQ.size)
                if answer[:P.COMMIT_REQ.size] != digest:
                    raise self._malformed(self.uid, "config-commit", f"bytes 1-32 (the committed hash) are "
                                          f"{answer[:P.COMMIT_REQ.size].hex()[:8]}, the config sent hashes to "
                                          f"{digest.hex()[:8]}")
                self.committed = True
                return
            except BoardError as e:
                if e.status not in (P.E_NO_TRANSFER, P.E_RANGE, P.E_INCOMPLETE) or attempt == restarts:
                    raise

    def read_config(self, length: int) -> bytes:
        """The board's active config, read back from its flash in chunks (at most what a board of its
        channel count can hold: a lying length cannot keep the host reading)."""
        top = P.max_config_bytes(self.info.n_channels if self.info else P.MAX_CHANNELS)
        if not 0 <= length <= top:
            raise ValueError(f"config read of {length} bytes: a board holds at most {top}")
        out = bytearray()
        while len(out) < length:
            n = min(self.max_chunk, length - len(out))
            data = self.request(P.CONFIG_READ, P.READ_REQ.pack(len(out), n), P.READ_RESP.size)
            (off,) = P.READ_RESP.unpack_from(data)
            chunk = data[P.READ_RESP.size:]
            if off != len(out) or not chunk or len(chunk) > n:
                raise BoardError(f"{self.port}: read back returned offset {off} with {len(chunk)} bytes, "
                                 f"asked for {n} at {len(out)}")
            out += chunk
        return bytes(out)

    def flash_hash(self) -> bytes:
        """SHA-256 the board computes over its config as re-read from flash (verify without the read-back bytes)."""
        return self.request(P.CONFIG_VERIFY, size=32)[:32]

    def start_stream(self, rate_hz: int) -> None:
        """Start streaming at `rate_hz`. When every answer was lost (timeout), ask the board whether it streams:
        if so the start took effect (its answers were lost, `start_answer_lost`), else the timeout is raised."""
        if not 1 <= rate_hz <= 65535:
            raise ValueError(f"stream rate {rate_hz} Hz: the protocol carries 1..65535")
        try:
            self.request(P.STREAM_START, P.START_REQ.pack(rate_hz))
        except BoardError as e:
            if e.kind != "timeout":
                raise
            try:
                streaming = self.identify().flags & P.FLAG_STREAMING
            except BoardError:
                raise e from None
            if not streaming:
                raise
            self.start_answer_lost = True

    def stop_stream(self) -> int:
        """Stop streaming; returns how many frames the board sent since the stream started."""
        return P.STOP_RESP.unpack_from(self.request(P.STREAM_STOP, size=P.STOP_RESP.size))[0]

    def set_params(self, first: int, thresholds, gains_q8) -> None:
        """Runtime thresholds (ADC counts) and gains (Q8.8) for channels first.. (not written to flash)."""
        v = np.stack([np.asarray(thresholds), np.asarray(gains_q8)], axis=1).astype("<u2")
        self.request(P.SET_PARAMS, P.PARAMS_REQ.pack(first, len(v)) + v.tobytes())

    def reset(self) -> None:
        self.request(P.RESET)

    def read_stream(self, max_wait: float = 0.01) -> list:
        """Stream frames (Frame or FrameRun) received so far, waiting up to `max_wait` for the first bytes;
        BoardError(kind="link") when the link is gone."""
        if max_wait > 0 and not self.waiting():
            select.select([self.ser.fileno()], [], [], max_wait)
        while self.waiting():
            self._read()
        out = list(self.stream)
        self.stream.clear()
        return out
