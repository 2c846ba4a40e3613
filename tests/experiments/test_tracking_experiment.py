"""The UR5 tracking experiment (Fig. 11), reduced, and the safety stack / scenes on the real scene."""
import argparse
import json
from dataclasses import replace

import numpy as np
import pytest
import torch

from skinsafe.core.experiments import tracking, tracking_report
from skinsafe.core.experiments.tracking import (
    TrackingConfig,
    claim,
    contacts_per_episode,
    per_seed,
    run_experiment,
    summary,
)
from skinsafe.core.experiments.tracking_runs import Learner, alignment_cos, run_episode
from skinsafe.core.learn.tracking_env import TrackingEnv
from skinsafe.core.safety.modulation import ModulationLayer
from skinsafe.core.safety.stack import SafetyStack, StrategyFilter, TeleopStream, TrajectorySource
from skinsafe.core.safety.tdm import TactileDangerModel

pytestmark = pytest.mark.xdist_group("tracking-experiment")  # one worker builds the module's costly fixtures, once


@pytest.fixture(scope="module")
def quick_results():
    cfg = replace(TrackingConfig.quick(), label_sets=("binary", "soft"))  # the paper's labels and the soft extension
    return cfg, run_experiment(cfg, progress=False, workers=0)


def test_both_label_sets_learn_apart_on_one_vanilla_run(quick_results):
    cfg, res = quick_results
    b, s = res["labels"]["binary"]["runs"], res["labels"]["soft"]["runs"]
    assert b["vanilla"] == s["vanilla"] and len(res["labels"]["binary"]["cpu_seconds"]["vanilla"]) == 1
    # the labels reach the learner: the same first re-training data give other models, other episodes
    fb, fs = b["tdm"]["0"][0]["fit"], s["tdm"]["0"][0]["fit"]
    assert fb["val_loss"] != fs["val_loss"]
    assert [r["contacts"] for r in b["tdm"]["0"][1:]] != [r["contacts"] for r in s["tdm"]["0"][1:]]


def test_quick_tracking_run_modulated_contacts_fewer_than_vanilla(quick_results):
    cfg, res = quick_results
    runs = res["labels"]["soft"]["runs"]
    assert set(runs) == {"vanilla", "tdm", "tdm2"}
    c = {m: np.array([r["contacts"] for r in runs[m]["0"]]) for m in runs}
    assert all(len(v) == cfg.run.episodes for v in c.values())
    assert c["vanilla"].min() > 20  # the balls really are in the way, felt by the skin readout
    # episode 0 has no experience yet: every method runs unmodulated and sees the same contacts
    assert c["tdm"][0] == c["vanilla"][0] == c["tdm2"][0]
    # after learning, the modulated runs touch less than vanilla over the learned episodes
    assert c["tdm2"][1:].sum() < c["vanilla"][1:].sum()
    rows = {r["method"]: r for r in summary(res["labels"]["soft"])}
    assert rows["vanilla"]["tracking_error_mm"] < 60  # vanilla follows the path
    assert contacts_per_episode(res["labels"]["soft"])["tdm2"] == c["tdm2"].tolist()  # one seed: its own
    # onsets beside ticks; the potential's alignment before each ball once there is a potential (episode 2 on)
    assert all(0 < r["onsets"] <= r["contacts"] for r in runs["vanilla"]["0"])
    assert all(v is None for r in runs["vanilla"]["0"] for v in r["alignment_cos"])
    cos = [v for r in runs["tdm2"]["0"][1:] for v in r["alignment_cos"]]
    assert len(cos) == 2 * cfg.run.n_balls and all(v is not None and -1 <= v <= 1 for v in cos)
    assert all(v is None for v in runs["tdm2"]["0"][0]["alignment_cos"])  # episode 1: nothing learned yet


def test_episode_logs_are_consistent(quick_results):
    cfg, res = quick_results
    cfg = cfg.run
    env = TrackingEnv(cfg, seed=0)
    ep = run_episode(env, None, seed=0)
    assert ep.contacts == res["labels"]["binary"]["runs"]["vanilla"]["0"][0]["contacts"]  # same seed, same episode
    assert ep.states.shape == (cfg.ticks, 4) and ep.dangers.shape[0] == cfg.ticks
    assert ep.contacts == int(ep.dangers.any(1).sum())
    assert len(ep.contact_points) == ep.contacts and len(ep.lit_points) == ep.dangers.sum()
    # contact points lie on the arm near a ball: within ball radius + arm radius + footprint
    d = np.linalg.norm(ep.contact_points[:, None] - np.array(res["balls"]["0"])[None], axis=2).min(1)
    assert (d < cfg.ball_radius + 0.08).all()
    # the exact path itself runs through the balls: that is where tracking must touch
    assert res["path_contact_ticks"]["0"] > 0.3 * cfg.ticks


def test_noisy_copies_are_labelled_by_the_skin_at_the_noisy_state(quick_results):
    """Fig. 11e's binary labels: a noisy copy of a touching state that no longer touches gets label 0."""
    cfg, _ = quick_results
    cfg = replace(cfg.run, labels="binary", augment=3)  # the oracle extension's copies
    env = TrackingEnv(cfg, seed=0)
    sc = env.scene
    ep = run_episode(env, None, seed=0)
    touched = ep.dangers.any(1)
    at_rest = sc.danger_at(ep.states).any(1)
    assert touched.sum() > 50 and (at_rest & touched).sum() >= 0.8 * touched.sum() and not (at_rest & ~touched).any()
    learner = Learner(cfg, sc, False, 0)
    learner.S, learner.A, learner.D = [ep.states], [ep.actions], [ep.dangers]
    S, A, D, src = learner.training_set()
    n = len(ep.states)
    copy, origin = src >= n, src % n
    assert len(S) == min(cfg.max_train, (cfg.augment + 1) * n) and np.array_equal(A, ep.actions[origin])
    assert np.array_equal(D[~copy], ep.dangers[origin[~copy]])  # visited: the episode's own events
    assert np.array_equal(D[copy], sc.danger_at(S[copy]))  # copies: the skin's events at the noisy state
    moved_off = copy & touched[origin] & ~D.any(1)
    share = moved_off.sum() / (copy & touched[origin]).sum()
    assert 0.3 < share < 0.9  # 61% of the copies of touching states touch nothing (sigma 0.05 rad > 2 cm penetration)
    clear = np.array([sc.ball_distance(np.r_[s, sc.robot.home[4:]]) for s in S[moved_off]])
    assert (clear > 0).mean() > 0.7  # most are off the balls (80%; the rest sink a taxel where MuJoCo's contact is unsensed)
    i = int(np.flatnonzero(moved_off & at_rest[origin])[0])  # one copy: its state touches at rest, the copy does not
    assert D[i].sum() == 0 and sc.danger_at(ep.states[origin[i]][None]).sum() > 0 and ep.dangers[origin[i]].sum() > 0


def test_alignment_cos_is_one_for_the_distance_gradient_itself(quick_results):
    cfg, _ = quick_results
    sc = TrackingEnv(cfg.run, seed=0).scene
    q = sc.desired(1.0)[0]
    h = 1e-4
    g = np.array([(sc.ball_distances(q + h * e)[0] - sc.ball_distances(q - h * e)[0]) / (2 * h) for e in np.eye(6)[:4]])
    assert alignment_cos(sc, q, -g, 0) == pytest.approx(1.0) and alignment_cos(sc, q, g, 0) == pytest.approx(-1.0)
    assert alignment_cos(sc, q, np.zeros(4), 0) is None


def test_claim_is_decided_on_paired_seeds_with_holms_correction():
    """The same means decide differently with the seeds' spread: 9 of 150 everywhere holds; 0 on nine seeds and
    90 on one (mean 9) is not resolved; 20 everywhere does not hold; vanilla below the TDM does not hold."""
    def seeds(tdm2, tdm=40.0):
        return [{"method": m, "seed": i, "contacts_ep6_10": v, "onsets_ep6_10": v / 10} for i, t2 in enumerate(tdm2)
                for m, v in (("vanilla", 150.0 + i), ("tdm", tdm), ("tdm2", t2))]

    for tdm2, verdict in (([9.0] * 10, "holds"), ([0.0] * 9 + [90.0], "not resolved"), ([20.0] * 10, "does not hold")):
        c = claim(seeds(tdm2))
        assert c.verdict == verdict and c.seeds == tuple(range(10)) and c.count == "contacts"
        assert c.tdm2_over_vanilla_ci95[0] <= c.tdm2_over_vanilla <= c.tdm2_over_vanilla_ci95[1]
    c = claim(seeds([9.0] * 10))
    share = next(x for x in c.comparisons if x.name.startswith("2-step TDM at most"))
    assert share.difference == pytest.approx(np.mean([15.0 + i / 10 - 9.0 for i in range(10)]))
    assert all(x.p_holm >= x.p for x in c.comparisons)  # Holm never lowers a p-value
    c = claim(seeds([9.0] * 10, tdm=200.0))  # vanilla below the TDM: "vanilla has the most contacts" fails
    assert c.verdict == "does not hold" and next(x for x in c.comparisons if x.name == "vanilla above TDM").verdict == "does not hold"
    assert claim(seeds([9.0] * 10), "onsets").means["tdm2"] == pytest.approx(0.9)
    assert claim([r for r in seeds([9.0]) if r["method"] != "tdm"]) is None
    rows = [{"contacts": k, "onsets": k % 3, "tracking_error": 0.01, "alignment_cos": [0.5, None, -0.1]} for k in range(10)]
    assert per_seed({"runs": {"tdm": {"3": rows}}}) == [
        {"method": "tdm", "seed": 3, "contacts_ep6_10": 7.0, "contacts_last": 9, "onsets_ep6_10": 1.0,
         "alignment_cos_ep6_10": pytest.approx(0.2), "tracking_error_mm": pytest.approx(10.0)}]


def test_tracking_document_report_and_options(tmp_path, quick_results):
    from skinsafe.core.app import experiment_tracking as app

    cfg, res = quick_results
    doc = tracking.document(res, cfg)
    assert doc["headline"] == "binary" and doc["labels"]["binary"]["role"] == "headline" and doc["runs"] is doc["labels"]["binary"]["runs"]
    assert doc["labels"]["binary"]["augment"] == 0 and doc["labels"]["soft"]["role"] == "extension"
    assert doc["config"]["augment"] == 0 and doc["config"]["labels"] == "binary" and "Holm" in doc["correction"]
    for name in ("binary", "soft"):  # each label set: its replicates, each with its own summary and claims
        lab = doc["labels"][name]
        assert {m: len(v) for m, v in lab["contacts_per_episode"].items()} == dict.fromkeys(tracking.METHODS, cfg.run.episodes)
        (rep,) = lab["replicates"]
        assert rep["seeds"] == [0] and {r["method"] for r in rep["summary"]} == set(tracking.METHODS)
        assert list(lab["settled"]["replicate_verdicts"]) == [rep["claim"]["verdict"]] and rep["claim_onsets"]["count"] == "onsets"
    md = tracking_report.markdown(doc)
    assert tracking_report.claim_statement(doc["labels"]["binary"]["replicates"][0]["claim"]) in md and "Extension" in md
    assert [p.name for p in tracking_report.plot(doc, tmp_path)] == ["contacts.png", "trajectories.png"]
    assert (tmp_path / "contacts.png").read_bytes()[:4] == b"\x89PNG"
    p = argparse.ArgumentParser()
    app.add_arguments(p)
    full = app.config_from_args(p.parse_args(["--seeds", "11,12", "15-16", "--labels", "binary", "soft"]))
    assert full.seeds == (11, 12, 15, 16) and full.label_sets == ("binary", "soft") and full.replicate_seeds == ()
    assert TrackingConfig().replicates("soft") == [tracking.HELD_OUT] and len(TrackingConfig().replicates("binary")) == 2
    again = app.config_from_args(p.parse_args(["--seeds", "11", "--replicate-seeds", "12-13", "--horizons", "1,3", "--rollout-dts", "0.1"]))
    assert again.replicate_seeds == (12, 13) and again.nstep_grid == ((1, 0.1), (3, 0.1))
    for argv, match in ((["--quick", "--episodes", "0"], "episodes"), (["--seeds", "11", "--replicate-seeds", "11"], "overlap"),
                        (["--seeds", "12-10"], "range")):
        with pytest.raises(SystemExit, match=match):
            app.config_from_args(p.parse_args(argv))


def test_stack_filters_planner_and_teleop_sources():
    times = np.linspace(0, 1, 126)
    targets = np.stack([np.sin(times), np.zeros_like(times)], 1)
    stream = TeleopStream(times, targets, latency=0.1, gain=0.0)
    planner = TrajectorySource(lambda t: (np.array([np.sin(t - 0.1), 0.0]), np.array([np.cos(t - 0.1), 0.0])), gain=0.0)
    stack = SafetyStack(np.array([1.0, 1.0]), dt=0.01)
    q = np.zeros(2)
    a = stack.run(stream, 0.5, q, None, 0.01)
    b = stack.run(planner, 0.5, q, None, 0.01)
    assert np.allclose(a, b, atol=2e-3) and a[0] == pytest.approx(np.cos(0.4), abs=2e-3)
    assert np.allclose(stack.tick(0.0, q, None, np.array([5.0, -1.0]), 0.01), [1.0, -0.2])  # limits, direction kept
    assert np.allclose(stack.tick(0.0, q, None, np.array([np.nan, 1.0]), 0.01), 0.0)  # broken command: stand still
    with pytest.raises(ValueError, match="increase"):
        TeleopStream([0.0, 0.0], np.zeros((2, 2)))


def test_strategy_filter_slows_down_into_learned_danger():
    torch.manual_seed(0)
    tdm = TactileDangerModel(2, 2, 10, (8,))
    with torch.no_grad():  # danger grows with the action along +x: logit = 40 a_x - 10 on every taxel
        tdm.trunk[0].weight.zero_()
        tdm.trunk[0].bias.fill_(1.0)
        tdm.trunk[0].weight[0, 2] = 40.0
        tdm.head.weight.zero_()
        tdm.head.weight[:, 0] = 1.0
        tdm.head.bias.fill_(-11.0)
    f = StrategyFilter(tdm)
    s = np.zeros(2)
    assert np.allclose(f(s, np.array([0.05, 0.0])), [0.05, 0.0])  # safe: the command itself
    assert np.allclose(f(s, np.array([1.0, 0.0])), [0.0, 0.0])  # certain danger: stop
    assert np.allclose(f(s, np.array([-1.0, 0.0])), [-1.0, 0.0])  # moving away is safe
    stack = SafetyStack(np.ones(2), strategy=f, modulation=ModulationLayer(lambda s_, a_: torch.zeros(len(s_)) + 0 * s_.sum(1)),
                        dt=0.01)
    assert np.allclose(stack.tick(0.0, s, None, np.array([1.0, 0.0]), 0.01), 0.0)


def test_strategy_filter_stops_early_with_the_exhaustive_argmax():
    """Scoring in prior order with the bound gives eq. 3's MAP over all candidates."""
    torch.manual_seed(1)
    tdm = TactileDangerModel(3, 3, 50, (16,))
    with torch.no_grad():
        tdm.head.bias.uniform_(-6.0, 1.0)
    f = StrategyFilter(tdm, scales=(1.0, 0.6, 0.3, 0.0), prior=(0.7, 0.15, 0.1, 0.05))
    rng = np.random.default_rng(0)
    picks = set()
    for _ in range(200):
        s, a = rng.normal(size=3), rng.normal(size=3) * rng.choice([0.1, 1.0, 10.0])
        cand = f.scales[:, None] * a
        scores = f.log_prior + f.fast.log_safety(np.broadcast_to(s, cand.shape), cand)
        want = cand[int(np.argmax(scores))]
        assert np.array_equal(f(s, a), want)
        picks.add(int(np.argmax(scores)))
    assert len(picks) >= 3  # the states reach past the first candidate


@pytest.mark.parametrize("scene", ["desk"])  # collaboration: tests/experiments/test_collaboration_pfl.py
def test_scenes_run_and_report(tmp_path, scene):
    from skinsafe.core.experiments import scenes as es

    args = argparse.Namespace(command_name=scene, out=str(tmp_path), pitch=0.02, duration=1.0 if scene == "desk" else 2.0,
                              gap=0.1, samples=600, steps=300, tangent_gain=0.0, seed=0, no_progress=True, touch=300.0,
                              forces=[300.0], margin=0.02)
    assert es.run(args) == 0
    res = json.loads((tmp_path / f"{scene}.json").read_text())
    assert (tmp_path / f"{scene}.png").read_bytes()[:4] == b"\x89PNG"
    if scene == "desk":
        assert (tmp_path / "desk_sweep.png").read_bytes()[:4] == b"\x89PNG"
        worst = {r["stack"]: r["min_clearance_mm"] for r in res["sweep_worst"]}
        assert worst["no modulation"] < 0  # a 300 N touch: the retraction hits the desk without modulation
        assert worst["TDM modulation, no stop"] < worst["TDM modulation"]  # the stop level keeps it off the desk
        assert worst["TDM modulation"] > 0 and worst["2-step TDM modulation"] > 0
        assert all(abs(r["touch_N"] - 300) < 30 for r in res["sweep"])  # the probe presses with the force asked
        assert (res["labels"], res["tangent_gain"]) == ("soft", 0.0)  # Fig. 14's row says what it ran with


@pytest.mark.parametrize("duration", [0.2, 0.25, 0.0, float("nan")])
def test_desk_shorter_than_its_settling_is_refused_by_name(tmp_path, duration):
    """The desk measures clearance from 0.25 s on: a run that ends before then is refused naming why (it was a
    numpy traceback on an empty clearance trace)."""
    from skinsafe.core.experiments import scenes as es

    args = argparse.Namespace(command_name="desk", out=str(tmp_path), duration=duration)
    with pytest.raises(SystemExit, match=r"--duration is .* s: the clearance is measured from 0.25 s on"):
        es.run(args)
    assert not any(tmp_path.iterdir())
