"""Experiments as Ray tasks: one task per method x seed, finished tasks reused by a restarted run."""
import json

import numpy as np
import pytest

from skinsafe.core.experiments import maze, runner
from skinsafe.core.experiments.maze_runs import run_one


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
    doc = json.loads(runner.task_file(tmp_path, tasks[1]).read_text())
    assert {"core/learn/agents.py", "core/learn/maze_env.py", "core/experiments/maze_runs.py"} <= set(doc["sources"])
    assert "core/experiments/maze.py" not in doc["sources"]  # the protocol's report can change without voiding runs
    doc["sources"]["core/learn/agents.py"] = "0" * 40
    runner.task_file(tmp_path, tasks[1]).write_text(json.dumps(doc))
    assert runner.cached(tmp_path, tasks[1]) is None and runner.cached(tmp_path, tasks[2]) == again[2]
    # nor one run on other library versions (torch, mujoco, numba, numpy are part of the key)
    doc = json.loads(runner.task_file(tmp_path, tasks[3]).read_text())
    assert doc["versions"] == runner.versions()
    doc["versions"]["mujoco"] = "0.0.1"
    runner.task_file(tmp_path, tasks[3]).write_text(json.dumps(doc))
    assert runner.cached(tmp_path, tasks[3]) is None
    runner.task_file(tmp_path, tasks[0]).write_text("{not json")  # a half-written file counts as missing
    assert runner.cached(tmp_path, tasks[0]) is None
    monkeypatch.setattr(runner.time, "sleep", lambda s: None)
    with pytest.raises(SystemExit, match="must not start Ray"):  # a missing task does start Ray (retried, then named)
        runner.run_tasks(run_one, tasks, tmp_path, workers=1, progress=False)


def test_agent_overrides_get_their_own_task_file_and_reach_the_agent(tmp_path):
    kw = maze.TdmOverrides(7, 0.6, 0.2).agent_kw()
    assert kw == {"fit": {"steps": 7, "min_steps": 7, "batch_size": 64, "val_fraction": 0.1}, "unseen_max": 0.6,
                  "prior_count": 0.2}
    assert maze.TdmOverrides().agent_kw() == {}
    for bad, match in (({"unseen_max": 0.0}, "unseen-max"), ({"prior_count": -1.0}, "prior-count"), ({"refit_steps": 0}, "refit")):
        with pytest.raises(ValueError, match=match):
            maze.TdmOverrides(**bad)
    plain = {"method": "AC-TDM", "seed": 0, "episodes": 1, "max_steps": 5}
    tuned = dict(plain, agent_kw=kw)
    assert runner.task_file(tmp_path, plain).name == "AC-TDM_s0.json"
    names = {runner.task_file(tmp_path, t).name for t in (tuned, dict(plain, agent_kw={"unseen_max": 0.5}),
                                                          dict(plain, config={"labels": "binary"}), dict(plain, config={"labels": "distance"}))}
    assert len(names) == 4 and all(n.startswith("AC-TDM_s0_") for n in names)  # configurations never share a file
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


def test_seeds_are_named_never_counted():
    from skinsafe.core.experiments.stats import parse_seeds

    assert parse_seeds("10-19") == list(range(10, 20))
    assert parse_seeds("11,12,13") == parse_seeds(["11", "12 13"]) == [11, 12, 13]
    assert parse_seeds("3") == [3]  # seed 3, not three seeds
    for bad in ("19-10", "a", ""):
        with pytest.raises(ValueError, match="seeds"):
            parse_seeds(bad)


def test_intervals_and_verdicts():
    from scipy import stats as sps

    from skinsafe.core.experiments.stats import compare, diff_ci, mean_ci

    x, y = [1.0, 2.0, 3.0, 4.0], [10.0, 12.0, 9.0, 15.0, 11.0]
    m, (lo, hi) = mean_ci(x)
    assert m == 2.5 and hi - m == pytest.approx(sps.t.ppf(0.975, 3) * np.std(x, ddof=1) / 2)
    d, ci = diff_ci(x, y)
    ref = sps.ttest_ind(y, x, equal_var=False).confidence_interval(0.95)
    assert d == pytest.approx(np.mean(y) - 2.5) and ci == pytest.approx([ref.low, ref.high])
    assert compare(ci) == "lower" and compare([-ci[1], -ci[0]]) == "higher" and compare([-1.0, 2.0]) == "not resolved"


def test_tuning_chooses_by_one_criterion_for_every_method():
    rows = [{"total_contacts_mean": 50.0, "goal_rate_last_mean": 0.7}, {"total_contacts_mean": 90.0, "goal_rate_last_mean": 0.9},
            {"total_contacts_mean": 70.0, "goal_rate_last_mean": 0.85}]
    assert maze.choose(rows) == 2  # fewest contacts among those reaching the goal, not the fewest overall
    # the sampler's objective orders trials as the rule does: every trial meeting the criterion first
    assert sorted(range(3), key=lambda i: maze.objective(rows[i])) == [2, 1, 0]
    assert maze.objective(rows[2]) == 70.0 and maze.objective(rows[0]) == pytest.approx(1e6 * 1.1 + 50.0)
    for r in rows:
        r["goal_rate_last_mean"] = 0.5
    assert maze.choose(rows) is None  # none reaches it: no rescue by the highest goal rate
    assert set(maze.SPACES) == set(maze.METHODS) == set(maze.DEFAULTS_SOURCE)
    for m in maze.TDM_METHODS:  # trial 0: the paper's filter, this project's mechanisms off and tuned as switches
        d = maze.defaults(m)
        assert (d["raw_floor"], d["unfiltered_entropy"], d["shrink"], d["contact_steps"], d["offline_transitions"]) == (0.0, False, False, 0, 0)
        assert d["lr"] == maze.defaults(m[:-4])["lr"]  # its base method's published learning rate
    assert maze.defaults("SAC")["lr"] == 3e-4 and maze.defaults("SAC-RP")["cost_penalty"] == 50.0 and maze.defaults("CPO")["target_kl"] == 0.01
    cfg = maze.MazeConfig(methods=("SAC-TDM", "RRL", "SAC"), ablation=True, ablation_seeds=(10, 11), ablation_episodes=3)
    chosen = {"SAC-TDM": {**maze.defaults("SAC-TDM"), "raw_floor": 0.05, "shrink": True}, "RRL": {}, "SAC": {}}
    abl = maze.ablation_tasks(chosen, cfg)
    # only what the chosen configuration has is removed: the floor and shrinkage
    assert sorted({h["variant"] for h, _ in abl}) == sorted(["SAC-TDM - 5% uniform floor", "SAC-TDM - visit-count shrinkage"]
                                                            + [f"RRL + {w.split(' (')[0]}" for w, _ in maze.BASELINE_EXTRAS])
    assert {t["seed"] for _, t in abl} == {10, 11} and all(h["agent_kw"] == t["agent_kw"] for h, t in abl)
    assert maze.MazeConfig().conditions() == {"episodes": 60, "max_steps": 200, "cost_limit": pytest.approx(68 / 60)}
    for bad, match in (({"tuning_seeds": (10,)}, "held-out"), ({"methods": ("X",)}, "unknown"), ({"trials": 0}, ">= 1"),
                       ({"ablation": True, "ablation_seeds": (3,)}, "evaluation seeds")):
        with pytest.raises(ValueError, match=match):
            maze.MazeConfig(**bad)


def test_full_protocol_reports_each_replicate_as_itself(tmp_path, monkeypatch):
    import argparse

    from skinsafe.core.app import experiment_maze as app
    from skinsafe.core.app import readme

    root, tmp_path = tmp_path, tmp_path / "results" / "maze"
    p = argparse.ArgumentParser()
    app.add_arguments(p)
    args = p.parse_args(["--out", str(tmp_path), "--methods", "AC-TDM,CPO", "--trials", "3", "--tuning-seeds", "0",
                         "--seeds", "10-11", "--episodes", "2", "--max-steps", "8", "--workers", "0", "--no-progress"])
    assert app.run(args) == 0
    doc = json.loads((tmp_path / "maze_results.json").read_text())
    assert doc["eval_seeds"] == [10, 11] and doc["tuning_conditions"] == doc["evaluation_conditions"]
    assert doc["evaluation_conditions"]["cost_limit"] == pytest.approx(68 / 2)  # CPO tuned and evaluated at one limit
    assert len(doc["replicates"]) == 2 and [r["tuning_seeds"] for r in doc["replicates"]] == [[0], [1]]
    for r in doc["replicates"]:  # each replicate: its own tuning (equal trials), summary, runs and verdicts
        assert {m: t["trials"] for m, t in r["tuning"].items()} == {"AC-TDM": 3, "CPO": 3}
        for m in ("AC-TDM", "CPO"):
            rec = r["tuning"][m]
            assert rec["configs"][0]["config"] == maze.defaults(m) and set(rec["space"]) == set(maze.SPACES[m])
            i = maze.choose(rec["configs"])
            assert rec["chosen_index"] == i and rec["chosen"] == rec["configs"][0 if i is None else i]["config"]
            assert rec["configs"][0]["agent_kw"].get("cost_limit") == (pytest.approx(34.0) if m == "CPO" else None)
        assert {(x["method"], x["seed"]) for x in r["per_seed"]} == {(m, s) for m in ("AC-TDM", "CPO") for s in (10, 11)}
        assert all(x["seed"] in (10, 11) and len(x["costs"]) == 2 for x in r["runs"])
        assert r["summary"]["claim"]["verdict"] in ("holds", "does not hold", "not resolved")
    settled = doc["claims"]["total"]
    assert settled["replicate_verdicts"] == [r["summary"]["claim"]["verdict"] for r in doc["replicates"]]
    assert settled["verdict"] == (settled["replicate_verdicts"][0] if settled["agrees"] else "not settled")
    assert not {"summary", "tuning", "runs", "per_seed"} & set(doc) and {"code_sha1", "versions"} <= set(doc["provenance"])
    grid = readme.maze_grid(root)  # the docs' table, one block per replicate, intervals as computed
    for r in doc["replicates"]:
        lo = r["summary"]["methods"]["CPO"]["total_contacts_ci95"][0]
        assert f"[{lo:,.1f}, " in grid
    # the tuner is a function of the runs: run again, every trial it asks is a finished task (Ray never starts)
    import ray

    monkeypatch.setattr(ray, "init", lambda *a, **k: (_ for _ in ()).throw(AssertionError("a new trial was asked")))
    assert app.run(args) == 0
    again = json.loads((tmp_path / "maze_results.json").read_text())
    assert [r["tuning"] for r in again["replicates"]] == [r["tuning"] for r in doc["replicates"]]
    with pytest.raises(SystemExit, match="held-out"):
        app.config_from_args(p.parse_args(["--tuning-seeds", "0-1", "--seeds", "1-3"]))


@pytest.mark.parametrize("method, kw", [("AC-TDM", None), ("SAC-TDM", None), ("SQRL", {"offline_transitions": 60, "pretrain_steps": 5})])
def test_a_shorter_run_is_the_start_of_a_longer_one(method, kw):
    """The ablation compares its shorter runs with the first episodes of the evaluation runs: that needs
    a run's first episodes not to depend on how many follow."""
    long, short = (run_one(method, 3, n, 12, kw) for n in (3, 2))
    for k in ("costs", "returns", "steps", "goals"):
        assert short[k] == long[k][:2]
    assert maze.first_episodes(long, 2)["costs"] == short["costs"]
