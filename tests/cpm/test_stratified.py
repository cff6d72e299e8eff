"""A coarse texel's stratified sample of its dense samples (`level.stratified_samples`): at most
k per texel, the weighted sum an unbiased estimate of the texel's sum (against the brute-force
sum over every sample), every sample at its own area when the texel has no more than k, and the
draws a function of (seed, level, texel) alone."""

from __future__ import annotations

import numpy as np
import pytest

from texelbake.cpm.level import stratified_samples, texel_ids
from texelbake.geometry.texels import morton

N = 8  # atlas side


def _geo(m=3000, seed=0, index=True):
    """m samples on an N x N atlas (uneven counts per texel, uneven areas) with the geometry
    stage's Z-order index (`sample_zorder`, `texel_zoffsets`) as `build._zorder_spooled` lays
    it out: ids ordered by their finest texel's Morton code, ascending within a texel."""
    rng = np.random.default_rng(seed)
    row = np.minimum((rng.random(m) ** 2 * N).astype(np.int64), N - 1)  # crowded low rows
    col = rng.integers(0, N, m)
    geo = {"sample_row": row, "sample_col": col, "sample_area": rng.uniform(0.5, 2.0, m)}
    if index:
        code = morton(row, col)
        geo["sample_zorder"] = np.argsort(code, kind="stable").astype(np.int64)
        geo["texel_zoffsets"] = np.r_[0, np.cumsum(np.bincount(code, minlength=N * N))]
    return geo


def _truth(geo, level, texels, value):
    tid = texel_ids(geo, N, level, None)
    pos = np.searchsorted(texels, tid)
    hit = (pos < len(texels)) & (texels[np.minimum(pos, len(texels) - 1)] == tid)
    return np.bincount(pos[hit], weights=(geo["sample_area"] * value)[hit],
                       minlength=len(texels))


def _estimate(ps, texels, value):
    return np.bincount(np.searchsorted(texels, ps.texel), weights=ps.weight[:, 0] *
                       value[ps.sample], minlength=len(texels))


@pytest.mark.parametrize("index", [True, False])
def test_stratified_sum_is_unbiased_against_the_brute_force_sum(index):
    """Over 1,500 seeds the mean of the weighted sums of a heavy-tailed per-sample value
    (a few samples carry most of it, as a highlight does) is the sum over every sample within
    4 standard errors; each draw holds at most k distinct samples of its own texel."""
    geo = _geo(index=index)
    level, k = 2, 24
    texels = np.unique(texel_ids(geo, N, level, None))
    value = np.random.default_rng(3).pareto(1.5, len(geo["sample_area"]))
    truth = _truth(geo, level, texels, value)
    est = []
    for seed in range(1500):  # independent draws
        ps = stratified_samples(geo, N, level, texels, seed, k)
        est.append(_estimate(ps, texels, value))
    first = stratified_samples(geo, N, level, texels, 0, k)
    assert np.all(texel_ids(geo, N, level, first.sample) == first.texel)
    for t in texels:  # loop over the level's few texels
        drawn = first.sample[first.texel == t]
        assert 0 < drawn.size <= k and np.unique(drawn).size == drawn.size
    est = np.array(est)
    se = est.std(axis=0) / np.sqrt(len(est))
    assert np.all(np.abs(est.mean(axis=0) - truth) <= 4 * se + 1e-12 * truth)
    # not the trivial estimator: a draw differs from the truth where a texel has more than k
    assert np.abs(est[0] - truth).max() > 1e-3 * truth.max()


def test_a_texel_of_at_most_k_samples_draws_every_one_at_its_area():
    geo = _geo(m=400)
    level = 1
    texels = np.unique(texel_ids(geo, N, level, None))
    ps = stratified_samples(geo, N, level, texels, 0, 10**6)
    tid = texel_ids(geo, N, level, None)
    for t in texels:  # loop over texels
        mine = np.sort(ps.sample[ps.texel == t])
        np.testing.assert_array_equal(mine, np.flatnonzero(tid == t))
    np.testing.assert_array_equal(ps.weight[:, 0], geo["sample_area"][ps.sample])
    assert ps.weight.shape == (len(ps.sample), 3) and ps.sample.dtype == np.int64


def test_draws_depend_on_seed_level_and_texel_only():
    """The same texel gets the same draws whichever texels share the call (a tile shard or the
    top shard), and another seed draws others."""
    geo = _geo()
    level, k = 2, 16
    texels = np.unique(texel_ids(geo, N, level, None))
    whole = stratified_samples(geo, N, level, texels, 7, k)
    for t in texels[::3]:  # loop over a few texels asked alone
        alone = stratified_samples(geo, N, level, np.array([t]), 7, k)
        np.testing.assert_array_equal(alone.sample, whole.sample[whole.texel == t])
        np.testing.assert_array_equal(alone.weight, whole.weight[whole.texel == t])
    other = stratified_samples(geo, N, level, texels, 8, k)
    assert not np.array_equal(other.sample, whole.sample)
    empty = stratified_samples(geo, N, level, np.zeros(0, np.int64), 7, k)
    assert empty.sample.shape == (0,) and empty.weight.shape == (0, 3)
