"""The collaboration experiment's model of the person for the modulation layer: a TDM learned from static contacts
with the person where they are in the way (`learn_person`), scaled by how often they are there."""
from __future__ import annotations

import numpy as np
import torch

from skinsafe.core.experiments.collaboration_scenario import CollabConfig, Layout


class _Presence(torch.nn.Module):
    """danger = presence x f_phi: the person is at the bench in a fraction of the deliveries."""

    def __init__(self, f, presence: float):
        super().__init__()
        self.f, self.presence = f, float(presence)

    def forward(self, s, a):
        return self.presence * self.f(s, a)


_POTENTIALS: dict = {}


def learn_person(sc, lay: Layout, cfg: CollabConfig):
    """A TDM from static contacts with the person where they are in the way, at configurations along
    the robot's plan (labels from the skin readout), as the modulation potential `presence x f_phi`;
    one per scenario, skin and options in a process."""
    import mujoco

    from skinsafe.core.experiments.arm_scene import STATE, static_contact_tdm
    from skinsafe.core.safety.potential import DangerPotential

    key = (lay.scenario, sc.design.n_taxels, float(np.sum(sc.design.taxels.positions)),
           (cfg.seed, cfg.samples, cfg.steps, cfg.presence, cfg.duration, cfg.person_speed))
    if key in _POTENTIALS:
        return _POTENTIALS[key]
    rng = np.random.default_rng(cfg.seed)
    n = cfg.samples
    Q = lay.sample(rng, n)
    A = rng.uniform(-1, 1, (n, len(STATE)))
    D = np.zeros((n, sc.design.n_taxels), np.float32)
    m, d, h = sc.model, sc.data, sc.human
    for i in range(n):
        mujoco.mj_resetData(m, d)
        for k, p in enumerate(lay.present):
            h.place(d, k, p)
        d.qpos[sc.qadr] = Q[i]
        mujoco.mj_forward(m, d)
        D[i] = sc.readout.read(d) > 0
    args = type("Args", (), {"seed": cfg.seed, "steps": cfg.steps})
    pot = _Presence(DangerPotential(static_contact_tdm(Q[:, STATE], A, D, args)), cfg.presence)
    _POTENTIALS[key] = pot
    return pot


