"""Seeds and confidence intervals for the experiments' claims (maze, tracking).

`parse_seeds("10-19")` / `parse_seeds("11,12,13")` name seeds (never a count, so held-out seeds can be
named). `mean_ci` is the 95% Student-t interval of a mean over seeds; `diff_ci` Welch's 95% interval of
a difference of two means (independent runs); `ratio_ci` a seeded percentile bootstrap of a ratio of
means over paired seeds. `compare` turns a difference interval into a verdict: "lower", "higher" or
"not resolved" (the interval contains 0). `welch_p` and `paired_p` are the two-sided p-values of those
differences, `holm` adjusts a family of p-values (Holm's step-down, family-wise error), `logrank_p` compares
times to an event where some runs never reach it (censored), with its sign.
"""
from __future__ import annotations

import numpy as np
from scipy import stats


def parse_seeds(text) -> list[int]:
    """Seeds from "10-19" (inclusive), "11,12,13", "3" (seed 3) or a list of those; sorted, no repeats."""
    parts = text if isinstance(text, (list, tuple)) else [text]
    out = set()
    for part in parts:
        for item in str(part).replace(" ", ",").split(","):
            if not item:
                continue
            lo, sep, hi = item.partition("-")
            try:
                a, b = (int(lo), int(hi)) if sep else (int(item), int(item))
            except ValueError:
                raise ValueError(f"seeds: cannot read {item!r}; name seeds as a range (10-19) or a list (11,12,13)") from None
            if a < 0 or b < a:
                raise ValueError(f"seeds: {item!r} is not a range of non-negative seeds; write it low-high, e.g. 10-19")
            out.update(range(a, b + 1))
    if not out:
        raise ValueError("seeds: none given; name seeds as a range (10-19) or a list (11,12,13)")
    return sorted(out)


def mean_ci(x, level: float = 0.95) -> tuple[float, list[float]]:
    """Mean and its Student-t interval; one value gives an interval of that value alone."""
    x = np.asarray(x, float)
    m = float(x.mean())
    if len(x) < 2 or np.all(x == x[0]):
        return m, [m, m]
    h = float(stats.t.ppf(0.5 + level / 2, len(x) - 1) * x.std(ddof=1) / np.sqrt(len(x)))
    return m, [m - h, m + h]


def diff_ci(a, b, level: float = 0.95) -> tuple[float, list[float]]:
    """mean(b) - mean(a) and Welch's interval (independent samples, unequal variances)."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    d = float(b.mean() - a.mean())
    va, vb = (a.var(ddof=1) / len(a) if len(a) > 1 else 0.0), (b.var(ddof=1) / len(b) if len(b) > 1 else 0.0)
    se = np.sqrt(va + vb)
    if se == 0:
        return d, [d, d]
    dof = (va + vb) ** 2 / ((va ** 2 / (len(a) - 1) if len(a) > 1 else 0) + (vb ** 2 / (len(b) - 1) if len(b) > 1 else 0))
    h = float(stats.t.ppf(0.5 + level / 2, dof) * se)
    return d, [d - h, d + h]


def compare(interval) -> str:
    """"lower" when the whole interval of (other - this) is above 0 (this is lower), "higher" when it is
    below 0, else "not resolved"."""
    lo, hi = interval
    return "lower" if lo > 0 else "higher" if hi < 0 else "not resolved"


def ratio_ci(num, den, level: float = 0.95, n: int = 2000, seed: int = 0) -> tuple[float, list[float]]:
    """mean(num) / mean(den) over paired seeds and its percentile bootstrap interval (seeds resampled)."""
    num, den = np.asarray(num, float), np.asarray(den, float)
    r = float(num.mean() / den.mean()) if den.mean() > 0 else float("inf")
    if len(num) < 2:
        return r, [r, r]
    idx = np.random.default_rng(seed).integers(len(num), size=(n, len(num)))
    d = den[idx].mean(1)
    boot = np.where(d > 0, num[idx].mean(1) / np.where(d > 0, d, 1), np.inf)
    lo, hi = np.quantile(boot, [0.5 - level / 2, 0.5 + level / 2])
    return r, [float(lo), float(hi)]


def _degenerate_p(d: float) -> float:
    """The p-value of a difference with no spread: 0 when it is not 0 (every seed agrees), else 1."""
    return 0.0 if d != 0 else 1.0


def welch_p(a, b) -> float:
    """Two-sided p-value of mean(b) - mean(a) by Welch's t-test (`diff_ci`'s test)."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    if (len(a) < 2 or np.ptp(a) == 0) and (len(b) < 2 or np.ptp(b) == 0):
        return _degenerate_p(float(b.mean() - a.mean()))
    if len(a) < 2 or len(b) < 2:
        return 1.0
    return float(stats.ttest_ind(b, a, equal_var=False).pvalue)


def paired_p(d) -> float:
    """Two-sided p-value of mean(d) = 0 for paired differences d (Student's t, `mean_ci`'s test)."""
    d = np.asarray(d, float)
    if len(d) < 2 or np.ptp(d) == 0:
        return _degenerate_p(float(d.mean())) if len(d) >= 2 else 1.0
    return float(stats.ttest_1samp(d, 0.0).pvalue)


def holm(p) -> list[float]:
    """Holm's step-down adjusted p-values (Holm 1979): the k-th smallest times (m - k + 1), made monotone, at most 1.
    Rejecting where the adjusted p < alpha keeps the family-wise error at alpha."""
    p = np.asarray(p, float)
    order = np.argsort(p, kind="stable")
    adj = np.minimum(1.0, np.maximum.accumulate(p[order] * (len(p) - np.arange(len(p)))))
    out = np.empty_like(adj)
    out[order] = adj
    return out.tolist()


def logrank_p(first, second, horizon: int) -> tuple[float, float]:
    """Log-rank test of two samples of event times (`horizon` + 1 or more: never, censored at `horizon`):
    (statistic, two-sided p); the statistic is positive when `first` reaches the event sooner."""
    def data(x):
        x = np.asarray(x, float)
        return stats.CensoredData(uncensored=x[x <= horizon], right=np.full(int((x > horizon).sum()), float(horizon)))

    if np.all(np.asarray(first) > horizon) and np.all(np.asarray(second) > horizon):
        return 0.0, 1.0  # neither ever reaches it: nothing to compare
    r = stats.logrank(data(first), data(second))
    return float(r.statistic), float(r.pvalue)
