"""The live view's publisher outside the control loop's process (`skinsafe run --view`).

A publisher thread in the loop's process would share its interpreter lock and real-time priority. The
loop's tap (`SharedTap`) encodes the newest tick at the view's rate into shared memory (`SharedFrames`, a
seqlock as core/skin/force_feed.py's: nobody waits), and the publisher process (`python -m
skinsafe.core.runtime.view_share`, started by `start_publisher`) sends it on as the view stream
(core/runtime/view_stream.py).
"""
from __future__ import annotations

import os
import subprocess
import sys
import time
from multiprocessing import resource_tracker, shared_memory

import numpy as np

from skinsafe.core.runtime.tap import Tap
from skinsafe.core.runtime.view_stream import ViewPublisher, frame_message
from skinsafe.core.skin.force_feed import release


class SharedFrames:
    """The newest encoded frame message in a named shared-memory block: `u64 seq | u64 length | message`. The
    writer makes `seq` odd, writes, makes it even; a reader copies and retries while it was odd or changed."""

    HEADER = 16

    def __init__(self, shm: shared_memory.SharedMemory, owner: bool):
        self.shm, self.owner, self.name = shm, owner, shm.name
        self.capacity = shm.size - self.HEADER
        self._word = np.ndarray((2,), np.uint64, shm.buf)
        self._data = np.ndarray((self.capacity,), np.uint8, shm.buf, self.HEADER)
        self._seen, self._msg = 0, None
        if owner:
            self._word[:] = 0

    @classmethod
    def create(cls, n_taxels: int) -> "SharedFrames":
        """A block for the frames of `n_taxels` taxels (their forces, a pool of all of them, the rest of a header)."""
        size = cls.HEADER + 4 * n_taxels + 12 * n_taxels + (64 << 10)
        return cls(shared_memory.SharedMemory(f"skinsafe-view-{os.getpid()}-{os.urandom(4).hex()}", True, size), True)

    @classmethod
    def attach(cls, name: str) -> "SharedFrames":
        shm = shared_memory.SharedMemory(name, create=False)
        resource_tracker.unregister(shm._name, "shared_memory")  # only the creator removes the block
        return cls(shm, owner=False)

    def write(self, msg: bytes) -> bool:
        """Publish `msg`; False (nothing written) when it does not fit."""
        if len(msg) > self.capacity:
            return False
        w = self._word
        w[0] += np.uint64(1)
        self._data[:len(msg)] = np.frombuffer(msg, np.uint8)
        w[1] = len(msg)
        w[0] += np.uint64(1)
        return True

    def newest(self) -> bytes | None:
        """The newest message (the same object until a newer one is written), None before the first."""
        w = self._word
        for _ in range(1000):
            s1 = int(w[0])
            if s1 == self._seen or s1 == 0:
                return self._msg
            if not s1 & 1:
                msg = self._data[:int(w[1])].tobytes()
                if int(w[0]) == s1:
                    self._seen, self._msg = s1, msg
                    return msg
            time.sleep(0)
        return self._msg  # the writer stopped mid-write: keep the last whole one

    def close(self) -> None:
        self._word = self._data = None
        release(self.shm, self.owner)


class SharedTap(Tap):
    """A tap that also encodes the newest tick into `SharedFrames` at most `rate_hz` times a second, in the loop
    (one JSON header and one copy of the forces, tens of microseconds); a frame too large is skipped and counted."""

    def __init__(self, frames: SharedFrames, rate_hz: float = 30.0):
        self.frames, self.period = frames, 1.0 / rate_hz
        self.due, self.seq, self.skipped = 0.0, 0, 0

    def publish(self, frame) -> None:
        self.frame = frame
        now = time.monotonic()
        if now < self.due:
            return
        self.due, self.seq = now + self.period, self.seq + 1
        if not self.frames.write(frame_message(self.seq, frame)):
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


def _serve(argv: list[str]) -> int:
    """`python -m skinsafe.core.runtime.view_share SHM HOST PORT`, the hello message on stdin: publish the block's
    frames until the run that started it ends."""
    name, host, port = argv
    hello_message = sys.stdin.buffer.read()
    frames = SharedFrames.attach(name)
    try:
        pub = ViewPublisher(frames.newest, hello_message, host, int(port))
    except OSError as e:
        print(f"error {e}", flush=True)
        return 2
    print(f"serving {pub.address[0]}:{pub.address[1]}", flush=True)
    parent = os.getppid()
    try:
        while os.getppid() == parent:
            time.sleep(0.2)
    except KeyboardInterrupt:
        pass
    pub.close()
    frames.close()
    return 0


if __name__ == "__main__":
    sys.exit(_serve(sys.argv[1:]))
