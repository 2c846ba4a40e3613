"""The live view stream of `skinsafe run --view`: the loop's tap shares the newest tick through shared memory
at the view's rate, and a publisher in its own process sends it to a viewer (the page, Blender)."""
import time

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from skinsafe.core.runtime.tap import Frame
from skinsafe.core.runtime.view_share import SharedFrames, SharedTap, start_publisher
from skinsafe.core.runtime.view_stream import ViewClient, frame_message, hello

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
    frames = SharedFrames.create(N, 6, [7])
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


def test_a_tick_that_does_not_fit_the_block_is_skipped_and_counted_never_half_written():
    frames = SharedFrames.create(10, 6, [7])
    tap = SharedTap(frames, rate_hz=1000.0)
    try:
        tap.publish(frame(1.0, np.ones(10)))
        first = frames.newest()
        for bad in (frame(2.0, np.ones(10), pool=np.arange(11)),  # a pool longer than the taxels
                    frame(2.0, np.ones(11)),  # other taxels
                    frame(2.0, np.ones(10))._replace(q=np.zeros(7)),  # other joints
                    frame(2.0, np.ones(10))._replace(flags=("x" * 5000,))):  # flags over the block's text
            time.sleep(0.002)
            tap.publish(bad)
        assert tap.skipped == 4 and frames.newest() is first and frames.newest().t == 1.0
    finally:
        frames.close()


floats = st.floats(allow_nan=True, allow_infinity=True, width=64)


@st.composite
def ticks(draw):
    n, nj = draw(st.integers(1, 300)), draw(st.integers(1, 8))
    arr = lambda k: np.array(draw(st.lists(floats, min_size=k, max_size=k)))  # noqa: E731
    retracting = draw(st.booleans())
    pool = np.array(draw(st.lists(st.integers(0, n - 1), max_size=n, unique=True)), np.int64) if retracting else None
    boards = draw(st.lists(st.integers(0, 2**31), max_size=6, unique=True))
    ages = {b: draw(st.floats(0, 10)) for b in boards if draw(st.booleans())}
    flags = tuple(draw(st.lists(st.sampled_from(["limited", "pfl:transient", "stale:board 3", "ñ"]), max_size=4)))
    f = Frame(draw(floats), arr(nj), None if draw(st.booleans()) else arr(n), arr(nj), retracting,
              0 if pool is None else len(pool), flags, draw(st.sampled_from(["", "skin-silent", "operator"])),
              None if draw(st.booleans()) else arr(nj), pool, draw(floats), draw(floats), ages,
              draw(st.integers(0, 2**40)))
    return n, nj, boards, f


@settings(max_examples=150, deadline=None)
@given(ticks())
def test_the_publisher_process_sends_exactly_the_message_the_loop_would_have_encoded(case):
    """The loop copies the tick's arrays; the publisher's message from them is the loop's own encoding, byte for byte
    (forces as float32, every float of q / command / planned, the pool, flags, stop, board ages); a tick without
    forces yet has every taxel NaN ("no fresh reading"), not an empty blob."""
    n, nj, boards, f = case
    sent = f if f.force is not None else f._replace(force=np.full(n, np.nan))
    frames = SharedFrames.create(n, nj, boards)
    try:
        with np.errstate(over="ignore"):  # forces beyond float32 are inf in both
            assert frames.write(f)
            assert frame_message(5, frames.newest()) == frame_message(5, sent)
    finally:
        frames.close()
