"""Board emulator process: interface boards (hardware/emulated_board.py) on pseudo-terminals.

Run: `python -m skinsafe.hardware.emulator --board 0x5C1A0000:256 --flash-dir DIR` (or
`skinsafe emulate`); it prints `board UID PORT` per board (and `other PORT` per `--not-a-board`
device), then `ready`. It ends within a second of SIGTERM, SIGINT or (with `--exit-on-stdin-eof`)
its stdin closing: the signal handler only records the signal, and the wake-up fd
(`signal.set_wakeup_fd`) wakes the main loop's `select`, which stops the board threads.
"""
from __future__ import annotations

import argparse
import gc
import math
import os
import select
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

from skinsafe.hardware import protocol as P
from skinsafe.hardware.board_config import channel_rows
from skinsafe.hardware.client import baud_problem
from skinsafe.hardware.emulated_board import BoardSpec, EmulatedBoard, Faults, NotABoard, flash_path

__all__ = ["EmulatorProcess", "add_arguments", "flash_path", "main", "serve"]
STOP_S = 0.5  # how long the board threads get to finish once the emulator stops
MAX_DELAY_S = 60.0  # a --delay beyond it only hangs the host side
SWITCH_S = 0.0005  # with --feed: the interpreter's thread switch interval (default 5 ms)

def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--board", action="append", default=[], metavar="UID:CHANNELS[:KEY=VALUE,...]",
                   help="emulate a board (uid in hex or decimal); repeatable; KEY=VALUE pairs override this board's "
                        f"faults and identity ({', '.join(OVERRIDES)}), e.g. 0x5C1A0001:64:drop=0.001,firmware=2.0.0")
    p.add_argument("--map", help="emulate every board of this taxel map (uid and capacity)")
    p.add_argument("--flash-dir", required=True, help="folder holding one flash file per board")
    p.add_argument("--baud", type=int, default=None, help="pace the link like a UART at this rate (8N1)")
    p.add_argument("--link-dir", help="also create symlinks board-UID -> pty here (for `deploy --all --glob`)")
    p.add_argument("--replay", help=".npy of forces in N to stream instead of the synthetic press: (T, channels), "
                   "or (T, taxels) in the --map's taxel order (e.g. recorded from a MuJoCo simulation)")
    p.add_argument("--feed", metavar="NAME", help="with --map: stream each board's channels from this shared-memory "
                   "force feed (core/skin/force_feed.py, written by a simulation) instead of the synthetic press")
    p.add_argument("--firmware", default="1.0.0", help="firmware version to report (fault: a wrong version)")
    p.add_argument("--protocol", type=int, default=P.PROTOCOL_VERSION, help="protocol version to speak")
    p.add_argument("--max-chunk", type=int, default=1024,
                   help=f"largest config chunk the board accepts ({P.MIN_CHUNK}..{P.MAX_CHUNK})")
    p.add_argument("--max-rate", dest="max_rate_hz", type=int, default=2000, help="fastest stream rate, Hz")
    p.add_argument("--drop", type=float, default=0.0, help="fault: probability a byte is lost")
    p.add_argument("--flip", type=float, default=0.0, help="fault: probability a byte gets a bit flipped")
    p.add_argument("--delay", type=float, default=0.0, help="fault: seconds before a response ...")
    p.add_argument("--delay-p", type=float, default=1.0, help="... with this probability (default: every one)")
    p.add_argument("--reset-at-chunk", type=int, default=None, help="fault: reboot when the k-th chunk arrives")
    p.add_argument("--resets", type=int, default=1, help="how often that reset happens (-1: always)")
    p.add_argument("--malformed", type=float, default=0.0, help="fault: probability an answer is cut short")
    p.add_argument("--old-frames", type=float, default=0.0,
                   help="fault: probability a stream frame is followed by an older one again (a replayed counter)")
    p.add_argument("--foreign-frames", type=float, default=0.0,
                   help="fault: probability a stream frame is followed by a frame of another board (another uid)")
    p.add_argument("--lost-start-answers", type=int, default=0, metavar="K",
                   help="fault: the first K stream-start answers are lost (the board starts all the same)")
    p.add_argument("--unplug-after", type=int, default=0, metavar="FRAMES",
                   help="fault: the cable is pulled (the pty closes) after this many stream frames")
    p.add_argument("--streaming", type=int, default=0, metavar="HZ",
                   help="fault: the board boots streaming at this rate, as if an earlier host had left it so")
    p.add_argument("--hashless-commit", type=int, default=0, choices=[0, 1],
                   help="fault: a commit is answered ok without the committed config's hash")
    p.add_argument("--flash-write-lost", type=int, default=0, choices=[0, 1],
                   help="fault: flash writes are silently lost (the board runs the new config from RAM)")
    p.add_argument("--config-len", type=int, default=None,
                   help="fault: identify reports this config length (reads past the config return erased 0xFF)")
    p.add_argument("--not-a-board", type=int, default=0, metavar="N",
                   help="also open N devices that answer text, not frames (link names other-K)")
    p.add_argument("--seed", type=int, default=0, help="run seed; each board's fault seed is derived from it and its uid")
    p.add_argument("--exit-on-stdin-eof", action="store_true", help="stop when stdin closes (parent died)")


OVERRIDES = {"drop": float, "flip": float, "delay": float, "delay_p": float, "reset_at_chunk": int, "resets": int,
             "malformed": float, "firmware": str, "protocol": int, "max_chunk": int, "max_rate_hz": int,
             "old_frames": float, "foreign_frames": float, "lost_start_answers": int, "unplug_after": int,
             "streaming": int, "hashless_commit": int, "flash_write_lost": int, "config_len": int}


def _firmware(text: str) -> tuple[int, int, int]:
    try:
        fw = tuple(int(x) for x in text.split("."))
    except ValueError:
        fw = ()
    if len(fw) != 3:
        raise SystemExit(f"firmware {text!r}: give MAJOR.MINOR.PATCH, e.g. 1.0.0")
    return fw


def _spec(uid: int, n: int, opts: dict, where: str) -> BoardSpec:
    """A board's spec from the run's options with its own overrides; checked before any pty opens."""
    for k in ("drop", "flip", "delay_p", "malformed", "old_frames", "foreign_frames"):
        if not 0.0 <= opts[k] <= 1.0:
            raise SystemExit(f"{where}: {k.replace('_', '-')} {opts[k]} is a probability; give 0..1")
    if not P.MIN_CHUNK <= opts["max_chunk"] <= P.MAX_CHUNK:
        raise SystemExit(f"{where}: max chunk {opts['max_chunk']} outside {P.MIN_CHUNK}..{P.MAX_CHUNK} "
                         "(the protocol minimum and what a frame can carry)")
    if not 1 <= n <= P.MAX_CHANNELS:
        raise SystemExit(f"{where}: {n} channels; a board has 1..{P.MAX_CHANNELS}")
    for k in ("delay", "lost_start_answers", "unplug_after", "streaming"):
        if opts[k] < 0:
            raise SystemExit(f"{where}: {k.replace('_', '-')} {opts[k]} is negative")
    if not (math.isfinite(opts["delay"]) and opts["delay"] <= MAX_DELAY_S):
        raise SystemExit(f"{where}: delay {opts['delay']} s: give 0..{MAX_DELAY_S:g} s")
    if opts["reset_at_chunk"] is not None and opts["reset_at_chunk"] < 1:
        raise SystemExit(f"{where}: reset-at-chunk {opts['reset_at_chunk']}: give the chunk, 1 or more")
    if opts["resets"] < -1:
        raise SystemExit(f"{where}: resets {opts['resets']}: give a count, or -1 for every transfer")
    if not 0 <= opts["protocol"] <= 255:
        raise SystemExit(f"{where}: protocol {opts['protocol']}: give 0..255 (the frame's 8-bit version field)")
    if not 1 <= opts["max_rate_hz"] <= 65535:
        raise SystemExit(f"{where}: max rate {opts['max_rate_hz']} Hz: give 1..65535 (the 16-bit identity field)")
    if opts["streaming"] > opts["max_rate_hz"]:
        raise SystemExit(f"{where}: streaming at {opts['streaming']} Hz exceeds the board's max rate {opts['max_rate_hz']}")
    if opts["config_len"] is not None and not 0 <= opts["config_len"] < 2 ** 32:
        raise SystemExit(f"{where}: config length {opts['config_len']} does not fit the 32-bit field")
    faults = Faults(opts["drop"], opts["flip"], opts["delay"], opts["delay_p"], opts["reset_at_chunk"], opts["resets"],
                    opts["malformed"], opts["seed"], opts["old_frames"], opts["foreign_frames"],
                    opts["lost_start_answers"], opts["unplug_after"], opts["streaming"], bool(opts["hashless_commit"]),
                    bool(opts["flash_write_lost"]), opts["config_len"])
    return BoardSpec(uid, n, _firmware(opts["firmware"]), opts["protocol"], opts["max_chunk"],
                     opts["max_rate_hz"], faults=faults)


def _specs(args):
    """(BoardSpec, the map's Board or None) per emulated board, and the map (or None)."""
    base = {k: getattr(args, k) for k in OVERRIDES} | {"seed": args.seed}
    if args.seed < 0 or args.not_a_board < 0:
        raise SystemExit(f"--seed {args.seed}, --not-a-board {args.not_a_board}: give numbers >= 0")
    if args.baud is not None and baud_problem(args.baud):
        raise SystemExit(baud_problem(args.baud))
    out = []
    for b in args.board:
        uid, _, rest = b.partition(":")
        n, _, extra = rest.partition(":")
        opts = dict(base)
        try:
            for kv in filter(None, extra.split(",")):
                k, v = kv.split("=")
                opts[k] = OVERRIDES[k](v)
            out.append((_spec(int(uid, 0), int(n or 256), opts, f"--board {b}"), None))
        except (ValueError, KeyError):
            raise SystemExit(f"--board {b!r}: give UID:CHANNELS[:KEY=VALUE,...], e.g. 0x5C1A0000:256:drop=0.001 "
                             f"(keys: {', '.join(OVERRIDES)})") from None
    design = None
    if args.map:
        from skinsafe.core.skin.taxel_map import load
        design = load(args.map)
        out += [(_spec(b.uid, b.capacity, base, f"board '{b.name}'"), b) for b in design.boards]
    if not out:
        raise SystemExit("give at least one --board UID:CHANNELS or --map skin.json")
    return out, design


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


def board_feed(feed, board, design, n_channels: int):
    """() -> (n_channels,) forces of `board`'s channels, read from the shared-memory `feed` (taxel order), or None
    while its writer is stuck in the middle of a write (the board then sends no frame, as a board whose ADC did not
    answer: the host names it silent if that lasts, never fed a stale press)."""
    from skinsafe.core.skin.force_feed import FeedError

    rows = channel_rows(design, board)
    channels = design.taxels.channel[rows].astype(np.intp)
    out = np.zeros(n_channels)

    def forces() -> np.ndarray | None:
        try:
            out[channels] = feed.read(rows)[2]
        except FeedError:
            return None
        return out
    return forces


def _open_feed(args, design):
    if not args.feed:
        return None
    from skinsafe.core.skin.force_feed import FeedError, ForceFeed
    if design is None:
        raise SystemExit("--feed needs --map: the feed holds forces in the map's taxel order")
    if args.replay:
        raise SystemExit("give --feed or --replay, not both")
    try:
        feed = ForceFeed.attach(args.feed)
    except FeedError as e:
        raise SystemExit(f"--feed: {e}") from None
    if feed.n != design.n_taxels:
        feed.close()
        raise SystemExit(f"--feed {args.feed} holds {feed.n} taxels, the map {design.n_taxels}; feed it from the "
                         "simulation of this map")
    sys.setswitchinterval(SWITCH_S)  # a simulation's boards stream in real time: no thread waits 5 ms for the GIL
    gc.freeze()  # ... nor for a collector pass over every object imported so far
    return feed


def serve(args, out=sys.stdout) -> int:
    """Start the boards, print `board UID PORT` lines and `ready`, run until SIGTERM/SIGINT (or stdin EOF)."""
    signals: list[int] = []
    wake_r, wake_w = os.pipe()
    for fd in (wake_r, wake_w):
        os.set_blocking(fd, False)
    old_fd = signal.set_wakeup_fd(wake_w)
    old = {s: signal.signal(s, lambda signum, _f: signals.append(signum)) for s in (signal.SIGTERM, signal.SIGINT)}
    specs, design = _specs(args)
    replay = np.load(args.replay) if args.replay else None
    feed = _open_feed(args, design)
    boards = [EmulatedBoard(s, flash_path(args.flash_dir, s.uid), args.baud,
                            None if replay is None else board_replay(replay, s, b, design),
                            feed=None if feed is None or b is None else board_feed(feed, b, design, s.n_channels))
              for s, b in specs]
    others = [NotABoard() for _ in range(args.not_a_board)]
    links = []
    if args.link_dir:
        Path(args.link_dir).mkdir(parents=True, exist_ok=True)
        names = [f"board-{b.spec.uid:016x}" for b in boards] + [f"board-other-{k}" for k in range(len(others))]
        for name, dev in zip(names, boards + others):
            link = Path(args.link_dir) / name
            link.unlink(missing_ok=True)
            link.symlink_to(dev.port)
            links.append(link)
    stop = threading.Event()
    threads = [threading.Thread(target=d.run, args=(stop,), daemon=True) for d in boards + others]
    for t in threads:
        t.start()
    for b in boards:
        print(f"board {b.spec.uid:#x} {b.port}", file=out)
    for d in others:
        print(f"other {d.port}", file=out)
    print("ready", file=out, flush=True)
    watch = [wake_r] + ([sys.stdin.fileno()] if args.exit_on_stdin_eof else [])
    while not signals:
        ready = select.select(watch, [], [], 1.0)[0]
        if wake_r in ready:
            os.read(wake_r, 512)
        if len(watch) > 1 and watch[1] in ready and not os.read(watch[1], 4096):
            break
    stop.set()  # here in the main loop, never in the signal handler
    deadline = time.monotonic() + STOP_S
    for t in threads:
        t.join(max(0.0, deadline - time.monotonic()))
    for link in links:
        link.unlink(missing_ok=True)
    for d, t in zip(boards + others, threads):
        if not t.is_alive():  # a thread still in a fault's delay keeps its fds; the process exit closes them
            d.close()  # (an unplugged board closed its own)
    if feed is not None and not any(t.is_alive() for t in threads):
        feed.close()
    signal.set_wakeup_fd(old_fd)
    for s, h in old.items():
        signal.signal(s, h)
    os.close(wake_r)
    os.close(wake_w)
    return 0


class EmulatorProcess:
    """Start `python -m skinsafe.hardware.emulator ...` as a child process; `.ports` maps uid -> pty path."""

    def __init__(self, boards: list[tuple], flash_dir: str | Path, *extra: str, timeout: float = 30.0):
        """`boards`: (uid, channels) or (uid, channels, "key=value,...") per board."""
        cmd = [sys.executable, "-m", "skinsafe.hardware.emulator", "--flash-dir", str(flash_dir),
               "--exit-on-stdin-eof", *extra]
        for uid, n, *over in boards:
            cmd += ["--board", f"{uid:#x}:{n}" + (f":{over[0]}" if over and over[0] else "")]
        self.proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        self.ports: dict[int, str] = {}
        self.others: list[str] = []
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            line = self.proc.stdout.readline()
            if not line:
                raise RuntimeError(f"emulator exited with {self.proc.wait()} before it was ready: {' '.join(cmd)}")
            if line.strip() == "ready":
                return
            if line.startswith("other "):
                self.others.append(line.split()[1])
                continue
            _, uid, port = line.split()
            self.ports[int(uid, 16)] = port
        self.close()
        raise RuntimeError("emulator did not become ready")

    def signal(self, signum: int = signal.SIGTERM, limit: float = 5.0) -> float:
        """Send `signum` and wait for the process to end; seconds it took (inf: it had to be killed)."""
        t0 = time.monotonic()
        self.proc.send_signal(signum)
        try:
            self.proc.wait(limit)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
            return float("inf")
        return time.monotonic() - t0

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.stdin.close()
            try:
                self.proc.wait(5)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        for f in (self.proc.stdin, self.proc.stdout):
            f.close()

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
