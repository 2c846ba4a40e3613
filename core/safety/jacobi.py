"""One-sided (Hestenes) Jacobi rotations: the SVD kernel of the small blocks the retraction and the
prioritised QP decompose every tick (3 x 6, 6 x 6). No LAPACK call: about 1 us per block where a
`gesdd` call with its workspace takes 10-15 us."""
from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, nogil=True)
def orthogonalise_columns(B, W) -> None:
    """Rotate pairs of B's columns (in place) until they are mutually orthogonal, applying every
    rotation to W's columns too: from W = I this leaves `B_in W = B_out`, so W holds the right singular
    vectors and B's column norms are the singular values. A column numerically zero (below 1e-30 of
    B's squared norm) is never rotated."""
    m, d = B.shape
    tiny = 1e-30 * np.sum(B * B)
    for _ in range(60):
        rotated = False
        for p in range(d - 1):
            for q in range(p + 1, d):
                alpha = beta = gamma = 0.0
                for i in range(m):
                    alpha += B[i, p] * B[i, p]
                    beta += B[i, q] * B[i, q]
                    gamma += B[i, p] * B[i, q]
                if alpha <= tiny or beta <= tiny or abs(gamma) <= 1e-15 * np.sqrt(alpha) * np.sqrt(beta):
                    continue
                rotated = True
                zeta = (beta - alpha) / (2.0 * gamma)
                t = (1.0 if zeta >= 0 else -1.0) / (abs(zeta) + np.sqrt(1.0 + zeta * zeta))
                c = 1.0 / np.sqrt(1.0 + t * t)
                s = c * t
                for i in range(m):
                    bp, bq = B[i, p], B[i, q]
                    B[i, p], B[i, q] = c * bp - s * bq, s * bp + c * bq
                for i in range(W.shape[0]):
                    wp, wq = W[i, p], W[i, q]
                    W[i, p], W[i, q] = c * wp - s * wq, s * wp + c * wq
        if not rotated:
            break
