"""Discrete soft actor-critic and actor-critic, each plain, with a reward penalty (-RP) or with the
strategy layer (-TDM): a tactile danger model learned online from the skin's danger events and the
Bayes filter of eq. 3 applied to the policy before every action.

Agents share one small interface used by the maze experiment (and any Gymnasium env with a discrete
action space and `info["cost"]`, `info["taxel_danger"]`): `act(obs) -> action`,
`observe(obs, action, reward, cost, danger, next_obs, terminated, truncated)`, `end_episode()`,
and, for the policy filter, `action_probs(features) -> (B, A)`.

Choices that make them learn (issue 16); each -TDM extra among them can be switched off for the
ablation of issue 31 (`raw_floor=0`, `unfiltered_entropy=False`, `shrink=False`, `contact_steps=0`;
`core.experiments.maze.TDM_EXTRAS`):

- The TDM is refitted every `refit_every` environment steps (25 gradient steps, warm started) and after
  every contact event (100, with the new contact in every batch: a uniform batch of thousands of safe
  samples saw it a handful of times and early stopping on a validation split that never saw it threw
  the lesson away; SAC-TDM seeds 0-3, contacts in the first 50 episodes 145/210/226/298 -> 155/118/191/148),
  with a validation split (`TDMTrainer`), not a few epochs at episode ends.
  The filter's danger is the TDM's shrunk by experience (`TDMShield`): untried actions are lowered,
  never removed, so the agent keeps exploring where its TDM only extrapolates; one try is enough to
  trust the TDM there (`prior_count` 0.01). With a prior worth half a try (0.5) a move that had just
  bumped kept p(not D) = 0.1 / (n + 0.5) after n bumps (0.067 after one), which a raw policy on that
  move lets through: SAC-TDM seed 0 made 132 contacts in its first 50 episodes, 79 of them repeats of
  53 (state, action) pairs. At 0.01, 200 episodes, seeds 0 and 1: SAC-TDM 77 / 69, AC-TDM 79 / 76
  total contacts (0.5: 157 / 192 and 250 / 216), all reaching the goal in the last 20 episodes.
- Discrete SAC takes one gradient step per environment step with one backward pass for critics, actor
  and temperature (every 2 steps, seed 0 collapsed onto bumping a wall: 22,178 contacts, goal 0.01).
- Discrete SAC's temperature aims at a discrete target entropy (a fraction of log |A|), and log
  alpha is bounded so the whole discounted entropy bonus, `alpha log|A| / (1 - gamma)`, stays below
  `entropy_share` (30%) of the task reward: exploring can never pay more than reaching the goal. At 10%
  (alpha <= 0.216) Q-estimate noise of ~1 reward unit made the policy near-deterministic: plain SAC
  settled on bumping a wall (a free "stay" here) and reached the goal in the last 20 episodes on 2 of 5
  seeds (seed 4: 22,125 contacts); at 30% seeds 0, 2, 3, 4 all reach it (757-3,973 contacts).
- SAC-TDM's critic targets, actor loss and temperature use the filtered (executed) policy
  p(a | not D, s), so the critic never bootstraps through actions the filter does not allow.
- The filter acts on the raw policy mixed with 5% of the uniform one (`raw_floor`): eq. 3 can only
  move probability the raw policy gives, and SAC's raw policy saturates on one action within a few
  episodes (in the maze bumping a wall is a free "stay": seed 0 sat on p(forward) = 1.000 facing a wall
  its TDM rated 98.5% dangerous and bumped 195 times in one episode). With the floor, SAC-TDM seed 0
  made 145 contacts in its first 50 episodes instead of 1,418; a stronger raw-entropy term (coefficient
  1) did not help (1,500).
- Actor-critic updates every `n_steps` environment steps (and at episode ends) with GAE(lambda)
  advantages bootstrapped from its critic; with the TDM its log-probabilities are the filtered ones.
"""
from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from skinsafe.core.learn.tdm_training import FitConfig, TDMTrainer
from skinsafe.core.safety.danger import action_log_safety, filter_log_probs
from skinsafe.core.safety.tdm import TactileDangerModel


def mlp(n_in: int, n_out: int, hidden=(64, 64)) -> nn.Sequential:
    layers, w = [], n_in
    for h in hidden:
        layers += [nn.Linear(w, h), nn.ReLU()]
        w = h
    layers.append(nn.Linear(w, n_out))
    return nn.Sequential(*layers)


class VisitCounts:
    """How much experience lies near each (state, action): a Gaussian kernel (bandwidth `width`) in the
    TDM's input space summed over the logged samples of each discrete action. Identical inputs are
    stored once with a count (the maze's states repeat), so a query costs (B x distinct inputs)."""

    def __init__(self, feat_dim: int, n_actions: int, width: float = 0.3, capacity: int = 4096):
        self.x = torch.zeros((capacity, feat_dim))
        self.n = torch.zeros((capacity, n_actions))
        self.index: dict[bytes, int] = {}
        self.inv = 1.0 / (2 * width ** 2)

    def add(self, feat: np.ndarray, action: int) -> None:
        key = np.round(feat, 3).tobytes()
        i = self.index.get(key)
        if i is None:
            i = len(self.index) % len(self.x)  # past capacity the oldest distinct inputs are overwritten
            self.index[key] = i
            self.x[i] = torch.as_tensor(feat)
            self.n[i] = 0
        self.n[i, action] += 1

    def __call__(self, s: torch.Tensor) -> torch.Tensor:
        """(B, A) kernel-weighted sample counts near each state, per action."""
        m = min(len(self.index), len(self.x))
        if m == 0:
            return torch.zeros((s.shape[0], self.n.shape[1]))
        return torch.exp(-torch.cdist(s, self.x[:m]).square() * self.inv) @ self.n[:m]


class TDMShield:
    """The strategy layer inside an agent: logs (features, action, per-taxel danger), refits its TDM
    every `refit_every` steps (`fit.steps` gradient steps, warm started) and after every contact event
    (`contact_steps`; validated on 10% of the samples) and gives log p(not D | s, a).

    Where the TDM has no experience of an action it extrapolates, and in the maze it extrapolates
    "moving is dangerous" to moves never tried, so eq. 3 would all but remove them and the agent stops
    exploring. The danger the filter uses is therefore the TDM's, shrunk toward a capped value by how
    much experience lies near (s, a): p = w p_TDM + (1 - w) min(p_TDM, `unseen_max`), w = n / (n +
    `prior_count`) with n from `VisitCounts`. An action tried often gets the TDM's own danger; an untried
    one at most `unseen_max`, so the filter lowers its chance but never removes it."""

    def __init__(self, feat_dim: int, n_actions: int, n_taxels: int, seed: int, refit_every: int = 20,
                 fit: FitConfig | None = None, hidden=(64, 64), unseen_max: float = 0.8, prior_count: float = 0.01,
                 contact_steps: int = 100, shrink: bool = True):
        self.model = TactileDangerModel(feat_dim, n_actions, n_taxels, hidden)
        self.trainer = TDMTrainer(self.model, fit or FitConfig(steps=25, min_steps=25, batch_size=64, val_fraction=0.1), seed=seed + 7919)
        self.n_actions, self.refit_every, self.contact_steps = n_actions, int(refit_every), int(contact_steps)
        self.counts = VisitCounts(feat_dim, n_actions)
        self.unseen_max, self.prior_count, self.shrink = float(unseen_max), float(prior_count), bool(shrink)
        self.eye = np.eye(n_actions, dtype=np.float32)
        self.since = 0

    def add(self, feat: np.ndarray, action: int, danger: np.ndarray) -> None:
        danger = np.asarray(danger, np.float32)
        self.trainer.add(feat, self.eye[action], danger)
        self.counts.add(feat, action)
        self.since += 1
        if danger.any() and self.contact_steps > 0:  # a new contact is news: learn it now, in every batch
            self.fit(self.contact_steps, focus=[self.trainer.last])
        elif self.since >= self.refit_every:
            self.fit()

    def fit(self, steps: int | None = None, focus=()) -> dict:
        self.since = 0
        return self.trainer.fit(steps, focus)

    @torch.no_grad()
    def log_safety(self, feat: torch.Tensor) -> torch.Tensor:
        """(B, A) log p(not D | s, a) for the filter: the TDM's, shrunk by experience (class doc; with
        `shrink` False the TDM's own)."""
        ls = action_log_safety(self.model, feat, self.n_actions)
        if not self.shrink:
            return ls
        n = self.counts(feat)
        w = n / (n + self.prior_count)
        capped = torch.clamp_min(ls, float(np.log1p(-self.unseen_max)))  # p(D) <= unseen_max
        return torch.log(w * ls.exp() + (1 - w) * capped.exp())

    def stats(self) -> dict:
        h = self.trainer.history
        return {"fits": len(h), "fit_seconds": self.trainer.seconds, "grad_steps": int(sum(r["steps"] for r in h)),
                "last": h[-1] if h else None}


class Agent:
    """Common acting and bookkeeping; subclasses implement `_logits` and learning."""

    def __init__(self, obs_dim: int, n_actions: int, n_taxels: int, features=None, seed: int = 0,
                 cost_penalty: float = 0.0, use_tdm: bool = False, gamma: float = 0.97, lr: float = 3e-3,
                 hidden=(64, 64), refit_every: int = 20, fit: FitConfig | None = None, unseen_max: float = 0.8,
                 prior_count: float = 0.01, raw_floor: float = 0.05, unfiltered_entropy: bool = True,
                 contact_steps: int = 100, shrink: bool = True, offline_transitions: int = 0, pretrain_steps: int = 2000):
        torch.manual_seed(seed)
        self.rng = np.random.default_rng(seed)
        self.features = features if features is not None else (lambda o: np.atleast_2d(np.asarray(o, np.float32)))
        self.feat_dim = int(self.features(np.zeros(obs_dim, np.float32)).shape[-1])
        self.n_actions, self.gamma, self.lr, self.hidden = n_actions, gamma, lr, hidden
        self.cost_penalty = float(cost_penalty)
        self.raw_floor, self.unfiltered_entropy = float(raw_floor), bool(unfiltered_entropy)
        self.shield = (TDMShield(self.feat_dim, n_actions, n_taxels, seed, refit_every, fit, unseen_max=unseen_max,
                                 prior_count=prior_count, contact_steps=contact_steps, shrink=shrink) if use_tdm else None)
        if offline_transitions and self.shield is None:
            raise ValueError(f"offline_transitions={offline_transitions}: only a -TDM agent, RRL or SQRL learns from an "
                             "offline phase; give 0 for this agent")
        self.offline_transitions, self.pretrain_steps = int(offline_transitions), int(pretrain_steps)

    def pretrain(self, obs, actions, costs, next_obs, terminated, dangers) -> None:
        """The offline phase of a -TDM agent (`offline_transitions` > 0, the random transitions RRL and SQRL
        get): its TDM and visit counts take their taxel events and the TDM is fitted on them for
        `pretrain_steps` gradient steps; the policy learns online only."""
        feats = self.features(np.asarray(obs, np.float32))
        actions = np.asarray(actions, np.int64)
        self.shield.trainer.add(feats, self.shield.eye[actions], np.asarray(dangers, np.float32))
        for f, a in zip(feats, actions):
            self.shield.counts.add(f, int(a))
        self.shield.fit(self.pretrain_steps)

    # p(a|s) of the raw policy, on features: the interface `safety.danger.PolicyFilter` wraps.
    @torch.no_grad()
    def action_probs(self, feats) -> np.ndarray:
        return torch.softmax(self._logits(torch.as_tensor(np.atleast_2d(feats))), -1).double().numpy()

    @torch.inference_mode()
    def behaviour_probs(self, feat: np.ndarray) -> np.ndarray:
        """The executed policy at one state: filtered by eq. 3 with the shield's danger when there is a TDM
        (the same `policy_log_probs` the learning uses)."""
        return self.policy_log_probs(torch.as_tensor(np.atleast_2d(feat))).exp()[0].double().numpy()

    def policy_log_probs(self, s: torch.Tensor) -> torch.Tensor:
        """log of the executed policy over a batch of features: filtered by the TDM (eq. 3) when there is one."""
        return self.executed_log_probs(F.log_softmax(self._logits(s), -1), s)

    def executed_log_probs(self, raw: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
        """The executed policy from the raw one's log-probabilities: with the TDM, the raw policy mixed
        with `raw_floor` of the uniform one, then filtered by eq. 3 (the floor keeps every action
        available to the filter: it can only move probability the raw policy gives)."""
        if self.shield is None:
            return raw
        if self.raw_floor > 0:
            raw = torch.logaddexp(raw + float(np.log1p(-self.raw_floor)), torch.full_like(raw, float(np.log(self.raw_floor / self.n_actions))))
        return filter_log_probs(raw, self.shield.log_safety(s))

    def raw_entropy(self, raw: torch.Tensor) -> torch.Tensor:
        """Mean entropy of the unfiltered policy, from its log-probabilities `raw`: with the TDM, the
        actions the filter removes get no gradient from the filtered loss, so without this term their
        logits drift (a raw policy of 0.99 on a filtered action defeats any filter whose safety estimate
        is not exactly 0). Off with `unfiltered_entropy` False (an ablation)."""
        if self.shield is None or not self.unfiltered_entropy:
            return torch.zeros(())
        return -(raw.exp() * raw).sum(-1).mean()

    def act(self, obs) -> int:
        p = self.behaviour_probs(self.features(obs))
        return int(self.rng.choice(self.n_actions, p=p / p.sum()))

    def observe(self, obs, action, reward, cost, danger, next_obs, terminated, truncated) -> None:
        if self.shield is not None:
            self.shield.add(self.features(obs)[0], action, danger)
        self._learn(self.features(obs)[0], action, reward - self.cost_penalty * cost, cost,
                    self.features(next_obs)[0], terminated, truncated)

    def end_episode(self) -> None:
        pass

    def stats(self) -> dict:
        """Learning diagnostics for the result file (TDM fits, temperature)."""
        return {"tdm": self.shield.stats()} if self.shield is not None else {}

    def _logits(self, feat: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError

    def _learn(self, s, a, r, c, s2, terminated, truncated) -> None:
        raise NotImplementedError


class TwinQ(nn.Module):
    """Two independent MLP critics evaluated together (one batched matrix product per layer instead of
    one per layer per critic): (B, n_in) -> (2, B, n_out). Each critic is initialised like `mlp`'s."""

    def __init__(self, n_in: int, n_out: int, hidden=(64, 64), k: int = 2):
        super().__init__()
        dims = [n_in, *hidden, n_out]
        self.w, self.b = nn.ParameterList(), nn.ParameterList()
        for i, o in zip(dims[:-1], dims[1:]):
            layers = [nn.Linear(i, o) for _ in range(k)]
            self.w.append(nn.Parameter(torch.stack([m.weight.detach().T for m in layers])))
            self.b.append(nn.Parameter(torch.stack([m.bias.detach()[None] for m in layers])))
        self.k = k

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h = x.expand(self.k, *x.shape)
        for j, (w, b) in enumerate(zip(self.w, self.b)):
            h = torch.baddbmm(b, h, w)
            if j < len(self.w) - 1:
                h = torch.relu(h)
        return h


class Replay:
    """A ring buffer of (s, a, r, c, s', done) for off-policy agents; `sample` can over-sample the
    transitions with a cost (recovery-rl's `pos_fraction` for its safety critic)."""

    def __init__(self, feat_dim: int, capacity: int = 50000):
        self.s = np.zeros((capacity, feat_dim), np.float32)
        self.s2 = np.zeros_like(self.s)
        self.a = np.zeros(capacity, np.int64)
        self.r = np.zeros(capacity, np.float32)
        self.c = np.zeros(capacity, np.float32)
        self.done = np.zeros(capacity, np.float32)
        self.capacity, self.n, self.i = capacity, 0, 0
        self.positives: list[int] = []  # indices of the transitions with a cost

    def add(self, s, a, r, c, s2, done) -> int:
        """Store one transition; returns its index."""
        i = self.i
        if self.n == self.capacity and self.c[i] > 0:  # overwriting a positive
            self.positives.remove(i)
        self.s[i], self.a[i], self.r[i], self.c[i], self.s2[i], self.done[i] = s, a, r, c, s2, done
        if c > 0:
            self.positives.append(i)
        self.i = (i + 1) % self.capacity
        self.n = min(self.n + 1, self.capacity)
        return i

    def sample(self, rng: np.random.Generator, batch: int, pos_fraction: float = 0.0, focus=()):
        """A batch drawn uniformly, except that `pos_fraction` of it comes from the transitions with a
        cost (while there are any) and the indices in `focus` are appended."""
        k = int(round(pos_fraction * batch)) if self.positives else 0
        idx = rng.integers(self.n, size=batch - k)
        if k:
            idx = np.concatenate([idx, np.asarray(self.positives)[rng.integers(len(self.positives), size=k)]])
        if len(focus):
            idx = np.concatenate([idx, np.asarray(focus, np.int64)])
        return tuple(torch.as_tensor(x[idx]) for x in (self.s, self.a, self.r, self.c, self.s2, self.done))


class DiscreteSAC(Agent):
    """Soft actor-critic for discrete actions (Christodoulou 2019): twin Q, expected soft values over
    the executed policy, a bounded automatic temperature toward a discrete target entropy (module doc)."""

    def __init__(self, *args, batch_size: int = 64, tau: float = 0.02, target_entropy_frac: float = 0.98,
                 entropy_share: float = 0.3, task_reward: float = 100.0, update_every: int = 1, actor_lr: float = 1e-3,
                 **kw):
        super().__init__(*args, **kw)
        f, A = self.feat_dim, self.n_actions
        self.actor = mlp(f, A, self.hidden)
        self.q, self.q_t = TwinQ(f, A, self.hidden), TwinQ(f, A, self.hidden)  # twin critics and their targets
        self.q_t.load_state_dict(self.q.state_dict())
        self.target_entropy = target_entropy_frac * np.log(A)
        # the whole discounted entropy bonus alpha log|A| / (1 - gamma) <= entropy_share * task reward
        self.alpha_max = entropy_share * task_reward * (1 - self.gamma) / np.log(A)
        self.log_alpha_bounds = (float(np.log(self.alpha_max / 10)), float(np.log(self.alpha_max)))
        self.log_alpha = torch.full((1,), self.log_alpha_bounds[1], requires_grad=True)  # explore fully at first
        # one optimiser, one backward pass per update: the critic, actor and temperature losses touch
        # disjoint parameters (the actor's loss sees the critics detached), so summing them is exact
        # one parameter group per learning rate: fused Adam's cost is per group (4 groups 236 us, 2 groups 123 us)
        self.opt = torch.optim.Adam([{"params": [*self.q.parameters(), self.log_alpha], "lr": self.lr},
                                     {"params": self.actor.parameters(), "lr": actor_lr}], fused=True)
        self.buffer = Replay(f)
        self.batch_size, self.tau, self.update_every = batch_size, tau, update_every
        self.targets, self.sources = list(self.q_t.parameters()), list(self.q.parameters())
        self.steps = 0

    def _logits(self, feat):
        return self.actor(feat)

    def _learn(self, s, a, r, c, s2, terminated, truncated):
        self.buffer.add(s, a, r, c, s2, float(terminated))
        self.steps += 1
        if self.buffer.n >= self.batch_size and self.steps % self.update_every == 0:
            self.update(*self.buffer.sample(self.rng, self.batch_size))

    def actor_extra_loss(self, s, probs) -> torch.Tensor:
        """Extra actor loss term (SQRL's safety penalty); none for plain SAC."""
        return torch.zeros(())

    def extra_loss(self) -> torch.Tensor:
        """Loss of extra networks trained alongside (the baselines' safety critic), summed into the one
        backward pass; their parameters join `self.opt` as another group."""
        return torch.zeros(())

    @torch.no_grad()
    def soft_value(self, s: torch.Tensor, logp: torch.Tensor | None = None) -> torch.Tensor:
        """V(s) = E_{a ~ executed policy}[min Q_target(s, a) - alpha log pi(a|s)]: with the TDM the
        expectation is over the filtered policy, so actions the filter removes weigh nothing. `logp`:
        the executed log-probabilities at `s` when already computed."""
        logp = self.policy_log_probs(s) if logp is None else logp.detach()
        q = self.q_t(s).min(0).values
        return (logp.exp() * (q - self.log_alpha.exp() * logp.clamp_min(-30))).sum(-1)

    def update(self, s, a, r, c, s2, done) -> None:
        alpha = self.log_alpha.exp().detach()
        # one actor pass (and one shield pass) over the states and next states together
        b = s.shape[0]
        both = torch.cat([s, s2])
        raw = F.log_softmax(self._logits(both), -1)
        executed = self.executed_log_probs(raw, both)
        logp = executed[:b]
        y = r + self.gamma * (1 - done) * self.soft_value(s2, executed[b:])
        idx = a[:, None]
        qs = self.q(s)  # (2, B, A)
        loss_q = 2 * F.mse_loss(qs.gather(2, idx.expand(2, -1, 1)).squeeze(2), y.expand(2, -1))  # sum of both critics' MSE
        p = logp.exp()
        q = qs.min(0).values.detach()
        loss_pi = ((p * (alpha * logp.clamp_min(-30) - q)).sum(-1).mean() + self.actor_extra_loss(s, p)
                   - alpha * self.raw_entropy(raw[:b]))
        entropy = -(p * logp.clamp_min(-30)).sum(-1).mean().detach()
        loss_alpha = self.log_alpha * (entropy - self.target_entropy)
        self.opt.zero_grad()
        (loss_q + loss_pi + loss_alpha.sum() + self.extra_loss()).backward()
        self.opt.step()
        with torch.no_grad():
            self.log_alpha.clamp_(*self.log_alpha_bounds)
            torch._foreach_lerp_(self.targets, self.sources, self.tau)

    def stats(self) -> dict:
        return {**super().stats(), "alpha": float(self.log_alpha.detach().exp()), "alpha_max": float(self.alpha_max)}


class ActorCritic(Agent):
    """Advantage actor-critic with batched updates: every `n_steps` transitions (and at episode ends)
    one actor and one critic step on GAE(lambda) advantages bootstrapped from V, plus an entropy bonus.
    With the TDM filter the log-probabilities are those of the filtered (executed) policy, so the
    gradient stays on-policy."""

    def __init__(self, *args, entropy_coef: float = 0.02, n_steps: int = 16, lam: float = 0.9,
                 value_scale: float = 100.0, **kw):
        super().__init__(*args, **kw)
        self.actor = mlp(self.feat_dim, self.n_actions, self.hidden)
        self.critic = mlp(self.feat_dim, 1, self.hidden)
        self.opt = torch.optim.Adam([*self.actor.parameters(), *self.critic.parameters()], lr=self.lr, fused=True)
        self.entropy_coef, self.n_steps, self.lam, self.value_scale = entropy_coef, n_steps, lam, value_scale
        self.batch = []

    def _logits(self, feat):
        return self.actor(feat)

    def _v(self, s: torch.Tensor) -> torch.Tensor:
        return self.critic(s).squeeze(-1) * self.value_scale  # the net works in units of the task reward

    def _learn(self, s, a, r, c, s2, terminated, truncated):
        self.batch.append((s, a, r, s2, terminated, terminated or truncated))
        if len(self.batch) >= self.n_steps or terminated or truncated:
            self.update()

    def update(self) -> None:
        if not self.batch:
            return
        s = torch.as_tensor(np.stack([b[0] for b in self.batch]))
        a = torch.as_tensor([b[1] for b in self.batch])
        r = np.array([b[2] for b in self.batch], np.float32)
        s2 = torch.as_tensor(np.stack([b[3] for b in self.batch]))
        term = np.array([b[4] for b in self.batch], np.float32)
        end = np.array([b[5] for b in self.batch], bool)
        end[-1] = True  # the batch's last transition closes its GAE sum (bootstrapped unless terminal)
        with torch.no_grad():
            v, v2 = self._v(s).numpy(), self._v(s2).numpy()
        delta = r + self.gamma * (1 - term) * v2 - v
        adv = np.zeros_like(delta)
        acc = 0.0
        for t in range(len(delta) - 1, -1, -1):
            acc = delta[t] + (0.0 if end[t] else self.gamma * self.lam * acc)
            adv[t] = acc
        adv_t = torch.as_tensor(adv)
        ret = torch.as_tensor(adv + v)
        raw = F.log_softmax(self._logits(s), -1)
        logp = self.executed_log_probs(raw, s)
        entropy = -(logp.exp() * logp.clamp_min(-30)).sum(-1).mean() + self.raw_entropy(raw)
        loss = (-(adv_t / self.value_scale * logp.gather(1, a[:, None]).squeeze(1)).mean() - self.entropy_coef * entropy
                + 0.5 * F.mse_loss(self._v(s) / self.value_scale, ret / self.value_scale))
        self.opt.zero_grad()
        loss.backward()
        self.opt.step()
        self.batch = []
