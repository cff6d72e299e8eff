"""The held-out measurement on a seeded sample of texels: which texels (`measured_texels`) and
the report's distribution-free intervals of the median and p5 (`quantile_ci`)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from scipy.stats import binom

from schemas.settings import BakeSettings
from texelbake.cpm.assemble import heldout_stats, quantile_ci
from texelbake.cpm.dense import heldout_snr
from texelbake.cpm.truth_sample import measured_texels


def _src(n=32, want=40, seed=0, fill=0.6, rng=None):
    """FitInputs' settings and sample rows/cols of an n x n atlas, `fill` of it occupied."""
    rng = rng or np.random.default_rng(1)
    occ = np.flatnonzero(rng.random(n * n) < fill)
    tex = np.repeat(occ, 3)  # three samples per occupied texel
    settings = BakeSettings(atlas_resolution=n, heldout_texels=want, seed=seed)
    return SimpleNamespace(settings=settings, geo={"sample_row": tex // n,
                                                   "sample_col": tex % n}), occ


def test_measured_texels_is_a_fixed_size_seeded_sample_any_chunk_agrees():
    src, occ = _src()
    m = measured_texels(src, 0, occ)
    assert m.dtype == bool and m.shape == occ.shape and m.sum() == 40
    # the same texels whichever chunk (tile) asks, in any order
    perm = np.random.default_rng(5).permutation(occ.size)
    np.testing.assert_array_equal(measured_texels(src, 0, occ[perm]), m[perm])
    np.testing.assert_array_equal(measured_texels(src, 0, occ[:50]), m[:50])
    # another seed or level picks other texels; a coarse level with few texels measures all
    other, _ = _src(seed=1)
    assert not np.array_equal(measured_texels(other, 0, occ), m)
    n2 = 32 >> 3
    coarse = np.arange(n2 * n2)
    assert measured_texels(src, 3, coarse).all()
    zero, _ = _src(want=0)
    assert measured_texels(zero, 0, occ).all()


def test_an_unmeasured_texel_has_no_snr():
    ref = np.ones((2, 3, 3))
    avis = np.full(3, np.nan)
    assert np.isnan(heldout_snr(ref, ref, avis, 1.0))
    assert heldout_snr(ref, ref, np.ones(3), 1.0) == np.inf


@pytest.mark.parametrize("q", [0.5, 0.05])
def test_quantile_interval_covers_at_its_confidence(q):
    # brute force: 2,000 samples of 256 from a skewed continuous law with a known quantile;
    # the interval must cover it in >= 95 % of them (exact binomial coverage here, computed
    # from the ranks: the simulation's 2-sigma band is +-1 %)
    rng = np.random.default_rng(7)
    true_q = -np.log(1 - q)  # Exp(1)
    n, trials = 256, 2000
    hits = 0
    for _ in range(trials):  # a loop over independent trials
        lo, hi = quantile_ci(rng.exponential(size=n), q, 10**9)
        hits += lo <= true_q <= hi
    a = 0.025
    r, s = int(binom.ppf(a, n, q)), int(binom.ppf(1 - a, n, q)) + 1
    exact = binom.cdf(s - 1, n, q) - binom.cdf(r - 1, n, q)
    assert exact >= 0.95
    assert abs(hits / trials - exact) < 0.015, (hits / trials, exact)


def test_interval_edges():
    x = np.arange(10.0)
    assert quantile_ci(x, 0.5, 10) == (4.5, 4.5)  # the whole population: no estimate
    lo, hi = quantile_ci(x, 0.05, 1000)  # 10 values cannot bound a 5th percentile below
    assert lo == -np.inf and np.isfinite(hi)
    st = heldout_stats(np.r_[np.arange(50.0), np.nan, np.inf], 400)
    assert st["n"] == 51 and st["population"] == 400
    assert st["p50_ci"][0] <= st["p50"] <= st["p50_ci"][1]
