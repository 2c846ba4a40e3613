"""The live view's publisher outside the control loop's process (`skinsafe run --view`).

A publisher thread in the loop's process would share its interpreter lock and real-time priority. The
loop's tap (`SharedTap`) copies the newest tick's arrays at the view's rate into shared memory
(`SharedFrames`, a seqlock as core/skin/force_feed.py's: nobody waits), and the publisher process (`python -m
skinsafe.core.runtime.view_share`, started by `start_publisher`) encodes it and sends it on as the view stream
(core/runtime/view_stream.py). The loop copies only while the publisher reads (a lease it renews with each read,
and it reads only while a viewer is connected): nothing is copied for a view nobody watches, or one that
stalls. Encoding the message in the loop, as before, grew with the retracting pool (its JSON list:
milliseconds with thousands of taxels); the copy does not (`skinsafe bench runtime --tap`).
"""
from __future__ import annotations

import os
import struct
import subprocess
import sys
import time
from multiprocessing import resource_tracker, shared_memory

import numpy as np

from skinsafe.core.runtime.tap import Tap
from skinsafe.core.runtime.tick import Tick
from skinsafe.core.runtime.view_stream import ViewPublisher, decode
from skinsafe.core.skin.force_feed import release


class SharedFrames:
    """Ticks in a named shared-memory block, as arrays (no encoding in the loop), in `slots` slots.

    One slot (the views'): the newest tick, a seqlock as core/skin/force_feed.py's (nobody waits). The writer makes
    the slot's `seq` odd, copies, makes it even; a reader copies and retries while it was odd or changed. A reader's
    `newest` also renews its lease (`wanted` for LEASE_S more): the writer skips ticks nobody will read.

    Several slots (the record's writer process, core/app/record_writer.py): a ring every tick goes through in order,
    `push` by the loop (False when full: it never waits) and `take` by the one reader, the forces as float64 and
    copied only when they are a new array (a new reading: the loop keeps its forces' array between readings; the
    reader gives the last one it took meanwhile), a tenth of the ticks at 100 readings a second.

    Layout: `u64 lease end (monotonic ns) | u64 head (ticks pushed) | u64 tail (ticks taken) | u64 0`, then each slot
    `u64 seq | u64 n_pool | u64 text_len | u64 ns | f64 [t, retracting, pool, potential, speed_factor, frames_lost,
    planned?, qd?, dt, force_new, reading_seq, ticked, command_age, command_refused, index, force?, telemetry?, forces copied?] | f64 q, qd,
    command, planned (n_joints each) | f64 board ages (the boards' order, NaN: none) | forces (n_taxels; float32, or
    float64 with `exact`) | i32 pool | text: the stop reason and the flags, U+001E between them`."""

    BLOCK, HEADER, SCALARS, TEXT = 4, 4, 18, 4096
    LEASE_S = 0.25  # several of the view's reads (30 Hz), well under a second of a stalled reader

    def __init__(self, shm: shared_memory.SharedMemory, owner: bool, n_taxels: int, n_joints: int, boards,
                 slots: int = 1, exact: bool = False):
        self.shm, self.owner, self.name = shm, owner, shm.name
        self.n, self.nj, self.boards, self.slots = n_taxels, n_joints, [int(b) for b in boards], slots
        self.dtype = np.dtype(np.float64 if exact else np.float32)
        self.nf = self.SCALARS + 4 * n_joints + len(self.boards)
        self.slot_size = self._slot_size(n_taxels, n_joints, len(self.boards), exact)
        self._block = np.ndarray((self.BLOCK,), np.uint64, shm.buf)
        self._views = [self._slot(8 * self.BLOCK + i * self.slot_size) for i in range(slots)]
        self._pack = struct.Struct(f"<{self.nf}d").pack_into
        self._none = (0.0,) * n_joints
        self._seen, self._frame = 0, None
        self._pushed = self._taken = None  # the ring's forces: the array last copied in, the one last copied out
        if owner:
            self._block[:] = 0

    def _slot(self, at: int) -> tuple:
        """(words, scalars and joints, forces, pool, text) of the slot at byte `at`, and its scalars' offset."""
        buf, n, f = self.shm.buf, self.n, at + 8 * (self.HEADER + self.nf)
        return (np.ndarray((self.HEADER,), np.uint64, buf, at), np.ndarray((self.nf,), np.float64, buf, at + 8 * self.HEADER),
                np.ndarray((n,), self.dtype, buf, f), np.ndarray((n,), np.int32, buf, f + self.dtype.itemsize * n),
                np.ndarray((self.TEXT,), np.uint8, buf, f + (self.dtype.itemsize + 4) * n), at + 8 * self.HEADER)

    @classmethod
    def _slot_size(cls, n_taxels: int, n_joints: int, n_boards: int, exact: bool) -> int:
        size = 8 * (cls.HEADER + cls.SCALARS + 4 * n_joints + n_boards) + (12 if exact else 8) * n_taxels + cls.TEXT
        return size + -size % 8

    @classmethod
    def size(cls, n_taxels: int, n_joints: int, n_boards: int, slots: int = 1, exact: bool = False) -> int:
        return 8 * cls.BLOCK + slots * cls._slot_size(n_taxels, n_joints, n_boards, exact)

    @classmethod
    def create(cls, n_taxels: int, n_joints: int, boards=(), slots: int = 1, exact: bool = False) -> "SharedFrames":
        """A block for the ticks of `n_taxels` taxels, `n_joints` joints and the boards of these uids."""
        name = f"skinsafe-view-{os.getpid()}-{os.urandom(4).hex()}"
        shm = shared_memory.SharedMemory(name, True, cls.size(n_taxels, n_joints, len(boards), slots, exact))
        return cls(shm, True, n_taxels, n_joints, boards, slots, exact)

    @classmethod
    def attach(cls, name: str, n_taxels: int, n_joints: int, boards=(), slots: int = 1,
               exact: bool = False) -> "SharedFrames":
        shm = shared_memory.SharedMemory(name, create=False)
        resource_tracker.unregister(shm._name, "shared_memory")  # only the creator removes the block
        return cls(shm, False, n_taxels, n_joints, boards, slots, exact)

    def write(self, f: Tick) -> bool:
        """Publish the tick `f` as the newest; False (nothing written) when it does not fit the block (a pool longer
        than the taxels, other joints, flags over TEXT bytes)."""
        return self._write(self._views[0], f, True)

    def room(self) -> bool:
        """Whether the ring has a free slot (the reader took what was there)."""
        return int(self._block[1]) - int(self._block[2]) < self.slots

    def push(self, f: Tick, telemetry: bool = True) -> bool:
        """Tick `f` into the ring after those pushed before; False (nothing written) when the ring is full or it does not
        fit. Without `telemetry` only what the record's safety topics hold (no forces, no pool)."""
        head = int(self._block[1])
        if head - int(self._block[2]) >= self.slots or not self._write(self._views[head % self.slots], f, telemetry):
            return False
        self._block[1] = head + 1
        return True

    def take(self) -> tuple[Tick, bool] | None:
        """The ring's oldest tick not yet taken and whether its telemetry came with it; None when it is empty."""
        tail = int(self._block[2])
        if tail >= int(self._block[1]):
            return None
        view = self._views[tail % self.slots]
        k = self._read(view, int(view[0][1]), int(view[0][2]))
        self._block[2] = tail + 1
        return k, bool(view[1][16])

    def _write(self, view: tuple, f: Tick, telemetry: bool) -> bool:
        words, _, force, pool_v, text_v, at = view
        pool = () if f.pool_taxels is None or not telemetry else f.pool_taxels
        text = "\x1e".join((f.stop, *f.flags)).encode()
        if len(pool) > self.n or len(f.q) != self.nj or len(f.command) != self.nj or len(text) > self.TEXT:
            return False
        if (f.force is not None and len(f.force) != self.n) or (f.planned is not None and len(f.planned) != self.nj):
            return False
        if f.qd is not None and len(f.qd) != self.nj:
            return False
        ages = f.board_age_s or {}
        ages = list(ages.values()) if list(ages) == self.boards else [ages.get(b, np.nan) for b in self.boards]
        planned = f.planned if f.planned is not None else self._none
        qd = f.qd if f.qd is not None else self._none
        has_force = telemetry and f.force is not None
        copy = has_force and (self.slots == 1 or f.force is not self._pushed)
        words[0] += np.uint64(1)
        self._pack(self.shm.buf, at, f.t, f.retracting, f.pool, f.potential, f.speed_factor, f.frames_lost,
                   f.planned is not None, f.qd is not None, f.dt, f.force_new, f.reading_seq, f.ticked, f.command_age,
                   f.command_refused, f.index, has_force, telemetry, copy, *f.q, *qd, *f.command, *planned, *ages)
        if copy:
            force[:] = f.force
            self._pushed = f.force if self.slots > 1 else None
        elif self.slots == 1:
            force[:] = np.nan
        pool_v[:len(pool)] = pool
        text_v[:len(text)] = np.frombuffer(text, np.uint8)
        words[1], words[2], words[3] = len(pool), len(text), f.ns
        words[0] += np.uint64(1)
        return True

    def wanted(self) -> bool:
        """Whether a reader took a tick within the last LEASE_S (the writer's test before copying one)."""
        return int(self._block[0]) > time.monotonic_ns()

    def newest(self) -> Tick | None:
        """The newest tick (the same object until a newer one is written), None before the first; the reader wants
        ticks for LEASE_S more."""
        self._block[0] = time.monotonic_ns() + int(self.LEASE_S * 1e9)
        view = self._views[0]
        w = view[0]
        for _ in range(1000):
            s1 = int(w[0])
            if s1 == self._seen or s1 == 0:
                return self._frame
            if not s1 & 1:
                f = self._read(view, int(w[1]), int(w[2]))
                if int(w[0]) == s1:
                    self._seen, self._frame = s1, f
                    return f
            time.sleep(0)
        return self._frame  # the writer stopped mid-write: keep the last whole one

    def _read(self, view: tuple, n_pool: int, n_text: int) -> Tick:
        words, f64, force, pool, text, _ = view
        v, nj, k = f64.copy(), self.nj, self.SCALARS
        stop, *flags = text[:n_text].tobytes().decode(errors="replace").split("\x1e")
        ages = {b: float(a) for b, a in zip(self.boards, v[k + 4 * nj:]) if a == a}
        if v[17] or self.slots == 1:
            self._taken = force.copy()
        return Tick(t=float(v[0]), q=v[k:k + nj], qd=v[k + nj:k + 2 * nj] if v[7] else None,
                    force=self._taken if v[15] or self.slots == 1 else None,
                    command=v[k + 2 * nj:k + 3 * nj], retracting=bool(v[1]), pool=int(v[2]), flags=tuple(flags),
                    stop=stop, planned=v[k + 3 * nj:k + 4 * nj] if v[6] else None,
                    pool_taxels=pool[:n_pool].copy() if v[1] and v[16] else None, potential=float(v[3]),
                    speed_factor=float(v[4]), board_age_s=ages, frames_lost=int(v[5]), dt=float(v[8]),
                    force_new=bool(v[9]), reading_seq=float(v[10]), ticked=bool(v[11]), command_age=float(v[12]),
                    command_refused=int(v[13]), index=int(v[14]), ns=int(words[3]))

    def close(self) -> None:
        self._block = self._views = None  # no view left on the block
        release(self.shm, self.owner)


class SharedTap(Tap):
    """A tap that also copies the newest tick into `SharedFrames` at most `rate_hz` times a second while a reader
    wants them, in the loop (its arrays as they are: the publisher process encodes them); a tick that does not fit
    is skipped and counted. `seq`: ticks copied."""

    def __init__(self, frames: SharedFrames, rate_hz: float = 30.0):
        self.frames, self.period = frames, 1.0 / rate_hz
        self.due, self.seq, self.skipped = 0.0, 0, 0

    def publish(self, frame) -> None:
        self.frame = frame
        now = time.monotonic()
        if now < self.due:
            return
        self.due = now + self.period
        if not self.frames.wanted():  # no viewer, or the publisher stalled: nobody reads it
            return
        self.seq += 1
        if not self.frames.write(frame):
            self.skipped += 1


def start_publisher(frames: SharedFrames, hello_message: bytes, host: str, port: int, preexec=None):
    """The publisher process of `frames` at (host, port); (the process, the address it serves)."""
    proc = subprocess.Popen([sys.executable, "-m", "skinsafe.core.runtime.view_share", frames.name, host, str(port)],
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, preexec_fn=preexec)
    proc.stdin.write(hello_message)
    proc.stdin.close()
    line = proc.stdout.readline().decode().strip()
    if not line.startswith("serving "):
        proc.wait(5)
        raise OSError(f"the view stream did not start at {host}:{port} (exit {proc.returncode}); is the port in use?")
    h, _, p = line.split()[1].rpartition(":")
    return proc, (h, int(p))


def wait_for_parent() -> None:
    """Return when the process that started this one ends, or on Ctrl-C (a view server's life)."""
    parent = os.getppid()
    try:
        while os.getppid() == parent:
            time.sleep(0.2)
    except KeyboardInterrupt:
        pass


def _serve(argv: list[str]) -> int:
    """`python -m skinsafe.core.runtime.view_share SHM HOST PORT`, the hello message on stdin: publish the block's
    frames until the run that started it ends."""
    name, host, port = argv
    hello_message = sys.stdin.buffer.read()
    h = decode(bytearray(hello_message))[0][0][0]
    frames = SharedFrames.attach(name, h["n_taxels"], len(h["joint_names"]), [int(b) for b in h["boards"]])
    try:
        pub = ViewPublisher(frames.newest, hello_message, host, int(port))
    except OSError as e:
        print(f"error {e}", flush=True)
        return 2
    print(f"serving {pub.address[0]}:{pub.address[1]}", flush=True)
    wait_for_parent()
    pub.close()
    frames.close()
    return 0


if __name__ == "__main__":
    sys.exit(_serve(sys.argv[1:]))
