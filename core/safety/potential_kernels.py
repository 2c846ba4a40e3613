"""Compiled kernels of `potential.FastPotential`: the trunk's layers forward and backward, and
the few-row pass over a TDM potential's wide head (the strategy filter's candidates and the
modulation's one state per control tick).

The head is stored as columns (hidden x N taxels, zero-padded to whole blocks of BLOCK taxels)
and read a block at a time: a forward pass computes the block's logits for every input row and
keeps its sigmoids, a backward pass turns the chosen row's sigmoids into the normal, and a fused
pass does both in one read of the head (a state whose candidates were not scored before). Only
the columns of hidden units that are not 0 for a row are read (after the trunk's last ReLU,
about half): exact, and half the work.
"""
from __future__ import annotations

import numba
import numpy as np
from numba import typed

_FAST = {"reassoc", "contract", "nsz", "arcp"}  # reorder sums, keep inf and NaN semantics
# The kernels use numpy's error model: a division by 0 gives inf or NaN (which the safety stack
# treats as a bad input) instead of raising, and divisions vectorise.


@numba.njit(cache=True, nogil=True, fastmath=_FAST, error_model="numpy")
def _mlp_forward(s, a, mean, std, Ws, bs, kinds):
    """Activations (input first) of the layers `Ws, bs` with `kinds` (0 linear, 1 ReLU, 2 tanh)
    on the normalised input `([s, a] - mean) / std`, float32; one row per action (one state row:
    the same state for every action)."""
    B, ds = a.shape[0], s.shape[1]
    x = np.empty((B, ds + a.shape[1]), np.float32)
    for r in range(B):
        sr = r if s.shape[0] > 1 else 0
        for j in range(x.shape[1]):
            x[r, j] = ((s[sr, j] if j < ds else a[r, j - ds]) - mean[j]) / std[j]
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


@numba.njit(cache=True, nogil=True, fastmath=_FAST, error_model="numpy")
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


BLOCK = 256
"""Taxels per block of the few-row passes: a block's logits (one float32 row per input row) stay
in L1 cache and its weights (hidden x BLOCK, 128 KB at 128 hidden) in L2 while every input row,
and then the gradient, use them."""


def columns(W: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The head W (N, H) as float32 columns (H, n), one contiguous row of taxel weights per hidden
    unit, and the bias (n,), zero-padded to whole blocks, n >= N (the passes take the real N)."""
    N, H = W.shape
    n = -(-N // BLOCK) * BLOCK
    Wc = np.zeros((H, n), np.float32)
    Wc[:, :N] = W.T
    bp = np.zeros(n, np.float32)
    bp[:N] = b
    return Wc, bp


@numba.njit(cache=True, nogil=True, fastmath=_FAST, error_model="numpy")
def _tdm_forward(s, a, mean, std, Ws, bs, kinds, Wc, b, N):
    """log p(not D) (B,) and sigmoid(z) (B, padded N) of a TDM potential's head logits z: one
    read of the head for every input row."""
    acts = _mlp_forward(s, a, mean, std, Ws, bs, kinds)
    log_safe, sig, _ = _head_pass(acts[len(Ws)], kinds, Wc, b, N, True, False)
    return log_safe, sig


@numba.njit(cache=True, nogil=True, fastmath=_FAST, error_model="numpy")
def _tdm_backward(s, a, mean, std, Ws, bs, kinds, Wc, sig, log_safe):
    """df/ds (B, ds) from `_tdm_forward`'s sigmoids: one more read of the head (its columns
    that the rows use)."""
    acts = _mlp_forward(s, a, mean, std, Ws, bs, kinds)
    h = acts[len(Ws)]
    idx, cnt = _used(h, kinds)
    g = np.zeros(h.shape, np.float32)
    for i0 in range(0, Wc.shape[1], BLOCK):
        for r in range(h.shape[0]):
            _dot_columns(g[r], sig[r, i0:i0 + BLOCK], Wc, idx[r], cnt[r], i0)
    return _normal_from(g, log_safe, std, Ws, acts, kinds, s.shape[1])


@numba.njit(cache=True, nogil=True, fastmath=_FAST, error_model="numpy")
def _tdm_fused(s, a, mean, std, Ws, bs, kinds, Wc, b, N):
    """log p(not D) (B,) and df/ds (B, ds) in one read of the head: each block's sigmoids turn
    into its share of the gradient while its weights are still in cache."""
    acts = _mlp_forward(s, a, mean, std, Ws, bs, kinds)
    log_safe, _, g = _head_pass(acts[len(Ws)], kinds, Wc, b, N, False, True)
    return log_safe, _normal_from(g, log_safe, std, Ws, acts, kinds, s.shape[1])


@numba.njit(cache=True, nogil=True, fastmath=_FAST, error_model="numpy")
def _normal_from(g, log_safe, std, Ws, acts, kinds, ds):
    """df/ds from g = sum_i sigmoid(z_i) W_i at the head's input: df/dz_i = (1 - f) sigmoid(z_i)."""
    for r in range(g.shape[0]):
        scale = np.float32(np.exp(log_safe[r]))
        for j in range(g.shape[1]):
            g[r, j] *= scale
    return _mlp_backward(g, std, Ws, acts, kinds)[:, :ds].astype(np.float64)


@numba.njit(cache=True, nogil=True)
def _used(h, kinds):
    """Per row of the head's input h (B, H), the hidden units whose columns the passes read
    (idx (B, H), cnt (B,)): where the trunk ends in a ReLU, those not 0 (about half; a 0 adds
    nothing to the logits and the ReLU zeroes its gradient, so skipping it is exact), else all."""
    B, H = h.shape
    relu = len(kinds) > 0 and kinds[len(kinds) - 1] == 1
    idx = np.empty((B, H), np.int64)
    cnt = np.zeros(B, np.int64)
    for r in range(B):
        for j in range(H):
            if h[r, j] != 0 or not relu:
                idx[r, cnt[r]] = j
                cnt[r] += 1
    return idx, cnt


@numba.njit(cache=True, nogil=True, fastmath=_FAST, error_model="numpy")
def _head_pass(h, kinds, Wc, b, N, keep, grad):
    """One pass over the head's columns for the rows of h (B, H), the output of layers `kinds`:
    log p(not D) (B,), with `keep` the sigmoids (B, padded N), with `grad`
    g = sum_i sigmoid(z_i) W_i (B, H) (0 where `_used` skips a unit)."""
    B, H = h.shape
    n = Wc.shape[1]
    idx, cnt = _used(h, kinds)
    total = np.zeros(B)
    sig = np.empty((B, n if keep else 0), np.float32)  # every block written below
    g = np.zeros((B, H if grad else 0), np.float32)
    z = np.empty((B, BLOCK), np.float32)
    e = np.empty(BLOCK, np.float32)
    for i0 in range(0, n, BLOCK):
        for r in range(B):
            zr = z[r]
            for i in range(BLOCK):
                zr[i] = b[i0 + i]
            _axpy_columns(zr, h[r], Wc, idx[r], cnt[r], i0)
        _block_softplus(total, z, e, min(BLOCK, N - i0))
        for r in range(B):
            if keep:
                sig[r, i0:i0 + BLOCK] = z[r]
            if grad:
                _dot_columns(g[r], z[r], Wc, idx[r], cnt[r], i0)
    return -total, sig, g


@numba.njit(cache=True, nogil=True, fastmath=_FAST, error_model="numpy")
def _axpy_columns(z, h, Wc, idx, cnt, i0):
    """z (BLOCK,) += sum_c h[idx[c]] Wc[idx[c], i0:i0 + BLOCK] over c < cnt, four columns at a
    time (one load and store of z per four products; the compiler vectorises over taxels)."""
    c = 0
    while c + 4 <= cnt:
        j0, j1, j2, j3 = idx[c], idx[c + 1], idx[c + 2], idx[c + 3]
        h0, h1, h2, h3 = h[j0], h[j1], h[j2], h[j3]
        w0, w1, w2, w3 = Wc[j0, i0:i0 + BLOCK], Wc[j1, i0:i0 + BLOCK], Wc[j2, i0:i0 + BLOCK], Wc[j3, i0:i0 + BLOCK]
        for i in range(BLOCK):
            z[i] += h0 * w0[i] + h1 * w1[i] + h2 * w2[i] + h3 * w3[i]
        c += 4
    for c in range(c, cnt):
        hj, w = h[idx[c]], Wc[idx[c], i0:i0 + BLOCK]
        for i in range(BLOCK):
            z[i] += hj * w[i]


@numba.njit(cache=True, nogil=True, fastmath=_FAST, error_model="numpy")
def _dot_columns(g, sig, Wc, idx, cnt, i0):
    """g[idx[c]] += sig . Wc[idx[c], i0:i0 + BLOCK] over c < cnt, four columns at a time."""
    c = 0
    while c + 4 <= cnt:
        j0, j1, j2, j3 = idx[c], idx[c + 1], idx[c + 2], idx[c + 3]
        w0, w1, w2, w3 = Wc[j0, i0:i0 + BLOCK], Wc[j1, i0:i0 + BLOCK], Wc[j2, i0:i0 + BLOCK], Wc[j3, i0:i0 + BLOCK]
        a0 = a1 = a2 = a3 = np.float32(0.0)
        for i in range(BLOCK):
            si = sig[i]
            a0 += w0[i] * si
            a1 += w1[i] * si
            a2 += w2[i] * si
            a3 += w3[i] * si
        g[j0] += a0
        g[j1] += a1
        g[j2] += a2
        g[j3] += a3
        c += 4
    for c in range(c, cnt):
        w = Wc[idx[c], i0:i0 + BLOCK]
        acc = np.float32(0.0)
        for i in range(BLOCK):
            acc += w[i] * sig[i]
        g[idx[c]] += acc


@numba.njit(cache=True, nogil=True, fastmath=_FAST, error_model="numpy")
def _block_softplus(total, z, e, m):
    """total[r] += sum_i softplus(z[r, i]) over the block's m real taxels, and z <- sigmoid(z)
    (0 past m). softplus(z) = max(z, 0) + log(1 + e) with e = exp(-|z|) (`_exp_neg32`, float32 as
    the logits are); no log1p: the logs of 64 factors (1 + e) in (1, 2] are taken as one log of
    their float64 product (float32 1 + e would drop every e under 6e-8)."""
    one = np.float32(1.0)
    for r in range(z.shape[0]):
        zr = z[r]
        for i in range(BLOCK):
            e[i] = -abs(zr[i])
        _exp_neg32(e)
        lin = 0.0
        for i in range(m):
            lin += max(np.float64(zr[i]), 0.0)
        total[r] += lin
        for start in range(0, m, 64):
            prod = 1.0
            for i in range(start, min(start + 64, m)):
                prod *= 1.0 + np.float64(e[i])
            total[r] += np.log(prod)
        for i in range(BLOCK):
            ei = e[i]
            zr[i] = (ei if zr[i] < 0 else one) / (one + ei)
        for i in range(m, BLOCK):
            zr[i] = np.float32(0.0)


_LOG2E, _LN2_HI, _LN2_LO = np.float32(1.44269504), np.float32(0.693359375), np.float32(-2.12194440e-4)
_P = tuple(np.float32(c) for c in (1.9875691500e-4, 1.3981999507e-3, 8.3334519073e-3, 4.1665795894e-2,
                                   1.6666665459e-1, 5.0000001201e-1))


@numba.njit(cache=True, nogil=True, fastmath=_FAST, error_model="numpy")
def _exp_neg32(x):
    """x <- exp(x) for float32 x <= 0 (Cephes' expf: 2^k exp(r), r = x - k ln2 in [-ln2/2, ln2/2]
    with a two-part ln2 and a degree-6 polynomial, relative error about 1e-7; 2^k from the
    exponent bits; 0 under -87, where float32 has no normal numbers left); a loop the compiler
    vectorises."""
    bits = np.empty(x.shape[0], np.int32)
    for i in range(x.shape[0]):
        v = max(x[i], np.float32(-87.0))
        under = x[i] < np.float32(-87.0)
        k = np.floor(v * _LOG2E + np.float32(0.5))
        r = (v - k * _LN2_HI) - k * _LN2_LO
        p = _P[0]
        p = p * r + _P[1]
        p = p * r + _P[2]
        p = p * r + _P[3]
        p = p * r + _P[4]
        p = p * r + _P[5]
        x[i] = p * r * r + r + np.float32(1.0)
        bits[i] = np.int32(0) if under else (np.int32(k) + np.int32(127)) << 23
    x *= bits.view(np.float32)
