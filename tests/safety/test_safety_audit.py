"""`skinsafe bench safety`: the audit's row keys (a contract) and its verdicts on a small run."""
import json

import pytest

from skinsafe.core.app.cli import main

KEYS = {"robot", "contacts", "cases", "feasible", "into_contact_mm_worst", "into_contact_mm_worst_all", "infeasible_cases",
        "dominant_ratio_min", "vel_limit_violations", "acc_limit_violations", "nonfinite_cases", "missing_cases",
        "fail_open", "ms_median", "ms_worst"}


def test_audit_rows_small_run(capsys):
    assert main(["bench", "safety", "--json", "--cases", "2", "--nonfinite", "12", "--contacts", "1,3", "--workers", "0"]) == 0
    rows = json.loads(capsys.readouterr().out)
    assert [(r["robot"], r["contacts"]) for r in rows] == [("ur5", 1), ("ur5", 3), ("panda", 1), ("panda", 3)]
    for r in rows:
        assert KEYS <= set(r) and r["cases"] == 2 and r["nonfinite_cases"] == 12
        assert r["vel_limit_violations"] == r["acc_limit_violations"] == r["fail_open"] == 0
        assert r["into_contact_mm_worst"] <= 0.5 and r["into_contact_mm_worst_all"] <= 2.0
        assert r["dominant_ratio_min"] is None or r["dominant_ratio_min"] > 0.95
    assert sum(r["missing_cases"] for r in rows) >= 8  # 4 of the 11 injection kinds are missing readings


def test_eq2_rows_show_the_bias(capsys):
    assert main(["bench", "safety", "--json", "--eq2"]) == 0
    rows = {r["samples"]: r for r in json.loads(capsys.readouterr().out)}
    assert rows[10]["bias_pct"] < -20 and rows[10]["reliable_frac"] == 0  # far off and marked so
    assert abs(rows[10000]["bias_pct"]) < 5


def test_chunks_reuse_and_merge():
    """A shorter run's chunks are the longer run's first chunks (the cache serves them), and the
    merged tick-time median lands in the bin of the true median."""
    import numpy as np

    from skinsafe.core.bench.safety import BINS, CHUNK, _quantile, tasks_for

    long, short = tasks_for(["ur5"], [1, 8], 10 * CHUNK, CHUNK, 0), tasks_for(["ur5"], [1, 8], 4 * CHUNK, 4 * CHUNK // 10, 0)
    assert len(long) == 20 and all(t in long for t in short) and len(short) == 8
    assert sum(t["cases"] for t in long) == 20 * CHUNK and sum(t["nonfinite"] for t in long) == 2 * CHUNK
    ms = np.random.default_rng(0).lognormal(-1, 1, 10001)
    counts = np.histogram(ms, BINS)[0]
    assert abs(np.log(_quantile(counts, 0.5) / np.median(ms))) < np.log(BINS[1] / BINS[0])


@pytest.mark.xdist_group("ray")  # a local Ray: never beside another test's (start-up timeouts on the shared cores)
def test_ray_fan_out_gives_the_in_process_rows(tmp_path, capsys):
    """The same chunks run as Ray tasks (cached, niced workers) and in this process: the same
    numbers (times aside), each chunk from its own random stream; the cache then serves a rerun."""
    args = ["bench", "safety", "--json", "--cases", "2", "--nonfinite", "2", "--contacts", "2", "--robots", "ur5"]
    assert main(args + ["--workers", "0"]) == 0
    here = json.loads(capsys.readouterr().out)
    assert main(args + ["--workers", "1", "--cache", str(tmp_path), "--out", str(tmp_path / "rows.json")]) == 0
    fanned = json.loads(capsys.readouterr().out)
    assert fanned == json.loads((tmp_path / "rows.json").read_text())
    assert len(list(tmp_path.glob("safety-ur5-2c-0_s0.json"))) == 1
    assert main(args + ["--from-cache", "--cache", str(tmp_path)]) == 0  # what a stopped run has finished
    assert json.loads(capsys.readouterr().out) == fanned  # only the finished chunk: no new work
    times = {"ms_median", "ms_worst", "ms_p999"}
    assert [{k: v for k, v in r.items() if k not in times} for r in fanned] == \
        [{k: v for k, v in r.items() if k not in times} for r in here]
