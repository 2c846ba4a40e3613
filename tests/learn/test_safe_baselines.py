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
    assert agent.eps_risk == pytest.approx(0.3)
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
    _set_risk(agent, [0.9, 0.2, 0.1, 0.6])
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
