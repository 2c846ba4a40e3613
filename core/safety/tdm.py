"""The tactile danger model (TDM, paper III-A): p(d_i | s, a) for every taxel at once.

A shared MLP trunk over (state, action) and one linear head to `n_taxels` logits, so a
10,000-taxel skin costs one extra matrix product. Trained with binary cross-entropy on logged
(state, action, per-taxel danger) triples; checkpoints are written atomically and read back with
`torch.load(weights_only=True)` (no pickled code runs on load).
"""
from __future__ import annotations

import io
import os

import numpy as np
import torch
from torch import Tensor, nn
from tqdm.auto import tqdm

from skinsafe.core.skin.files import atomic_write

SCHEMA_VERSION = 1


class TactileDangerModel(nn.Module):
    """Logits of p(d_i | s, a) for all taxels: (B, state_dim), (B, action_dim) -> (B, n_taxels).

    Discrete actions are passed one-hot (`action_dim` = number of actions).
    """

    def __init__(self, state_dim: int, action_dim: int, n_taxels: int, hidden=(128, 128)):
        super().__init__()
        for name, v in (("state_dim", state_dim), ("action_dim", action_dim), ("n_taxels", n_taxels)):
            if int(v) < 1:
                raise ValueError(f"TactileDangerModel: {name} is {v}; give a positive size")
        self.state_dim, self.action_dim, self.n_taxels = int(state_dim), int(action_dim), int(n_taxels)
        self.hidden = tuple(int(h) for h in hidden)
        layers, width = [], self.state_dim + self.action_dim
        for h in self.hidden:
            layers += [nn.Linear(width, h), nn.ReLU()]
            width = h
        self.trunk = nn.Sequential(*layers)
        self.head = nn.Linear(width, self.n_taxels)
        # Contacts are rare: start every taxel at p = 1% instead of 50%.
        nn.init.constant_(self.head.bias, -4.6)

    def forward(self, s: Tensor, a: Tensor) -> Tensor:
        return self.head(self.trunk(torch.cat([s, a], dim=-1)))

    def config(self) -> dict:
        return {"state_dim": self.state_dim, "action_dim": self.action_dim, "n_taxels": self.n_taxels,
                "hidden": list(self.hidden)}


def one_hot(actions, n_actions: int) -> Tensor:
    """(B,) integer actions -> (B, n_actions) float one-hot."""
    a = torch.as_tensor(np.asarray(actions), dtype=torch.long)
    return torch.nn.functional.one_hot(a, n_actions).float()


def _as_float(x, name: str, rows: int | None = None, ndim: int = 2) -> Tensor:
    t = torch.as_tensor(np.asarray(x, dtype=np.float32))
    if t.ndim != ndim:
        raise ValueError(f"train_tdm: '{name}' has shape {tuple(t.shape)}; expected a {ndim}-D array (samples first)")
    if rows is not None and t.shape[0] != rows:
        raise ValueError(f"train_tdm: '{name}' has {t.shape[0]} rows but states has {rows}; give one row per sample")
    if not torch.isfinite(t).all():
        raise ValueError(f"train_tdm: '{name}' contains NaN or Inf; drop or fix those samples")
    return t


def train_tdm(model: TactileDangerModel, states, actions, dangers, epochs: int = 50, lr: float = 1e-3,
              batch_size: int = 256, seed: int = 0, progress: bool = True, pos_weight=None,
              weight_decay: float = 0.0) -> dict:
    """Fit the model by binary cross-entropy on (states (B,S), actions (B,A), dangers (B,N) in {0,1}).

    `pos_weight` (scalar or (N,)) up-weights the rare positive (contact) labels. Returns the history
    {"loss": per-epoch mean loss}. Deterministic for a given model initialisation and `seed`.
    """
    s = _as_float(states, "states")
    n = s.shape[0]
    a = _as_float(actions, "actions", n)
    d = _as_float(dangers, "dangers", n)
    for name, t, want in (("states", s, model.state_dim), ("actions", a, model.action_dim),
                          ("dangers", d, model.n_taxels)):
        if t.shape[1] != want:
            raise ValueError(f"train_tdm: '{name}' has {t.shape[1]} columns but the model expects {want}; "
                             "build the model with matching sizes (actions one-hot for discrete)")
    if n == 0:
        raise ValueError("train_tdm: no samples; log some (state, action, danger) data first")
    if ((d != 0) & (d != 1)).any():
        raise ValueError("train_tdm: 'dangers' must be 0/1 per taxel (threshold readings with core.events)")
    gen = torch.Generator().manual_seed(int(seed))  # batch order; leaves the global RNG alone
    pw = None if pos_weight is None else torch.as_tensor(pos_weight, dtype=torch.float32)
    loss_fn = nn.BCEWithLogitsLoss(pos_weight=pw)
    opt = torch.optim.Adam(model.parameters(), lr=lr, weight_decay=weight_decay)
    history = {"loss": []}
    model.train()
    bar = tqdm(range(int(epochs)), desc="train TDM", disable=not progress, leave=False)
    for _ in bar:
        perm = torch.randperm(n, generator=gen)
        total = 0.0
        for i in range(0, n, batch_size):
            idx = perm[i:i + batch_size]
            loss = loss_fn(model(s[idx], a[idx]), d[idx])
            opt.zero_grad()
            loss.backward()
            opt.step()
            total += float(loss.detach()) * len(idx)
        history["loss"].append(total / n)
        bar.set_postfix(loss=f"{history['loss'][-1]:.4f}")
    model.eval()
    return history


def save_tdm(model: TactileDangerModel, path: str | os.PathLike) -> None:
    """Write the model's sizes and weights to `path` (atomically; plain tensors, no pickled code)."""
    buf = io.BytesIO()
    torch.save({"schema_version": SCHEMA_VERSION, "config": model.config(),
                "state_dict": {k: v.detach().cpu() for k, v in model.state_dict().items()}}, buf)
    atomic_write(path, buf.getvalue())


def load_tdm(path: str | os.PathLike) -> TactileDangerModel:
    """Read a checkpoint written by `save_tdm` with `torch.load(weights_only=True)`."""
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except FileNotFoundError:
        raise
    except Exception as e:  # corrupt file or one holding arbitrary pickled objects
        raise ValueError(f"{path}: not a TDM checkpoint readable with weights_only=True ({e}); "
                         "re-create it with skinsafe.core.safety.tdm.save_tdm") from e
    if not isinstance(ckpt, dict) or ckpt.get("schema_version") != SCHEMA_VERSION:
        got = ckpt.get("schema_version") if isinstance(ckpt, dict) else type(ckpt).__name__
        raise ValueError(f"{path}: field 'schema_version' is {got!r}, this version reads {SCHEMA_VERSION}; "
                         "re-save the model with this version of skinsafe")
    c = ckpt["config"]
    model = TactileDangerModel(c["state_dim"], c["action_dim"], c["n_taxels"], tuple(c["hidden"]))
    model.load_state_dict(ckpt["state_dict"])
    model.eval()
    return model
