"""Tactile danger potentials for the modulation layer (paper eq. 4, 5 and 8).

- `DangerPotential`: f_phi(s, a) = p(D | s, a), the total danger (eq. 1, in log space) of a
  tactile danger model's per-taxel logits; differentiable in s.
- `potential_and_normal`: f and n = df/ds (eq. 5) for a batch, by autograd.
- The n-step potential w_phi (eq. 8): Monte Carlo rollouts through the learned potential with a
  configurable policy pi' (uniform by default), horizon T and discount gamma
  (`nstep_targets`), distilled into a small network (`NStepPotential`, `distill_nstep`) that is
  used in place of f. w (a discounted sum, up to sum_t gamma^t) is clipped at 1: the
  modulation eigenvalue 1 - w must stay in [0, 1], and "danger within the horizon for sure" is
  all the modulation needs (dividing by sum_t gamma^t instead would cap the foresight at
  1 / sum_t gamma^t of a certain danger one step ahead). D_t is replaced by its expectation
  f(s_t, a_t) (same mean as sampling D_t, less variance); rollouts do not stop at a danger event.

`FastPotential`'s compiled kernels are in `potential_kernels.py`.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable

import numba
import numpy as np
import torch
from numba import typed
from scipy.special import expit
from torch import nn

from skinsafe.core.safety.danger import total_danger
from skinsafe.core.safety.potential_kernels import (
    _FAST,
    FUSED_ROWS,
    _find_row,
    _mlp_backward,
    _mlp_forward,
    _tdm_backward,
    _tdm_forward,
    _tdm_fused,
    columns,
)

Potential = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]
"""(s (B, d), a (B, m)) -> (B,) potential in [0, 1], differentiable in s."""


class DangerPotential(nn.Module):
    """f_phi(s, a): the total danger of a TDM's per-taxel logits `tdm(s, a) -> (B, N)` (eq. 4)."""

    def __init__(self, tdm: nn.Module):
        super().__init__()
        self.tdm = tdm

    def forward(self, s: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
        return total_danger(self.tdm(s, a))


def _as_tensor(x, dtype) -> torch.Tensor:
    x = torch.as_tensor(np.asarray(x), dtype=dtype)
    return x[None] if x.ndim == 1 else x


def potential_and_normal(potential: Potential, s, a, dtype=torch.float32) -> tuple[np.ndarray, np.ndarray]:
    """f (B,) and n = df/ds (B, d) as float64 arrays, batched (eq. 5).

    The batch rows must be independent (no batch statistics in the potential), so the gradient
    of sum(f) is each row's own gradient.
    """
    s_t = _as_tensor(s, dtype).clone().requires_grad_(True)
    a_t = _as_tensor(a, dtype)
    if s_t.shape[0] != a_t.shape[0]:
        raise ValueError(f"potential: states have {s_t.shape[0]} rows but actions {a_t.shape[0]}; give one action per state")
    with torch.enable_grad():
        f = potential(s_t, a_t)
        (n,) = torch.autograd.grad(f.sum(), s_t)
    return f.detach().double().numpy(), n.double().numpy()


class FastPotential:
    """A compiled snapshot of a potential whose network is Linear/ReLU/Tanh layers, with the
    gradient written out (no autograd, float32 layers, float64 total danger): the same f and n
    as `potential_and_normal`, several times faster for one state per control tick. Rebuild it
    after every training.

    Supports `DangerPotential` over a TDM with `trunk` (Sequential) and `head` (Linear), and
    `NStepPotential`; anything else raises TypeError (use `potential_and_normal`). The small
    layers run in one compiled call each way (`_mlp_forward`, `_mlp_backward`). A TDM's wide head
    is read by compiled passes for a few rows (`potential_kernels`: one read for f and its
    normal, or one for the scores of the strategy filter's candidates and one more for the
    chosen one's normal); batches of more rows go through BLAS (`_head_terms`).
    """

    def __init__(self, potential: nn.Module):
        if isinstance(potential, DangerPotential) and hasattr(potential.tdm, "trunk") and hasattr(potential.tdm, "head"):
            mods, self.output = list(potential.tdm.trunk) + [potential.tdm.head], "total_danger"
            self.mean = self.std = None
        elif isinstance(potential, NStepPotential):
            mods, self.output = list(potential.net), "sigmoid"
            self.mean = potential.mean.detach().float().numpy()
            self.std = potential.std.detach().float().numpy()
        else:
            raise TypeError(f"FastPotential: {type(potential).__name__} is not a DangerPotential over a TDM "
                            "or an NStepPotential; use potential_and_normal instead")
        layers: list[list] = []
        for m in mods:
            if isinstance(m, nn.Linear):
                layers.append([m.weight.detach().float().numpy().copy(), m.bias.detach().float().numpy().copy(), 0])
            elif isinstance(m, (nn.ReLU, nn.Tanh)):
                layers[-1][2] = 1 if isinstance(m, nn.ReLU) else 2
            else:
                raise TypeError(f"FastPotential: layer {type(m).__name__} is not supported (Linear, ReLU, Tanh)")
        self.head = tuple(layers.pop()[:2]) if self.output == "total_danger" else None
        n_in = layers[0][0].shape[1] if layers else self.head[0].shape[1]
        self.mean = np.zeros(n_in, np.float32) if self.mean is None else self.mean
        self.std = np.ones(n_in, np.float32) if self.std is None else self.std
        self._W = typed.List.empty_list(numba.float32[:, ::1])
        self._b = typed.List.empty_list(numba.float32[::1])
        for w, b, _ in layers:
            self._W.append(np.ascontiguousarray(w))
            self._b.append(np.ascontiguousarray(b))
        self._kinds = np.array([k for _, _, k in layers], dtype=np.int64)
        self._memo = []  # (s, a, log_safe, sigmoids) of the last two few-row log_safety calls
        self._padded = None  # the head as padded columns for the few-row passes, made on first use

    def _trunk(self, s, a):
        """The activations of the compiled layers (input first) for states and actions."""
        s, a = np.atleast_2d(np.asarray(s, dtype=np.float64)), np.atleast_2d(np.asarray(a, dtype=np.float64))
        if s.shape[0] not in (1, a.shape[0]):
            raise ValueError(f"potential: states have {s.shape[0]} rows but actions {a.shape[0]}; give one action per "
                             "state (or one state for all actions)")
        if s.shape[1] + a.shape[1] != len(self.mean):
            raise ValueError(f"potential: a state of {s.shape[1]} and an action of {a.shape[1]} values; the network "
                             f"takes {len(self.mean)} inputs in all (state then action)")
        return _mlp_forward(s, a, self.mean, self.std, self._W, self._b, self._kinds)

    def _danger(self, s, a, grad: bool):
        """The trunk's activations, log p(not D) (B,) and, with `grad`, `sum_i sigmoid(z_i) W_i`
        (the gradient at the head's input up to the factor 1 - f) of the head's logits z."""
        acts = self._trunk(s, a)
        w, b = self.head
        log_safe, sig = _head_terms(_rows_times(acts[len(acts) - 1], w.T) + b, grad)
        return acts, log_safe, _rows_times(sig, w) if grad else None

    def _inputs(self, s, a):
        s, a = np.atleast_2d(np.asarray(s, dtype=np.float64)), np.atleast_2d(np.asarray(a, dtype=np.float64))
        if s.shape[0] not in (1, a.shape[0]) or s.shape[1] + a.shape[1] != len(self.mean):
            self._trunk(s, a)  # raises the clear error
        if self._padded is None:
            self._padded = columns(*self.head)
        return s, a

    def _forward(self, s, a):
        """(s, a, log p(not D) (B,), sigmoids of the head logits) for a few rows: one compiled
        pass over the head (`_tdm_forward`)."""
        s, a = self._inputs(s, a)
        return (s, a) + _tdm_forward(s, a, self.mean, self.std, self._W, self._b, self._kinds, *self._padded,
                                     len(self.head[1]))

    def _normal(self, s, a, sig, log_safe):
        """df/ds from `_forward`'s sigmoids (one more pass over the head)."""
        return _tdm_backward(s, a, self.mean, self.std, self._W, self._b, self._kinds, self._padded[0], sig, log_safe)

    def _fused(self, s, a):
        """(log p(not D) (B,), df/ds (B, d)) for a few rows in one pass over the head."""
        s, a = self._inputs(s, a)
        return _tdm_fused(s, a, self.mean, self.std, self._W, self._b, self._kinds, *self._padded, len(self.head[1]))

    def log_safety(self, s, a) -> np.ndarray:
        """log p(not D | s, a) (B,) of a TDM potential (eq. 1 in log space) for states (B, d), or
        one state (1, d) for all B actions. For a few rows (the strategy filter's candidates) the
        head's sigmoids are kept: the modulation of the chosen candidate then needs only the
        backward pass (`__call__`)."""
        if self.output != "total_danger":
            raise TypeError("FastPotential.log_safety needs a DangerPotential over a TDM")
        if np.ndim(a) != 2 or len(a) > FUSED_ROWS:
            return self._danger(s, a, False)[1]
        s2, a2, log_safe, sig = self._forward(s, a)
        # copies: a caller may reuse its arrays; the filter scores in up to two calls
        self._memo = [(s2.copy(), a2.copy(), log_safe, sig)] + self._memo[:1]
        return log_safe

    def __call__(self, s, a) -> tuple[np.ndarray, np.ndarray]:
        """f (B,) and df/ds (B, d) for states (B, d) or (d,) and actions (B, m) or (m,)."""
        d = np.shape(s)[-1]
        if self.output == "total_danger":
            if np.ndim(a) == 1 or len(a) <= FUSED_ROWS:
                m, k = self._recall(s, a)
                if k < 0:
                    log_safe, n = self._fused(s, a)
                    return -np.expm1(log_safe), n
                ms, ma, log_safe, sig = self._memo[m]
                s2, a2, log_safe, sig = ms[k if len(ms) > 1 else 0][None], ma[k][None], log_safe[k:k + 1], sig[k:k + 1]
                return -np.expm1(log_safe), self._normal(s2, a2, sig, log_safe)
            acts, log_safe, g = self._danger(s, a, True)
            f = -np.expm1(log_safe)  # eq. 1 in log space
            g *= np.exp(log_safe).astype(np.float32)[:, None]  # df/dz_i = (1 - f) sigmoid(z_i)
        else:
            acts = self._trunk(s, a)
            f = expit(acts[len(acts) - 1][:, 0].astype(np.float64))
            g = (f * (1.0 - f)).astype(np.float32)[:, None]
        return f, _mlp_backward(g, self.std, self._W, acts, self._kinds)[:, :d].astype(np.float64)

    def _recall(self, s, a) -> tuple[int, int]:
        """(call, row) of the last two `log_safety` calls that scored exactly this one (s, a), or
        (-1, -1)."""
        if np.ndim(s) != 1 or np.ndim(a) != 1:
            return -1, -1
        s, a = np.asarray(s, dtype=np.float64), np.asarray(a, dtype=np.float64)
        for m, (ms, ma, _, _) in enumerate(self._memo):
            k = _find_row(ms, ma, s, a)
            if k >= 0:
                return m, k
        return -1, -1


def _head_terms(z: np.ndarray, grad: bool):
    """From logits z (B, N) float32: log p(not D) = -sum_i softplus(z_i) (B,) float64 and, with
    `grad`, sigmoid(z) (B, N). softplus(z) = max(z, 0) + log(1 + e) with e = exp(-|z|) (numpy's
    vectorised exp); no log1p: the logs of 64 factors (1 + e) in (1, 2] are taken as one log of
    their float64 product (exact to ~1e-14; float32 1 + e would drop every e under 6e-8)."""
    return _head_sums(z, np.exp(-np.abs(z)), grad)


@numba.njit(cache=True, nogil=True, fastmath=_FAST)
def _head_sums(z, e, grad):
    B, N = z.shape
    log_safe = np.empty(B)
    sig = np.empty((B, N) if grad else (0, 0), np.float32)
    for r in range(B):
        total = 0.0
        for i in range(N):
            total += max(z[r, i], np.float32(0.0))
        for start in range(0, N, 64):
            prod = 1.0
            for i in range(start, min(start + 64, N)):
                prod *= 1.0 + e[r, i]
            total += np.log(prod)
        log_safe[r] = -total
        if grad:
            for i in range(N):
                sig[r, i] = (np.float32(1.0) if z[r, i] >= 0 else e[r, i]) / (np.float32(1.0) + e[r, i])
    return log_safe, sig


def _rows_times(x: np.ndarray, w: np.ndarray) -> np.ndarray:
    """x @ w; for a few rows one matrix-vector product per row (OpenBLAS's GEMM with 2-8 rows
    is several times slower than that many GEMVs on a 4,096-row TDM head)."""
    if not 1 < len(x) <= 8:
        return x @ w
    out = np.empty((len(x), w.shape[1]), dtype=np.result_type(x, w))
    for r in range(len(x)):
        np.dot(x[r], w, out=out[r])
    return out


# ---------------------------------------------------------------- n-step potential (eq. 8)

class UniformPolicy:
    """pi'(a | s) = U([low, high]) per action dimension (the paper's default exploration policy)."""

    def __init__(self, low, high):
        self.low = torch.as_tensor(np.asarray(low, dtype=np.float32))
        self.high = torch.as_tensor(np.asarray(high, dtype=np.float32))
        if self.low.shape != self.high.shape or bool((self.high < self.low).any()):
            raise ValueError("UniformPolicy: 'low' and 'high' must have the same shape with low <= high")

    def __call__(self, s: torch.Tensor, gen: torch.Generator) -> torch.Tensor:
        u = torch.rand((s.shape[0],) + tuple(self.low.shape), generator=gen, dtype=s.dtype)
        return self.low + u * (self.high - self.low)


class EulerDynamics:
    """s' = s + dt * a for velocity actions (a has the state's dimension)."""

    def __init__(self, dt: float):
        self.dt = float(dt)

    def __call__(self, s: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
        return s + self.dt * a


@dataclass
class NStepConfig:
    """Monte Carlo settings of eq. 8: horizon T, discount gamma, rollouts per (s, a)."""

    horizon: int = 2
    gamma: float = 0.9
    samples: int = 16

    def check(self) -> None:
        if self.horizon < 1:
            raise ValueError(f"n-step potential: horizon is {self.horizon}; use T >= 1")
        if not 0.0 < self.gamma <= 1.0:
            raise ValueError(f"n-step potential: gamma is {self.gamma}; use 0 < gamma <= 1")
        if self.samples < 1:
            raise ValueError(f"n-step potential: samples is {self.samples}; use at least 1 rollout")


@torch.no_grad()
def nstep_targets(potential: Potential, s0, a0, dynamics, policy, cfg: NStepConfig,
                  seed: int = 0, chunk: int = 65536) -> np.ndarray:
    """min(w(s0, a0), 1) (B,) estimated with `cfg.samples` rollouts of `cfg.horizon` steps
    (evaluated `chunk` rollouts at a time to bound memory)."""
    cfg.check()
    gen = torch.Generator().manual_seed(seed)
    s_all = _as_tensor(s0, torch.float32)
    a_all = _as_tensor(a0, torch.float32)
    k = cfg.samples if cfg.horizon > 1 else 1
    rows = max(1, chunk // k)
    out = []
    for i in range(0, s_all.shape[0], rows):
        s = s_all[i:i + rows].repeat_interleave(k, 0)
        a = a_all[i:i + rows].repeat_interleave(k, 0)
        total = torch.zeros(s.shape[0])
        for t in range(cfg.horizon):
            if t > 0:
                s = dynamics(s, a)
                a = policy(s, gen)
            total += cfg.gamma ** t * potential(s, a)
        out.append(total.view(-1, k).mean(1).clamp(max=1.0))
    return torch.cat(out).double().numpy() if out else np.zeros(0)


class NStepPotential(nn.Module):
    """The distilled n-step potential w_phi(s, a) in [0, 1]: an MLP on normalised inputs."""

    def __init__(self, state_dim: int, action_dim: int, hidden: int = 64):
        super().__init__()
        self.register_buffer("mean", torch.zeros(state_dim + action_dim))
        self.register_buffer("std", torch.ones(state_dim + action_dim))
        self.net = nn.Sequential(nn.Linear(state_dim + action_dim, hidden), nn.Tanh(),
                                 nn.Linear(hidden, hidden), nn.Tanh(), nn.Linear(hidden, 1))

    def forward(self, s: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
        x = (torch.cat([s, a], dim=-1) - self.mean) / self.std
        return torch.sigmoid(self.net(x)).squeeze(-1)


def distill_nstep(potential: Potential, states, actions, dynamics, policy, cfg: NStepConfig,
                  state_noise: float = 0.05, epochs: int = 150, lr: float = 3e-3, hidden: int = 64,
                  seed: int = 0, net: NStepPotential | None = None) -> tuple[NStepPotential, dict]:
    """Fit an `NStepPotential` to Monte Carlo targets of eq. 8.

    Training points: the given (state, action) pairs, the same states with Gaussian noise
    (`state_noise`) and policy actions, so the net also sees the neighbourhood it will be asked
    about. `net` warm-starts from a previous fit. Returns the net and {"mc_s", "fit_s", "rmse"}.
    """
    s = _as_tensor(states, torch.float32)
    a = _as_tensor(actions, torch.float32)
    if len(s) == 0 or len(s) != len(a):
        raise ValueError(f"distill_nstep: got {len(s)} states and {len(a)} actions; give the same, non-zero number")
    gen = torch.Generator().manual_seed(seed)
    s_near = s + state_noise * torch.randn(s.shape, generator=gen)
    xs = torch.cat([s, s_near])
    xa = torch.cat([a, policy(s_near, gen)])
    t0 = time.perf_counter()
    y = torch.as_tensor(nstep_targets(potential, xs, xa, dynamics, policy, cfg, seed), dtype=torch.float32).clamp(0, 1)
    t1 = time.perf_counter()
    torch.manual_seed(seed)
    if net is None:
        net = NStepPotential(s.shape[1], a.shape[1], hidden)
    x = torch.cat([xs, xa], 1)
    net.mean.copy_(x.mean(0))
    net.std.copy_(x.std(0).clamp_min(1e-3))
    opt = torch.optim.Adam(net.parameters(), lr=lr)
    bs = 512
    for _ in range(epochs):
        perm = torch.randperm(len(x), generator=gen)
        for i in range(0, len(x), bs):
            idx = perm[i:i + bs]
            loss = nn.functional.binary_cross_entropy(net(xs[idx], xa[idx]).clamp(1e-6, 1 - 1e-6), y[idx])
            opt.zero_grad()
            loss.backward()
            opt.step()
    with torch.no_grad():
        rmse = float(torch.sqrt(((net(xs, xa) - y) ** 2).mean()))
    return net, {"mc_s": t1 - t0, "fit_s": time.perf_counter() - t1, "rmse": rmse}


def nstep_trade(potential: Potential, states, actions, dynamics, policy, horizons=(1, 2, 4, 8),
                samples=(1, 4, 16, 64), gamma: float = 0.9, reference_samples: int = 1024) -> list[dict]:
    """Rows {horizon, samples, err, ms}: Monte Carlo error of w (RMS, against `reference_samples`
    rollouts) and the time to estimate w for all given states, per horizon and sample count."""
    rows = []
    for T in horizons:
        ref = nstep_targets(potential, states, actions, dynamics, policy, NStepConfig(T, gamma, reference_samples), seed=12345)
        for k in samples:
            cfg = NStepConfig(T, gamma, k)
            t0 = time.perf_counter()
            w = nstep_targets(potential, states, actions, dynamics, policy, cfg, seed=1)
            ms = (time.perf_counter() - t0) * 1e3
            rows.append({"horizon": T, "samples": k, "err": float(np.sqrt(np.mean((w - ref) ** 2))), "ms": ms})
    return rows
