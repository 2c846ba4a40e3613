"""Link faults between boards and host, for tests and `skinsafe bench runtime --faults`: a proxy on
pseudo-terminals that passes every byte until a fault's time comes.

Each board's port gets a new pseudo-terminal for the host; one thread copies bytes both ways. From
`arm()` on, the boards' stream is cut into whole frames (`FrameParser`, re-encoded byte for byte) so
a fault lands between frames. Faults, `at` seconds after `arm()` on one board (default the first):
- board-unplug: the host's side of the link closes (reads fail, as a pulled USB cable);
- frame-delay: the board's frames are held back `delay_s` (default 50 ms), then delivered at once;
- frame-lag: every frame from then on arrives later than the one before (by half the time since the fault:
  a link slower than the board), steadily, never a gap of more than 1.5 frame periods;
- frame-replay: a frame is sent again 20 ms after it first went through (its counter is older);
- foreign-uid: a copy of a frame with another board's uid;
- crc-storm: the next 10 frames arrive with one byte of their payload flipped (the board silent with corrupt frames);
- crc-burst: every other frame, 5 of them, corrupt so (good frames between: the 5-corrupt-frames-within-1-s path);
  `spans[board]`: host time from its first corrupt frame to its 5th.
`onsets`: board id -> host time.monotonic() its fault took effect (the first bad, held or lost byte; a frame-lag, a
ramp, once the newest frame passed to the host is older than the run's silence since the board sent it,
measured on the frames the proxy passed: `arm(silence_s)`).
"""
from __future__ import annotations

import os
import select
import threading
import time
import tty

from skinsafe.hardware import protocol as P

LINK_FAULTS = ("board-unplug", "frame-delay", "frame-lag", "frame-replay", "foreign-uid", "crc-storm", "crc-burst")
BURST_FRAMES = 5  # crc-burst: corrupt frames, every other one (the boards' reader names 5 within 1 s a storm)
LAG_RATE = 0.5  # frame-lag: s of extra delay per s since the fault
DELAY_S = 0.05
REPLAY_AFTER_S = 0.02
STORM_FRAMES = 10


class _Link:
    def __init__(self, port: str, delay_s: float):
        self.delay_s = delay_s
        self.board = os.open(port, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)
        os.set_blocking(self.master, False)
        self.port = os.ttyname(self.slave)
        self.parser = P.FrameParser(P.MAX_PAYLOAD)
        self.framed = False
        self.held: list[tuple[float, bytes, float]] = []  # (due time, bytes, time read from the board) to the host
        self.passed: list[tuple[float, float]] = []  # a frame-lag's frames: (read from the board, written to the host)
        self.silence_s: float | None = None
        self.fault = None  # (kind, start time)
        self.storm = 0
        self.span: float | None = None  # crc-burst: its first corrupt frame -> its last
        self.replay = None  # bytes of a frame to send again
        self.unplugged = False
        self.onset: float | None = None  # host time the fault took effect

    def to_host(self, data: bytes, now: float) -> None:
        if self.unplugged:
            return
        if not self.framed:
            self.held.append((now, data, now))
            return
        for f in self.parser.feed(data):
            raw = P.encode_frame(f.type, f.seq, f.uid, f.payload, f.version)
            self.held.append((now, self._apply(raw, f, now), now))

    def _apply(self, raw: bytes, f: P.Frame, now: float) -> bytes:
        kind, start = self.fault or ("", float("inf"))
        if now < start or f.type != P.STREAM_DATA:
            return raw
        if kind == "frame-delay" and now < start + self.delay_s:
            self.onset = self.onset or now
            self.held.append((start + self.delay_s, raw, now))
            return b""
        if kind == "frame-lag":
            self.held.append((now + (now - start) * LAG_RATE, raw, now))
            return b""
        if kind == "frame-replay" and self.replay is None:
            self.replay = raw
            self.onset = now + REPLAY_AFTER_S
            self.held.append((now + REPLAY_AFTER_S, raw, now))
        elif kind == "foreign-uid" and self.replay is None:
            self.replay, self.onset = raw, now
            return raw + P.encode_frame(f.type, f.seq, f.uid ^ 0x1000, f.payload, f.version)
        elif kind == "crc-storm" and self.storm < STORM_FRAMES or kind == "crc-burst" and self.storm < 2 * BURST_FRAMES:
            self.onset = self.onset or now
            self.storm += 1
            if kind == "crc-burst" and self.storm % 2 == 0:
                return raw
            if kind == "crc-burst" and self.storm == 2 * BURST_FRAMES - 1:
                self.span = now - self.onset
            b = bytearray(raw)
            b[P.HEADER_SIZE + 4] ^= 0xFF
            return bytes(b)
        return raw

    def flush(self, now: float) -> None:
        if self.fault and self.fault[0] == "board-unplug" and now >= self.fault[1] and not self.unplugged:
            self.unplugged = True
            self.onset = time.monotonic()
            os.close(self.master)
            self.held = []
            return
        due = [(b, read) for t, b, read in self.held if t <= now]
        self.held = [h for h in self.held if h[0] > now]
        data = b"".join(b for b, _ in due)
        if self.fault and self.fault[0] == "frame-lag":
            self.passed += [(read, now) for b, read in due if b]
            self._lag_onset()
        if data and not self.unplugged:
            try:
                os.write(self.master, data)
            except (BlockingIOError, OSError):
                pass  # a host that does not read loses data, as on a full USB buffer

    def _lag_onset(self) -> None:
        """The first time the newest frame written to the host was older than the silence (since read from the board)."""
        if self.onset is not None or self.silence_s is None:
            return
        for (read, wrote), (_, later) in zip(self.passed, self.passed[1:]):
            if later >= self.fault[1] and read + self.silence_s < later:
                self.onset = max(wrote, read + self.silence_s)
                return
        self.passed = self.passed[-1:]  # the newest is all a later onset needs

    def close(self) -> None:
        for fd in (self.board, self.slave) + (() if self.unplugged else (self.master,)):
            try:
                os.close(fd)
            except OSError:
                pass


class LinkFaults:
    """Proxies for `ports` (board id -> port) with `faults` [(kind, at, board id or None)]; `.ports` for the host."""

    def __init__(self, ports: dict[int, str], faults: list[tuple[str, float, int | None]], delay_s: float = DELAY_S):
        self.links = {b: _Link(p, delay_s) for b, p in ports.items()}
        self.ports = {b: link.port for b, link in self.links.items()}
        first = min(ports)
        self.faults = [(kind, at, first if b is None else b) for kind, at, b in faults]
        unknown = [b for _, _, b in self.faults if b not in self.links]
        if unknown:
            self.close()
            raise ValueError(f"link fault on board {unknown[0]}: the map's boards are {sorted(self.links)}")
        self._run = True
        self.thread = threading.Thread(target=self._pump, name="link-faults", daemon=True)
        self.thread.start()

    @property
    def onsets(self) -> dict[int, float]:
        return {b: x.onset for b, x in self.links.items() if x.onset is not None}

    @property
    def spans(self) -> dict[int, float]:
        return {b: x.span for b, x in self.links.items() if x.span is not None}

    def arm(self, silence_s: float) -> None:
        """Start the fault clock (the robot starts moving); `silence_s`: the run's, for a frame-lag's onset."""
        now = time.monotonic()
        for kind, at, b in self.faults:
            self.links[b].fault = (kind, now + at)
            self.links[b].framed = True
            self.links[b].silence_s = silence_s

    def _pump(self) -> None:
        while self._run:
            links = list(self.links.values())
            fds = [x.board for x in links] + [x.master for x in links if not x.unplugged]
            try:
                ready = select.select(fds, [], [], 0.002)[0]
            except (OSError, ValueError):
                ready = []
            now = time.monotonic()
            for x in links:
                if x.board in ready:
                    try:
                        x.to_host(os.read(x.board, 65536), now)
                    except (BlockingIOError, OSError):
                        pass
                if not x.unplugged and x.master in ready:
                    try:
                        os.write(x.board, os.read(x.master, 65536))
                    except (BlockingIOError, OSError):
                        pass
                x.flush(now)

    def close(self) -> None:
        self._run = False
        if hasattr(self, "thread"):
            self.thread.join(1.0)
        for x in self.links.values():
            x.close()

    def __enter__(self) -> "LinkFaults":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
