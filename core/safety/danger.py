"""Total danger (eq. 1), marginal danger (eq. 2) and the danger-aware policy (eq. 3), paper III-A.

Everything runs in log space: with thousands of taxels `prod(1 - p_i)` underflows, while
`log p(not D | s, a) = sum_i logsigmoid(-logit_i)` stays exact, and `p(D) = -expm1(log p(not D))`
keeps precision when the danger is tiny.

Eq. 3 is Bayes' rule, `p(a | not D, s) = p(not D | s, a) p(a | s) / p(not D | s)`, whose normaliser
is `p(not D | s) = E_{a ~ p(a|s)} [p(not D | s, a)]`: exact for discrete actions (a sum), by
sampling for continuous ones (sampling-importance-resampling). Eq. 2 with the paper's uniform
target `U(a|s)` (the action-agnostic marginal) is `marginal_danger`, an importance-sampling estimate
whose weights `U/p` are clipped and whose variance and effective sample size are reported.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy.special import logsumexp


def log_total_safety(logits):
    """log p(not D | s, a) = sum_i log(1 - sigmoid(logit_i)) over the last axis (torch or numpy)."""
    if isinstance(logits, torch.Tensor):
        return torch.nn.functional.logsigmoid(-logits).sum(dim=-1)
    x = np.asarray(logits, dtype=float)
    return -np.logaddexp(0.0, x).sum(axis=-1)


def total_danger(logits):
    """Eq. 1: p(D | s, a) = 1 - prod_i (1 - p(d_i | s, a)), exact via -expm1 of the log safety."""
    ls = log_total_safety(logits)
    return -torch.expm1(ls) if isinstance(ls, torch.Tensor) else -np.expm1(ls)


def log_total_safety_probs(p) -> np.ndarray:
    """log p(not D) = sum_i log1p(-p_i) from per-taxel probabilities (last axis)."""
    p = np.asarray(p, dtype=float)
    if ((p < 0) | (p > 1) | ~np.isfinite(p)).any():
        raise ValueError("log_total_safety_probs: probabilities must lie in [0, 1]; pass logits to log_total_safety instead")
    with np.errstate(divide="ignore"):
        return np.log1p(-p).sum(axis=-1)


def total_danger_probs(p) -> np.ndarray:
    """Eq. 1 from per-taxel probabilities (last axis)."""
    return -np.expm1(log_total_safety_probs(p))


MIN_ESS = 50.0
"""Eq. 2's estimate counts as reliable only with an effective sample size of at least this and
at most 5% of the untruncated estimate removed by the weight truncation: otherwise the
truncation at sqrt(K) and the few large weights bias it (`skinsafe bench safety --eq2`)."""


@dataclass
class MarginalEstimate:
    """Importance-sampling estimate of eq. 2 and the health of its weights."""

    value: float  # estimate of p(D | s)
    weight_mean: float  # mean importance weight U/p after clipping (1 for a well-matched proposal)
    weight_var: float  # variance of the clipped weights
    ess: float  # effective sample size (sum w)^2 / sum w^2, in [1, n]
    n: int
    clipped: int  # how many weights hit max_weight
    truncated: float = 0.0  # fraction of the untruncated estimate that the clipping removed

    @property
    def reliable(self) -> bool:
        """ESS >= MIN_ESS and the truncation removed at most 5% of the estimate (see MIN_ESS)."""
        return self.ess >= MIN_ESS and self.truncated <= 0.05


def marginal_danger(danger, log_p, log_u=None, max_weight: float | None = None) -> MarginalEstimate:
    """Eq. 2: p(D|s) = E_{a~p(a|s)}[p(D|s,a) U(a|s) / p(a|s)] from K samples a_k ~ p(a|s).

    danger: (K,) p(D|s,a_k); log_p: (K,) log p(a_k|s); log_u: (K,) log U(a_k|s) of the target
    (defaults to the proposal itself, weights 1). Weights are formed in log space and clipped at
    `max_weight` (default sqrt(K), truncated importance sampling, as E_p[U/p] = 1), so an action
    with p(a|s) -> 0 cannot make the estimate infinite; the clipping is counted.
    """
    danger = np.asarray(danger, dtype=float).ravel()
    log_p = np.asarray(log_p, dtype=float).ravel()
    k = danger.size
    if k == 0 or log_p.size != k:
        raise ValueError(f"marginal_danger: got {k} danger values and {log_p.size} log-probabilities; give one per sample (K >= 1)")
    if ((danger < 0) | (danger > 1) | ~np.isfinite(danger)).any():
        raise ValueError("marginal_danger: danger values must be probabilities in [0, 1]")
    log_u = log_p if log_u is None else np.asarray(log_u, dtype=float).ravel()
    if log_u.size != k:
        raise ValueError(f"marginal_danger: log_u has {log_u.size} values for {k} samples")
    with np.errstate(invalid="ignore"):
        log_w = np.where(np.isneginf(log_u), -np.inf, log_u - log_p)  # U = 0 -> weight 0 even where p = 0
    if max_weight is None:
        max_weight = np.sqrt(k)  # E_p[U/p] = 1 for a normalised U: truncate at sqrt(K) times the mean
    w = np.exp(np.minimum(log_w, np.log(max_weight)))
    raw = float(np.mean(danger * np.exp(np.minimum(log_w, 700.0))))
    clipped = int((log_w > np.log(max_weight)).sum())
    s1, s2 = w.sum(), (w * w).sum()
    ess = float(s1 * s1 / s2) if s2 > 0 else 0.0
    return MarginalEstimate(value=float(np.clip(np.mean(danger * w), 0.0, 1.0)), weight_mean=float(w.mean()),
                            weight_var=float(w.var()), ess=ess, n=k, clipped=clipped,
                            truncated=float(1 - np.mean(danger * w) / raw) if raw > 0 else 0.0)


def marginal_danger_discrete(danger, target=None) -> np.ndarray:
    """Eq. 2 exactly for discrete actions: sum_a U(a|s) p(D|s,a) over the last axis (U uniform by default)."""
    danger = np.asarray(danger, dtype=float)
    if target is None:
        return danger.mean(axis=-1)
    return (danger * np.asarray(target, dtype=float)).sum(axis=-1)


def filter_log_probs(log_probs, log_safety):
    """Eq. 3 for discrete actions, exact, in log space (last axis = actions; torch or numpy).

    Returns log p(a | not D, s) = log p(not D|s,a) + log p(a|s) - log p(not D|s). When every action is
    dangerous the normaliser is tiny but still exact in log space (the least dangerous actions win);
    only where it is exactly zero (every action certainly dangerous) the original policy is kept.
    """
    if isinstance(log_probs, torch.Tensor):
        joint = log_probs + log_safety
        z = torch.logsumexp(joint, dim=-1, keepdim=True)
        ok = torch.isfinite(z)
        return torch.where(ok, joint - torch.where(ok, z, torch.zeros_like(z)), log_probs)
    log_probs = np.asarray(log_probs, dtype=float)
    joint = log_probs + np.asarray(log_safety, dtype=float)
    z = logsumexp(joint, axis=-1, keepdims=True)
    ok = np.isfinite(z)
    with np.errstate(invalid="ignore"):
        return np.where(ok, joint - np.where(ok, z, 0.0), log_probs)


def filter_probs(probs, log_safety) -> np.ndarray:
    """Eq. 3 for discrete actions from probabilities p(a|s) (last axis); a distribution on every row."""
    probs = np.asarray(probs, dtype=float)
    if (probs < 0).any() or not np.isfinite(probs).all():
        raise ValueError("filter_probs: p(a|s) must be finite and non-negative")
    with np.errstate(divide="ignore"):
        out = np.exp(filter_log_probs(np.log(probs), log_safety))
    return out / out.sum(axis=-1, keepdims=True)


def filter_samples(log_safety, rng: np.random.Generator) -> tuple[int, float]:
    """Eq. 3 for continuous actions by sampling-importance-resampling.

    Given log p(not D|s,a_k) of K actions a_k ~ p(a|s), pick index k with probability proportional
    to p(not D|s,a_k) (a draw from p(a|not D,s) as K grows) and return (k, log p(not D|s) estimate).
    If every candidate is certainly dangerous, the index is uniform (the policy is kept).
    """
    ls = np.asarray(log_safety, dtype=float).ravel()
    if ls.size == 0:
        raise ValueError("filter_samples: need at least one candidate action")
    z = logsumexp(ls)
    if not np.isfinite(z):
        return int(rng.integers(ls.size)), float(z)
    w = np.exp(ls - z)
    return int(rng.choice(ls.size, p=w / w.sum())), float(z - np.log(ls.size))


def action_log_safety(model, states: torch.Tensor, n_actions: int) -> torch.Tensor:
    """(B, A) log p(not D | s, a) of every discrete action under a danger model (logits of (s, one-hot a))."""
    b = states.shape[0]
    s = states.repeat_interleave(n_actions, dim=0)
    a = torch.eye(n_actions, dtype=states.dtype).repeat(b, 1)
    return log_total_safety(model(s, a)).reshape(b, n_actions)


class PolicyFilter:
    """Wraps any discrete policy exposing `action_probs(states) -> (B, A)` p(a|s) and returns p(a|not D, s).

    The danger model maps (states (B,S), one-hot actions (B,A)) tensors to per-taxel logits (B,N), for
    example a `TactileDangerModel`. The filter is itself such a policy, so filters compose.
    """

    def __init__(self, policy, danger_model, n_actions: int):
        if not hasattr(policy, "action_probs"):
            raise TypeError(f"PolicyFilter: {type(policy).__name__} has no action_probs(states) method; "
                            "expose p(a|s) as action_probs(states) -> (B, n_actions)")
        self.policy, self.model, self.n_actions = policy, danger_model, int(n_actions)

    @torch.no_grad()
    def log_safety(self, states) -> np.ndarray:
        s = torch.as_tensor(np.atleast_2d(np.asarray(states, dtype=np.float32)))
        return action_log_safety(self.model, s, self.n_actions).double().numpy()

    def action_probs(self, states) -> np.ndarray:
        probs = np.atleast_2d(np.asarray(self.policy.action_probs(states), dtype=float))
        if probs.shape[-1] != self.n_actions:
            raise ValueError(f"PolicyFilter: policy returned {probs.shape[-1]} action probabilities, expected {self.n_actions}")
        return filter_probs(probs, self.log_safety(states))

    def act(self, state, rng: np.random.Generator) -> int:
        p = self.action_probs(np.asarray(state)[None])[0]
        return int(rng.choice(self.n_actions, p=p))
