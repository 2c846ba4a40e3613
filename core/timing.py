"""Timing for benchmarks: medians of repeated runs in one process, interleaved blocks and pooled intervals
(machines here are noisy). The host's real-time settings are core/realtime.py's.

A leaf of the package: numpy and the standard library only, so every core layer may import it
(import-linter: the lowest layer)."""
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


def cpu_median_ms(fn: Callable[[], object], repeat: int) -> float:
    """Median CPU time of this process for `fn()`, ms: a figure other processes' load skews less than wall time."""
    times = []
    for _ in range(repeat):
        t0 = time.process_time()
        fn()
        times.append(time.process_time() - t0)
    return float(np.median(times) * 1e3)


def interleaved_ms(fns: list[Callable[[], object]], repeat: int = 200, warmup: int = 3, block: int = 20) -> list[np.ndarray]:
    """Wall times (ms) of each of `fns`, `repeat` calls each, taken in alternating blocks of
    `block` calls: on a shared machine the load then falls on all of them alike, so their ratios
    hold even when the times do not. The first call of each block is not recorded (it pays for
    the caches the other function's block evicted, a cost of the bench, not of the code)."""
    for fn in fns:
        for _ in range(warmup):
            fn()
    times: list[list[float]] = [[] for _ in fns]
    while len(times[0]) < repeat:
        for k, fn in enumerate(fns):
            fn()
            for _ in range(min(block, repeat - len(times[k]))):
                t0 = time.perf_counter()
                fn()
                times[k].append(time.perf_counter() - t0)
    return [np.array(t) * 1e3 for t in times]


def pct(a: np.ndarray, p: float) -> float:
    """Percentile `p` of the samples `a` (nan without any)."""
    return float(np.percentile(a, p)) if len(a) else float("nan")


def pooled_change_ci95(a: list[np.ndarray], b: list[np.ndarray], draws: np.ndarray, p: float = 99) -> list[float]:
    """The 95% interval of (percentile `p` of a's samples pooled / of b's - 1), the pairs (a[k], b[k]) resampled:
    `draws` holds rows of pair indices drawn with replacement; draws without samples are left out."""
    ratio = [pct(np.concatenate([a[k] for k in d]), p) / pct(np.concatenate([b[k] for k in d]), p) - 1 for d in draws]
    return [round(float(x), 4) for x in np.nanpercentile(ratio, [2.5, 97.5])]
