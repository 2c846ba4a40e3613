"""Host side of the board protocol over pyserial: requests with retries and back-off, config transfer, streaming."""
from __future__ import annotations

import collections
import select
import time

import numpy as np
import serial

from skinsafe.hardware import protocol as P

BITS_PER_BYTE = 10  # 8N1


class BoardError(Exception):
    """A board refused a request, stopped answering, or speaks an incompatible protocol."""

    def __init__(self, message: str, status: int | None = None):
        super().__init__(message)
        self.status = status


class BoardClient:
    """One serial link to one board.

    `timeout` is the wait for an answer on top of the wire time of request and answer at `baud`;
    failed requests (timeout, CRC error) are re-sent up to `retries` times, sleeping
    `backoff * 2**k` seconds before the k-th retry. Every request is idempotent on the board.
    """

    def __init__(self, port: str, baud: int = 1_000_000, timeout: float = 0.25, retries: int = 4,
                 backoff: float = 0.01, uid: int = P.BROADCAST_UID):
        self.port, self.baud, self.timeout, self.retries, self.backoff, self.uid = \
            port, baud, timeout, retries, backoff, uid
        try:
            self.ser = serial.Serial(port, baud, timeout=0.005, write_timeout=2.0)
        except (serial.SerialException, OSError, ValueError) as e:
            raise BoardError(f"{port}: cannot open the serial port ({e}); check the path and permissions") from None
        self.ser.reset_input_buffer()
        self.parser = P.FrameParser(runs=True)
        self.stream = collections.deque(maxlen=100_000)
        self.seq = 0
        self.tx_bytes = self.rx_bytes = self.resent = 0
        self.max_chunk = 1024
        self.last_uid = uid

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
    def _read(self) -> list[P.Frame]:
        try:
            data = self.ser.read(self.ser.in_waiting or 1)
        except (serial.SerialException, OSError) as e:
            raise BoardError(f"{self.port}: the serial link failed ({e}); check the cable and the board") from None
        self.rx_bytes += len(data)
        frames = []
        for f in self.parser.feed(data) if data else ():
            if f.version != P.PROTOCOL_VERSION:
                raise BoardError(f"{self.port}: board speaks protocol version {f.version}, this host speaks "
                                 f"{P.PROTOCOL_VERSION}; update the board firmware or skinsafe")
            if f.type == P.STREAM_DATA:
                self.stream.append(f)
            else:
                frames.append(f)
        return frames

    def request(self, msg_type: int, payload: bytes = b"") -> bytes:
        """Send a command and return the data of its OK answer; raise BoardError on refusal or silence."""
        name = P.COMMANDS.get(msg_type, hex(msg_type))
        why = "no answer"
        for attempt in range(self.retries + 1):
            if attempt:
                self.resent += 1
                self.parser.buf.clear()  # a half frame left by a lost byte would swallow the next answer
                time.sleep(min(self.backoff * 2 ** (attempt - 1), 1.0))
            self.seq = (self.seq + 1) & 0xFFFF
            frame = P.encode_frame(msg_type, self.seq, self.uid, payload)
            try:
                self.ser.write(frame)
            except (serial.SerialException, OSError) as e:
                raise BoardError(f"{self.port}: the serial link failed ({e}); check the cable and the board") from None
            self.tx_bytes += len(frame)
            wire = (len(frame) + self.max_chunk + 2 * P.OVERHEAD) * BITS_PER_BYTE / self.baud
            deadline = time.monotonic() + self.timeout + wire
            crc = self.parser.crc_errors
            while time.monotonic() < deadline:
                match = [f for f in self._read() if f.type == msg_type | P.RESPONSE and f.seq == self.seq]
                if match:
                    p = match[0].payload
                    if not p:
                        why = "empty answer"
                        break
                    self.last_uid = match[0].uid
                    if p[0] != P.OK:
                        raise BoardError(f"{self.port}: board {match[0].uid:#x} refused {name}: {P.error_text(p)}",
                                         p[0])
                    return p[1:]
                if self.parser.crc_errors != crc:
                    why = "CRC error"
                    break
            else:
                why = "timeout"
        raise BoardError(f"{self.port}: {name} failed after {self.retries + 1} tries ({why}); "
                         "check the cable, the port and that the board is powered")

    # -- commands ----------------------------------------------------------------------------
    def identify(self) -> P.Identity:
        """Who is on this port; also sizes config chunks to what the board accepts."""
        data = self.request(P.IDENTIFY)
        info = P.Identity.unpack(self.last_uid, data)
        self.max_chunk = max(16, min(info.max_chunk, P.MAX_PAYLOAD - 64))
        return info

    def write_config(self, data: bytes, digest: bytes, restarts: int = 2) -> None:
        """Begin, send every chunk, commit. A board that lost the transfer (it reset) gets it again from the start."""
        for attempt in range(restarts + 1):
            try:
                self.request(P.CONFIG_BEGIN, P.BEGIN_REQ.pack(len(data), digest))
                step = self.max_chunk
                for off in range(0, len(data), step):
                    nxt = P.CHUNK_RESP.unpack(self.request(P.CONFIG_CHUNK, P.CHUNK_REQ.pack(off) + data[off:off + step]))[0]
                    if nxt != min(off + step, len(data)):
                        raise BoardError(f"{self.port}: board acknowledged up to byte {nxt}, sent up to {off + step}",
                                         P.E_RANGE)
                self.request(P.CONFIG_COMMIT, P.COMMIT_REQ.pack(digest))
                return
            except BoardError as e:
                if e.status not in (P.E_NO_TRANSFER, P.E_RANGE, P.E_INCOMPLETE) or attempt == restarts:
                    raise

    def read_config(self, length: int) -> bytes:
        """The board's active config, read back from its flash in chunks."""
        out = bytearray()
        while len(out) < length:
            n = min(self.max_chunk, length - len(out))
            data = self.request(P.CONFIG_READ, P.READ_REQ.pack(len(out), n))
            (off,) = P.READ_RESP.unpack_from(data)
            chunk = data[P.READ_RESP.size:]
            if off != len(out) or not chunk:
                raise BoardError(f"{self.port}: read back returned offset {off} with {len(chunk)} bytes, "
                                 f"asked for {n} at {len(out)}")
            out += chunk
        return bytes(out)

    def flash_hash(self) -> bytes:
        """SHA-256 the board computes over its config as re-read from flash (verify without the read-back bytes)."""
        return self.request(P.CONFIG_VERIFY)[:32]

    def start_stream(self, rate_hz: int) -> None:
        self.request(P.STREAM_START, P.START_REQ.pack(rate_hz))

    def stop_stream(self) -> None:
        self.request(P.STREAM_STOP)

    def set_params(self, first: int, thresholds, gains_q8) -> None:
        """Runtime thresholds (ADC counts) and gains (Q8.8) for channels first.. (not written to flash)."""
        v = np.stack([np.asarray(thresholds), np.asarray(gains_q8)], axis=1).astype("<u2")
        self.request(P.SET_PARAMS, P.PARAMS_REQ.pack(first, len(v)) + v.tobytes())

    def reset(self) -> None:
        self.request(P.RESET)

    def read_stream(self, max_wait: float = 0.01) -> list:
        """Stream frames (Frame or FrameRun) received so far, waiting up to `max_wait` for the first bytes."""
        if max_wait > 0 and not self.ser.in_waiting:
            select.select([self.ser.fileno()], [], [], max_wait)
        while self.ser.in_waiting:
            self._read()
        out = list(self.stream)
        self.stream.clear()
        return out
