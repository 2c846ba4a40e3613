"""The maze environment (reward, cost, termination on hand-placed positions), the agents and the experiment."""
import json
from dataclasses import asdict

import numpy as np
import pytest
import torch

from skinsafe.core.app import experiment_maze as app_maze
from skinsafe.core.experiments import maze, maze_report
from skinsafe.core.experiments.maze_claims import claim_check, converged_at, convergence
from skinsafe.core.experiments.verdicts import Settled, settle
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


QUICK_METHODS = ["SAC", "SAC-TDM", "AC-TDM", "CPO"]


def test_quick_experiment_writes_plots_table_and_claim(tmp_path):
    args = experiment_maze_args(tmp_path)
    assert app_maze.run(args) == 0
    data = json.loads((tmp_path / "maze_results.json").read_text())
    (rep,) = data["replicates"]  # --quick: one replicate of the published defaults, no tuning
    s = rep["summary"]
    assert list(s["methods"]) == QUICK_METHODS and rep["tuning"] == {} and data["tuning_conditions"] is None
    assert data["evaluation_conditions"] == {"episodes": 2, "max_steps": 20, "cost_limit": pytest.approx(68 / 2)}
    for r in rep["runs"]:
        assert len(r["returns"]) == len(r["costs"]) == len(r["goals"]) == 2
        assert all(0 <= c <= n <= 20 for c, n in zip(r["costs"], r["steps"]))
    for m, v in s["methods"].items():
        totals = [sum(r["costs"]) for r in rep["runs"] if r["method"] == m]
        assert v["total_contacts_mean"] == pytest.approx(np.mean(totals))
        assert v["goal_rate_mean"] == pytest.approx(np.mean([np.mean(r["goals"]) for r in rep["runs"] if r["method"] == m]))
    tdm = next(r for r in rep["runs"] if r["method"] == "SAC-TDM")
    assert tdm["tdm_fits"][-1]["steps"] >= 1  # refits during episodes
    assert s["claim"]["verdict"] in ("holds", "does not hold", "not resolved")
    assert data["claims"]["total"]["replicate_verdicts"] == [s["claim"]["verdict"]] and data["claims"]["total"]["agrees"]
    assert (tmp_path / "maze_curves.png").read_bytes()[:4] == b"\x89PNG"
    md = (tmp_path / "maze_contacts.md").read_text()
    assert "| SAC-TDM |" in md and maze_report.claim_statement(s["claim"]) in md
    # one task file per run; a configuration (published defaults, CPO's cost limit) adds a digest to its name
    names = sorted(p.name for p in (tmp_path / "tasks").glob("*.json"))
    assert sorted(n.split("_s0_")[0] for n in names) == sorted(QUICK_METHODS)
    assert rep["chosen"]["CPO"] == {**maze.defaults("CPO"), "cost_limit": pytest.approx(68 / 2)}
    assert set(data["defaults_source"]) == set(QUICK_METHODS) and "Holm" in data["correction"]
    assert data["eval_seeds"] == [0] and data["ablation"] == []
    assert [(p["method"], p["seed"]) for p in rep["per_seed"]] == [(m, 0) for m in QUICK_METHODS]
    assert not {"summary", "tuning", "runs", "per_seed"} & set(data)  # nothing of one replicate at the top level


def test_claim_check_counts_the_pairs_and_the_goal_reaching_methods():
    def rows(totals, goals):
        return [{"method": m, "seed": i, "total_contacts": t + i, "online_contacts": t + i, "goal_rate_last": goals[m]}
                for m, t in totals.items() for i in range(5)]

    goals = {"SAC": 0.9, "SAC-TDM": 0.95, "RRL": 0.1}
    c = claim_check(rows({"SAC": 100.0, "SAC-TDM": 20.0, "RRL": 50.0}, goals), ["SAC", "SAC-TDM", "RRL"])
    assert c.verdict == "holds" and [x.name for x in c.comparisons] == ["SAC-TDM vs SAC", "SAC-TDM vs RRL"]
    assert c.comparisons[0].difference == pytest.approx(80.0) and c.reaching == ("SAC", "SAC-TDM")
    assert c.learned == {"SAC": True, "SAC-TDM": True} and c.verdict_among_reaching == "holds"
    c = claim_check(rows({"SAC": 100.0, "SAC-TDM": 20.0, "RRL": 10.0}, goals), ["SAC", "SAC-TDM", "RRL"])
    # RRL touches less but never learned the task: among the goal-reaching methods the claim holds
    assert c.verdict == "does not hold" and c.verdict_among_reaching == "holds" and not c.holds_on_means
    assert claim_check(rows({"SAC": 1.0}, goals), ["SAC"]) is None


def experiment_maze_args(out):
    import argparse
    p = argparse.ArgumentParser()
    app_maze.add_arguments(p)
    return p.parse_args(["--quick", "--out", str(out), "--workers", "0", "--no-progress", "--methods", ",".join(QUICK_METHODS)])


def _maze_agent(name, seed=0):
    env = MazeEnv(max_steps=30)
    return env, make_agent(name, 4, 4, env.n_taxels, MazeFeatures(env.walls), seed=seed)


def test_sac_temperature_is_bounded_so_exploring_never_outweighs_the_goal():
    env, agent = _maze_agent("SAC")
    bonus = agent.alpha_max * np.log(4) / (1 - agent.gamma)
    assert bonus == pytest.approx(0.3 * 100.0)  # the whole discounted entropy bonus: 30% of the goal reward
    feats = MazeFeatures(env.walls)
    s = feats(env.reset()[0])[0]
    for _ in range(64):
        agent.buffer.add(s, 0, 0.0, 0.0, s, 0.0)
    with torch.no_grad():
        agent.log_alpha.fill_(5.0)  # far outside: the next update brings it back within bounds
    agent.update(*agent.buffer.sample(agent.rng, 64))
    assert agent.alpha_max / 10 * (1 - 1e-6) <= float(agent.log_alpha.detach().exp()) <= agent.alpha_max * (1 + 1e-6)  # float32


def test_sac_tdm_values_and_policy_ignore_actions_the_filter_removes():
    env, agent = _maze_agent("SAC-TDM")
    with torch.no_grad():  # a danger model certain that action 0 is dangerous everywhere
        first = agent.shield.model.trunk[0]
        first.weight.zero_()
        first.bias.zero_()
        first.weight[0, agent.feat_dim + 0] = 1.0  # hidden unit 0 = one-hot of action 0
        agent.shield.model.trunk[2].weight.zero_()
        agent.shield.model.trunk[2].bias.zero_()
        agent.shield.model.trunk[2].weight[0, 0] = 1.0
        agent.shield.model.head.weight.zero_()
        agent.shield.model.head.weight[:, 0] = 40.0
        agent.q_t.w[-1].zero_()  # both target critics love action 0
        agent.q_t.b[-1].copy_(torch.tensor([1000.0, 1.0, 2.0, 3.0]))
    s = torch.as_tensor(MazeFeatures(env.walls)(env.reset()[0]))
    untried = float(agent.policy_log_probs(s).exp()[0, 0].detach())
    assert 0.05 < untried < float(agent.action_probs(s.numpy())[0, 0])  # untried: p(D) capped at 0.5, lowered, not removed
    for _ in range(1000):  # experience of action 0 here: the TDM's own danger counts
        agent.shield.counts.add(s.numpy()[0], 0)
    assert agent.policy_log_probs(s).exp()[0, 0] < 1e-3
    assert float(agent.soft_value(s)[0]) < 5.0  # only actions 1-3 count
    plain = make_agent("SAC", 4, 4, env.n_taxels, MazeFeatures(env.walls), seed=0)
    with torch.no_grad():
        plain.q_t.w[-1].zero_()
        plain.q_t.b[-1].copy_(torch.tensor([1000.0, 1.0, 2.0, 3.0]))
    assert float(plain.soft_value(s)[0]) > 100.0


def test_actor_critic_learns_during_the_episode():
    env, agent = _maze_agent("AC")
    before = [w.detach().clone() for w in agent.actor.parameters()]
    obs, _ = env.reset()
    for _ in range(agent.n_steps):
        a = agent.act(obs)
        nxt, r, term, trunc, info = env.step(a)
        agent.observe(obs, a, r, info["cost"], info["taxel_danger"], nxt, term, trunc)
        obs = nxt
    assert not term and not trunc  # no episode end yet ...
    assert any(not torch.equal(b, w) for b, w in zip(before, agent.actor.parameters()))  # ... and it learned


def test_visit_counts_are_local_to_the_state_and_the_action():
    from skinsafe.core.learn.agents import VisitCounts

    c = VisitCounts(3, 2, width=0.3)
    for x, a in (([0, 0, 0], 1), ([0, 0, 0], 1), ([1, 0, 0], 0)):
        c.add(np.array(x, np.float32), a)
    assert len(c.index) == 2  # identical inputs stored once
    n = c(torch.tensor([[0.0, 0, 0], [1, 0, 0], [5, 5, 5]])).numpy()
    k = np.exp(-1 / (2 * 0.3 ** 2))  # kernel weight one unit away
    np.testing.assert_allclose(n, [[k, 2], [1, 2 * k], [0, 0]], atol=1e-6)


def test_sqrl_multiplier_follows_the_risk_constraint():
    """The reference's dual step: log nu falls while E_pi[Q_risk] is under eps and rises while it is over,
    by Adam at a tenth of the learning rate, from nu = 100 (recovery-rl's maze)."""
    env, agent = _maze_agent("SQRL")
    assert agent.nu == pytest.approx(100.0) and agent.nu_lr == pytest.approx(0.1 * agent.lr)
    log_nu = torch.tensor([np.log(100.0)], dtype=torch.float64, requires_grad=True)  # the float Adam is torch's Adam
    adam = torch.optim.Adam([log_nu], lr=agent.nu_lr)
    for g in (0.1, -0.3, 0.05):
        log_nu.grad = torch.tensor([g], dtype=torch.float64)
        adam.step()
        agent._dual_step(g)
    assert agent.log_nu == pytest.approx(float(log_nu.detach()), abs=1e-6)
    agent.log_nu, agent._nu_adam = float(np.log(100.0)), [0.0, 0.0, 0]
    s = MazeFeatures(env.walls)(env.reset()[0])[0]
    for _ in range(64):
        agent.buffer.add(s, 0, 0.0, 0.0, s, 0.0)
        agent.risk_replay.add(s, 0, 0.0, 0.0, s, 0.0)
    for _ in range(20):
        agent.update(*agent.buffer.sample(agent.rng, 64))
    assert agent.nu < 100.0 * np.exp(-19 * agent.nu_lr)  # ~lr per Adam step on log nu
    low = agent.nu
    for buf in ("buffer", "risk_replay"):
        setattr(agent, buf, type(agent.buffer)(agent.feat_dim))
    for a in range(4):  # every action touches: the safety critic learns risk -> 1
        for _ in range(16):
            agent.buffer.add(s, a, 0.0, 1.0, s, 0.0)
            agent.risk_replay.add(s, a, 0.0, 1.0, s, 0.0)
    for _ in range(150):
        agent.update(*agent.buffer.sample(agent.rng, 64))
    assert float(agent.risk(torch.as_tensor(s[None])).min().detach()) > agent.eps_risk and agent.nu > low


def test_twin_critics_are_two_independent_mlps():
    from skinsafe.core.learn.agents import TwinQ, mlp

    torch.manual_seed(0)
    twin = TwinQ(5, 3, (8, 8))
    x = torch.randn(7, 5)
    out = twin(x)
    assert out.shape == (2, 7, 3) and not torch.allclose(out[0], out[1])  # initialised independently
    for k in range(2):
        net = mlp(5, 3, (8, 8))
        with torch.no_grad():
            for layer, w, b in zip([m for m in net if isinstance(m, torch.nn.Linear)], twin.w, twin.b):
                layer.weight.copy_(w[k].T)
                layer.bias.copy_(b[k, 0])
        torch.testing.assert_close(out[k], net(x))


def test_tdm_filter_overrides_a_saturated_raw_policy():
    """eq. 3 can only move the probability the raw policy gives: a raw policy saturated on a move the TDM
    knows is dangerous defeats it, unless the raw policy keeps a floor of the uniform one."""
    env, floored = _maze_agent("SAC-TDM")
    _, bare = _maze_agent("SAC-TDM")
    bare.raw_floor = 0.0
    s = torch.as_tensor(MazeFeatures(env.walls)(env.reset()[0]))
    for agent in (floored, bare):
        with torch.no_grad():
            agent.actor[-1].weight.zero_()
            agent.actor[-1].bias.copy_(torch.tensor([40.0, 0.0, 0.0, 0.0]))  # raw p(action 0) = 1 - 1e-17
            head = agent.shield.model.head
            head.weight.zero_()
            head.bias.copy_(torch.full_like(head.bias, -30.0))
        for a in range(4):  # the TDM has seen every move here: its own danger counts
            for _ in range(200):
                agent.shield.counts.add(s.numpy()[0], a)
    with torch.no_grad():  # action 0 rated 99% dangerous on one taxel, the others safe
        for agent in (floored, bare):
            first = agent.shield.model.trunk[0]
            first.weight.zero_()
            first.bias.zero_()
            first.weight[0, agent.feat_dim + 0] = 1.0
            agent.shield.model.trunk[2].weight.zero_()
            agent.shield.model.trunk[2].bias.zero_()
            agent.shield.model.trunk[2].weight[0, 0] = 1.0
            agent.shield.model.head.weight[0, 0] = 30.0 + np.log(99.0)  # logit log(99): p(D | action 0) = 0.99
    p_bare = bare.policy_log_probs(s).exp()[0].detach().numpy()
    p_floor = floored.policy_log_probs(s).exp()[0].detach().numpy()
    assert p_bare[0] > 0.99  # the filter changes nothing on a saturated raw policy
    w = 200 / (200 + floored.shield.prior_count)  # experience weight of the shield (`TDMShield`): 200 samples of action 0
    safe = 1 - (w * 0.99 + (1 - w) * 0.8)
    expect = (0.95 + 0.0125) * safe / ((0.95 + 0.0125) * safe + 3 * 0.0125)  # floor 5%: (1 - f) p + f / 4
    assert p_floor[0] == pytest.approx(expect, rel=1e-3)
    assert p_floor[0] < 0.25


def test_one_bump_is_enough_for_the_filter_to_trust_the_tdm_but_an_untried_move_stays_possible():
    """After one try the filter uses the TDM's own danger (a move that bumped is all but removed); a move
    never tried keeps at least 1 - unseen_max of safety however dangerous the TDM extrapolates it."""
    env, agent = _maze_agent("SAC-TDM")
    shield = agent.shield
    s = MazeFeatures(env.walls)(env.reset()[0])
    with torch.no_grad():  # the TDM rates every move 99.9% dangerous on taxel 0
        for layer in (shield.model.trunk[0], shield.model.trunk[2]):
            layer.weight.zero_()
            layer.bias.zero_()
        shield.model.head.weight.zero_()
        shield.model.head.bias.fill_(-30.0)
        shield.model.head.bias[0] = float(np.log(999.0))
    shield.counts.add(s[0], FORWARD)  # forward tried (and bumped) once; the others never
    safe = shield.log_safety(torch.as_tensor(s)).exp()[0].numpy()
    w = 1 / (1 + shield.prior_count)
    assert safe[FORWARD] == pytest.approx(w * 0.001 + (1 - w) * (1 - shield.unseen_max), rel=1e-3)
    assert safe[FORWARD] < 0.005  # with a prior worth half a try it was 0.067: a saturated raw policy bumped again
    assert np.allclose(safe[[BACKWARD, LEFT, RIGHT]], 1 - shield.unseen_max, atol=1e-5)


def test_wall_moves_are_the_moves_that_bump_and_a_reset_can_start_anywhere():
    """`wall_moves` (CPO's budget) counts exactly the forward/backward moves that cost a contact in MuJoCo."""
    from skinsafe.core.learn.maze_env import wall_moves

    env = MazeEnv(max_steps=5)
    bumps = 0
    for r, c in np.argwhere(~env.walls):
        for h in range(4):
            for a in (FORWARD, BACKWARD):
                obs, _ = env.reset(options={"start": (int(r), int(c), h)})
                assert env.cell == (r, c) and env.heading == h and env.t == 0
                bumps += int(env.step(a)[4]["cost"])
    assert bumps == wall_moves(env.walls) == 68
    assert maze.cpo_budget(200) == pytest.approx(68 / 200)


def test_the_tdm_extras_can_each_be_removed():
    """The ablation's switches: no floor, no entropy on the unfiltered policy, no shrinkage (the TDM's own
    safety), no contact refit."""
    env = MazeEnv(max_steps=30)
    feats = MazeFeatures(env.walls)
    s = torch.as_tensor(feats(env.reset()[0]))
    full = make_agent("AC-TDM", 4, 4, env.n_taxels, feats, seed=0)
    bare = make_agent("AC-TDM", 4, 4, env.n_taxels, feats, seed=0, raw_floor=0.0, unfiltered_entropy=False,
                      shrink=False, contact_steps=0)
    from skinsafe.core.safety.danger import action_log_safety

    with torch.no_grad():
        raw = torch.log_softmax(full._logits(s), -1)
        for agent in (full, bare):  # a TDM sure that every move is dangerous (each taxel at 50%)
            agent.shield.model.head.bias.zero_()
        tdm_own = action_log_safety(bare.shield.model, s, 4)
    assert float(full.raw_entropy(raw)) > 1.0 and float(bare.raw_entropy(raw)) == 0.0
    torch.testing.assert_close(bare.shield.log_safety(s), tdm_own)
    assert float(tdm_own.max()) < np.log(1e-3)
    torch.testing.assert_close(full.shield.log_safety(s), torch.full_like(tdm_own, float(np.log(0.2))))  # untried: capped
    torch.testing.assert_close(bare.executed_log_probs(raw, s), torch.log_softmax(raw + tdm_own, -1))
    env.place(1, 1, 1)
    danger = env.step(FORWARD)[4]["taxel_danger"]
    for agent in (full, bare):
        agent.shield.add(feats(env.place(1, 1, 1))[0], FORWARD, danger)
    assert full.shield.stats()["grad_steps"] == 100 and bare.shield.stats()["fits"] == 0


def test_claim_is_decided_on_intervals_over_seeds_and_names_the_seeds_that_break_it():
    def per_seed(tdm, rrl, rrl_goal=1.0, offline=0.0):
        return ([{"method": "SAC-TDM", "seed": i, "total_contacts": t, "online_contacts": t, "goal_rate_last": 1.0}
                 for i, t in enumerate(tdm)]
                + [{"method": "RRL", "seed": i, "total_contacts": t + offline, "online_contacts": t, "goal_rate_last": rrl_goal}
                   for i, t in enumerate(rrl)])

    both = ["SAC-TDM", "RRL"]
    c = claim_check(per_seed([60, 62, 64, 66], [100, 110, 105, 95]), both)
    assert c.verdict == "holds" and c.comparisons[0].ci95[0] > 0 and c.seeds_beaten == ()
    c = claim_check(per_seed([60, 62, 64, 66], [40, 150, 45, 160]), both)  # RRL lower on two seeds, higher on two
    assert c.verdict == "not resolved" and c.holds_on_means
    assert [(b["seed"], b["total_contacts"]) for b in c.seeds_beaten] == [(0, 40), (2, 45)]
    assert "seed 0: 40" in maze_report.claim_statement(asdict(c))
    ps = per_seed([60, 62, 64, 66], [30, 31, 29, 30], offline=900)  # online fewer, but the offline phase counts
    assert claim_check(ps, both).verdict == "holds" and claim_check(ps, both, "online_contacts").verdict == "does not hold"


def test_never_converged_runs_are_censored_and_compared_by_log_rank():
    # the first window of 10 episodes with >= 8 goals starts at episode 4 (2 misses, 8 goals); never: 31
    assert converged_at([0] * 5 + [1] * 20) == 4 and converged_at([0] * 30) == 31
    runs = [{"method": m, "goals": [0] * k + [1] * (40 - k)} for m, ks in (("AC", (20, 22, 24, 40, 40)), ("AC-TDM", (5, 6, 7, 5, 6)))
            for k in ks]
    c = convergence(runs, ["AC", "AC-TDM"])
    assert c.methods["AC"] == {"converged": 3, "never": 2, "median_episode_converged": 21.0}
    (x,) = c.comparisons
    assert x.name == "AC-TDM vs AC" and x.difference > 0 and x.verdict == "holds"  # the -TDM variant converges sooner
    assert convergence([dict(r, method="AC") for r in runs[:5]] + [dict(r, method="AC-TDM") for r in runs[:5]],
                       ["AC", "AC-TDM"]).comparisons[0].verdict == "not resolved"
    reps = ["holds", "not resolved"]
    assert settle(reps) == Settled("not settled", tuple(reps), False) and settle(reps[:1] * 2).verdict == "holds"
