"""Online training of a tactile danger model (paper III-A) as a real training loop.

`TDMTrainer` keeps the experience (state, action, per-taxel danger) an agent or controller logs,
splits it into training and validation samples as it arrives (a fixed fraction, by a seeded
draw per sample), and refits the model with a budget of gradient steps per fit (Adam, warm
started: the optimiser and the weights carry over between fits). Every `eval_every` steps the
validation loss is measured; the fit stops early when it has not improved for `patience`
evaluations and the best weights are kept. Each fit appends a record to `history`: gradient
steps, losses, the validation AUC of the total danger p(D | s, a) (eq. 1) against "any taxel
fired", its expected calibration error and Brier score, and the wall time, so the cost of
learning is measured, not guessed.

Labels may be soft (any value in [0, 1]): binary cross-entropy with a soft target is still a
proper scoring rule. `skinsafe.core.safety.tdm.train_tdm` stays the one-shot, epoch-based fit
for offline data sets.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import torch
from scipy.stats import rankdata
from torch import nn

from skinsafe.core.safety.danger import total_danger
from skinsafe.core.safety.tdm import TactileDangerModel


def auc(scores, labels) -> float | None:
    """Area under the ROC curve (Mann-Whitney, ties counted half); None without both classes."""
    y = np.asarray(labels, bool).ravel()
    n_pos, n_neg = int(y.sum()), int((~y).sum())
    if n_pos == 0 or n_neg == 0:
        return None
    r = rankdata(np.asarray(scores, float).ravel())
    return float((r[y].sum() - n_pos * (n_pos + 1) / 2) / (n_pos * n_neg))


def calibration(probs, labels, bins: int = 10) -> dict:
    """Expected calibration error over `bins` equal-width bins and the Brier score."""
    p = np.clip(np.asarray(probs, float).ravel(), 0, 1)
    y = np.asarray(labels, float).ravel()
    if p.size == 0:
        return {"ece": None, "brier": None}
    which = np.minimum((p * bins).astype(int), bins - 1)
    ece = sum(abs(p[which == b].mean() - y[which == b].mean()) * np.mean(which == b)
              for b in range(bins) if (which == b).any())
    return {"ece": float(ece), "brier": float(np.mean((p - y) ** 2))}


@dataclass
class FitConfig:
    """The budget and schedule of one refit."""

    steps: int = 200  # most gradient steps per fit
    min_steps: int = 0  # gradient steps before early stopping may end a fit
    batch_size: int = 128
    lr: float = 3e-3
    val_fraction: float = 0.2
    eval_every: int = 10  # steps between validation checks
    patience: int = 3  # checks without improvement before stopping
    min_val: int = 20  # validation samples needed before early stopping is trusted
    capacity: int = 50_000  # most samples kept (oldest dropped first)
    total_weight: float = 0.0  # weight of an extra BCE of eq. 1's total danger against the largest taxel label


class TDMTrainer:
    """Experience, validation split and budgeted refits of one `TactileDangerModel` (module doc)."""

    def __init__(self, model: TactileDangerModel, cfg: FitConfig | None = None, seed: int = 0):
        self.model, self.cfg = model, cfg or FitConfig()
        self.rng = np.random.default_rng(seed)
        self.gen = torch.Generator().manual_seed(seed)
        self.opt = torch.optim.Adam(model.parameters(), lr=self.cfg.lr, fused=True)
        cap = self.cfg.capacity
        self.s = np.zeros((cap, model.state_dim), np.float32)
        self.a = np.zeros((cap, model.action_dim), np.float32)
        self.d = np.zeros((cap, model.n_taxels), np.float32)
        self.val = np.zeros(cap, bool)
        self.n = self.i = 0
        self.history: list[dict] = []
        self.seconds = 0.0

    def add(self, states, actions, dangers) -> None:
        """Log samples: states (B, S) or (S,), actions (B, A) (one-hot for discrete), dangers (B, N) in [0, 1]."""
        s, a, d = (np.atleast_2d(np.asarray(x, np.float32)) for x in (states, actions, dangers))
        if not (len(s) == len(a) == len(d)):
            raise ValueError(f"TDMTrainer.add: {len(s)} states, {len(a)} actions, {len(d)} danger rows; give one of each per sample")
        if s.shape[1] != self.model.state_dim or a.shape[1] != self.model.action_dim or d.shape[1] != self.model.n_taxels:
            raise ValueError(f"TDMTrainer.add: sizes (S={s.shape[1]}, A={a.shape[1]}, N={d.shape[1]}) do not match the model "
                             f"(S={self.model.state_dim}, A={self.model.action_dim}, N={self.model.n_taxels})")
        if not (np.isfinite(s).all() and np.isfinite(a).all()) or ((d < 0) | (d > 1) | ~np.isfinite(d)).any():
            raise ValueError("TDMTrainer.add: states and actions must be finite and dangers in [0, 1]")
        for k in range(len(s)):
            i = self.i
            self.s[i], self.a[i], self.d[i] = s[k], a[k], d[k]
            self.val[i] = self.rng.random() < self.cfg.val_fraction
            self.i = (i + 1) % self.cfg.capacity
            self.n = min(self.n + 1, self.cfg.capacity)

    def _split(self):
        idx = np.arange(self.n)
        return idx[~self.val[: self.n]], idx[self.val[: self.n]]

    def _loss(self, logits: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
        """Per-taxel BCE, plus (with `total_weight`) the BCE of the total danger p(D) = 1 - prod(1 - p_i)
        (eq. 1, in log space) against max_i d_i: the quantity the filter and the potential use."""
        loss = nn.functional.binary_cross_entropy_with_logits(logits, d)
        if self.cfg.total_weight > 0:
            log_safe = nn.functional.logsigmoid(-logits).sum(-1)  # log p(not D)
            log_danger = torch.log(-torch.expm1(log_safe.clamp(max=-1e-6)))
            y = d.max(-1).values
            loss = loss - self.cfg.total_weight * (y * log_danger + (1 - y) * log_safe).mean()
        return loss

    @torch.no_grad()
    def _val_loss(self, idx) -> float:
        s, a, d = (torch.as_tensor(x[idx]) for x in (self.s, self.a, self.d))
        return float(self._loss(self.model(s, a), d))

    @property
    def last(self) -> int:
        """Index of the most recently logged sample (for `fit(focus=...)`)."""
        return (self.i - 1) % self.cfg.capacity

    def fit(self, steps: int | None = None, focus=()) -> dict:
        """One refit of at most `steps` gradient steps (default the config's); returns its record.
        `focus`: sample indices put in every batch (those in the training split), e.g. a contact just
        logged, which a uniform batch of a few thousand samples would see a handful of times. A focused
        fit runs its whole budget and keeps its weights: the validation split has never seen the new
        sample, so early stopping on it would throw the lesson away."""
        cfg = self.cfg
        steps = cfg.steps if steps is None else int(steps)
        train, val = self._split()
        focus = np.asarray([i for i in focus if i < self.n and not self.val[i]], np.int64)
        if len(train) == 0:
            return {}
        t0 = time.perf_counter()
        check = len(val) >= cfg.min_val and not len(focus)
        best, best_state, bad, done, loss = (self._val_loss(val) if check else np.inf), None, 0, 0, np.nan
        if check:  # a fit that never beats the weights it started from keeps them
            best_state = {k: t.clone() for k, t in self.model.state_dict().items()}
        self.model.train()
        while done < steps:
            pick = train[torch.randint(len(train), (min(cfg.batch_size, len(train)),), generator=self.gen).numpy()]
            if len(focus):
                pick = np.concatenate([pick, focus])
            out = self.model(torch.as_tensor(self.s[pick]), torch.as_tensor(self.a[pick]))
            loss = self._loss(out, torch.as_tensor(self.d[pick]))
            self.opt.zero_grad()
            loss.backward()
            self.opt.step()
            done += 1
            if check and done % cfg.eval_every == 0 and done >= cfg.min_steps:
                v = self._val_loss(val)
                if v < best * (1 - 1e-3):  # relative: per-taxel losses of rare events are tiny
                    best, bad = v, 0
                    best_state = {k: t.clone() for k, t in self.model.state_dict().items()}
                else:
                    bad += 1
                    if bad >= cfg.patience:
                        break
        if best_state is not None:
            self.model.load_state_dict(best_state)
        self.model.eval()
        dt = time.perf_counter() - t0
        self.seconds += dt
        rec = {"fit": len(self.history), "samples": int(self.n), "steps": done, "train_loss": float(loss.detach()) if torch.is_tensor(loss) else float(loss),
               "seconds": dt, **self.evaluate(val)}
        self.history.append(rec)
        return rec

    @torch.no_grad()
    def evaluate(self, idx=None) -> dict:
        """Validation loss, AUC and calibration of p(D | s, a) against "any taxel fired" (label > 0.5)."""
        idx = self._split()[1] if idx is None else idx
        if len(idx) == 0:
            return {"val_samples": 0, "val_loss": None, "auc": None, "ece": None, "brier": None}
        s, a = torch.as_tensor(self.s[idx]), torch.as_tensor(self.a[idx])
        p = total_danger(self.model(s, a)).double().numpy()
        y = (self.d[idx] > 0.5).any(1)
        return {"val_samples": int(len(idx)), "val_loss": self._val_loss(idx), "auc": auc(p, y), **calibration(p, y)}
