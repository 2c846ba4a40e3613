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
        with pytest.raises(SystemExit, match="seeds"):
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
    assert set(maze.SPACES) == set(maze.METHODS)
    for m in maze.TDM_METHODS:  # the -TDM mechanisms are switches of their search space, the offline phase too
        space = maze.SPACES[m]
        assert space["raw_floor"][1] == [0.05, 0.0] and space["shrink"][1] == [True, False]
        assert space["contact_steps"][1] == [100, 0] and space["offline_transitions"][1] == [0, 4000]
    for m in maze.BASELINES_GIVEN:
        assert maze.SPACES[m]["offline_transitions"][1] == [4000, 0]
    chosen = {"SAC-TDM": {"prior_count": 0.5}, "RRL": {}, "SAC": {}}
    abl = maze.ablation_tasks(chosen, ["SAC-TDM", "RRL", "SAC"], {"episodes": 3, "max_steps": 5}, [10, 11])
    variants = sorted({h["variant"] for h, _ in abl})
    # the prior count is already 0.5: that variant is the chosen configuration itself and is left out
    assert variants == sorted([f"SAC-TDM - {w.split(' (')[0]}" for w, _ in maze.TDM_EXTRAS[:4]]
                              + [f"RRL + {w.split(' (')[0]}" for w, _ in maze.BASELINE_EXTRAS])
    assert {t["seed"] for _, t in abl} == {10, 11} and all(h["agent_kw"] == t["agent_kw"] for h, t in abl)


def test_convergence_and_replicate_verdicts_from_numbers():
    # the first window of 10 episodes with >= 8 goals starts at episode 4 (2 misses, 8 goals); never: 31
    assert maze.converged_at([0] * 5 + [1] * 20) == 4 and maze.converged_at([0] * 30) == 31
    assert maze.converged_at([1, 0] * 4 + [1] * 12) == 5
    runs = [{"method": m, "goals": [0] * k + [1] * (40 - k)} for m, ks in (("AC", (20, 22, 24)), ("AC-TDM", (5, 6, 7)))
            for k in ks]
    c = maze.convergence(runs, ["AC", "AC-TDM"])
    assert c["methods"]["AC-TDM"]["episode_mean"] == 5.0 and c["methods"]["AC"]["episode_mean"] == 21.0
    p = c["pairs"]["AC-TDM vs AC"]
    assert p["difference"] == 16.0 and p["ci95"][0] > 0 and p["verdict"] == "faster"
    claim = {"verdict": "holds", "holds": True, "statement": "S.", "online_only": {"verdict": "does not hold"}}
    reps = [{"tuning_seeds": [0, 1], "summary": {"claim": claim}},
            {"tuning_seeds": [2, 3], "summary": {"claim": dict(claim, verdict="does not hold")}}]
    out = maze.settle(claim, reps)
    assert out["verdict"] == "not settled" and out["holds"] is False and out["verdict_agrees"] is False
    assert out["replicate_verdicts"] == ["holds", "does not hold"] and "not settled" in out["statement"]
    assert out["online_only"]["verdict"] == "does not hold"  # both replicates agree on it
    same = maze.settle(claim, reps[:1] * 2)
    assert same["verdict"] == "holds" and same["verdict_agrees"]
    slower = {"pairs": {"AC-TDM vs AC": dict(p, verdict="not resolved")}}
    reps = [{"summary": {"convergence": c}}, {"summary": {"convergence": slower}}]
    settled = maze.settle_convergence(c, reps)["pairs"]["AC-TDM vs AC"]
    assert settled["verdict"] == "not settled" and settled["replicate_verdicts"] == ["faster", "not resolved"]
    assert maze.settle_convergence(c, reps[:1] * 2)["pairs"]["AC-TDM vs AC"]["verdict"] == "faster"


def test_full_protocol_tunes_evaluates_on_held_out_seeds_and_ablates(tmp_path, monkeypatch):
    import argparse

    from skinsafe.core.app import readme

    root, tmp_path = tmp_path, tmp_path / "results" / "maze"

    p = argparse.ArgumentParser()
    maze.add_arguments(p)
    args = p.parse_args(["--out", str(tmp_path), "--methods", "AC-TDM,CPO", "--trials", "3", "--tuning-seeds", "0",
                         "--seeds", "10-11", "--episodes", "2", "--tuning-episodes", "1", "--max-steps", "8", "--ablation-seeds", "10-11",
                         "--ablation-episodes", "1", "--workers", "0", "--no-progress"])
    assert maze.run(args) == 0
    doc = json.loads((tmp_path / "maze_results.json").read_text())
    assert doc["eval_seeds"] == [10, 11]
    assert {m: t["trials"] for m, t in doc["tuning"].items()} == {"AC-TDM": 3, "CPO": 3}  # equal effort by construction
    for m in ("AC-TDM", "CPO"):
        rec = doc["tuning"][m]
        assert rec["tuning_seeds"] == [0] and len(rec["configs"]) == 3 and set(rec["space"]) == set(maze.SPACES[m])
        assert rec["configs"][0]["config"] == {k: d for k, (d, _) in maze.SPACES[m].items()}  # trial 0: the defaults
        i = maze.choose(rec["configs"])
        assert rec["chosen_index"] == i and rec["met_criterion"] == (i is not None)
        assert rec["chosen"] == rec["configs"][0 if i is None else i]["config"]  # none met: the default, reported so
        assert all(set(c["config"]) == set(maze.SPACES[m]) for c in rec["configs"])
    assert len(doc["replicates"]) == 2 and [r["tuning_seeds"] for r in doc["replicates"]] == [[0], [1]]
    assert doc["verdict_agrees"] == (len({(r["verdict"], r["online_only_verdict"]) for r in doc["replicates"]}) == 1)
    assert doc["summary"]["claim"]["replicate_verdicts"] == [r["verdict"] for r in doc["replicates"]]
    for r in doc["replicates"]:  # each replicate keeps its own verdict and statement, not the settled claim's
        assert r["verdict"] != "not settled" and "Replicates:" not in r["statement"]
    assert {"code_sha1", "versions"} <= set(doc["provenance"]) and "AC-TDM vs AC" not in doc["summary"]["convergence"]["pairs"]
    never = [m for m in ("AC-TDM", "CPO") if not doc["tuning"][m]["met_criterion"]]
    assert doc["summary"]["claim"].get("never_met_criterion", []) == never
    assert {(r["method"], r["seed"]) for r in doc["per_seed"]} == {(m, s) for m in ("AC-TDM", "CPO") for s in (10, 11)}
    assert all({"method", "seed", "total_contacts", "goal_rate"} <= set(r) for r in doc["per_seed"])
    for r in doc["runs"]:  # the evaluation runs are the chosen configurations on the held-out seeds
        assert r["seed"] in (10, 11) and len(r["costs"]) == 2
    rows = {r["variant"]: r for r in doc["ablation"]}
    assert "AC-TDM (chosen configuration)" in rows and "AC-TDM - visit-count shrinkage" in rows
    for r in rows.values():
        assert {"variant", "removed", "total_contacts_mean", "ci95"} <= set(r) and r["ci95"][0] <= r["total_contacts_mean"] <= r["ci95"][1]
    per = [p["total_contacts"] for p in rows["AC-TDM - visit-count shrinkage"]["per_seed"]]
    assert rows["AC-TDM - visit-count shrinkage"]["total_contacts_mean"] == pytest.approx(np.mean(per))
    # each variant against the same (first) episodes of its method's evaluation runs
    ref = rows["AC-TDM (chosen configuration)"]
    assert ref["episodes"] == 1 and [p["total_contacts"] for p in ref["per_seed"]] == [
        r["costs"][0] for r in doc["runs"] if r["method"] == "AC-TDM"]
    cpo = doc["summary"]["methods"]["CPO"]["agent_kw"]
    assert cpo == {**doc["tuning"]["CPO"]["chosen"], "cost_limit": pytest.approx(68 / 2)}  # wall-facing moves over the run's episodes
    assert doc["tuning"]["CPO"]["configs"][0]["agent_kw"]["cost_limit"] == pytest.approx(68 / 1)  # tuning ran 1 episode
    assert "Ablation" in (tmp_path / "maze_contacts.md").read_text()
    grid = readme.maze_grid(root)  # the docs' table: every method's trials, intervals as computed (not clipped at 0)
    lows = [doc["summary"]["methods"][m]["total_contacts_ci95"][0] for m in ("AC-TDM", "CPO")]
    assert all(f"[{lo:,.1f}, " in grid for lo in lows)
    for m in ("AC-TDM", "CPO"):
        rec = doc["tuning"][m]
        want = f"trial {rec['chosen_index']} of 3: " if rec["met_criterion"] else "no trial of 3 met the goal criterion: defaults"
        assert want in grid
    with pytest.raises(SystemExit, match="held-out"):
        maze.run(p.parse_args(["--out", str(tmp_path), "--tuning-seeds", "0-1", "--seeds", "1-3"]))
    # the tuner is a function of the runs: run again, every trial it asks is a finished task (Ray never starts)
    import ray

    monkeypatch.setattr(ray, "init", lambda *a, **k: (_ for _ in ()).throw(AssertionError("a new trial was asked")))
    assert maze.run(args) == 0
    again = json.loads((tmp_path / "maze_results.json").read_text())
    assert again["tuning"] == doc["tuning"] and again["replicates"] == doc["replicates"]


@pytest.mark.parametrize("method, kw", [("AC-TDM", None), ("SAC-TDM", None), ("SQRL", {"offline_transitions": 60, "pretrain_steps": 5})])
def test_a_shorter_run_is_the_start_of_a_longer_one(method, kw):
    """The ablation compares its shorter runs with the first episodes of the evaluation runs: that needs
    a run's first episodes not to depend on how many follow."""
    long, short = (run_one(method, 3, n, 12, kw) for n in (3, 2))
    for k in ("costs", "returns", "steps", "goals"):
        assert short[k] == long[k][:2]
    assert maze.first_episodes(long, 2)["costs"] == short["costs"]
