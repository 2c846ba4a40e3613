"""The live view stream of `skinsafe run --view`: the loop's tap shares the newest tick through shared memory
at the view's rate, and a publisher in its own process sends it to a viewer (the page, Blender)."""
import dataclasses
import subprocess
import sys
import time

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from skinsafe.core.design.sample import make_sample_design
from skinsafe.core.robot.models import build_ur5
from skinsafe.core.runtime.tick import Tick
from skinsafe.core.runtime.view_share import SharedFrames, SharedTap, start_publisher
from skinsafe.core.runtime.view_stream import ViewClient, frame_message, hello
from skinsafe.core.skin.taxel_map import save

N = 5000


def frame(t: float, force: np.ndarray, pool=None) -> Tick:
    return Tick(t=t, q=np.arange(6.0) * t, force=force, command=np.full(6, -t), retracting=pool is not None,
                pool=0 if pool is None else len(pool), flags=("limited",), pool_taxels=pool, potential=0.25,
                speed_factor=0.5, board_age_s={7: 0.004}, frames_lost=3)


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
        for k in range(20):  # no viewer yet: the publisher reads nothing and the loop copies nothing
            tap.publish(frame(k * 1e-3, np.full(N, float(k))))
            time.sleep(0.01)
        assert tap.seq == 0 and not frames.wanted()
        client = ViewClient(host, port)
        assert client.hello["n_taxels"] == N and np.array_equal(client.ids, ids)
        deadline = time.monotonic() + 10
        while not frames.wanted() and time.monotonic() < deadline:  # the publisher reads at 30 Hz once watched
            time.sleep(0.005)
        time.sleep(tap.period)  # the tap is due again
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
        assert frames.newest() is None  # a reader: the tap copies for the next LEASE_S
        tap.publish(frame(1.0, np.ones(10)))
        first = frames.newest()
        for bad in (frame(2.0, np.ones(10), pool=np.arange(11)),  # a pool longer than the taxels
                    frame(2.0, np.ones(11)),  # other taxels
                    dataclasses.replace(frame(2.0, np.ones(10)), q=np.zeros(7)),  # other joints
                    dataclasses.replace(frame(2.0, np.ones(10)), flags=("x" * 5000,))):  # flags over the block's text
            time.sleep(0.002)
            tap.publish(bad)
        assert tap.skipped == 4 and frames.newest() is first and frames.newest().t == 1.0
    finally:
        frames.close()


def test_the_loop_copies_only_while_a_reader_takes_ticks():
    """Without a read within LEASE_S (no viewer connected, the publisher stalled or gone) the tap copies nothing;
    one read resumes the copies at the tap's rate."""
    frames = SharedFrames.create(10, 6, [7])
    tap = SharedTap(frames, rate_hz=1000.0)
    try:
        def publish_for(seconds):
            end, seq = time.monotonic() + seconds, tap.seq
            while time.monotonic() < end:
                tap.publish(frame(time.monotonic(), np.ones(10)))
                time.sleep(0.002)
            return tap.seq - seq
        assert publish_for(0.1) == 0 and frames.newest() is None
        copied = publish_for(SharedFrames.LEASE_S / 2)  # within the lease of that read: every 1 ms due tick
        assert copied >= 10 and frames.newest().t > 0
        time.sleep(SharedFrames.LEASE_S)  # the reader stalls
        assert publish_for(0.1) == 0
    finally:
        frames.close()


def test_nothing_is_copied_for_a_page_nobody_has_open(tmp_path):
    """`run --view`'s chain (the loop's tap, the publisher process, the page's process): while no browser has the
    page open the page process is off the stream, so the publisher reads nothing and the loop copies nothing; a
    browser opening it starts the copies, closing it stops them again."""
    from skinsafe.core.bench.remote_viewer import open_page

    robot = build_ur5()
    design = make_sample_design("ur5", robot=robot)
    skin = save(design, tmp_path / "skin.json")
    n = design.n_taxels
    frames = SharedFrames.create(n, len(robot.home), [b.uid for b in design.boards])
    tap = SharedTap(frames, rate_hz=30.0)
    joints = [robot.model.joint(i).name for i in range(robot.model.njnt)]
    msg = hello(n, design.taxels.ids, joints, {b.uid: b.name for b in design.boards}, str(skin))
    pub = page = None

    def copies(seconds):
        seq, end = tap.seq, time.monotonic() + seconds
        while time.monotonic() < end:
            tap.publish(Tick(t=time.monotonic(), q=robot.home, force=np.ones(n), command=0 * robot.home))
            time.sleep(0.005)
        return tap.seq - seq

    try:
        pub, (host, port) = start_publisher(frames, msg, "127.0.0.1", 0)
        page = subprocess.Popen([sys.executable, "-m", "skinsafe.core.app.cli", "view", f"{host}:{port}", "--port",
                                 "0", "--until-ended"], stdout=subprocess.PIPE, text=True)
        line = "-"
        while line and not line.startswith("skinsafe view:"):  # after viser's banner
            line = page.stdout.readline()
        assert line.startswith("skinsafe view: live"), line
        url = line.rsplit(" at ", 1)[1].strip()
        assert copies(1.5) == 0  # the page served, nobody looking
        with open_page(url):  # a browser opens the page (elsewhere: nothing drawn here)
            deadline = time.monotonic() + 30
            while copies(0.5) == 0:
                assert time.monotonic() < deadline, "no copies with the page open"
            assert copies(1.0) >= 15  # at the view's 30 Hz
        time.sleep(3.0)  # the page process notices the browser left and leaves the stream
        assert copies(1.0) == 0
    finally:
        for proc in (page, pub):
            if proc is not None:
                proc.terminate()
                proc.wait(10)
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
    f = Tick(t=draw(floats), q=arr(nj), force=None if draw(st.booleans()) else arr(n), command=arr(nj),
             retracting=retracting, pool=0 if pool is None else len(pool), flags=flags,
             stop=draw(st.sampled_from(["", "skin-silent", "operator"])),
             planned=None if draw(st.booleans()) else arr(nj), pool_taxels=pool, potential=draw(floats),
             speed_factor=draw(floats), board_age_s=ages, frames_lost=draw(st.integers(0, 2**40)))
    return n, nj, boards, f


@settings(max_examples=150, deadline=None)
@given(ticks())
def test_the_publisher_process_sends_exactly_the_message_the_loop_would_have_encoded(case):
    """The loop copies the tick's arrays; the publisher's message from them is the loop's own encoding, byte for byte
    (forces as float32, every float of q / command / planned, the pool, flags, stop, board ages); a tick without
    forces yet has every taxel NaN ("no fresh reading"), not an empty blob."""
    n, nj, boards, f = case
    sent = f if f.force is not None else dataclasses.replace(f, force=np.full(n, np.nan))
    frames = SharedFrames.create(n, nj, boards)
    try:
        with np.errstate(over="ignore"):  # forces beyond float32 are inf in both
            assert frames.write(f)
            assert frame_message(5, frames.newest()) == frame_message(5, sent)
    finally:
        frames.close()
