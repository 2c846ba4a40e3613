"""Recovery RL and SQRL follow the reference rules (recovery-rl code base): which action acts, which one is learned."""
import numpy as np
import pytest
import torch

from skinsafe.core.learn.baselines import make_agent
from skinsafe.core.learn.maze_env import MazeEnv, MazeFeatures

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _agent(name):
    env = MazeEnv(max_steps=30)
    return env, make_agent(name, 4, 4, env.n_taxels, MazeFeatures(env.walls), seed=0)


def _set_risk(agent, risk):
    """Q_risk(s, .) = `risk` at every state (the safety critic's last layer is a constant)."""
    last = agent.risk.q[-1]
    with torch.no_grad():
        last.weight.zero_()
        last.bias.copy_(torch.logit(torch.tensor(risk)))


def _propose(agent, action):
    """The task policy proposes `action` with probability ~1 everywhere."""
    last = agent.actor[-1]
    with torch.no_grad():
        last.weight.zero_()
        last.bias.fill_(-50.0)
        last.bias[action] = 50.0


def test_recovery_acts_only_on_risky_proposals_and_the_task_policy_learns_its_proposal():
    env, agent = _agent("RRL")
    _set_risk(agent, [0.9, 0.1, 0.05, 0.6])
    assert agent.eps_risk == pytest.approx(0.15) and agent.pos_fraction == pytest.approx(0.3)  # recovery-rl's maze
    obs, _ = env.reset()
    _propose(agent, 0)  # Q_risk 0.9 > eps: the recovery policy (argmin Q_risk) acts instead
    a = agent.act(obs)
    assert (agent._proposed, a) == (0, 2)
    nxt, r, term, trunc, info = env.step(a)
    agent.observe(obs, a, r, info["cost"], info["taxel_danger"], nxt, term, trunc)
    # action relabelling: the task transition holds the proposed action, the safety critic's the executed one
    assert agent.buffer.a[agent.buffer.n - 1] == 0 and agent.risk_replay.a[agent.risk_replay.n - 1] == 2
    np.testing.assert_array_equal(agent.buffer.s2[0], agent.risk_replay.s2[0])  # same transition that happened
    _propose(agent, 1)  # Q_risk 0.1 <= eps: the task policy's action runs
    assert [agent.act(obs) for _ in range(5)] == [1] * 5 and agent._proposed == 1


def test_sqrl_samples_only_actions_under_the_risk_threshold():
    env, agent = _agent("SQRL")
    obs, _ = env.reset()
    _set_risk(agent, [0.9, 0.12, 0.1, 0.6])
    _propose(agent, 0)  # the policy's favourite is rejected; the rest keep their (tiny, equal) probabilities
    acts = {agent.act(obs) for _ in range(200)}
    assert acts == {1, 2}
    _set_risk(agent, [0.9, 0.8, 0.7, 0.6])  # nothing is safe: the least risky action
    assert {agent.act(obs) for _ in range(20)} == {3}


def test_safety_critic_target_is_the_discounted_violation_chance_under_the_task_policy():
    from skinsafe.core.learn.baselines import SafetyCritic

    torch.manual_seed(0)
    critic = SafetyCritic(3, 2, (8,), gamma_safe=0.5)
    s, s2 = torch.randn(4, 3), torch.randn(4, 3)
    a = torch.tensor([0, 1, 0, 1])
    c = torch.tensor([1.0, 0.0, 0.0, 0.0])
    done = torch.tensor([0.0, 0.0, 1.0, 0.0])
    p = torch.tensor([[1.0, 0.0], [0.0, 1.0], [0.5, 0.5], [0.25, 0.75]])
    with torch.no_grad():
        q2 = torch.sigmoid(critic.q_t(s2))
        y = torch.stack([torch.tensor(1.0), 0.5 * q2[1, 1], torch.tensor(0.0), 0.5 * (0.25 * q2[3, 0] + 0.75 * q2[3, 1])])
        pred = critic(s).gather(1, a[:, None]).squeeze(1)
    want = torch.nn.functional.binary_cross_entropy(pred, y)
    torch.testing.assert_close(critic.loss(s, a, c, s2, done, p), want)


def test_replay_batches_hold_the_positive_fraction_and_the_focus():
    from skinsafe.core.learn.agents import Replay

    buf = Replay(2, capacity=100)
    for i in range(100):
        buf.add(np.array([i, 0.0]), 0, 0.0, float(i % 25 == 0), np.zeros(2), 0.0)
    rng = np.random.default_rng(0)
    s, a, r, c, s2, d = buf.sample(rng, 40, pos_fraction=0.3, focus=[7])
    assert len(c) == 41 and c[28:40].sum() == 12 and s[40, 0] == 7  # 12 of 40 drawn from the 4 contacts, then the focus
    assert sorted(buf.positives) == [0, 25, 50, 75]
    buf.add(np.zeros(2), 0, 0.0, 0.0, np.zeros(2), 0.0)  # overwrites index 0, a positive
    assert sorted(buf.positives) == [25, 50, 75]


def test_offline_phase_teaches_q_risk_the_walls_before_any_online_step():
    """Recovery RL's offline phase: random transitions from random placements, Q_risk pre-trained on them:
    afterwards it rates the moves that ran into a wall far above those that did not."""
    from skinsafe.core.learn.maze_env import random_rollouts

    env = MazeEnv(max_steps=30)
    agent = make_agent("RRL", 4, 4, env.n_taxels, MazeFeatures(env.walls), seed=0, offline_transitions=600, pretrain_steps=400)
    data = random_rollouts(env, agent.offline_transitions, np.random.default_rng(1))
    assert len(data["actions"]) == 600 and 0.1 < data["costs"].mean() < 0.4  # a random walk bumps ~1 move in 5
    with torch.no_grad():
        before = agent.risk(torch.as_tensor(agent.features(data["obs"]))).gather(1, torch.as_tensor(data["actions"])[:, None])
    agent.pretrain(data["obs"], data["actions"], data["costs"], data["next_obs"], data["terminated"])
    assert agent.risk_replay.n == 600 and len(agent.risk_replay.positives) == int(data["costs"].sum())
    with torch.no_grad():
        q = agent.risk(torch.as_tensor(agent.features(data["obs"]))).gather(1, torch.as_tensor(data["actions"])[:, None])[:, 0]
    bump = data["costs"] > 0
    assert float(before.std()) < 0.05  # untrained: flat
    assert float(q[bump].mean()) > 0.8 and float(q[~bump].mean()) < 0.3


def test_tdm_extras_given_to_the_baselines():
    env, agent = _agent("SQRL")
    obs, _ = env.reset()
    feat = agent.features(obs)
    _set_risk(agent, [0.9, 0.9, 0.9, 0.05])
    assert agent.q_risk(feat)[0] == pytest.approx(0.9)
    shrunk = make_agent("SQRL", 4, 4, env.n_taxels, MazeFeatures(env.walls), seed=0, shrink=True)
    _set_risk(shrunk, [0.9, 0.9, 0.9, 0.05])
    # untried: risk capped at eps, so nothing is rejected before it is tried; once tried, Q_risk's own value
    np.testing.assert_allclose(shrunk.q_risk(feat), [0.15, 0.15, 0.15, 0.05], rtol=1e-5)
    shrunk.counts.add(feat[0], 0)
    w = 1 / (1 + 0.01)  # one try against a prior worth a hundredth of one, as the -TDM shield
    assert shrunk.q_risk(feat)[0] == pytest.approx(w * 0.9 + (1 - w) * 0.15, rel=1e-5)
    assert {shrunk.act(obs) for _ in range(50)} == {1, 2, 3}
    _propose(agent, 0)
    floored = make_agent("RRL", 4, 4, env.n_taxels, MazeFeatures(env.walls), seed=0, floor=0.2)
    _propose(floored, 0)
    np.testing.assert_allclose(floored.task_probs(feat), [0.85, 0.05, 0.05, 0.05], atol=1e-6)
    refit = make_agent("RRL", 4, 4, env.n_taxels, MazeFeatures(env.walls), seed=0, contact_steps=30)
    before = [p.detach().clone() for p in refit.risk.q.parameters()]
    refit.act(obs)
    nxt, r, term, trunc, info = env.step(1)  # backward from the start cell runs into the wall
    assert info["cost"] == 1.0
    refit.observe(obs, 1, r, info["cost"], info["taxel_danger"], nxt, term, trunc)
    assert refit.buffer.n == 1 and any(not torch.equal(b, p) for b, p in zip(before, refit.risk.q.parameters()))
    assert float(refit.risk(torch.as_tensor(feat))[0, 1]) > 0.5  # the contact learned at once


def test_a_tdm_agent_may_take_the_same_offline_phase():
    """The offline data RRL and SQRL get, offered to a -TDM agent (a switch of its search space): its TDM
    learns the random transitions' wall contacts before any online step; an agent with neither a TDM nor a
    safety critic refuses it."""
    from skinsafe.core.learn.maze_env import random_rollouts

    env = MazeEnv(max_steps=30)
    agent = make_agent("AC-TDM", 4, 4, env.n_taxels, MazeFeatures(env.walls), seed=0, offline_transitions=600, pretrain_steps=300)
    data = random_rollouts(env, agent.offline_transitions, np.random.default_rng(1))
    assert data["dangers"].shape == (600, env.n_taxels) and (data["dangers"].any(1) == (data["costs"] > 0)).all()
    feats = torch.as_tensor(agent.features(data["obs"]))
    agent.pretrain(**data)
    assert agent.shield.trainer.n == 600 and agent.shield.stats()["grad_steps"] > 0
    p_danger = 1 - agent.shield.log_safety(feats).exp().gather(1, torch.as_tensor(data["actions"])[:, None])[:, 0]
    bump = data["costs"] > 0
    assert float(p_danger[bump].mean()) > 0.5 and float(p_danger[~bump].mean()) < 0.2
    with pytest.raises(ValueError, match="offline_transitions"):
        make_agent("AC", 4, 4, env.n_taxels, MazeFeatures(env.walls), seed=0, offline_transitions=100)
