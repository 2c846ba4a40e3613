"""The loop's per-tick figures in bounded memory: exact while short, within REL of the exact rank after."""
import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from skinsafe.core.runtime.tick_figures import HI, LO, REL, Figure


def test_a_short_run_is_kept_exactly():
    x = np.random.default_rng(0).lognormal(-7, 0.5, 5000)
    f = Figure(keep=5000)
    for v in x:
        f.add(float(v))
    assert np.array_equal(f.exact(), x) and f.max == x.max()
    for p in (50, 99, 99.9):
        assert f.percentile(p) == np.percentile(x, p)


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 10_000), st.floats(-9, 1), st.floats(0.01, 2), st.sampled_from([1, 50, 99, 99.9, 100]))
def test_a_long_run_keeps_percentiles_within_rel_of_the_sample_of_that_rank(seed, mu, sigma, p):
    x = np.random.default_rng(seed).lognormal(mu, sigma, 3000)
    x = x[(x > LO) & (x < HI)]  # in the histogram's range
    f = Figure(keep=100)
    for v in x:
        f.add(float(v))
    assert f.exact() is None and f.n == len(x) and f.max == x.max()
    ranked = np.sort(x)[max(math.ceil(p / 100 * len(x)), 1) - 1]  # the sample of that rank
    assert abs(f.percentile(p) / ranked - 1) <= REL


def test_samples_out_of_range_are_counted_without_an_error():
    f = Figure(keep=2)
    for v in (0.0, -1.0, math.nan, math.inf, 1e-3):
        f.add(v)
    assert f.n == 5 and f.max == math.inf and f.exact() is None
    assert f.percentile(100) == math.inf and f.percentile(20) < 1.001e-6
    assert math.isnan(Figure().percentile(50))
