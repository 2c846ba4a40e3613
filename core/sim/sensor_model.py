"""What a board sends: an FSR force-to-ADC-count model, and a sample-and-hold with latency.

An FSR's resistance falls with force as a power law, `R = r_1n * (F / 1 N)^-alpha`, down to a
floor `r_min` (saturation), and is open below its turn-on force. In a voltage divider with `r_m` the ADC sees `v = r_m / (r_m + R)`:
a nonlinear, saturating curve (as `R -> 0`, `v -> 1`). `encode` adds ADC noise and quantises;
`decode` inverts the curve. Simulated readings and real board readings go through the same
`decode`, so the safety layers see the same kind of numbers from both.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np


@dataclass
class FSRModel:
    """Interlink-402-like FSR in a divider read by an ADC on a board sampling at `rate_hz`."""

    r_1n: float = 6.0e3  # ohm at 1 N
    alpha: float = 0.9  # power-law exponent of R(F)
    r_m: float = 10.0e3  # divider resistor, ohm
    r_min: float = 250.0  # ohm: the FSR's resistance does not fall below this (saturation)
    f_on: float = 0.1  # N: below this the FSR is open (reads 0)
    bits: int = 12
    noise_counts: float = 2.0  # std of additive ADC noise, counts
    rate_hz: float = 100.0  # board sample rate
    latency_s: float = 0.005  # from sampling to the host having the value

    def __post_init__(self):
        for name in ("r_1n", "alpha", "r_m", "r_min", "rate_hz"):
            if not getattr(self, name) > 0:
                raise ValueError(f"FSRModel.{name} is {getattr(self, name)}; give a positive number")
        if not (1 <= self.bits <= 16):
            raise ValueError(f"FSRModel.bits is {self.bits}; give 1..16 (counts are uint16)")
        if self.f_on < 0 or self.noise_counts < 0 or self.latency_s < 0:
            raise ValueError("FSRModel.f_on, noise_counts and latency_s must be >= 0")

    @property
    def full_scale(self) -> int:
        return (1 << self.bits) - 1

    def voltage(self, force: np.ndarray) -> np.ndarray:
        """Noise-free divider output as a fraction of the supply, (N,)."""
        f = np.asarray(force, float)
        on = f >= max(self.f_on, 1e-12)
        r = np.maximum(self.r_1n * np.power(np.where(on, f, 1.0), -self.alpha), self.r_min)
        return np.where(on, self.r_m / (self.r_m + r), 0.0)

    def encode(self, force: np.ndarray, rng: np.random.Generator | None = None) -> np.ndarray:
        """(N,) force [N] -> (N,) uint16 ADC counts, with noise when `rng` is given."""
        c = self.voltage(force) * self.full_scale
        if rng is not None and self.noise_counts > 0:
            c = c + rng.normal(0.0, self.noise_counts, c.shape)
        return np.clip(np.rint(c), 0, self.full_scale).astype(np.uint16)

    def decode(self, counts: np.ndarray) -> np.ndarray:
        """(N,) ADC counts -> (N,) force [N], the inverse curve.

        Counts below the turn-on force's count read 0; counts at or above the saturation count
        read the saturation force (`max_force`), the largest the board can tell apart.
        """
        c = np.asarray(counts, float)
        v = np.clip(c / self.full_scale, 0.5 / self.full_scale, self.r_m / (self.r_m + self.r_min))
        r = self.r_m * (1.0 - v) / v
        f = np.power(r / self.r_1n, -1.0 / self.alpha)
        return np.where(c >= self.on_count, f, 0.0)

    @property
    def on_count(self) -> float:
        """The smallest count that means contact (the turn-on force's count, at least 1)."""
        return max(1.0, float(self.voltage(np.array([self.f_on]))[0] * self.full_scale) - 0.5)

    @property
    def max_force(self) -> float:
        """The force at which the reading saturates (R reaches r_min), N."""
        return float((self.r_min / self.r_1n) ** (-1.0 / self.alpha))


class BoardSampler:
    """Sample-and-hold at the board's rate with its latency, like readings arriving from boards.

    `update(t, force)` is called every simulation step with the true taxel forces; it samples
    them (encoded to counts) every `1 / rate_hz` s and returns the counts the host has at time
    `t`: the newest sample taken at least `latency_s` earlier (zeros before the first).
    """

    def __init__(self, fsr: FSRModel, n: int, seed: int | None = 0, noise: bool = True):
        self.fsr = fsr
        self.rng = np.random.default_rng(seed) if noise else None
        self.period = 1.0 / fsr.rate_hz
        self.held = np.zeros(n, dtype=np.uint16)
        self.pending: deque[tuple[float, np.ndarray]] = deque()
        self.next_sample = 0.0

    def update(self, t: float, force: np.ndarray) -> np.ndarray:
        """(N,) uint16 counts available at time `t` (the same array object until it changes)."""
        if t + 1e-12 >= self.next_sample:
            self.pending.append((t + self.fsr.latency_s, self.fsr.encode(force, self.rng)))
            self.next_sample = (np.floor((t + 1e-12) / self.period) + 1) * self.period
        while self.pending and self.pending[0][0] <= t + 1e-12:
            self.held = self.pending.popleft()[1]
        return self.held

    def read(self, t: float, force: np.ndarray) -> np.ndarray:
        """(N,) force [N] as the host decodes it at time `t`."""
        return self.fsr.decode(self.update(t, force))
