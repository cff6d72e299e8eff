"""The held-out truth of a texel of many samples summed over a seeded subset
(`texelbake.cpm.truth_sample.truth_samples`, `held_scale`, BakeSettings.heldout_samples), on the walled square of
tests/cpm/test_classify.py: level 1's one texel holds its 64 samples, a quarter of them in the
wall's shadow for some held-out directions."""

from __future__ import annotations

import dataclasses

import numpy as np

from tests.cpm.test_classify import _grid_samples, _inputs, _up, _walled
from texelbake.cpm.dense import LevelPass, avis_sums, dense_of, dense_sums, held_scale
from texelbake.cpm.truth_sample import avis_samples, truth_samples
from texelbake.geometry.texels import morton
from texelbake.tol import TOL

ONE = np.zeros(1, np.int64)


def _src(**update):
    pos = _grid_samples()
    src = _inputs(pos, _up(len(pos)), mesh=_walled(0.4, 0.2, 0.8))
    return dataclasses.replace(src, settings=src.settings.model_copy(update=update))


def test_every_sample_when_the_texel_is_small_enough():
    """heldout_samples at or above the texel's count (and 0) keep every sample at its area:
    the truth is the exact sum, bit for bit."""
    exact = dense_sums(_src(heldout_samples=0), 1, ONE)
    for k in (64, 1000):
        got = dense_sums(_src(heldout_samples=k), 1, ONE)
        np.testing.assert_array_equal(got.ref, exact.ref)
        np.testing.assert_array_equal(got.avis_h, exact.avis_h)
        assert np.all(held_scale(got.area, got.area_held) == 1.0)


def _scaled(d):
    f = held_scale(d.area, d.area_held)
    return d.ref * f[:, None, None, None], d.avis_h * f[:, None]


def test_the_truth_is_the_kept_samples_scaled_to_the_texel():
    """16 of 64 samples (p = 1/4): the truth (ref, a_vis on the held-out views) is the sum over
    the kept samples alone (each summed by itself, with every sample kept) times the texel's
    area over theirs; and its error against the sum over every sample is within 5 standard
    deviations of the ratio estimator, sqrt((1 - p) / p sum_j (y_j - R a_j)^2) with y_j a
    sample's own term, a_j its area and R the texel's truth per unit area."""
    src = _src(heldout_samples=16)
    dense, dseg = dense_of(LevelPass.of(src, 1), ONE)
    keep = truth_samples(src, 1, ONE, dense, dseg)
    ref, avis_h = _scaled(dense_sums(src, 1, ONE))
    every = _src(heldout_samples=0)
    single = [dense_sums(every, 1, ONE, dense[j:j + 1]) for j in range(len(dense))]
    y = np.array([d.ref[0] for d in single])  # (64, h_i, h_o, 3)
    v = np.array([d.avis_h[0] for d in single])  # (64, h_o)
    a = src.geo["sample_area"][dense]
    scale = a.sum() / a[keep].sum()
    np.testing.assert_allclose(ref[0], scale * y[keep].sum(axis=0), rtol=1e-10, atol=1e-15)
    np.testing.assert_allclose(avis_h[0], scale * v[keep].sum(axis=0), rtol=1e-10, atol=1e-15)
    p = 0.25
    for est, per in ((ref[0], y), (avis_h[0], v)):
        truth = per.sum(axis=0)
        z = per - (truth / a.sum()) * a.reshape((-1,) + (1,) * (per.ndim - 1))
        sigma = np.sqrt((1 - p) / p * (z ** 2).sum(axis=0))
        assert np.all(np.abs(est - truth) <= 5.0 * sigma + 1e-12)
    assert 0 < keep.sum() < 64 and np.abs(ref[0] - y.sum(axis=0)).max() > 0


def test_every_texel_of_a_flat_level_is_exact_on_the_subset():
    """On the flat square every sample's Eq. 7 term per unit area is the same, so the scaled
    truth equals the sum over every sample whichever samples are kept."""
    pos = _grid_samples()
    flat = _inputs(pos, _up(len(pos)))
    src = dataclasses.replace(flat, settings=flat.settings.model_copy(
        update={"heldout_samples": 16}))
    ref, avis_h = _scaled(dense_sums(src, 1, ONE))
    exact = dense_sums(flat, 1, ONE)  # the default heldout_samples: every sample
    np.testing.assert_allclose(ref, exact.ref, rtol=1e-12)
    np.testing.assert_allclose(avis_h, exact.avis_h, rtol=1e-12)


def test_the_subset_depends_on_the_sample_not_the_chunk():
    """A texel's kept samples are the same whether its samples are given together
    or a part at a time (a tile holds only its share of a top level's texel): keys are per
    sample id and p is from the texel's count in the whole atlas."""
    src = _src(heldout_samples=16)
    lp = LevelPass.of(src, 1)
    dense, dseg = dense_of(lp, ONE)
    keep = truth_samples(src, 1, ONE, dense, dseg)
    for part in (slice(0, 20), slice(20, 64)):
        np.testing.assert_array_equal(truth_samples(src, 1, ONE, dense[part], dseg[part]),
                                      keep[part])
    assert 0 < keep.sum() < 64


def test_an_exact_texel_measures_exact_on_a_subset():
    """The flat square's level-1 texel (one facet, one material, nothing above: one exact
    point) measured on 16 of its 64 samples: every sample's Eq. 7 term is the point's, so the
    ratio of the weighted truth to its weighted a_vis is exact whichever samples are kept, and
    the point, kept or not, is evaluated for the approximation."""
    from texelbake.cpm.level import level_candidates
    from texelbake.stages.cpm import fit_level

    pos = _grid_samples()
    src = _inputs(pos, _up(len(pos)))
    src = dataclasses.replace(src, settings=src.settings.model_copy(
        update={"heldout_samples": 16, "classed_levels": 2}))
    fine = np.arange(4, dtype=np.int64)
    out0 = fit_level(src, 0, fine, level_candidates(src, 0, fine, None))
    out = fit_level(src, 1, ONE, level_candidates(src, 1, ONE, out0))
    assert out["c"][0] == 1 and out["snr_ho"][0] >= TOL.exact_fit_db
    dense, dseg = dense_of(LevelPass.of(src, 1), ONE)
    assert 0 < truth_samples(src, 1, ONE, dense, dseg).sum() < 64


def test_a_texel_with_no_sample_kept_is_not_measured():
    """heldout_samples 1 of 64: some seed keeps none of the texel's samples; its truth has no
    area to scale from, so its held-out a_vis is NaN and its SNR NaN (left out of the report's
    percentiles), never a zero truth measured as an error."""
    from texelbake.cpm.dense import heldout_snr

    for seed in range(64):  # loop over seeds until one keeps nothing (P = 0.36 each)
        src = _src(heldout_samples=1, seed=seed)
        dense, dseg = dense_of(LevelPass.of(src, 1), ONE)
        if not truth_samples(src, 1, ONE, dense, dseg).any():
            break
    else:
        raise AssertionError("every seed kept a sample")
    d = dense_sums(src, 1, ONE)
    ref, avis_h = _scaled(d)
    assert d.area_held[0] == 0 and np.isnan(avis_h).all()
    assert np.isnan(heldout_snr(ref[0], np.zeros_like(ref[0]), avis_h[0], float(d.area[0])))


def _zordered(src):
    """`src` with the geometry stage's Z-order index of its 2 x 2 atlas (`sample_zorder`,
    `texel_zoffsets`), built here from the samples' finest codes."""
    geo = dict(src.geo)
    code = morton(geo["sample_row"], geo["sample_col"])
    geo["sample_zorder"] = np.argsort(code, kind="stable")
    geo["texel_zoffsets"] = np.r_[0, np.cumsum(np.bincount(code, minlength=4))]
    return dataclasses.replace(src, geo=geo)


def test_avis_samples_keep_every_kth_of_the_zorder_run():
    """A texel over avis_fit_samples keeps ranks lo, lo + k, ... of its Z-order run, k =
    ceil(samples / cap), by hand at both levels of the walled square; a texel's part (a
    tile's share) keeps its part of the same samples, none when it holds none of them; a cap
    at or above the count (or 0) keeps every sample (None)."""
    src = _zordered(_src(avis_fit_samples=10))
    zo = src.geo["sample_zorder"]
    dense, dseg = dense_of(LevelPass.of(src, 1), ONE)
    keep = avis_samples(src, 1, ONE, dense, dseg)
    np.testing.assert_array_equal(keep, np.isin(dense, zo[0:64:7]))  # ceil(64 / 10) = 7
    assert keep.sum() == 10
    four = np.arange(4, dtype=np.int64)
    dense0, dseg0 = dense_of(LevelPass.of(src, 0), four)
    want = np.zeros(dense0.size, bool)
    for t in range(4):  # loop over the four finest texels, each a run of 16: every 2nd
        run = zo[src.geo["texel_zoffsets"][morton(np.array([t // 2]), np.array([t % 2]))[0]]
                 + np.arange(0, 16, 2)]
        want |= (dseg0 == t) & np.isin(dense0, run)
    np.testing.assert_array_equal(avis_samples(src, 0, four, dense0, dseg0), want)
    part = dense[dense != zo[0]][:20]  # a tile's share of the level-1 texel
    seg = np.zeros(part.size, np.int64)
    np.testing.assert_array_equal(avis_samples(src, 1, ONE, part, seg),
                                  np.isin(part, zo[0:64:7]))
    lone = np.array([zo[1]])  # not among the kept
    assert avis_samples(src, 1, ONE, lone, np.zeros(1, np.int64)).tolist() == [False]
    for cap in (0, 64, 1000):
        assert avis_samples(_zordered(_src(avis_fit_samples=cap)), 1, ONE, dense, dseg) is None


def test_avis_sums_over_the_subset_scaled_to_the_texel():
    """a_vis over the subset is its samples' own a_vis times the texel's area over theirs
    (each sample summed alone with every sample cast); at or above the count it is the sum
    over every sample bit for bit; on the flat square, with every sample's a_vis per unit
    area A cos(theta), it is that closed form whichever samples are kept."""
    src = _zordered(_src(avis_fit_samples=10))
    lp = LevelPass.of(src, 1)
    dense, dseg = dense_of(lp, ONE)
    keep = avis_samples(src, 1, ONE, dense, dseg)
    every = _zordered(_src(avis_fit_samples=0))
    lp0 = LevelPass.of(every, 1)
    got, area = avis_sums(lp, ONE, dense, dseg)
    each = np.array([avis_sums(lp0, ONE, dense[j:j + 1], np.zeros(1, np.int64))[0][0]
                     for j in range(dense.size)])  # (64, n_o)
    a = src.geo["sample_area"][dense]
    np.testing.assert_allclose(got[0], a.sum() / a[keep].sum() * each[keep].sum(axis=0),
                               rtol=1e-12, atol=1e-15)
    full, area0 = avis_sums(lp0, ONE, dense, dseg)
    assert area[0] == area0[0] and np.abs(got - full).max() > 0  # the wall's shadow differs
    for cap in (64, 1000):
        same, _ = avis_sums(LevelPass.of(_zordered(_src(avis_fit_samples=cap)), 1), ONE,
                            dense, dseg)
        np.testing.assert_array_equal(same, full)
    pos = _grid_samples()
    flat = _zordered(_inputs(pos, _up(len(pos))))
    flat = dataclasses.replace(flat, settings=flat.settings.model_copy(
        update={"avis_fit_samples": 10}))
    lpf = LevelPass.of(flat, 1)
    dense, dseg = dense_of(lpf, ONE)
    got, area = avis_sums(lpf, ONE, dense, dseg)
    cos = lpf.dirs["dirs_o"][:, 2]
    np.testing.assert_allclose(got[0], np.where(cos > TOL.grazing_cos, area[0] * cos, 0.0),
                               rtol=1e-12, atol=1e-15)
