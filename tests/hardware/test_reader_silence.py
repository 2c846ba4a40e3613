"""The boards' reader names every silence to the loop, each time, together with the NaN readings it causes."""
import numpy as np
import pytest

from skinsafe.hardware.flat_design import flat_design
from skinsafe.hardware.skin_reader import BoardsReader, _Board


def test_a_second_silence_of_the_same_length_is_named_again():
    """A board named silent before the robot moved (the loop lets that pass) and silent again later for the same
    40.3 ms: the second silence reaches the loop by name, not only as NaN readings (the fault storm's
    misnamed frame delays: the reader named each text once)."""
    d = flat_design(64, 2)
    reader = BoardsReader(d, {}, 50, 0.25, 0.02, 2.0, 0.0, 5, {})
    rows = [np.flatnonzero(d.taxels.board == b.id) for b in d.boards]
    reader.boards = {b.id: _Board(b.uid, b.name, rows[k], k) for k, b in enumerate(d.boards)}
    reader.force = np.zeros(d.n_taxels)
    names = []
    for t0 in (10.0, 20.0):  # the board's last frame; named 40.3 ms later, both times
        b = reader.boards[d.boards[0].id]
        b.arrived, b.silent_at, b.silence = t0, 0.0, None
        reader.boards[d.boards[1].id].arrived = t0 + 0.04
        reader.force[:] = 0.0
        assert reader._silent(t0 + 0.0403)
        assert np.isnan(reader.force[rows[0]]).all() and not np.isnan(reader.force[rows[1]]).any()
        names.append(reader._take_faults())
    assert [f[:3] for f in names[0]] == [f[:3] for f in names[1]] and len(names[1]) == 1
    kind, source, text, onset = names[1][0]
    assert kind == "board-silent" and source == "board 'board0'" and "silent for 40.3 ms" in text
    assert onset == pytest.approx(20.0 + 0.02)  # its next frame was due one frame period after its last
    b = reader.boards[d.boards[0].id]
    reader._fault("crc-storm", b, "CRC storm")
    reader._fault("crc-storm", b, "CRC storm")  # a fault seen on every pass is still named once
    assert [f[:2] for f in reader._take_faults()] == [("crc-storm", "board 'board0'")]


def test_frames_arriving_steadily_but_stale_are_named_late_between_arrivals_and_a_plain_silence_silent():
    """Board 0's frames keep arriving (the last 10 ms ago) but its newest was sent 51 ms ago by its own clock: late
    (onset: when that frame became older than the 40 ms silence), its taxels NaN; board 1's last frame came with the
    usual delay 41 ms ago: the silence check names it silent, and the between-arrival check leaves it to that."""
    d = flat_design(64, 2)
    reader = BoardsReader(d, {}, 50, 0.25, 0.02, 2.0, 0.0, 5, {})
    rows = [np.flatnonzero(d.taxels.board == b.id) for b in d.boards]
    reader.boards = {b.id: _Board(b.uid, b.name, rows[k], k) for k, b in enumerate(d.boards)}
    reader.force = np.zeros(d.n_taxels)
    late, quiet = reader.boards[d.boards[0].id], reader.boards[d.boards[1].id]
    now = 10.0
    late.arrived, late.sent = now - 0.010, now - 0.051
    quiet.arrived, quiet.sent = now - 0.041, now - 0.0415
    assert reader.stale_s == pytest.approx(0.05)  # the silence + half a frame period
    assert reader._silent(now) | reader._stale(now)
    faults = {f[1]: f for f in reader._take_faults()}
    kind, _, text, onset = faults["board 'board0'"]
    assert kind == "board-late" and "late by the board's own clock" in text and onset == pytest.approx(now - 0.011)
    assert faults["board 'board1'"][0] == "board-silent"
    assert np.isnan(reader.force).all() and late.late
    assert not reader._stale(now + 0.1) and not reader._take_faults()  # named once per episode


def test_an_ending_reader_is_named_by_its_exit_status_before_it_can_be_reaped():
    """The kernel sets an ending process's status before it closes its pipes: a pipe's hang-up seen first still names
    the exit code (SIGKILL: -9; exit(3): 3), and a running process has none (the race a loaded host showed: the
    reader's death named only as 'its pipe closed')."""
    import os
    import signal
    import subprocess
    import sys
    import time

    from skinsafe.hardware.skin_source import ending_status

    p = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])
    q = subprocess.Popen([sys.executable, "-c", "import sys; sys.exit(3)"])
    try:
        time.sleep(0.2)
        assert ending_status(p.pid) is None
        os.kill(p.pid, signal.SIGKILL)
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline and (ending_status(p.pid) is None or ending_status(q.pid) is None):
            time.sleep(0.01)
        assert ending_status(p.pid) == -9 and ending_status(q.pid) == 3
    finally:
        p.kill()
        assert p.wait() == -9 and q.wait() == 3
    assert ending_status(p.pid) is None  # reaped: nothing to read


def test_a_reader_that_dies_in_the_preflight_is_named_by_its_exit_code(tmp_path):
    """The pre-flight names a reader that ended before it answered by its exit code, at once (its pipe closes
    before it can be reaped: once named 'did not answer within 5000000030 s' after a 1.5 s crash)."""
    import time

    from skinsafe.core.skin.taxel_map import save
    from skinsafe.hardware.deploy import deploy
    from skinsafe.hardware.emulator import EmulatorProcess
    from skinsafe.hardware.skin_source import PreflightRefused, SkinSource

    d = flat_design(64, 1)
    save(d, tmp_path / "skin.json")
    with EmulatorProcess([], tmp_path / "flash", "--map", str(tmp_path / "skin.json")) as em:
        ports = {b.id: em.ports[b.uid] for b in d.boards}
        assert [r.status for r in deploy(d, ports)] == ["updated"]
        source = SkinSource(d, ports, rate_hz=100)
        t = time.monotonic()
        try:
            with pytest.raises(PreflightRefused, match="the boards' reader ended with exit code 1 before the pre-flight"):
                source.preflight(b"\0" * 32, 10 ** 15)  # the reader cannot keep 10^15 frames: MemoryError, exit 1
        finally:
            source.close()
        assert time.monotonic() - t < 30
