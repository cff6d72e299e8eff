"""texelbake.metrics against hand computation."""

from __future__ import annotations

import math

import numpy as np
import pytest

from texelbake import metrics
from texelbake.errors import ShapeError


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
    from texelbake.render.images import read_image

    d = np.array([[0.0, 5.0], [10.0, 20.0]])
    p = metrics.write_difference_map(tmp_path / "d.png", d)
    px = read_image(p)
    assert px.shape == (2, 2, 3)
    # clipped at vmax = 10: the last two pixels get the same colour, the first the darkest
    np.testing.assert_array_equal(px[1, 0], px[1, 1])
    assert px[0, 0].sum() < px[0, 1].sum() < px[1, 0].sum()
