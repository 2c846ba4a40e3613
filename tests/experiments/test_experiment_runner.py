"""Experiments as Ray tasks: one task per method x seed, finished tasks reused by a restarted run."""
import json

import pytest

from skinsafe.core.experiments import runner
from skinsafe.core.experiments.maze import run_one


def test_tasks_run_on_ray_are_cached_and_reused(tmp_path, monkeypatch):
    tasks = [{"method": m, "seed": s, "episodes": 1, "max_steps": 6} for m in ("AC", "CPO") for s in (0, 1)]
    first = runner.run_tasks(run_one, tasks, tmp_path, workers=1, progress=False)
    assert [(r["method"], r["seed"]) for r in first] == [(t["method"], t["seed"]) for t in tasks]
    assert all(len(r["costs"]) == 1 and r["steps"][0] <= 6 for r in first)
    files = sorted(p.name for p in tmp_path.glob("*.json"))
    assert files == ["AC_s0.json", "AC_s1.json", "CPO_s0.json", "CPO_s1.json"]

    import ray

    def no_ray(*a, **k):
        raise AssertionError("a restarted run with every task finished must not start Ray")

    monkeypatch.setattr(ray, "init", no_ray)
    again = runner.run_tasks(run_one, tasks, tmp_path, workers=1, progress=False)
    assert again == json.loads(json.dumps(first))
    # another configuration of one task is not taken from the cache
    changed = dict(tasks[0], max_steps=7)
    assert runner.cached(tmp_path, changed) is None and runner.cached(tmp_path, tasks[0]) == again[0]
    # a result run by other code is not taken either: every loaded skinsafe source is recorded
    doc = json.loads((tmp_path / "AC_s1.json").read_text())
    assert {"core/learn/agents.py", "core/learn/maze_env.py", "core/experiments/maze.py"} <= set(doc["sources"])
    doc["sources"]["core/learn/agents.py"] = "0" * 40
    (tmp_path / "AC_s1.json").write_text(json.dumps(doc))
    assert runner.cached(tmp_path, tasks[1]) is None and runner.cached(tmp_path, tasks[2]) == again[2]
    (tmp_path / "AC_s0.json").write_text("{not json")  # a half-written file counts as missing
    assert runner.cached(tmp_path, tasks[0]) is None
    monkeypatch.setattr(runner.time, "sleep", lambda s: None)
    with pytest.raises(SystemExit, match="must not start Ray"):  # a missing task does start Ray (retried, then named)
        runner.run_tasks(run_one, tasks, tmp_path, workers=1, progress=False)


def test_agent_overrides_get_their_own_task_file_and_reach_the_agent(tmp_path):
    import argparse

    from skinsafe.core.experiments import maze

    p = argparse.ArgumentParser()
    maze.add_arguments(p)
    kw = maze.tdm_overrides(p.parse_args(["--tdm-refit-steps", "7", "--tdm-unseen-max", "0.6", "--tdm-prior-count", "0.2"]))
    assert kw == {"fit": {"steps": 7, "min_steps": 7, "batch_size": 64, "val_fraction": 0.1}, "unseen_max": 0.6,
                  "prior_count": 0.2}
    assert maze.tdm_overrides(p.parse_args([])) == {}
    with pytest.raises(SystemExit, match="unseen-max"):
        maze.tdm_overrides(p.parse_args(["--tdm-unseen-max", "0"]))
    with pytest.raises(SystemExit, match="prior-count"):
        maze.tdm_overrides(p.parse_args(["--tdm-prior-count", "-1"]))
    plain = {"method": "AC-TDM", "seed": 0, "episodes": 1, "max_steps": 5}
    tuned = dict(plain, agent_kw=kw)
    assert runner.task_file(tmp_path, plain).name == "AC-TDM_s0.json"
    assert runner.task_file(tmp_path, tuned).name.startswith("AC-TDM_s0_") and runner.task_file(tmp_path, tuned) != runner.task_file(
        tmp_path, dict(plain, agent_kw={"unseen_max": 0.5}))
    r = run_one(**tuned)
    assert r["stats"]["tdm"]["fits"] >= 1 and all(f["steps"] in (7, 100) for f in r["tdm_fits"])


def test_a_ray_that_cannot_start_is_retried_then_named(tmp_path, monkeypatch):
    import ray

    calls = []

    def fails(*a, **k):
        calls.append(k.get("address"))
        raise Exception("The current node timed out during startup.")

    monkeypatch.setattr(ray, "init", fails)
    monkeypatch.setattr(runner.time, "sleep", lambda s: None)
    with pytest.raises(SystemExit, match="re-run the same command"):
        runner.run_tasks(run_one, [{"method": "AC", "seed": 0, "episodes": 1, "max_steps": 2}], tmp_path, workers=1,
                         progress=False)
    assert calls == ["local"] * 3
