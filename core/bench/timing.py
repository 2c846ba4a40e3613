"""Timing for benchmarks: medians of repeated runs in one process (machines here are noisy)."""
from __future__ import annotations

import time
from typing import Callable

import numpy as np


def median_ms(fn: Callable[[], object], repeat: int = 50, warmup: int = 3, min_time_s: float = 0.0) -> float:
    """Median wall time of `fn()` in milliseconds over `repeat` runs (more while under `min_time_s`)."""
    for _ in range(warmup):
        fn()
    times = []
    start = time.perf_counter()
    while len(times) < repeat or time.perf_counter() - start < min_time_s:
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times) * 1e3)
