"""The live view stream of `skinsafe run --view`: the loop's tap shares the newest tick through shared memory
at the view's rate, and a publisher in its own process sends it to a viewer (the page, Blender)."""
import time

import numpy as np
import pytest

from skinsafe.core.runtime.tap import Frame
from skinsafe.core.runtime.view_share import SharedFrames, SharedTap, start_publisher
from skinsafe.core.runtime.view_stream import ViewClient, hello

N = 5000


def frame(t: float, force: np.ndarray, pool=None) -> Frame:
    return Frame(t, np.arange(6.0) * t, force, np.full(6, -t), pool is not None, 0 if pool is None else len(pool),
                 ("limited",), "", None, pool, 0.25, 0.5, {7: 0.004}, 3)


def newest(client: ViewClient, timeout: float = 10.0):
    got, deadline = None, time.monotonic() + timeout
    while time.monotonic() < deadline:
        got = client.poll() or got
        if got is not None and got[0]["t"] >= 2.0:
            return got
        time.sleep(0.02)
    return got


def test_the_publisher_process_sends_the_newest_shared_tick_and_the_loop_never_writes_faster_than_the_view():
    frames = SharedFrames.create(N)
    tap = SharedTap(frames, rate_hz=30.0)
    ids = np.arange(N) * 3
    proc = None
    try:
        proc, (host, port) = start_publisher(frames, hello(N, ids, [f"j{i}" for i in range(6)], {7: "b0"}), "127.0.0.1", 0)
        client = ViewClient(host, port)
        assert client.hello["n_taxels"] == N and np.array_equal(client.ids, ids)
        for k in range(200):  # 200 ticks in well under 1/30 s: one of them is shared, the tap keeps the newest
            tap.publish(frame(k * 1e-3, np.full(N, float(k))))
        assert tap.seq == 1 and tap.latest().t == pytest.approx(0.199)
        time.sleep(0.05)
        force = np.linspace(0, 40, N)
        tap.publish(frame(2.0, force, pool=np.array([4, 9])))
        header, forces = newest(client)
        assert header["t"] == 2.0 and header["pool"] == [4, 9] and header["flags"] == ["limited"]
        assert header["q"] == [0.0, 2.0, 4.0, 6.0, 8.0, 10.0] and header["board_age_ms"] == {"7": 4.0}
        np.testing.assert_allclose(forces, force.astype(np.float32))
        client.close()
    finally:
        if proc is not None:
            proc.terminate()
            proc.wait(5)
        frames.close()


def test_a_frame_too_large_for_the_block_is_skipped_and_counted_never_half_written():
    frames = SharedFrames.create(10)
    tap = SharedTap(frames, rate_hz=1000.0)
    try:
        tap.publish(frame(1.0, np.ones(10)))
        first = frames.newest()
        time.sleep(0.002)
        tap.publish(frame(2.0, np.ones(10), pool=np.arange(100_000)))  # a header far larger than 10 taxels allow
        assert tap.skipped == 1 and frames.newest() is first
    finally:
        frames.close()
