"""Simulated taxel forces shared between processes: one named shared-memory block, read under a seqlock.

A simulation (the `sim` robot driver, or a franky-sim world) writes the (N,) taxel forces of every
physics step in the taxel map's order; the board emulator (`--feed NAME`) reads each board's
channels from it when it builds a stream frame. numpy and the standard library only, so hardware,
core.sim and a process in another virtual environment can all import it.

Layout (little-endian, 8-byte words): `seq` (u64), `t` (f64, the writer's clock, s), `n` (u64),
`magic` (u64), then `n` float64 forces. Seqlock: the writer makes `seq` odd, writes, makes it even;
a reader copies and retries while `seq` was odd or changed under it, so a torn read is impossible
(one writer per feed; readers never block the writer). Word stores are ordered on x86-64, the
machines this runs on.
"""
from __future__ import annotations

import os
import time
from multiprocessing import resource_tracker, shared_memory

import numpy as np

MAGIC = 0x534B494E46454544  # "SKINFEED"
HEADER_WORDS = 4
READ_SPIN_S = 1.0  # a reader gives up after this long behind a writer that never finishes (it died mid-write)


class FeedError(Exception):
    """A feed that does not exist, is not a force feed, or whose writer died mid-write."""


class ForceFeed:
    """(N,) taxel forces in a named shared-memory block; `create` in the writer, `attach` in readers."""

    def __init__(self, shm: shared_memory.SharedMemory, owner: bool, n: int = 0):
        self.shm, self.owner, self.name = shm, owner, shm.name
        head = np.ndarray((HEADER_WORDS,), np.uint64, shm.buf)
        if owner:
            head[:] = (0, 0, n, MAGIC)
        elif int(head[3]) != MAGIC:
            shm.close()
            raise FeedError(f"shared memory '{shm.name}' is not a skinsafe force feed")
        self.n = int(head[2])
        self._head = head
        self._t = np.ndarray((1,), np.float64, shm.buf, 8)
        self._seq = np.ndarray((1,), np.uint64, shm.buf, 0)
        self.forces = np.ndarray((self.n,), np.float64, shm.buf, 8 * HEADER_WORDS)

    @classmethod
    def create(cls, name: str | None, n: int) -> "ForceFeed":
        """A new feed of `n` taxels (all zero, seq 0); `name` None picks a unique one."""
        if n < 1:
            raise ValueError(f"ForceFeed: n = {n}; a feed holds at least one taxel")
        name = name or f"skinsafe-feed-{os.getpid()}-{os.urandom(4).hex()}"
        try:
            shm = shared_memory.SharedMemory(name, create=True, size=8 * (HEADER_WORDS + n))
        except FileExistsError:
            raise FeedError(f"force feed '{name}' exists already (another run uses it); choose another name") from None
        return cls(shm, owner=True, n=n)

    @classmethod
    def attach(cls, name: str) -> "ForceFeed":
        """The existing feed `name` (FeedError when there is none)."""
        try:
            shm = shared_memory.SharedMemory(name, create=False)
        except (FileNotFoundError, ValueError) as e:
            raise FeedError(f"force feed '{name}' does not exist ({e}); start the simulation that writes it first") \
                from None
        # only the creator may unlink: Python 3.11's tracker would remove the block when this process exits
        resource_tracker.unregister(shm._name, "shared_memory")
        return cls(shm, owner=False)

    def write(self, forces: np.ndarray, t: float) -> None:
        """Publish one step's forces (N,) at time `t`."""
        seq = self._seq
        seq[0] += np.uint64(1)  # odd: writing
        self.forces[:] = forces
        self._t[0] = t
        seq[0] += np.uint64(1)  # even: complete

    def read(self, index: np.ndarray | None = None) -> tuple[int, float, np.ndarray]:
        """(writes so far, their time, a copy of the forces (or of `forces[index]`, an integer index array)),
        never torn."""
        deadline = None
        while True:
            s1 = int(self._seq[0])
            if not s1 & 1:
                out = self.forces.copy() if index is None else self.forces[index]
                t = float(self._t[0])
                if int(self._seq[0]) == s1:
                    return s1 >> 1, t, out
            deadline = deadline or time.monotonic() + READ_SPIN_S
            time.sleep(0)  # let a writer that was descheduled mid-write finish
            if time.monotonic() > deadline:
                raise FeedError(f"force feed '{self.name}': its writer stopped in the middle of a write")

    def close(self) -> None:
        """Detach (and, in the creator, remove the block)."""
        self.forces = self._head = self._t = self._seq = None
        release(self.shm, self.owner)

    def __enter__(self) -> "ForceFeed":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def release(shm: shared_memory.SharedMemory, owner: bool) -> None:
    """Detach from a shared-memory block; its creator (`owner`) also removes it."""
    shm.close()
    if owner:
        try:
            shm.unlink()
        except FileNotFoundError:
            pass
