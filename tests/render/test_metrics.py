"""texelbake.render.metrics against hand computation."""

from __future__ import annotations

import math

import numpy as np
import pytest

from texelbake.errors import ShapeError
from texelbake.render import metrics


def test_rmse_psnr_snr_by_hand():
    ref = np.zeros((2, 2, 3))
    ref[0, 0] = (2.0, 0.0, 0.0)  # peak 2, sum of squares 4
    img = ref.copy()
    img[1, 1, 2] = 0.6  # one error of 0.6 over 12 values
    mse = 0.36 / 12.0
    assert metrics.rmse(img, ref) == pytest.approx(math.sqrt(mse), rel=1e-12)
    assert metrics.psnr_db(img, ref) == pytest.approx(20 * math.log10(2.0 / math.sqrt(mse)),
                                                      rel=1e-12)
    assert metrics.psnr_db(img, ref, peak=1.0) == pytest.approx(
        20 * math.log10(1.0 / math.sqrt(mse)), rel=1e-12)
    assert metrics.snr_db(img, ref) == pytest.approx(10 * math.log10(4.0 / 0.36), rel=1e-12)


def test_exact_match_is_infinite_and_bad_inputs_raise():
    ref = np.full((3, 3, 3), 0.25)
    assert metrics.psnr_db(ref, ref) == math.inf
    assert metrics.snr_db(ref, ref) == math.inf
    assert metrics.rmse(ref, ref) == 0.0
    with pytest.raises(ShapeError):
        metrics.rmse(ref, ref[:2])
    with pytest.raises(ShapeError):
        metrics.psnr_db(ref, np.zeros_like(ref))  # no peak
    with pytest.raises(ShapeError):
        metrics.snr_db(ref, np.zeros_like(ref))
    bad = ref.copy()
    bad[0, 0, 0] = np.nan
    with pytest.raises(ShapeError):
        metrics.rmse(bad, ref)


def test_lab_and_delta_e_by_hand():
    # white -> L* = 100, a* = b* = 0; black -> 0; mid grey 0.18 -> L* = 116 * 0.18^(1/3) - 16
    lab = metrics.linear_to_lab(np.array([[1.0, 1.0, 1.0], [0.0, 0.0, 0.0], [0.18] * 3]))
    np.testing.assert_allclose(lab[0], (100.0, 0.0, 0.0), atol=1e-9)
    np.testing.assert_allclose(lab[1], (0.0, 0.0, 0.0), atol=1e-9)
    np.testing.assert_allclose(lab[2], (116 * 0.18 ** (1 / 3) - 16, 0.0, 0.0), atol=1e-9)
    ref = np.ones((2, 2, 3))
    img = ref.copy()
    img[0, 0] = 0.0
    d = metrics.difference_map(img, ref, white=1.0)
    assert d.shape == (2, 2)
    np.testing.assert_allclose(d, [[100.0, 0.0], [0.0, 0.0]], atol=1e-9)
    # default white: the reference's 99.5th percentile luminance (1 here)
    np.testing.assert_allclose(metrics.difference_map(img, ref), d, atol=1e-9)


def test_difference_map_png(tmp_path):
    from texelbake.io.images import read_image

    d = np.array([[0.0, 5.0], [10.0, 20.0]])
    p = metrics.write_difference_map(tmp_path / "d.png", d)
    px = read_image(p)
    assert px.shape == (2, 2, 3)
    # clipped at vmax = 10: the last two pixels get the same colour, the first the darkest
    np.testing.assert_array_equal(px[1, 0], px[1, 1])
    assert px[0, 0].sum() < px[0, 1].sum() < px[1, 0].sum()


def test_object_mask_is_the_dilated_union_by_brute_force():
    rng = np.random.default_rng(4)
    a = rng.random((12, 15)) > 0.93
    b = rng.random((12, 15)) > 0.93
    got = metrics.object_mask(a.astype(float), b)
    u = a | b
    want = np.zeros_like(u)
    for i, j in zip(*np.nonzero(u), strict=True):  # brute force: every 3 x 3 neighbourhood
        want[max(i - 1, 0):i + 2, max(j - 1, 0):j + 2] = True
    np.testing.assert_array_equal(got, want)
    with pytest.raises(ShapeError):
        metrics.object_mask(a, b[:, :3])


def test_object_errors_by_hand_and_the_black_frame_no_longer_helps():
    """PSNR over the object's pixels uses only those pixels (by hand: peak 2, RMSE 0.1 over the
    four object pixels -> 20 log10(20)); the same error over a frame 25x larger reads 14 dB
    better over the frame (10 log10 25), which is what the reports no longer headline."""
    ref = np.zeros((10, 10, 3))
    ref[4:6, 4:6] = 2.0
    img = ref.copy()
    img[4:6, 4:6] += 0.1
    mask = np.zeros((10, 10), bool)
    mask[4:6, 4:6] = True
    e = metrics.object_errors(img, ref, mask)
    assert e["object_pixels"] == 4
    assert e["psnr_db_object"] == pytest.approx(20 * np.log10(2.0 / 0.1), abs=1e-9)
    assert metrics.psnr_db(img, ref) - e["psnr_db_object"] == pytest.approx(
        10 * np.log10(25.0), abs=1e-9)
    de = metrics.difference_map(img, ref)[mask]
    assert e["delta_e_mean"] == pytest.approx(de.mean()) and e["delta_e_p95"] > 0
    # FLIP: 0 for identical images, larger for larger errors, within [0, 1]
    assert metrics.object_errors(ref, ref, mask)["flip_mean"] == 0.0
    worse = ref.copy()
    worse[4:6, 4:6] = 0.5
    assert 0.0 < e["flip_mean"] < metrics.object_errors(worse, ref, mask)["flip_mean"] <= 1.0
    # nothing to compare: NaN, never a division error
    empty = metrics.object_errors(img, ref, np.zeros((10, 10), bool))
    assert empty["object_pixels"] == 0 and np.isnan(empty["psnr_db_object"])
