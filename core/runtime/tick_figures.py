"""A per-tick figure of the loop (its period, work, a contact's latency) in bounded memory, for runs of any length.

The first `keep` samples are kept exactly (a bench pools short runs' samples); every sample also goes into a
histogram of logarithmic bins (relative width `REL`), so a shift-long run's percentiles cost a fixed 1.5 MB
per figure and are within `REL` of the exact ones; the largest is exact. A list of Python floats grew by
32 bytes a tick: 115 MB per figure per hour at 1 kHz.
"""
from __future__ import annotations

import math
from array import array

import numpy as np

KEEP = 300_000  # samples kept exactly: 5 min at 1 kHz
LO, HI = 1e-6, 1e2  # the histogram's range (a sample outside counts in its end bin; the max stays exact)
REL = 1e-4  # each bin's width relative to its lower edge


class Figure:
    """Samples of one figure: `add(x)` in the loop (under a microsecond), `percentile`, `max`, `exact()`."""

    _step = math.log1p(REL)
    _bins = int(math.log(HI / LO) / _step) + 1

    def __init__(self, keep: int = KEEP):
        self._kept = array("d", bytes(8 * keep))  # array, not numpy: a store in the loop costs a quarter
        self._counts = array("q", bytes(8 * self._bins))
        self.n, self.max = 0, -math.inf

    def add(self, x: float) -> None:
        if self.n < len(self._kept):
            self._kept[self.n] = x
        self.n += 1
        if x > self.max:
            self.max = x
        if x >= HI:
            k = self._bins - 1
        elif x > LO:
            k = int(math.log(x / LO) / self._step)
        else:  # below the range, or nan
            k = 0
        self._counts[k] += 1

    def exact(self) -> np.ndarray | None:
        """Every sample in order, or None once there were more than `keep`."""
        return np.frombuffer(self._kept, float, self.n) if self.n <= len(self._kept) else None

    def percentile(self, p: float) -> float:
        """Percentile `p`: numpy's (linear interpolation) while every sample is kept; after, the geometric centre of
        the bin holding the sample of that rank (within REL of it); nan without samples."""
        if not self.n:
            return math.nan
        kept = self.exact()
        if kept is not None:
            return float(np.percentile(kept, p))
        k = int(np.searchsorted(np.cumsum(np.frombuffer(self._counts, np.int64)), math.ceil(p / 100 * self.n)))
        return self.max if k == self._bins - 1 else min(LO * math.exp((k + 0.5) * self._step), self.max)
