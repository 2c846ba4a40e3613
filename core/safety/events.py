"""Tactile danger events (paper III-A): d_i = 1(f_i > f_th,i) for every stimulus a board reports."""
from __future__ import annotations

import numpy as np


def danger_events(readings: dict[str, np.ndarray], thresholds: dict[str, np.ndarray]) -> np.ndarray:
    """(N,) bool: taxel i is in danger when any stimulus exceeds its per-taxel threshold.

    `readings` maps a stimulus ("force", "temperature", "classifier") to (N,) or (B, N) values;
    stimuli without a threshold are ignored; NaN readings never count as danger.
    """
    out = None
    for name, value in readings.items():
        if name not in thresholds:
            continue
        d = np.asarray(value) > thresholds[name]
        out = d if out is None else out | d
    if out is None:
        raise ValueError(f"no reading matches a threshold: readings {sorted(readings)}, thresholds {sorted(thresholds)}")
    return out
