"""Haar compression (texelbake.cpm.haar): round trip, Parseval optimality, point evaluation."""

import math

import numpy as np
import pytest

from texelbake.cpm.haar import compress_haar, decompress_haar, eval_haar_point, haar_point_terms
from texelbake.errors import NumericalError, SettingsError, ShapeError


def _smooth_maps(rng, shape, res):
    """Smooth maps with a few sharp edges, like a_vis faces."""
    y, x = np.meshgrid(np.linspace(0, 1, res), np.linspace(0, 1, res), indexing="ij")
    base = np.cos(2.0 * x + rng.random(shape + (1, 1))) * (1 + y)
    step = (x + 0.3 * y > rng.random(shape + (1, 1))).astype(float)
    return base + 0.5 * step


@pytest.mark.parametrize("res", [1, 2, 8, 32])
def test_round_trip_lossless(rng, res):
    maps = rng.normal(size=(3, 6, res, res))
    c = compress_haar(maps, 1.0, dtype=np.float64)
    assert c.batch_shape == (3, 6) and c.res == res and c.n_maps == 18
    rec = decompress_haar(c)
    assert rec.shape == maps.shape and rec.dtype == np.float64
    # orthonormal transform in float64: round-off only (~log2(res) * 1e-16 of the values)
    np.testing.assert_allclose(rec, maps, rtol=0, atol=1e-12)


def test_float32_storage_round_trip(rng):
    maps = rng.normal(size=(4, 16, 16))
    c = compress_haar(maps, 1.0)
    assert c.values.dtype == np.float32 and c.indices.dtype == np.int32
    # float32 values: relative rounding 2^-24 per coefficient
    np.testing.assert_allclose(decompress_haar(c), maps, rtol=0, atol=1e-5)


def test_truncation_error_is_dropped_energy(rng):
    """Parseval: with an orthonormal basis the L2 error equals the norm of the dropped
    coefficients, and keeping the largest ones is optimal (pywt computes the truth)."""
    import pywt

    res = 16
    maps = _smooth_maps(rng, (5,), res)
    keep = 0.1
    c = compress_haar(maps, keep, dtype=np.float64)
    k = math.ceil(keep * res * res)
    assert np.all(np.diff(c.offsets) <= k)
    err = decompress_haar(c) - maps
    for i in range(5):
        arr, _ = pywt.coeffs_to_array(pywt.wavedec2(maps[i], "haar", mode="periodization"))
        mags = np.sort(np.abs(arr.ravel()))[::-1]
        dropped = np.sum(mags[k:] ** 2)
        np.testing.assert_allclose(np.sum(err[i] ** 2), dropped, rtol=1e-9, atol=1e-20)


def test_error_decreases_with_kept_fraction(rng):
    maps = _smooth_maps(rng, (6,), 32)
    errs = []
    for keep in (0.01, 0.04, 0.065, 0.2, 1.0):
        rec = decompress_haar(compress_haar(maps, keep, dtype=np.float64))
        errs.append(np.linalg.norm(rec - maps) / np.linalg.norm(maps))
    assert all(a >= b for a, b in zip(errs, errs[1:], strict=False))
    assert errs[-1] < 1e-12 and errs[0] > 1e-3


def test_zero_maps_store_nothing():
    c = compress_haar(np.zeros((2, 6, 8, 8)), 0.1)
    assert c.nnz == 0
    assert np.all(decompress_haar(c) == 0)
    assert np.all(eval_haar_point(c, np.array([0, 11]), np.array([1, 7]), np.array([0, 3])) == 0)


@pytest.mark.parametrize("res", [1, 2, 4, 64])
def test_point_eval_equals_full_inverse(rng, res):
    maps = _smooth_maps(rng, (4, 6), res)
    c = compress_haar(maps, 0.05)
    full = decompress_haar(c).reshape(-1, res, res)
    n = 2000
    mi = rng.integers(0, c.n_maps, n)
    iu = rng.integers(0, res, n)
    iv = rng.integers(0, res, n)
    for dense_limit in (0, 1 << 30):  # the read maps and the whole table gathered
        pts = eval_haar_point(c, mi, iu, iv, dense_limit=dense_limit)
        assert pts.shape == (n,) and pts.dtype == np.float64
        np.testing.assert_allclose(pts, full[mi, iv, iu], rtol=0, atol=1e-12)


def test_point_terms_count_is_logarithmic():
    idx, val = haar_point_terms(64, np.array([5, 63]), np.array([0, 17]))
    assert idx.shape == (2, 3 * 6 + 1) and val.shape == idx.shape
    # every point touches distinct coefficients, one per (level, subband) plus the mean
    assert all(len(set(row)) == idx.shape[1] for row in idx)


def test_errors(rng):
    with pytest.raises(SettingsError, match="power of two"):
        compress_haar(np.zeros((6, 12, 12)), 0.1)
    with pytest.raises(ShapeError):
        compress_haar(np.zeros((6, 8, 4)), 0.1)
    with pytest.raises(SettingsError, match="keep_fraction"):
        compress_haar(np.zeros((6, 8, 8)), 0.0)
    with pytest.raises(SettingsError, match="keep_fraction"):
        compress_haar(np.zeros((6, 8, 8)), 1.5)
    bad = np.zeros((2, 4, 4))
    bad[1, 2, 3] = np.nan
    with pytest.raises(NumericalError):
        compress_haar(bad, 0.5)
    c = compress_haar(rng.normal(size=(2, 4, 4)), 0.5)
    with pytest.raises(ShapeError):
        eval_haar_point(c, np.array([2]), np.array([0]), np.array([0]))
    with pytest.raises(ShapeError):
        eval_haar_point(c, np.array([0]), np.array([4]), np.array([0]))


def test_empty_batch_and_queries():
    c = compress_haar(np.zeros((0, 6, 8, 8)), 0.1)
    assert c.n_maps == 0 and decompress_haar(c).shape == (0, 6, 8, 8)
    out = eval_haar_point(c, np.zeros(0, int), np.zeros(0, int), np.zeros(0, int))
    assert out.shape == (0,) and out.dtype == np.float64


def test_deterministic(rng):
    maps = _smooth_maps(rng, (3, 6), 16)
    a, b = compress_haar(maps, 0.06), compress_haar(maps.copy(), 0.06)
    assert a.indices.tobytes() == b.indices.tobytes()
    assert a.values.tobytes() == b.values.tobytes()


def test_budget_mask_equalises_relative_residuals(rng):
    from texelbake.cpm.haar import budget_mask

    # two groups, one with a heavy tail: the budget goes where the residual is larger
    imp = np.vstack([np.sort(rng.uniform(0, 1, 50))[::-1] ** 4,
                     np.sort(rng.uniform(0, 1, 50))[::-1] ** 0.5]) / 10.0
    mask = budget_mask(imp, 40)
    assert mask.sum() <= 40 and mask.sum(axis=1).min() >= 1
    dropped = np.where(mask, 0.0, imp).sum(axis=1)
    assert mask[1].sum() > mask[0].sum()
    # one more coefficient for the worse group would not fit; the residuals are within the
    # next coefficient of each other
    assert abs(dropped[0] - dropped[1]) <= max(imp[0][~mask[0]].max(), imp[1][~mask[1]].max())
    # kept entries are each group's largest
    for g in range(2):
        assert imp[g][mask[g]].min() >= imp[g][~mask[g]].max()


def test_support_mean_matches_a_direct_average(rng):
    from texelbake.cpm.haar import haar_support_mean

    w = rng.uniform(0, 1, (2, 8, 8))
    m = haar_support_mean(w)
    np.testing.assert_allclose(m[:, 0, 0], w.mean(axis=(1, 2)))
    # subband of side 2 (rows/cols 2:4): supports are 4x4 blocks
    np.testing.assert_allclose(m[:, 3, 1], w[:, 4:8, 4:8].mean(axis=(1, 2)))  # 'da' (1, 1)
    np.testing.assert_allclose(m[:, 0, 3], w[:, 0:4, 4:8].mean(axis=(1, 2)))  # 'ad' (0, 1)
    # finest subband (side 4): 2x2 blocks
    np.testing.assert_allclose(m[:, 6, 5], w[:, 4:6, 2:4].mean(axis=(1, 2)))  # 'dd' (2, 1)


def test_float16_values_round_trip_exactly(rng):
    from texelbake.cpm.haar import dequantize_values, quantize_values

    v = rng.normal(0, 1, 1000) * 10.0 ** rng.uniform(-6, 0, 1000)
    scale = np.full(1000, np.abs(v).max(), np.float32)
    q, deq = quantize_values(v, scale)
    np.testing.assert_allclose(deq, v, rtol=1e-3, atol=1e-3 * scale[0])
    q2, deq2 = quantize_values(deq, scale)  # re-storing a read table changes nothing
    np.testing.assert_array_equal(q2, q)
    np.testing.assert_array_equal(dequantize_values(q2, scale), deq)


def test_point_eval_on_the_read_maps_equals_the_whole_table_bit_for_bit(rng):
    """A large table's pixels are gathered from the maps they read, scattered dense in blocks
    of at most `dense_limit` entries (one map a block, a few, all): the same values, bit for
    bit, as the whole table's dense array, for pixels of repeated and unsorted maps."""
    res = 16
    c = compress_haar(_smooth_maps(rng, (30, 6), res), 0.05)
    n = 3000
    mi = rng.integers(0, c.n_maps, n)
    iu, iv = rng.integers(0, res, n), rng.integers(0, res, n)
    want = eval_haar_point(c, mi, iu, iv, dense_limit=1 << 30)
    for limit in (0, 3 * res * res, 50 * res * res):
        np.testing.assert_array_equal(eval_haar_point(c, mi, iu, iv, dense_limit=limit), want)
