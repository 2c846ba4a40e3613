"""The maze environment (reward, cost, termination on hand-placed positions), the agents and the experiment."""
import json

import numpy as np
import pytest

from skinsafe.core.experiments import maze as experiment_maze
from skinsafe.core.learn.baselines import AGENTS, make_agent
from skinsafe.core.learn.maze_env import BACKWARD, FORWARD, LEFT, RIGHT, MazeEnv, MazeFeatures, parse_layout

pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def env():
    return MazeEnv(max_steps=5)


def test_free_move_costs_nothing_and_lands_on_the_next_cell(env):
    env.reset()
    obs, r, term, trunc, info = env.step(FORWARD)  # start (1,1) facing +x -> (1,2)
    assert (r, term, trunc, info["cost"], info["cell"]) == (0.0, False, False, 0.0, (1, 2))
    np.testing.assert_allclose(obs, [2.5 * 0.4, 5.5 * 0.4, 1, 0], atol=1e-6)
    assert not info["taxel_danger"].any()


def test_bumping_a_wall_costs_one_and_lights_the_facing_taxels(env):
    env.place(1, 1, 1)  # facing +y, the border wall is above
    obs, r, term, trunc, info = env.step(FORWARD)
    assert info["cost"] == 1.0 and info["cell"] == (1, 1) and r == 0.0
    assert set(np.flatnonzero(info["taxel_danger"])) <= {15, 0, 1} and info["taxel_danger"][0]
    env.place(1, 1, 1)
    _, _, _, _, info = env.step(BACKWARD)  # (2,1) below is free
    assert info["cost"] == 0.0 and info["cell"] == (2, 1)
    env.place(1, 2, 0)  # facing +x, (1,3) free; backward to (1,1) free; facing down (2,2) is a wall
    env.step(RIGHT)
    _, _, _, _, info = env.step(FORWARD)
    assert info["cost"] == 1.0 and info["taxel_danger"][0]
    env.place(1, 2, 3)  # facing -y (wall below): moving backward hits the wall behind (+y border)
    _, _, _, _, info = env.step(BACKWARD)
    assert info["cost"] == 1.0 and info["taxel_danger"][8] and not info["taxel_danger"][0]


def test_turns_never_touch_and_reaching_the_goal_pays_100_and_terminates(env):
    env.place(1, 1, 0)
    for a in (LEFT, LEFT, RIGHT, RIGHT):
        assert env.step(a)[4]["cost"] == 0.0
    env.place(5, 5, 1)  # below the goal (4,5), facing +y
    obs, r, term, trunc, info = env.step(FORWARD)
    assert (r, term, info["cell"]) == (100.0, True, (4, 5))


def test_episode_truncates_at_max_steps(env):
    env.reset()
    for k in range(5):
        *_, term, trunc, _ = env.step(LEFT)
    assert trunc and not term


def test_bad_layout_and_action_are_refused(env):
    with pytest.raises(ValueError, match="exactly one 'G'"):
        parse_layout(["###", "#S#", "###"])
    with pytest.raises(ValueError, match="border"):
        parse_layout(["#####", "#S.G.", "#####"])
    with pytest.raises(ValueError, match="not one of 0..3"):
        env.step(7)
    with pytest.raises(ValueError, match="wall"):
        env.place(0, 0)


def test_features_peak_at_the_robot_cell(env):
    f = MazeFeatures(env.walls)
    obs = env.place(2, 3, 2)
    v = f(obs)[0]
    assert v.shape == (f.dim,) and np.argmax(v[:-4]) == 2 * 7 + 3
    np.testing.assert_allclose(v[-4:], [0, 1, 0, 0], atol=1e-6)  # heading -x


@pytest.mark.parametrize("name", list(AGENTS))
def test_every_agent_runs_an_episode(name):
    env = MazeEnv(max_steps=40)
    agent = make_agent(name, 4, 4, env.n_taxels, MazeFeatures(env.walls), seed=0)
    obs, _ = env.reset()
    for _ in range(2):
        while True:
            a = agent.act(obs)
            assert 0 <= a < 4
            nxt, r, term, trunc, info = env.step(a)
            agent.observe(obs, a, r, info["cost"], info["taxel_danger"], nxt, term, trunc)
            obs = nxt
            if term or trunc:
                break
        agent.end_episode()
        obs, _ = env.reset()
    p = agent.action_probs(MazeFeatures(env.walls)(obs))
    assert p.shape == (1, 4) and p.sum() == pytest.approx(1.0)


def test_tdm_agent_learns_to_avoid_a_wall_it_bumped():
    env = MazeEnv(max_steps=200)
    feats = MazeFeatures(env.walls)
    agent = make_agent("AC-TDM", 4, 4, env.n_taxels, feats, seed=0)
    for _ in range(40):  # bump the top wall from the start cell, and move freely to the right
        env.place(1, 1, 1)
        s = env._obs()
        for a in (FORWARD, RIGHT):
            nxt, r, term, trunc, info = env.step(a)
            agent.shield.add(feats(s)[0], a, info["taxel_danger"])
            s = nxt
    for _ in range(5):
        agent.shield.fit()
    p_raw = agent.action_probs(feats(env.place(1, 1, 1)))[0]
    p_filtered = agent.behaviour_probs(feats(env.place(1, 1, 1)))
    assert p_filtered[FORWARD] < 0.2 * p_raw[FORWARD]
    assert p_filtered.sum() == pytest.approx(1.0)


def test_quick_experiment_writes_plots_table_and_claim(tmp_path):
    args = experiment_maze_args(tmp_path)
    assert experiment_maze.run(args) == 0
    data = json.loads((tmp_path / "maze_results.json").read_text())
    s = data["summary"]
    assert set(s["methods"]) == set(experiment_maze.METHODS)
    assert s["config"] == experiment_maze.QUICK
    for r in data["runs"]:
        assert len(r["returns"]) == len(r["costs"]) == experiment_maze.QUICK["episodes"]
        assert all(0 <= c <= experiment_maze.QUICK["max_steps"] for c in r["costs"])
    for m, v in s["methods"].items():
        totals = [sum(r["costs"]) for r in data["runs"] if r["method"] == m]
        assert v["total_contacts_mean"] == pytest.approx(np.mean(totals))
    assert s["claim"]["holds"] in (True, False) and s["claim"]["statement"]
    assert (tmp_path / "maze_curves.png").read_bytes()[:4] == b"\x89PNG"
    md = (tmp_path / "maze_contacts.md").read_text()
    assert "| SAC-TDM |" in md and s["claim"]["statement"] in md


def test_claim_check_reports_both_ways():
    rows = {m: {"total_contacts_mean": v} for m, v in (("SAC", 100.0), ("SAC-TDM", 20.0), ("RRL", 50.0))}
    c = experiment_maze.claim_check(rows)
    assert c["holds"] and c["ratio_best_other_to_best_tdm"] == pytest.approx(2.5)
    assert "80% fewer contacts than SAC" in c["statement"]
    rows["RRL"]["total_contacts_mean"] = 10.0
    c = experiment_maze.claim_check(rows)
    assert not c["holds"] and "RRL" in c["statement"]


def experiment_maze_args(out):
    import argparse
    p = argparse.ArgumentParser()
    experiment_maze.add_arguments(p)
    return p.parse_args(["--quick", "--out", str(out), "--workers", "1", "--no-progress"])
