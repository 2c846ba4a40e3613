"""Stable taxel ids: module id x 65536 + the taxel's index in its module (taxel order), so an edit of
one module never renumbers another's taxels. The taxel map, the boards' configs (32-bit id field) and
the live view match taxels by these ids."""
from __future__ import annotations

import warnings
from dataclasses import replace

import numpy as np

from skinsafe.core.skin.model import DesignError, SkinDesign

SHIFT = 16  # 65,536 taxels per module (256 x 256), 65,536 modules: ids fit 32 bits


def stable_ids(module: np.ndarray) -> np.ndarray:
    """(N,) int64 ids of taxels whose module ids are `module` (N,): module << 16 | index in the module."""
    module = np.asarray(module, np.int64)
    n = len(module)
    if n and (module.min() < 0 or module.max() >= 1 << SHIFT):
        raise DesignError(f"taxel ids: module id {int(module.max() if module.max() >= 1 << SHIFT else module.min())} "
                          f"is outside 0..{(1 << SHIFT) - 1}; give modules small non-negative ids")
    order = np.argsort(module, kind="stable")
    m = module[order]
    starts = np.flatnonzero(np.r_[True, m[1:] != m[:-1]]) if n else np.zeros(0, np.intp)
    rank = np.arange(n) - np.repeat(starts, np.diff(np.r_[starts, n]))
    if n and rank.max() >= 1 << SHIFT:
        raise DesignError(f"taxel ids: a module has more than {1 << SHIFT} taxels; split it")
    index = np.empty(n, np.int64)
    index[order] = rank
    return (module << SHIFT) | index


def with_stable_ids(design: SkinDesign) -> SkinDesign:
    """The design with every taxel's id made stable (`stable_ids` of its module column)."""
    return design.with_taxels(replace(design.taxels, ids=stable_ids(design.taxels.module)))


class IdRuleWarning(UserWarning):
    """A taxel map written under another id rule was converted to the stable one on load."""


def converted(design: SkinDesign, source: str) -> SkinDesign:
    """The design with stable ids; where its ids followed another rule (0..N-1, as maps made on the
    command line before the one rule), an `IdRuleWarning` names what changed and that the boards
    deployed with the old ids need a new deploy."""
    ids = stable_ids(design.taxels.module)
    old = design.taxels.ids
    changed = np.flatnonzero(old != ids)
    if not len(changed):
        return design
    i = int(changed[0])
    warnings.warn(IdRuleWarning(
        f"{source}: {len(changed)} of {len(ids)} taxel ids followed another rule and were converted to the stable "
        f"one (module id x 65,536 + index: e.g. taxel {int(old[i])} of module {int(design.taxels.module[i])} is now "
        f"{int(ids[i])}); boards deployed with this map need a new `skinsafe deploy`, and saving the map keeps the "
        "conversion"), stacklevel=3)
    return design.with_taxels(replace(design.taxels, ids=ids))
