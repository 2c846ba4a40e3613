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


def interleaved_ms(fns: dict[str, Callable[[], object]], repeat: int = 50, rounds: int = 7) -> dict[str, float]:
    """Median wall times (ms) of several functions measured in alternating rounds of `repeat`
    runs each, so a change in the machine's load between them shifts all alike (their ratios hold)."""
    per = {k: [] for k in fns}
    for _ in range(rounds):
        for k, fn in fns.items():
            per[k].append(median_ms(fn, repeat=repeat, warmup=1))
    return {k: float(np.median(v)) for k, v in per.items()}
