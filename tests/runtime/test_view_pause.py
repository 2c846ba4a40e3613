"""bench runtime --view alternating: the view's processes found, paused and resumed, and each tick and contact
frame of a run put in the block (view working or paused) it began in."""
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from skinsafe.core.bench.view_pause import Pauser, blocks, compare, pair_blocks, view_processes


def _state(pid: int) -> str:
    return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]


def _run(periods, at, latency, wait, start=100.0):
    return {"period_ms_all": list(periods), "start_mono": start, "latency_tick_all": list(at),
            "latency_ms_all": list(latency), "latency_wait_ms_all": list(wait)}


def test_each_tick_and_contact_frame_counts_in_the_block_it_began_in():
    # blocks of 0.5 s from t=100.1: working, paused, working, paused, working (100.1 .. 102.6); the run's ticks
    # from t=100 s come 1 ms apart while the view works and 1.25 ms apart while it is paused, until t=102.3
    switches = [(100.1 + 0.5 * k, bool(k % 2)) for k in range(6)]
    paused_at = lambda t: any(t0 <= t < t1 and p for (t0, p), (t1, _) in zip(switches, switches[1:]))  # noqa: E731
    start, period = [100.0], []
    while start[-1] < 102.3:
        period.append(1.25 if paused_at(start[-1] + 1e-3) else 1.0)
        start.append(start[-1] + period[-1] / 1e3)
    start, period = np.array(start), np.array(period)
    at = np.arange(5, len(start), 7)  # a contact frame every 7th tick: 2 ms while working, 3 ms while paused
    latency = np.array([3.0 if paused_at(start[k]) else 2.0 for k in at])
    run = _run(period, at, latency, np.full(len(at), 0.5))
    b = blocks(run, switches)
    assert [p for p, _ in b] == [False, True, False, True]  # the last block passes the run's end: left out
    for (t0, p), (t1, _), (bp, s) in zip(switches, switches[1:], b):
        began = np.flatnonzero((start >= t0 - 1e-9) & (start < t1 - 1e-9))
        assert bp == p and len(s["period"]) == len(began)
        assert set(s["latency"]) == {3.0 if p else 2.0} and len(s["latency"]) == np.isin(at, began).sum()
        np.testing.assert_allclose(s["latency_tick"], s["latency"] - 0.5)
    pairs = pair_blocks([(run, switches)])
    assert len(pairs) == 2
    out = compare(pairs, ("period", "latency", "latency_tick"), draws=200)
    assert np.isclose(out["period_ms_p99_paused"], 1.25) and np.isclose(out["period_ms_p99_working"], 1.0, atol=0.01)
    assert np.isclose(out["latency_p99_vs_paused"], 2 / 3 - 1) and out["blocks"] == 4
    assert np.isclose(out["latency_p50_vs_paused"], 2 / 3 - 1) and np.isclose(out["period_ms_p50_paused"], 1.25)
    lo, hi = out["latency_tick_p99_vs_paused_ci95"]
    assert np.isclose(lo, 1.5 / 2.5 - 1) and np.isclose(hi, lo)  # every resample the same: no spread


def test_the_view_processes_are_found_paused_and_resumed_and_nothing_else(tmp_path):
    browser = tmp_path / "fakebrowser"
    browser.symlink_to(shutil.which("yes"))  # busy: it uses CPU while it is not paused
    # a shell (not the view) starting the "browser", and one named as the view's publisher module
    shell = subprocess.Popen(["bash", "-c", f"{browser} > /dev/null & wait"], start_new_session=True)
    # (a process that does not fork: a forked shell carries its parent's argv until it execs, a third match)
    publisher = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)",
                                  "skinsafe.core.runtime.view_share"], start_new_session=True)
    other = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"], start_new_session=True)
    try:
        deadline = time.monotonic() + 10
        while len(view_processes(os.getpid(), str(browser))) < 2 and time.monotonic() < deadline:
            time.sleep(0.05)
        found = view_processes(os.getpid(), str(browser))
        assert publisher.pid in found and shell.pid not in found and other.pid not in found and len(found) == 2
        pauser = Pauser(os.getpid(), str(browser), 0.2)
        pauser.start()
        time.sleep(0.3)  # inside the second block: paused
        assert {_state(p) for p in found} == {"T"} and _state(other.pid) != "T"
        time.sleep(0.2)  # the third: working again
        assert "T" not in {_state(p) for p in found}
        pauser.stop()
        assert [p for _, p in pauser.switches[:3]] == [False, True, False]
        assert "T" not in {_state(p) for p in found} and pauser.cpu_s > 0.05  # the "browser" ran ~0.3 s of 0.5
    finally:
        for p in (shell, publisher, other):  # each with what it started (the busy "browser")
            os.killpg(p.pid, signal.SIGKILL)
            p.wait()
