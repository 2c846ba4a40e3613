"""Safe-RL baselines for the maze, written for discrete actions after the reference update rules:
Recovery RL and SQRL after the recovery-rl code base (Thananjeyan et al. 2021, a safety critic
Q_risk trained by `c + (1 - c) gamma_safe E_pi Q_risk'`), CPO after OmniSafe's CPO (trust region on
the KL of a categorical policy, conjugate gradients, the dual for (lambda, nu), infeasible-case
recovery step and a backtracking line search).

As their reference specifies (recovery-rl's scripts/maze.sh and arg_utils.py; issue 31):

- an offline phase before online training (recovery-rl runs it for Recovery RL and for its SQRL, both
  with a safety critic): `offline_transitions` transitions of random 20-step rollouts from random
  placements (recovery-rl's `transition_function`; 10,000 there, 20% of its 500 x 100-step budget, here
  `offline_transitions` = 4,000, 25% of the maze's 80 x 200), Q_risk pre-trained on them for `pretrain_steps` (10,000
  there, 2,000 here: 32 passes over the data) and kept in its replay. The offline contacts are reported
  apart from the online ones (`offline_contacts`), as recovery-rl counts them apart;
- the safety critic's batches hold `pos_fraction` = 30% transitions with a contact;
- the risk threshold eps = 0.15 and gamma_safe = 0.5 of recovery-rl's maze;
- SQRL's multiplier nu from 100, updated like the reference's dual: log nu by Adam at a tenth of the
  learning rate on `log nu (eps - E_pi Q_risk)`.

The tuning protocol (`core.experiments.maze.SPACES`, `tune`) searches around these (these first), with as
many trials as every other method gets; the offline phase is a switch of that search. Departures: Q_risk is a network over the maze features with target rate
tau = 0.05 (recovery-rl: 0.0002), recovery is argmin_a Q_risk (exact for 4 actions), the policies are
categorical.

The -TDM agents' extras can be given to RRL and SQRL (the ablation of issue 31): `floor` (the uniform
share mixed into the task policy before rejection or recovery), `shrink` (visit-count shrinkage of
Q_risk: an untried action's risk is at most eps, so it is never rejected or overridden before it is
tried, `agents.VisitCounts`) and `contact_steps` (after a contact, that many extra safety-critic steps
with the contact in every batch).

Why RRL and SQRL rarely reached the goal before the offline phase (issue 16, seed 1, 30 episodes of 200
macro-actions): Q_risk is learned only from executed actions, and a move it rates above eps is never
executed again, so its over-estimate is never corrected (SQRL: 38 of 210 bump-free (cell, heading,
action) pairs rejected, none of them ever tried, 34 rated above gamma_safe = 0.5, a value no bump-free
move can have at the Bellman fixed point). With a sparse +100 and no per-step reward, the task policy
then settles on proposals that never run: RRL's recovery overrode 48% of the steps and from episode 4 on
the robot turned back and forth in 1-3 cells.
"""
from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from skinsafe.core.learn.agents import ActorCritic, Agent, DiscreteSAC, Replay, VisitCounts, mlp


class SafetyCritic:
    """Q_risk(s, a): discounted probability of a future constraint violation (recovery-rl's safety critic).
    Online its loss joins the agent's one backward pass (`DiscreteSAC.extra_loss`), `soft_update` follows;
    its own steps (`step`: offline pre-training, contact refits) use its own Adam."""

    def __init__(self, feat_dim: int, n_actions: int, hidden, gamma_safe: float = 0.5, tau: float = 0.05,
                 lr: float = 3e-3):
        self.q = mlp(feat_dim, n_actions, hidden)
        torch.nn.init.constant_(self.q[-1].bias, -3.0)  # start optimistic (risk ~5%), like the TDM's prior
        self.q_t = mlp(feat_dim, n_actions, hidden)
        self.q_t.load_state_dict(self.q.state_dict())
        self.gamma_safe, self.tau = gamma_safe, tau
        self.targets, self.sources = list(self.q_t.parameters()), list(self.q.parameters())
        self.opt = torch.optim.Adam(self.q.parameters(), lr=lr)

    def __call__(self, s: torch.Tensor) -> torch.Tensor:
        return torch.sigmoid(self.q(s))

    def loss(self, s, a, c, s2, done, next_probs: torch.Tensor) -> torch.Tensor:
        with torch.no_grad():
            q2 = (next_probs * torch.sigmoid(self.q_t(s2))).sum(-1)
            y = c + (1 - c) * (1 - done) * self.gamma_safe * q2
        return F.binary_cross_entropy(self(s).gather(1, a[:, None]).squeeze(1), y.clamp(0, 1))

    def step(self, s, a, c, s2, done, next_probs: torch.Tensor) -> None:
        """One gradient step of its own on a batch, then the target update."""
        loss = self.loss(s, a, c, s2, done, next_probs)
        self.opt.zero_grad()
        loss.backward()
        self.opt.step()
        self.soft_update()

    @torch.no_grad()
    def soft_update(self) -> None:
        torch._foreach_lerp_(self.targets, self.sources, self.tau)


class _RiskSAC(DiscreteSAC):
    """SAC with a safety critic on its own replay of executed transitions (`risk_replay`), batches with
    `pos_fraction` contacts, an offline phase (`pretrain`) and the optional -TDM extras (module doc)."""

    def __init__(self, *args, eps_risk: float = 0.15, gamma_safe: float = 0.5, pos_fraction: float = 0.3,
                 offline_transitions: int = 4000, pretrain_steps: int = 2000, floor: float = 0.0,
                 shrink: bool = False, contact_steps: int = 0, **kw):
        super().__init__(*args, **kw)
        self.risk = SafetyCritic(self.feat_dim, self.n_actions, self.hidden, gamma_safe, lr=self.lr)
        self.opt.param_groups[0]["params"] += list(self.risk.q.parameters())  # same lr: the same fused group
        self.eps_risk, self.pos_fraction = float(eps_risk), float(pos_fraction)
        self.offline_transitions, self.pretrain_steps = int(offline_transitions), int(pretrain_steps)
        self.floor, self.contact_steps = float(floor), int(contact_steps)
        self.counts = VisitCounts(self.feat_dim, self.n_actions) if shrink else None
        self.risk_replay = Replay(self.feat_dim)
        self._proposed = 0
        self._risk_batch = None

    def _risk_sample(self, focus=()):
        s, a, _, c, s2, d = self.risk_replay.sample(self.rng, self.batch_size, self.pos_fraction, focus)
        return s, a, c, s2, d

    def _next_probs(self, s2: torch.Tensor) -> torch.Tensor:
        with torch.no_grad():
            return torch.softmax(self.actor(s2), -1)

    def pretrain(self, obs, actions, costs, next_obs, terminated, dangers=None) -> None:
        """The offline phase: store the transitions in the risk replay and fit Q_risk on them (Q_risk learns
        from the contact events `costs`; the per-taxel `dangers` are a -TDM agent's, `Agent.pretrain`)."""
        for o, a, c, o2, t in zip(obs, actions, costs, next_obs, terminated):
            s = self.features(o)[0]
            self.risk_replay.add(s, int(a), 0.0, float(c), self.features(o2)[0], float(t))
            if self.counts is not None:
                self.counts.add(s, int(a))
        for _ in range(self.pretrain_steps if self.risk_replay.n else 0):
            b = self._risk_sample()
            self.risk.step(*b, self._next_probs(b[3]))

    def update(self, s, a, r, c, s2, done) -> None:
        self._risk_batch = self._risk_sample()
        super().update(s, a, r, c, s2, done)
        self.risk.soft_update()

    def extra_loss(self) -> torch.Tensor:
        s, a, c, s2, done = self._risk_batch
        return self.risk.loss(s, a, c, s2, done, self._next_probs(s2))

    @torch.no_grad()
    def q_risk(self, feat: np.ndarray) -> np.ndarray:
        """Q_risk of every action at one state; with `shrink`, an action with no experience nearby has at
        most eps (w Q + (1 - w) min(Q, eps), w = n / (n + 0.01), as the -TDM shield)."""
        f = torch.as_tensor(feat)
        q = self.risk(f).double()  # in double, so that a capped risk compares equal to eps
        if self.counts is not None:
            n = self.counts(f).double()
            w = n / (n + 0.01)
            q = w * q + (1 - w) * q.clamp_max(self.eps_risk)
        return q.numpy()[0]

    def task_probs(self, feat: np.ndarray) -> np.ndarray:
        """The task policy at one state, mixed with `floor` of the uniform one."""
        p = self.action_probs(feat)[0]
        return (1 - self.floor) * p + self.floor / self.n_actions if self.floor > 0 else p

    def observe(self, obs, action, reward, cost, danger, next_obs, terminated, truncated) -> None:
        s, s2 = self.features(obs)[0], self.features(next_obs)[0]
        # Task transition with the proposed action, risk transition with the executed one.
        self.buffer.add(s, self._proposed, reward, cost, s2, float(terminated))
        i = self.risk_replay.add(s, action, 0.0, cost, s2, float(terminated))
        if self.counts is not None:
            self.counts.add(s, action)
        if cost > 0 and self.contact_steps > 0:  # the -TDM's contact refit, given to the safety critic
            for _ in range(self.contact_steps):
                b = self._risk_sample(focus=[i])
                self.risk.step(*b, self._next_probs(b[3]))
        self.steps += 1
        if self.buffer.n >= self.batch_size and self.steps % self.update_every == 0:
            self.update(*self.buffer.sample(self.rng, self.batch_size))

    def stats(self) -> dict:
        return {**super().stats(), "eps_risk": self.eps_risk}


class RecoveryRL(_RiskSAC):
    """Recovery RL (model-free recovery): the task policy proposes a ~ pi(s); if Q_risk(s, a) > eps the
    recovery policy (here argmin_a Q_risk, exact for discrete actions) acts instead. The task policy
    learns from its proposed action (recovery is part of its environment); Q_risk from the executed one."""

    def act(self, obs) -> int:
        feat = self.features(obs)
        p = self.task_probs(feat)
        proposed = int(self.rng.choice(self.n_actions, p=p / p.sum()))
        risk = self.q_risk(feat)
        self._proposed = proposed
        return int(np.argmin(risk)) if risk[proposed] > self.eps_risk else proposed


class SQRL(_RiskSAC):
    """SQRL: actions whose Q_risk exceeds eps are rejected from the policy's distribution (the least
    risky one is taken if none is left), and the actor pays nu (E_pi[Q_risk] - eps) with the multiplier
    nu = exp(log nu) updated by the reference's dual step: Adam on `log nu (eps - E_pi[Q_risk])` at
    `nu_lr` (default a tenth of the learning rate, as recovery-rl), from `nu` = 100 (its maze setting)."""

    def __init__(self, *args, nu: float = 100.0, nu_lr: float | None = None, **kw):
        super().__init__(*args, **kw)
        self.log_nu = float(np.log(nu))
        self.nu_lr = 0.1 * self.lr if nu_lr is None else float(nu_lr)
        self._nu_adam = [0.0, 0.0, 0]  # Adam's moments and step count for the one scalar log nu

    @property
    def nu(self) -> float:
        return float(np.exp(self.log_nu))

    def _dual_step(self, grad: float, b1: float = 0.9, b2: float = 0.999, eps: float = 1e-8) -> None:
        """One Adam step on log nu (torch.optim.Adam's update in floats: ~1 us instead of ~80 us per step)."""
        m, v, t = self._nu_adam
        t += 1
        m, v = b1 * m + (1 - b1) * grad, b2 * v + (1 - b2) * grad * grad
        self.log_nu -= self.nu_lr * (m / (1 - b1 ** t)) / (np.sqrt(v / (1 - b2 ** t)) + eps)
        self._nu_adam = [m, v, t]

    def act(self, obs) -> int:
        feat = self.features(obs)
        p = self.task_probs(feat)
        risk = self.q_risk(feat)
        safe = risk <= self.eps_risk
        if not safe.any():
            action = int(np.argmin(risk))
        else:
            p = np.where(safe, p, 0.0)
            if p.sum() <= 0:
                p = safe.astype(float)
            action = int(self.rng.choice(self.n_actions, p=p / p.sum()))
        self._proposed = action  # the task policy learns the action that ran
        return action

    def actor_extra_loss(self, s, probs) -> torch.Tensor:
        with torch.no_grad():
            risk = self.risk(s)
        expected = (probs * risk).sum(-1).mean()
        nu = self.nu
        self._dual_step(self.eps_risk - float(expected.detach()))  # d/d log nu of log nu (eps - E_pi Q_risk)
        return nu * (expected - self.eps_risk)

    def stats(self) -> dict:
        return {**super().stats(), "nu": self.nu}


class CPO(Agent):
    """Constrained policy optimisation with a categorical policy (OmniSafe's update rule).

    Every `episodes_per_update` episodes: GAE advantages for reward and cost, the reward and cost
    surrogate gradients g, b, x = H^-1 g and p = H^-1 b by conjugate gradients on the KL Hessian, the
    CPO dual (cases 0-4) for (lambda, nu), step (x - nu p) / lambda (or the pure cost-decreasing step
    when infeasible), and a backtracking line search on KL, reward and cost.
    """

    def __init__(self, *args, cost_limit: float = 5.0, target_kl: float = 0.02, episodes_per_update: int = 2,
                 lam: float = 0.95, cg_iters: int = 10, **kw):
        super().__init__(*args, **kw)
        self.actor = mlp(self.feat_dim, self.n_actions, self.hidden)
        self.v_r, self.v_c = mlp(self.feat_dim, 1, self.hidden), mlp(self.feat_dim, 1, self.hidden)
        self.opt_v = torch.optim.Adam([*self.v_r.parameters(), *self.v_c.parameters()], lr=self.lr)
        self.cost_limit, self.target_kl, self.lam, self.cg_iters = cost_limit, target_kl, lam, cg_iters
        self.episodes_per_update = episodes_per_update
        self.batch, self.current, self.last_case = [], [], None

    def _logits(self, feat):
        return self.actor(feat)

    def _learn(self, s, a, r, c, s2, terminated, truncated):
        self.current.append((s, a, r, c, s2, terminated))

    def end_episode(self) -> None:
        if self.current:
            self.batch.append(self.current)
        self.current = []
        if len(self.batch) >= self.episodes_per_update:
            self.update(self.batch)
            self.batch = []

    def _gae(self, ep, vnet, col) -> tuple[np.ndarray, np.ndarray]:
        s = torch.as_tensor(np.stack([e[0] for e in ep]))
        with torch.no_grad():
            v = vnet(s).squeeze(1).numpy()
            last = ep[-1]
            v_end = 0.0 if last[5] else float(vnet(torch.as_tensor(last[4][None]))[0, 0])
        x = np.array([e[col] for e in ep], np.float32)
        v_next = np.append(v[1:], v_end)
        delta = x + self.gamma * v_next - v
        adv = np.zeros_like(delta)
        acc = 0.0
        for t in range(len(ep) - 1, -1, -1):
            acc = delta[t] + self.gamma * self.lam * acc
            adv[t] = acc
        return adv, adv + v

    def _flat_grad(self, y, create_graph=False, retain_graph=None) -> torch.Tensor:
        g = torch.autograd.grad(y, list(self.actor.parameters()), create_graph=create_graph, retain_graph=retain_graph)
        return torch.cat([t.reshape(-1) for t in g])

    def _set_flat(self, flat) -> None:
        i = 0
        for w in self.actor.parameters():
            n = w.numel()
            w.data.copy_(flat[i:i + n].view_as(w))
            i += n

    def _cg(self, hvp, b) -> torch.Tensor:
        x = torch.zeros_like(b)
        r, p = b.clone(), b.clone()
        rr = r @ r
        for _ in range(self.cg_iters):
            hp = hvp(p)
            alpha = rr / (p @ hp + 1e-10)
            x += alpha * p
            r -= alpha * hp
            rr_new = r @ r
            if rr_new < 1e-10:
                break
            p = r + (rr_new / rr) * p
            rr = rr_new
        return x

    def update(self, episodes) -> None:
        s = torch.as_tensor(np.concatenate([np.stack([e[0] for e in ep]) for ep in episodes]))
        a = torch.as_tensor(np.concatenate([[e[1] for e in ep] for ep in episodes]))
        adv_r, ret_r, adv_c, ret_c = [], [], [], []
        for ep in episodes:
            x, y = self._gae(ep, self.v_r, 2)
            adv_r.append(x), ret_r.append(y)
            x, y = self._gae(ep, self.v_c, 3)
            adv_c.append(x), ret_c.append(y)
        adv_r = torch.as_tensor(np.concatenate(adv_r))
        adv_c = torch.as_tensor(np.concatenate(adv_c))
        adv_r = (adv_r - adv_r.mean()) / (adv_r.std() + 1e-8) if len(adv_r) > 1 else adv_r
        adv_c = adv_c - adv_c.mean()
        ep_cost = float(np.mean([sum(e[3] for e in ep) for ep in episodes]))
        c = ep_cost - self.cost_limit

        with torch.no_grad():
            logp_old = F.log_softmax(self.actor(s), -1)
            old_params = torch.cat([w.reshape(-1) for w in self.actor.parameters()])
        logp_a_old = logp_old.gather(1, a[:, None]).squeeze(1)

        def surrogates():
            logp = F.log_softmax(self.actor(s), -1)
            ratio = torch.exp(logp.gather(1, a[:, None]).squeeze(1) - logp_a_old)
            return (ratio * adv_r).mean(), (ratio * adv_c).mean(), logp

        def kl_of(logp):
            return (logp_old.exp() * (logp_old - logp)).sum(-1).mean()

        loss_r, loss_c, _ = surrogates()
        g = self._flat_grad(loss_r, retain_graph=True)
        b = self._flat_grad(loss_c)

        def hvp(v):
            kl = kl_of(F.log_softmax(self.actor(s), -1))
            grad_kl = self._flat_grad(kl, create_graph=True)
            return self._flat_grad(grad_kl @ v) + 0.1 * v

        x = self._cg(hvp, g)
        q = float(g @ x)
        delta = self.target_kl
        if float(b @ b) <= 1e-8 and c < 0:  # no cost gradient and feasible: plain TRPO
            p_dir, r_, s_, case = torch.zeros_like(g), 0.0, 0.0, 4
        else:
            p_dir = self._cg(hvp, b)
            r_, s_ = float(g @ p_dir), float(b @ p_dir)
            A, B = q - r_ ** 2 / (s_ + 1e-8), 2 * delta - c ** 2 / (s_ + 1e-8)
            case = 3 if (c < 0 and B < 0) else 2 if (c < 0 and B >= 0) else 1 if (c >= 0 and B >= 0) else 0
        if case in (3, 4):
            lam, nu = np.sqrt(max(q, 1e-12) / (2 * delta)), 0.0
        elif case in (1, 2):
            A, B = q - r_ ** 2 / (s_ + 1e-8), 2 * delta - c ** 2 / (s_ + 1e-8)
            lam_a, lam_b = np.sqrt(max(A, 1e-12) / max(B, 1e-12)), np.sqrt(max(q, 1e-12) / (2 * delta))
            rc = r_ / c if c != 0 else np.inf
            (lo_a, hi_a), (lo_b, hi_b) = ((0, rc), (rc, np.inf)) if c < 0 else ((rc, np.inf), (0, rc))
            lam_a, lam_b = np.clip(lam_a, max(lo_a, 0), max(hi_a, 0)), np.clip(lam_b, max(lo_b, 0), max(hi_b, 0))
            f_a = -0.5 * (A / (lam_a + 1e-8) + B * lam_a) - r_ * c / (s_ + 1e-8)
            f_b = -0.5 * (q / (lam_b + 1e-8) + 2 * delta * lam_b)
            lam = lam_a if f_a >= f_b else lam_b
            nu = max(0.0, lam * c - r_) / (s_ + 1e-8)
        if case == 0:  # infeasible: step purely to decrease the cost
            step = -np.sqrt(2 * delta / (s_ + 1e-8)) * p_dir
        else:
            step = (x - nu * p_dir) / (lam + 1e-8)
        self.last_case = case
        with torch.no_grad():
            base_r, base_c = float(loss_r), float(loss_c)
            for frac in 0.8 ** np.arange(15):
                self._set_flat(old_params + frac * step)
                new_r, new_c, logp = surrogates()
                kl = float(kl_of(logp))
                ok_r = case == 0 or float(new_r) >= base_r - 1e-8
                ok_c = (float(new_c) <= base_c) if case == 0 else (float(new_c) - base_c <= max(-c, 0.0) + 1e-8)
                if np.isfinite(kl) and kl <= delta and ok_r and ok_c:
                    break
            else:
                self._set_flat(old_params)
        ret_r = torch.as_tensor(np.concatenate(ret_r))
        ret_c = torch.as_tensor(np.concatenate(ret_c))
        for _ in range(20):
            loss_v = F.mse_loss(self.v_r(s).squeeze(1), ret_r) + F.mse_loss(self.v_c(s).squeeze(1), ret_c)
            self.opt_v.zero_grad()
            loss_v.backward()
            self.opt_v.step()


AGENTS = {
    "SAC": (DiscreteSAC, {}), "SAC-RP": (DiscreteSAC, {"cost_penalty": 1.0}), "SAC-TDM": (DiscreteSAC, {"use_tdm": True}),
    "AC": (ActorCritic, {}), "AC-RP": (ActorCritic, {"cost_penalty": 1.0}), "AC-TDM": (ActorCritic, {"use_tdm": True}),
    "RRL": (RecoveryRL, {}), "CPO": (CPO, {}), "SQRL": (SQRL, {}),
}
"""The agents of the paper's Fig. 9 by name: class and keyword arguments."""


def make_agent(name: str, obs_dim: int, n_actions: int, n_taxels: int, features=None, seed: int = 0,
               rp_penalty: float = 1.0, **overrides) -> Agent:
    """An agent by its name in the paper's Fig. 9 (SAC, SAC-RP, SAC-TDM, AC, AC-RP, AC-TDM, RRL, CPO, SQRL);
    `overrides` replace the class's keyword arguments (e.g. `refit_every`, `fit` for the -TDM agents)."""
    if name not in AGENTS:
        raise ValueError(f"unknown agent '{name}'; choose from {', '.join(AGENTS)}")
    cls, kw = AGENTS[name]
    if "cost_penalty" in kw:
        kw = dict(kw, cost_penalty=rp_penalty)
    return cls(obs_dim, n_actions, n_taxels, features=features, seed=seed, **{**kw, **overrides})
