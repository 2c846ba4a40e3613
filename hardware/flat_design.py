"""A flat test map: taxels spread evenly over boards of exactly that many channels (benchmarks, tests, the demo)."""
from __future__ import annotations

import numpy as np

from skinsafe.core.skin.ids import stable_ids
from skinsafe.core.skin.model import Board, Module, RobotRef, SkinDesign, Taxels, frames_from_normals


def flat_design(n_taxels: int, n_boards: int, threshold: float = 5.0, uid_base: int = 0x5C1A0000) -> SkinDesign:
    """A design of `n_taxels` on one body, spread evenly over `n_boards` boards of exactly that many channels."""
    per = -(-n_taxels // n_boards)
    board = (np.arange(n_taxels) // per).astype(np.int32)
    channel = (np.arange(n_taxels) % per).astype(np.int32)
    rng = np.random.default_rng(0)
    return SkinDesign(
        RobotRef(), ["forearm_link"],
        [Module(i, f"module{i}", "forearm_link", rows=1, cols=per, board=i) for i in range(n_boards)],
        [Board(i, f"board{i}", uid_base + i, per) for i in range(n_boards)],
        Taxels(ids=stable_ids(board), body=np.zeros(n_taxels, np.int32),
               positions=rng.normal(size=(n_taxels, 3)) * 0.05,
               frames=frames_from_normals(np.tile([0.0, 0.0, 1.0], (n_taxels, 1)), np.array([1.0, 0, 0])),
               module=board.copy(), board=board, channel=channel, area=np.full(n_taxels, 3e-5),
               enabled=np.ones(n_taxels, bool), thresholds={"force": np.full(n_taxels, threshold)}))
