"""Compiled kernels of `potential.FastPotential`: the trunk's layers forward and backward, and
the few-row pass over a TDM potential's wide head (the strategy filter's candidates and the
modulation's one state per control tick).

The head (N taxels x hidden) is stored as contiguous panels of PANEL taxels; a forward pass reads
each panel once for every input row and keeps the head's sigmoids, a backward pass turns the
chosen row's sigmoids into the normal.
"""
from __future__ import annotations

import numba
import numpy as np
from numba import typed

_FAST = {"reassoc", "contract", "nsz", "arcp"}  # reorder sums, keep inf and NaN semantics


@numba.njit(cache=True, nogil=True, fastmath=_FAST)
def _mlp_forward(s, a, mean, std, Ws, bs, kinds):
    """Activations (input first) of the layers `Ws, bs` with `kinds` (0 linear, 1 ReLU, 2 tanh)
    on the normalised input `([s, a] - mean) / std`, float32."""
    B, ds = s.shape
    x = np.empty((B, ds + a.shape[1]), np.float32)
    for r in range(B):
        for j in range(x.shape[1]):
            x[r, j] = ((s[r, j] if j < ds else a[r, j - ds]) - mean[j]) / std[j]
    acts = typed.List()
    acts.append(x)
    for k in range(len(Ws)):
        W, bias = Ws[k], bs[k]
        y = np.empty((B, W.shape[0]), np.float32)
        for r in range(B):
            for o in range(W.shape[0]):
                acc = bias[o]
                for i in range(W.shape[1]):
                    acc += W[o, i] * x[r, i]
                if kinds[k] == 1:
                    acc = max(acc, np.float32(0.0))
                elif kinds[k] == 2:
                    acc = np.tanh(acc)
                y[r, o] = acc
        acts.append(y)
        x = y
    return acts


@numba.njit(cache=True, nogil=True, fastmath=_FAST)
def _mlp_backward(g, std, Ws, acts, kinds):
    """The gradient `g` at the last layer's output taken back to the (unnormalised) input."""
    B = g.shape[0]
    for k in range(len(Ws) - 1, -1, -1):
        W, y = Ws[k], acts[k + 1]
        if kinds[k] == 1:
            g = np.where(y > 0, g, np.float32(0.0))
        elif kinds[k] == 2:
            g = g * (np.float32(1.0) - y * y)
        out = np.zeros((B, W.shape[1]), np.float32)
        for r in range(B):
            for o in range(W.shape[0]):
                go = g[r, o]
                for i in range(W.shape[1]):
                    out[r, i] += go * W[o, i]
        g = out
    return g / std


FUSED_ROWS = 8
"""Up to this many rows the TDM potential runs compiled, one pass over the head forward
(`_tdm_forward`) and one backward (`_tdm_backward`); more rows (batches for training and
experiments) go through BLAS."""


@numba.njit(cache=True, nogil=True)
def _find_row(ms, ma, s, a):
    """The row k with ms[k or 0] == s and ma[k] == a (exactly), or -1."""
    for k in range(ma.shape[0]):
        row = ms[k if ms.shape[0] > 1 else 0]
        same = len(row) == len(s) and ma.shape[1] == len(a)
        for j in range(len(s)):
            if not same or row[j] != s[j]:
                same = False
                break
        for j in range(len(a)):
            if not same or ma[k, j] != a[j]:
                same = False
                break
        if same:
            return k
    return -1


PANEL = 64
"""Head rows per panel of the fused pass (`panels`): one panel's weights (PANEL x hidden float32,
32 KB at 128 hidden) stay in L1 cache while every input row uses them."""


def panels(W: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The head (N, H) as contiguous panels (P, H, PANEL), `out[p, j, i] = W[p * PANEL + i, j]`,
    and the bias (P, PANEL); the last panel padded with zeros (its length is taken from N)."""
    N, H = W.shape
    P = -(-N // PANEL)
    Wp = np.zeros((P * PANEL, H), np.float32)
    Wp[:N] = W
    bp = np.zeros(P * PANEL, np.float32)
    bp[:N] = b
    return np.ascontiguousarray(Wp.reshape(P, PANEL, H).transpose(0, 2, 1)), bp.reshape(P, PANEL)


@numba.njit(cache=True, nogil=True, fastmath=_FAST)
def _tdm_forward(s, a, mean, std, Ws, bs, kinds, Wp, bp, N):
    """log p(not D) (B,) and sigmoid(z) (B, P * PANEL) of a TDM potential's head logits z. The
    head is read once, one panel (`panels`) at a time, for every input row: the panel's logits
    (`z += W[:, j] h_j`, vertical SIMD), exp(-|z|) in float64 (`_exp_neg`; numpy's float32 exp
    agrees to an ulp) and the softplus sums exactly as `_head_sums` (one log per 64 factors)."""
    acts = _mlp_forward(s, a, mean, std, Ws, bs, kinds)
    h = acts[len(acts) - 1]
    B, P, H = h.shape[0], Wp.shape[0], Wp.shape[1]
    total = np.zeros(B)
    sig = np.zeros((B, P * PANEL), np.float32)
    z = np.empty(PANEL, np.float32)
    x = np.empty(PANEL)
    for p in range(P):
        Wk = Wp[p]
        m = min(PANEL, N - p * PANEL)
        for r in range(B):
            hr = h[r]
            for i in range(PANEL):
                z[i] = bp[p, i]
            for j in range(H):
                hj = hr[j]
                for i in range(PANEL):
                    z[i] += Wk[j, i] * hj
            for i in range(PANEL):
                x[i] = -abs(np.float64(z[i]))
            _exp_neg(x, PANEL)
            prod = 1.0
            for i in range(m):
                e = np.float32(x[i])
                total[r] += max(np.float64(z[i]), 0.0)
                prod *= 1.0 + np.float64(e)
                sig[r, p * PANEL + i] = (np.float32(1.0) if z[i] >= 0 else e) / (np.float32(1.0) + e)
            total[r] += np.log(prod)
    return -total, sig


@numba.njit(cache=True, nogil=True, fastmath=_FAST)
def _tdm_backward(s, a, mean, std, Ws, bs, kinds, Wp, sig, log_safe):
    """df/ds (B, ds) from `_tdm_forward`'s sigmoids: `(1 - f) sum_i sigmoid(z_i) W_i` (one
    more read of the head) taken back through the trunk (its forward recomputed: small)."""
    acts = _mlp_forward(s, a, mean, std, Ws, bs, kinds)
    B, P, H = sig.shape[0], Wp.shape[0], Wp.shape[1]
    g = np.zeros((B, H), np.float32)
    for p in range(P):
        Wk = Wp[p]
        for r in range(B):
            sg = sig[r, p * PANEL:(p + 1) * PANEL]
            for j in range(H):
                acc = np.float32(0.0)
                for i in range(PANEL):
                    acc += Wk[j, i] * sg[i]
                g[r, j] += acc
    for r in range(B):
        scale = np.float32(np.exp(log_safe[r]))  # df/dz_i = (1 - f) sigmoid(z_i)
        for j in range(H):
            g[r, j] *= scale
    return _mlp_backward(g, std, Ws, acts, kinds)[:, :s.shape[1]].astype(np.float64)


@numba.njit(cache=True, nogil=True, fastmath=_FAST)
def _exp_neg(x, m):
    """x[:m] <- exp(x[:m]) for x <= 0 (float64; under -700 it is 0 to float32 anyway): 2^k exp(r)
    with r = x - k ln2 in [-ln2/2, ln2/2] (two-part ln2) and a degree-10 Taylor polynomial
    (relative error < 1e-12), 2^k from the exponent bits; a loop the compiler vectorises."""
    bits = np.empty(m, np.int64)
    for i in range(m):
        v = max(x[i], -700.0)
        k = np.floor(v * 1.4426950408889634 + 0.5)
        r = (v - k * 0.693145751953125) - k * 1.4286068203094173e-06
        p = 1.0 + r * (1.0 + r * (0.5 + r * (1 / 6 + r * (1 / 24 + r * (1 / 120 + r * (1 / 720 + r * (
            1 / 5040 + r * (1 / 40320 + r * (1 / 362880 + r / 3628800)))))))))
        x[i] = p
        bits[i] = (np.int64(k) + 1023) << 52
    scale = bits.view(np.float64)
    for i in range(m):
        x[i] *= scale[i]
