"""In-plane strain of a wrapped FPC module: how far its pads' distances on the surface are from the
flat circuit's.

A flexible circuit bends but does not stretch: wrapped without strain, every pair of neighbouring
pads keeps its flat distance measured along the surface. For each pair of grid neighbours (rows,
columns and both diagonals) the surface length is the arc of the normal section through the two
pads: the chord `c`, bent by the normal curvature along it, `k = (n_b - n_a) . (p_b - p_a) / c^2`
(exact on a circle, and on a cylinder's helix for the diagonals), gives `2 asin(k c / 2) / k`.
Bending alone therefore reads ~0 (1e-6 on a 25 mm cylinder); strain is `arc / flat - 1`, positive
where the circuit would have to stretch, negative where it would have to crowd.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np


def grid_pairs(row: np.ndarray, col: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs (a, b) of grid neighbours: along rows, columns and both diagonals (template order)."""
    return _pairs(np.asarray(row, np.intp).tobytes(), np.asarray(col, np.intp).tobytes())


@lru_cache(maxsize=256)
def _pairs(row_bytes: bytes, col_bytes: bytes) -> tuple[np.ndarray, np.ndarray]:
    row, col = np.frombuffer(row_bytes, np.intp), np.frombuffer(col_bytes, np.intp)
    if not len(row):
        return np.zeros(0, np.intp), np.zeros(0, np.intp)
    grid = np.full((row.max() + 3, col.max() + 3), -1, np.intp)  # a border of -1 around the cells
    grid[row + 1, col + 1] = np.arange(len(row))
    a, b = [], []
    for dr, dc in ((0, 1), (1, 0), (1, 1), (1, -1)):
        j = grid[row + 1 + dr, col + 1 + dc]
        a.append(np.flatnonzero(j >= 0)), b.append(j[j >= 0])
    return np.concatenate(a), np.concatenate(b)


def surface_length(pa: np.ndarray, pb: np.ndarray, na: np.ndarray, nb: np.ndarray) -> np.ndarray:
    """(m,) length along the surface between points pa, pb (m,3) with unit normals na, nb: the
    normal-section arc over the chord (see the module docstring)."""
    d = pb - pa
    c2 = np.sum(d * d, axis=1)
    c = np.sqrt(c2)
    with np.errstate(divide="ignore", invalid="ignore"):
        k = np.abs(np.sum((nb - na) * d, axis=1)) / np.maximum(c2, 1e-300)
        s = np.clip(k * c / 2, 0.0, 1.0)
        arc = np.where(k * c > 1e-9, 2 * np.arcsin(s) / np.maximum(k, 1e-300), c)
    return arc


@dataclass(frozen=True)
class Strain:
    """A placed module's in-plane strain: per neighbour pair (a, b) its signed strain; `worst` is
    the pair of the largest magnitude (-1 without pairs)."""

    a: np.ndarray
    b: np.ndarray
    strain: np.ndarray

    @property
    def max(self) -> float:
        return float(np.abs(self.strain).max()) if len(self.strain) else 0.0

    @property
    def worst(self) -> int:
        return int(np.argmax(np.abs(self.strain))) if len(self.strain) else -1

    def per_pad(self, n: int) -> np.ndarray:
        """(n,) the largest strain magnitude of the pairs each pad is in."""
        out = np.zeros(n)
        np.maximum.at(out, self.a, np.abs(self.strain))
        np.maximum.at(out, self.b, np.abs(self.strain))
        return out


def module_strain(uv: np.ndarray, row: np.ndarray, col: np.ndarray, positions: np.ndarray,
                  normals: np.ndarray) -> Strain:
    """The strain of a module whose flat pads `uv` (n,2) (grid `row`, `col`) sit at `positions`
    (n,3) with unit `normals` (n,3) on the surface."""
    a, b = grid_pairs(row, col)
    flat = np.linalg.norm(uv[a] - uv[b], axis=1)
    arc = surface_length(positions[a], positions[b], normals[a], normals[b])
    return Strain(a, b, arc / np.maximum(flat, 1e-300) - 1.0)
