"""Board emulator: interface boards on pseudo-terminals, in their own process.

Each emulated board owns a pty (`os.openpty`); the host opens the slave path with pyserial like
`/dev/ttyUSB0`. Flash is a file written atomically on commit. Faults (dropped bytes, flipped bits,
delays, a reset in the middle of a transfer, a wrong firmware or protocol version) are injected on
the emulated link. At `baud`, the emulator paces its link at 10 bits per byte (8N1), so a pty
takes as long as a real UART would. Streams synthetic readings or replays recorded forces.

Run: `python -m skinsafe.hardware.emulator --board 0x5C1A0000:256 --flash-dir DIR` (or
`skinsafe emulate`); it prints `board UID PORT` per board, then `ready`.
"""
from __future__ import annotations

import argparse
import hashlib
import os
import select
import signal
import subprocess
import sys
import threading
import time
import tty
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from skinsafe.core.skin.files import atomic_write
from skinsafe.core.skin.model import DesignError
from skinsafe.hardware import protocol as P
from skinsafe.hardware.board_config import ENTRY, GAIN_ONE, BoardConfig, channel_rows, default_sensor
from skinsafe.hardware.board_config import HEADER as CONFIG_HEADER

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
    seed: int = 0


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
                 replay: np.ndarray | None = None, encode=None):
        self.spec, self.flash_path, self.baud = spec, Path(flash_path), baud
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)
        os.set_blocking(self.master, False)
        self.port = os.ttyname(self.slave)
        self.rng = np.random.default_rng(spec.faults.seed)
        self.encode = encode or default_sensor().encode
        self.replay = replay
        self.resets_left = spec.faults.resets
        self.chunks_seen = 0
        self.tx_dropped = 0
        self._boot()

    # -- state -------------------------------------------------------------------------------
    def _boot(self) -> None:
        self.boots = getattr(self, "boots", -1) + 1
        self.parser = P.FrameParser()
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
        self.gain = np.ones(n)
        self.params_changed = False
        if self.config is not None:
            e = self.config.entries
            on = (e["flags"] & 1).astype(bool)
            self.threshold[e["channel"][on]] = e["threshold"][on]
            self.gain[e["channel"]] = e["gain"] / GAIN_ONE

    @property
    def config_hash(self) -> bytes:
        return hashlib.sha256(self.config_bytes).digest() if self.config is not None else bytes(32)

    def identity(self) -> P.Identity:
        flags = (P.FLAG_STREAMING * self.streaming | P.FLAG_CONFIG_VALID * (self.config is not None)
                 | P.FLAG_PARAMS_CHANGED * self.params_changed)
        return P.Identity(self.spec.uid, self.spec.protocol, self.spec.firmware, self.spec.n_channels,
                          self.spec.max_chunk, P.CAP_FORCE | P.CAP_SET_PARAMS | P.CAP_READBACK,
                          self.spec.max_rate_hz, flags, self.config_hash, len(self.config_bytes))

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
            if frame.uid not in (P.BROADCAST_UID, self.spec.uid) or frame.type & P.RESPONSE:
                continue
            handler = self.HANDLERS.get(frame.type)
            try:
                out = handler(self, frame.payload) if handler else P.response(P.E_UNKNOWN, b"%d" % frame.type)
            except Exception as e:  # a malformed request must never kill the board
                out = P.response(P.E_MALFORMED, str(e).encode("ascii", "replace")[:200])
            if out is None:
                continue
            f = self.spec.faults
            if f.delay_s and (f.delay_p >= 1 or self.rng.random() < f.delay_p):
                time.sleep(f.delay_s)
            self.send(P.encode_frame(frame.type | P.RESPONSE, frame.seq, self.spec.uid, out, self.spec.protocol))
            if frame.type == P.RESET:
                self.reboot()

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
        limit = CONFIG_HEADER.size + ENTRY.itemsize * self.spec.n_channels
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
            return P.response(P.E_CONFIG, str(e).encode()[:200])
        if cfg.uid != self.spec.uid or cfg.capacity != self.spec.n_channels:
            return P.response(P.E_CONFIG, b"config for uid %#x with %d channels; this board is %#x with %d"
                              % (cfg.uid, cfg.capacity, self.spec.uid, self.spec.n_channels))
        try:
            atomic_write(self.flash_path, data)
        except OSError as e:
            return P.response(P.E_FLASH, str(e).encode()[:200])
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
        offset, length = P.READ_REQ.unpack(p)
        if length > self.spec.max_chunk:
            return P.response(P.E_PARAM, b"read of %d bytes exceeds max chunk %d" % (length, self.spec.max_chunk))
        return P.response(P.OK, P.READ_RESP.pack(offset) + self.config_bytes[offset:offset + length])

    def _start(self, p: bytes) -> bytes:
        (rate,) = P.START_REQ.unpack(p)
        if not 1 <= rate <= self.spec.max_rate_hz:
            return P.response(P.E_PARAM, b"rate %d Hz outside 1..%d" % (rate, self.spec.max_rate_hz))
        self.streaming, self.rate, self.next_tick = True, rate, time.monotonic()
        return P.response(P.OK)

    def _stop(self, _: bytes) -> bytes:
        self.streaming = False
        return P.response(P.OK)

    def _params(self, p: bytes) -> bytes:
        first, count = P.PARAMS_REQ.unpack_from(p)
        if first + count > self.spec.n_channels or len(p) != P.PARAMS_REQ.size + 4 * count:
            return P.response(P.E_PARAM, b"channels %d..%d of %d" % (first, first + count, self.spec.n_channels))
        v = np.frombuffer(p, "<u2", 2 * count, P.PARAMS_REQ.size).reshape(count, 2)
        self.threshold[first:first + count] = v[:, 0]
        self.gain[first:first + count] = v[:, 1] / GAIN_ONE
        self.params_changed = True
        return P.response(P.OK)

    def _reset(self, _: bytes) -> bytes:
        return P.response(P.OK)

    HANDLERS = {P.IDENTIFY: _identify, P.CONFIG_BEGIN: _begin, P.CONFIG_CHUNK: _chunk, P.CONFIG_COMMIT: _commit,
                P.CONFIG_READ: _read, P.STREAM_START: _start, P.STREAM_STOP: _stop, P.SET_PARAMS: _params,
                P.RESET: _reset, P.CONFIG_VERIFY: _verify}

    # -- streaming ---------------------------------------------------------------------------
    def forces(self, t: float) -> np.ndarray:
        """Synthetic forces (N): a 12 N press sweeping across the channels once a second, or a replay."""
        n = self.spec.n_channels
        if self.replay is not None:
            return self.replay[self.sample % len(self.replay)]
        c = np.arange(n)
        centre = (t % 1.0) * n
        return 12.0 * np.exp(-0.5 * ((c - centre) / max(1.0, n / 64)) ** 2)

    def stream_frame(self) -> bytes:
        t = time.monotonic() - self.t0
        counts = np.clip(np.asarray(self.encode(self.forces(t)), float) * self.gain, 0, 65535).astype("<u2")
        over = int((counts > self.threshold).sum())
        head = P.STREAM_HEAD.pack(int(t * 1e6), self.sample & 0xFFFFFFFF, len(counts), over)
        self.sample += 1
        return P.encode_frame(P.STREAM_DATA, self.sample, self.spec.uid, head + counts.tobytes(), self.spec.protocol)

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
                self.send(self.stream_frame())
                self.next_tick = max(self.next_tick + 1.0 / self.rate, time.monotonic() - 1.0 / self.rate)

    def close(self) -> None:
        os.close(self.master)
        os.close(self.slave)


def flash_path(flash_dir: str | Path, uid: int) -> Path:
    return Path(flash_dir) / f"board-{uid:016x}.flash"


# -- process ---------------------------------------------------------------------------------
def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--board", action="append", default=[], metavar="UID:CHANNELS",
                   help="emulate a board (uid in hex or decimal); repeatable")
    p.add_argument("--map", help="emulate every board of this taxel map (uid and capacity)")
    p.add_argument("--flash-dir", required=True, help="folder holding one flash file per board")
    p.add_argument("--baud", type=int, default=None, help="pace the link like a UART at this rate (8N1)")
    p.add_argument("--link-dir", help="also create symlinks board-UID -> pty here (for `deploy --all --glob`)")
    p.add_argument("--replay", help=".npy of forces in N to stream instead of the synthetic press: (T, channels), "
                   "or (T, taxels) in the --map's taxel order (e.g. recorded from a MuJoCo simulation)")
    p.add_argument("--firmware", default="1.0.0", help="firmware version to report (fault: a wrong version)")
    p.add_argument("--protocol", type=int, default=P.PROTOCOL_VERSION, help="protocol version to speak")
    p.add_argument("--max-chunk", type=int, default=1024, help="largest config chunk the board accepts")
    p.add_argument("--drop", type=float, default=0.0, help="fault: probability a byte is lost")
    p.add_argument("--flip", type=float, default=0.0, help="fault: probability a byte gets a bit flipped")
    p.add_argument("--delay", type=float, default=0.0, help="fault: seconds before a response ...")
    p.add_argument("--delay-p", type=float, default=1.0, help="... with this probability (default: every one)")
    p.add_argument("--reset-at-chunk", type=int, default=None, help="fault: reboot when the k-th chunk arrives")
    p.add_argument("--resets", type=int, default=1, help="how often that reset happens (-1: always)")
    p.add_argument("--seed", type=int, default=0, help="seed of the fault generator")
    p.add_argument("--exit-on-stdin-eof", action="store_true", help="stop when stdin closes (parent died)")


def _specs(args):
    """(BoardSpec, the map's Board or None) per emulated board, and the map (or None)."""
    faults = Faults(args.drop, args.flip, args.delay, args.delay_p, args.reset_at_chunk, args.resets, args.seed)
    try:
        fw = tuple(int(x) for x in args.firmware.split("."))
    except ValueError:
        fw = ()
    if len(fw) != 3:
        raise SystemExit(f"--firmware {args.firmware!r}: give MAJOR.MINOR.PATCH, e.g. 1.0.0")
    pairs = []
    for b in args.board:
        uid, _, n = b.partition(":")
        try:
            pairs.append((int(uid, 0), int(n or 256), None))
        except ValueError:
            raise SystemExit(f"--board {b!r}: give UID:CHANNELS, e.g. 0x5C1A0000:256") from None
    design = None
    if args.map:
        from skinsafe.core.skin.taxel_map import load
        design = load(args.map)
        pairs += [(b.uid, b.capacity, b) for b in design.boards]
    if not pairs:
        raise SystemExit("give at least one --board UID:CHANNELS or --map skin.json")
    return [(BoardSpec(uid, n, fw, args.protocol, args.max_chunk, faults=faults), b) for uid, n, b in pairs], design


def board_replay(forces: np.ndarray, spec: BoardSpec, board, design) -> np.ndarray:
    """A board's (T, channels) forces from a replay of (T, channels), or of (T, taxels) in the map's order
    (e.g. `SkinReadout.read` recorded every step of a MuJoCo simulation)."""
    if forces.ndim == 2 and design is not None and board is not None and forces.shape[1] == design.n_taxels:
        rows = channel_rows(design, board)
        out = np.zeros((len(forces), spec.n_channels))
        out[:, design.taxels.channel[rows]] = forces[:, rows]
        return out
    if forces.ndim == 2 and forces.shape[1] == spec.n_channels:
        return forces
    taxels = f" or (T, {design.n_taxels}) taxels of the map" if design is not None else ""
    raise SystemExit(f"--replay has shape {forces.shape}; board {spec.uid:#x} needs (T, {spec.n_channels}) "
                     f"channels{taxels}")


def serve(args, out=sys.stdout) -> int:
    """Start the boards, print `board UID PORT` lines and `ready`, run until a signal (or stdin EOF)."""
    specs, design = _specs(args)
    replay = np.load(args.replay) if args.replay else None
    boards = [EmulatedBoard(s, flash_path(args.flash_dir, s.uid), args.baud,
                            None if replay is None else board_replay(replay, s, b, design)) for s, b in specs]
    links = []
    if args.link_dir:
        Path(args.link_dir).mkdir(parents=True, exist_ok=True)
        for b in boards:
            link = Path(args.link_dir) / f"board-{b.spec.uid:016x}"
            link.unlink(missing_ok=True)
            link.symlink_to(b.port)
            links.append(link)
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    threads = [threading.Thread(target=b.run, args=(stop,), daemon=True) for b in boards]
    for t in threads:
        t.start()
    for b in boards:
        print(f"board {b.spec.uid:#x} {b.port}", file=out)
    print("ready", file=out, flush=True)
    if args.exit_on_stdin_eof:
        threading.Thread(target=lambda: (sys.stdin.read(), stop.set()), daemon=True).start()
    try:
        while not stop.wait(0.2):
            pass
    except KeyboardInterrupt:
        stop.set()
    for t in threads:
        t.join(1.0)
    for link in links:
        link.unlink(missing_ok=True)
    for b in boards:
        b.close()
    return 0


class EmulatorProcess:
    """Start `python -m skinsafe.hardware.emulator ...` as a child process; `.ports` maps uid -> pty path."""

    def __init__(self, boards: list[tuple[int, int]], flash_dir: str | Path, *extra: str, timeout: float = 30.0):
        cmd = [sys.executable, "-m", "skinsafe.hardware.emulator", "--flash-dir", str(flash_dir),
               "--exit-on-stdin-eof", *extra]
        for uid, n in boards:
            cmd += ["--board", f"{uid:#x}:{n}"]
        self.proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        self.ports: dict[int, str] = {}
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            line = self.proc.stdout.readline()
            if not line:
                raise RuntimeError(f"emulator exited with {self.proc.wait()} before it was ready: {' '.join(cmd)}")
            if line.strip() == "ready":
                return
            _, uid, port = line.split()
            self.ports[int(uid, 16)] = port
        self.close()
        raise RuntimeError("emulator did not become ready")

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.stdin.close()
            try:
                self.proc.wait(5)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self.proc.stdout.close()

    def __enter__(self) -> "EmulatorProcess":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m skinsafe.hardware.emulator", description=__doc__.split("\n\n")[0])
    add_arguments(p)
    return serve(p.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
