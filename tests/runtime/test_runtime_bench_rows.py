"""The runtime bench's view comparison: pooled tails, their ratio to the runs without the view, the noise floor; the
host's own stalls beside the loop's figures."""
import numpy as np

from skinsafe.core.bench.runtime import _host, _vs_off
from skinsafe.core.realtime import host_stalls, steal_s


def _run(periods, latencies, waits=None):
    waits = np.zeros(len(latencies)) if waits is None else waits
    return {"period_ms_all": list(periods), "latency_ms_all": list(latencies), "latency_wait_ms_all": list(waits)}


def test_view_rows_pool_every_sample_and_compare_with_off_and_off_with_itself():
    rng = np.random.default_rng(0)
    flat = [_run(np.full(1000, 1.0), np.full(100, 2.0)) for _ in range(4)]
    off = flat[:3] + [_run(np.r_[np.full(970, 1.0), np.full(30, 1.5)], np.full(100, 2.0))]  # one run with a tail
    page = [_run(np.full(1000, 1.02), rng.uniform(2.0, 2.04, 100)) for _ in range(4)]
    row = _vs_off({"off": off, "page": page}, "page")
    # pooled over 4,000 ticks the tail of 30 slow ticks (0.75%) is below the p99: 1.0 against 1.02
    assert np.isclose(row["period_ms_p99_pooled"], 1.02) and np.isclose(row["period_p99_vs_off"], 0.02)
    assert 0 < row["latency_p99_vs_off"] <= 0.02 and row["within_5pct"]
    # off's halves (runs 0, 2 against 1, 3): in the slow run's half the 30 are 1.5% of the ticks, its p99 1.5
    assert row["off_halves_period_p99"] == [1.0, 1.5]
    assert np.isclose(row["off_spread"], 1 / 3) and not row["resolvable"]  # |1.0 / 1.5 - 1|
    slow = [_run(np.full(1000, 1.1), np.full(100, 2.0)) for _ in range(4)]
    far = _vs_off({"off": flat, "slow": slow}, "slow")
    assert np.isclose(far["period_p99_vs_off"], 0.1) and not far["within_5pct"] and far["resolvable"]
    assert not far["not_slower_5pct"]
    fast = _vs_off({"off": slow, "page": flat}, "page")  # the view's runs 9% faster: not within, not slower
    assert not fast["within_5pct"] and fast["not_slower_5pct"]
    # the tick's part: each latency less its wait (here the frames waited 1.5 ms with the view, 1.0 without)
    waited = [_run(np.full(1000, 1.0), np.full(100, 2.5), np.full(100, 1.5)) for _ in range(4)]
    base = [_run(np.full(1000, 1.0), np.full(100, 2.0), np.full(100, 1.0)) for _ in range(4)]
    tick = _vs_off({"off": base, "page": waited}, "page")
    assert np.isclose(tick["latency_tick_ms_p99_pooled"], 1.0) and np.isclose(tick["latency_tick_p99_vs_off"], 0.0)
    assert np.isclose(tick["latency_p99_vs_off"], 0.25)
    assert _vs_off({"page": page}, "page") == {"view": "page"}  # nothing to compare without off


def test_view_change_interval_resamples_the_repeats_as_pairs():
    rng = np.random.default_rng(1)

    def runs(scale, load):  # repeat k's tail is set by the machine's load in minute k, for every mode alike
        return [_run(np.r_[np.full(980, 1.0), np.full(20, scale * x)], np.full(100, scale * x)) for x in load]
    load = rng.uniform(1.0, 1.5, 10)  # the runs' own tails differ by up to 50% with the same code
    near = _vs_off({"off": runs(1.0, load), "page": runs(1.02, load)}, "page")
    for name in ("period", "latency"):  # paired, the load cancels: +2% exactly, in every resample
        assert np.allclose(near[f"{name}_p99_vs_off_ci95"], 0.02, atol=1e-9)
    assert near["shown_within_5pct"] and near["shown_not_slower_5pct"]
    slow = _vs_off({"off": runs(1.0, load), "page": runs(1.1, load)}, "page")
    assert np.allclose(slow["period_p99_vs_off_ci95"], 0.1) and not slow["shown_not_slower_5pct"]
    # unpaired loads (the view's runs in other minutes): the interval is wide, covers the point, shows nothing
    other = _vs_off({"off": runs(1.0, load), "page": runs(1.0, rng.permutation(load))}, "page")
    lo, hi = other["period_p99_vs_off_ci95"]
    assert lo <= other["period_p99_vs_off"] <= hi and hi - lo > 0.1
    assert not other["shown_within_5pct"]
    assert "period_p99_vs_off_ci95" not in _vs_off({"off": runs(1.0, load[:1]), "page": runs(1.0, load[:1])}, "page")


def test_the_host_rows_take_the_worst_stall_and_steal_and_sum_the_switches():
    runs = [{"host_stall_ms_max": 0.4, "host_switched_out": 1, "steal_ms": 20.0},
            {"host_stall_ms_max": 2.5, "host_switched_out": 0, "steal_ms": None},
            {"host_stall_ms_max": 0.1, "host_switched_out": 2, "steal_ms": 10.0}]
    assert _host(runs) == {"host_stall_ms_max": 2.5, "host_switched_out": 3, "steal_ms_max": 20.0}
    assert _host([{"steal_ms": None}])["steal_ms_max"] is None


def test_the_host_stall_probe_counts_every_gap_over_its_threshold():
    """At a threshold no clock read beats, every gap is a stall (its count in the thousands in 0.1 s); at 1 s none
    of 0.1 s is; the probe's scheduling and cores are restored."""
    import os

    cpus, policy = os.sched_getaffinity(0), os.sched_getscheduler(0)
    every = host_stalls(0.1, threshold_s=1e-12, window_s=0.05)
    assert every["stalls"] > 1000 and 0 < every["stall_ms_max"] < 100
    none = host_stalls(0.1, threshold_s=1.0, window_s=0.05)
    assert none["stalls"] == 0 and none["stall_ms_max"] == 0.0
    assert os.sched_getaffinity(0) == cpus and os.sched_getscheduler(0) == policy
    assert steal_s(min(cpus)) is None or steal_s(min(cpus)) >= 0
