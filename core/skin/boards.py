"""Interface boards: assign whole modules to boards and number their channels."""
from __future__ import annotations

import numpy as np

from skinsafe.core.skin.model import Board, DesignError


def assign_boards(module_ids: np.ndarray, module_sizes: dict[int, int], capacity: int,
                  boards: list[Board] | None = None, uid_base: int = 0x5C1A0000) -> tuple[list[Board], dict[int, int]]:
    """First-fit-decreasing assignment keeping every module on one board.

    `module_sizes` maps module id -> taxel count. Existing `boards` are filled first, new ones
    (with `capacity` channels) are added as needed. Returns (boards, module id -> board id).
    A module larger than a board is an error.
    """
    boards = list(boards or [])
    free = {b.id: b.capacity for b in boards}
    out: dict[int, int] = {}
    for mid in sorted(module_sizes, key=lambda m: (-module_sizes[m], m)):
        size = module_sizes[mid]
        target = next((bid for bid in free if free[bid] >= size), None)
        if target is None:
            if size > capacity:
                raise DesignError(f"module {mid}: {size} taxels exceed a board's {capacity} channels; "
                                  "split the module or use boards with more channels")
            target = max([b.id for b in boards], default=-1) + 1
            boards.append(Board(id=target, name=f"board{target}", uid=uid_base + target, capacity=capacity))
            free[target] = capacity
        free[target] -= size
        out[mid] = target
    return boards, out


def number_channels(module: np.ndarray, board: np.ndarray) -> np.ndarray:
    """Channel numbers 0.. per board, in taxel order, so a module's taxels stay consecutive."""
    channel = np.zeros(len(board), dtype=np.int32)
    for b in np.unique(board):
        on = np.flatnonzero(board == b)
        order = on[np.argsort(module[on], kind="stable")]
        channel[order] = np.arange(len(order), dtype=np.int32)
    return channel
