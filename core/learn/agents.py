"""Discrete soft actor-critic and actor-critic, each plain, with a reward penalty (-RP) or with the
strategy layer (-TDM): a tactile danger model learned online from the skin's danger events and the
Bayes filter of eq. 3 applied to the policy before every action.

Agents share one small interface used by the maze experiment (and any Gymnasium env with a discrete
action space and `info["cost"]`, `info["taxel_danger"]`): `act(obs) -> action`,
`observe(obs, action, reward, cost, danger, next_obs, terminated, truncated)`, `end_episode()`,
and, for the policy filter, `action_probs(features) -> (B, A)`.
"""
from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from skinsafe.core.safety.danger import PolicyFilter, action_log_safety, filter_log_probs
from skinsafe.core.safety.tdm import TactileDangerModel, one_hot, train_tdm


def mlp(n_in: int, n_out: int, hidden=(64, 64)) -> nn.Sequential:
    layers, w = [], n_in
    for h in hidden:
        layers += [nn.Linear(w, h), nn.ReLU()]
        w = h
    layers.append(nn.Linear(w, n_out))
    return nn.Sequential(*layers)


class TDMShield:
    """The strategy layer inside an agent: logs (features, action, per-taxel danger), refits a TDM after
    every episode and gives log p(not D | s, a) for every action."""

    def __init__(self, feat_dim: int, n_actions: int, n_taxels: int, seed: int, capacity: int = 20000,
                 epochs: int = 3, hidden=(64, 64)):
        self.model = TactileDangerModel(feat_dim, n_actions, n_taxels, hidden)
        self.n_actions, self.capacity, self.epochs, self.seed = n_actions, capacity, epochs, seed
        self.s, self.a, self.d = [], [], []
        self.fits = 0

    def add(self, feat: np.ndarray, action: int, danger: np.ndarray) -> None:
        self.s.append(feat)
        self.a.append(action)
        self.d.append(np.asarray(danger, np.float32))

    def fit(self) -> None:
        if not self.s:
            return
        s, a, d = (x[-self.capacity:] for x in (self.s, self.a, self.d))
        self.s, self.a, self.d = list(s), list(a), list(d)
        train_tdm(self.model, np.stack(s), one_hot(a, self.n_actions), np.stack(d), epochs=self.epochs, lr=3e-3,
                  batch_size=128, seed=self.seed + self.fits, progress=False)
        self.fits += 1

    @torch.no_grad()
    def log_safety(self, feat: torch.Tensor) -> torch.Tensor:
        return action_log_safety(self.model, feat, self.n_actions)


class Agent:
    """Common acting and bookkeeping; subclasses implement `_logits` and learning."""

    def __init__(self, obs_dim: int, n_actions: int, n_taxels: int, features=None, seed: int = 0,
                 cost_penalty: float = 0.0, use_tdm: bool = False, gamma: float = 0.97, lr: float = 3e-3,
                 hidden=(64, 64)):
        torch.manual_seed(seed)
        self.rng = np.random.default_rng(seed)
        self.features = features if features is not None else (lambda o: np.atleast_2d(np.asarray(o, np.float32)))
        self.feat_dim = int(self.features(np.zeros(obs_dim, np.float32)).shape[-1])
        self.n_actions, self.gamma, self.lr, self.hidden = n_actions, gamma, lr, hidden
        self.cost_penalty = float(cost_penalty)
        self.shield = TDMShield(self.feat_dim, n_actions, n_taxels, seed) if use_tdm else None
        self.filter = PolicyFilter(self, self.shield.model, n_actions) if use_tdm else None

    # p(a|s) of the raw policy, on features: the interface PolicyFilter wraps.
    @torch.no_grad()
    def action_probs(self, feats) -> np.ndarray:
        return torch.softmax(self._logits(torch.as_tensor(np.atleast_2d(feats))), -1).double().numpy()

    def behaviour_probs(self, feat: np.ndarray) -> np.ndarray:
        return (self.filter or self).action_probs(feat)[0]

    def act(self, obs) -> int:
        p = self.behaviour_probs(self.features(obs))
        return int(self.rng.choice(self.n_actions, p=p / p.sum()))

    def observe(self, obs, action, reward, cost, danger, next_obs, terminated, truncated) -> None:
        if self.shield is not None:
            self.shield.add(self.features(obs)[0], action, danger)
        self._learn(self.features(obs)[0], action, reward - self.cost_penalty * cost, cost,
                    self.features(next_obs)[0], terminated, truncated)

    def end_episode(self) -> None:
        if self.shield is not None:
            self.shield.fit()

    def _logits(self, feat: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError

    def _learn(self, s, a, r, c, s2, terminated, truncated) -> None:
        raise NotImplementedError


class Replay:
    """A ring buffer of (s, a, r, c, s', done) for off-policy agents."""

    def __init__(self, feat_dim: int, capacity: int = 20000):
        self.s = np.zeros((capacity, feat_dim), np.float32)
        self.s2 = np.zeros_like(self.s)
        self.a = np.zeros(capacity, np.int64)
        self.r = np.zeros(capacity, np.float32)
        self.c = np.zeros(capacity, np.float32)
        self.done = np.zeros(capacity, np.float32)
        self.capacity, self.n, self.i = capacity, 0, 0

    def add(self, s, a, r, c, s2, done) -> None:
        i = self.i
        self.s[i], self.a[i], self.r[i], self.c[i], self.s2[i], self.done[i] = s, a, r, c, s2, done
        self.i = (i + 1) % self.capacity
        self.n = min(self.n + 1, self.capacity)

    def sample(self, rng: np.random.Generator, batch: int):
        idx = rng.integers(self.n, size=batch)
        return tuple(torch.as_tensor(x[idx]) for x in (self.s, self.a, self.r, self.c, self.s2, self.done))


class DiscreteSAC(Agent):
    """Soft actor-critic for discrete actions (Christodoulou 2019): twin Q, expected soft values,
    automatic temperature toward a target entropy."""

    def __init__(self, *args, batch_size: int = 64, tau: float = 0.05, target_entropy_frac: float = 0.8,
                 update_every: int = 2, **kw):
        super().__init__(*args, **kw)
        f, A = self.feat_dim, self.n_actions
        self.actor = mlp(f, A, self.hidden)
        self.q1, self.q2 = mlp(f, A, self.hidden), mlp(f, A, self.hidden)
        self.q1_t, self.q2_t = mlp(f, A, self.hidden), mlp(f, A, self.hidden)
        self.q1_t.load_state_dict(self.q1.state_dict())
        self.q2_t.load_state_dict(self.q2.state_dict())
        self.log_alpha = torch.zeros(1, requires_grad=True)
        self.target_entropy = target_entropy_frac * np.log(A)
        self.opt_actor = torch.optim.Adam(self.actor.parameters(), lr=self.lr, foreach=True)
        self.opt_q = torch.optim.Adam([*self.q1.parameters(), *self.q2.parameters()], lr=self.lr, foreach=True)
        self.opt_alpha = torch.optim.Adam([self.log_alpha], lr=self.lr)
        self.buffer = Replay(f)
        self.batch_size, self.tau, self.update_every = batch_size, tau, update_every
        self.targets = [*self.q1_t.parameters(), *self.q2_t.parameters()]
        self.sources = [*self.q1.parameters(), *self.q2.parameters()]

    def _logits(self, feat):
        return self.actor(feat)

    def _learn(self, s, a, r, c, s2, terminated, truncated):
        self.buffer.add(s, a, r, c, s2, float(terminated))
        if self.buffer.n >= self.batch_size and self.buffer.n % self.update_every == 0:
            self.update(*self.buffer.sample(self.rng, self.batch_size))

    def actor_extra_loss(self, s, probs) -> torch.Tensor:
        """Extra actor loss term (SQRL's safety penalty); none for plain SAC."""
        return torch.zeros(())

    def update(self, s, a, r, c, s2, done) -> None:
        alpha = self.log_alpha.exp().detach()
        with torch.no_grad():
            logp2 = F.log_softmax(self.actor(s2), -1)
            q2 = torch.min(self.q1_t(s2), self.q2_t(s2))
            v2 = (logp2.exp() * (q2 - alpha * logp2)).sum(-1)
            y = r + self.gamma * (1 - done) * v2
        idx = a[:, None]
        loss_q = F.mse_loss(self.q1(s).gather(1, idx).squeeze(1), y) + F.mse_loss(self.q2(s).gather(1, idx).squeeze(1), y)
        self.opt_q.zero_grad()
        loss_q.backward()
        self.opt_q.step()
        logp = F.log_softmax(self.actor(s), -1)
        p = logp.exp()
        with torch.no_grad():
            q = torch.min(self.q1(s), self.q2(s))
        loss_pi = (p * (alpha * logp - q)).sum(-1).mean() + self.actor_extra_loss(s, p)
        self.opt_actor.zero_grad()
        loss_pi.backward()
        self.opt_actor.step()
        entropy = -(p.detach() * logp.detach()).sum(-1).mean()
        loss_alpha = self.log_alpha * (entropy - self.target_entropy)
        self.opt_alpha.zero_grad()
        loss_alpha.backward()
        self.opt_alpha.step()
        with torch.no_grad():
            torch._foreach_lerp_(self.targets, self.sources, self.tau)


class ActorCritic(Agent):
    """Episodic advantage actor-critic: Monte-Carlo returns (bootstrapped on truncation) minus V(s),
    one actor and one critic step per episode, entropy bonus. With the TDM filter the log-probabilities
    are those of the filtered (executed) policy, so the gradient stays on-policy."""

    def __init__(self, *args, entropy_coef: float = 0.01, **kw):
        super().__init__(*args, **kw)
        self.actor = mlp(self.feat_dim, self.n_actions, self.hidden)
        self.critic = mlp(self.feat_dim, 1, self.hidden)
        self.opt = torch.optim.Adam([*self.actor.parameters(), *self.critic.parameters()], lr=self.lr)
        self.entropy_coef = entropy_coef
        self.episode = []
        self.bootstrap = None

    def _logits(self, feat):
        return self.actor(feat)

    def behaviour_log_probs(self, s: torch.Tensor) -> torch.Tensor:
        logp = F.log_softmax(self.actor(s), -1)
        if self.shield is not None:
            logp = filter_log_probs(logp, self.shield.log_safety(s))
        return logp

    def _learn(self, s, a, r, c, s2, terminated, truncated):
        self.episode.append((s, a, r))
        self.bootstrap = None if terminated else s2

    def end_episode(self) -> None:
        if self.episode:
            s = torch.as_tensor(np.stack([e[0] for e in self.episode]))
            a = torch.as_tensor([e[1] for e in self.episode])
            rewards = [e[2] for e in self.episode]
            with torch.no_grad():
                g = 0.0 if self.bootstrap is None else float(self.critic(torch.as_tensor(self.bootstrap[None]))[0, 0])
            returns = np.zeros(len(rewards), np.float32)
            for t in range(len(rewards) - 1, -1, -1):
                g = rewards[t] + self.gamma * g
                returns[t] = g
            v = self.critic(s).squeeze(1)
            adv = torch.as_tensor(returns) - v.detach()
            logp = self.behaviour_log_probs(s)
            entropy = -(logp.exp() * logp.clamp_min(-1e9)).sum(-1).mean()
            loss = (-(adv * logp.gather(1, a[:, None]).squeeze(1)).mean() - self.entropy_coef * entropy
                    + 0.5 * F.mse_loss(v, torch.as_tensor(returns)))
            self.opt.zero_grad()
            loss.backward()
            self.opt.step()
        self.episode, self.bootstrap = [], None
        super().end_episode()
