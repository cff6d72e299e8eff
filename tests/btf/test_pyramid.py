"""YCbCr and Laplacian pyramids of the BTF stage (seed 001, §3.1)."""

import numpy as np
import pytest

from texelbake.btf.color import RGB_FROM_YCBCR, rgb_to_ycbcr, ycbcr_to_rgb
from texelbake.btf.laplacian import (
    build_pyramid,
    collapse,
    expand,
    level_shapes,
    reduce,
    top_level_for,
)
from texelbake.errors import SettingsError, ShapeError


def test_ycbcr_round_trip_float64_and_float32(rng):
    rgb = rng.random((50, 7, 3)) * 4.0  # HDR values above 1 are allowed
    back = ycbcr_to_rgb(rgb_to_ycbcr(rgb))
    assert np.abs(back - rgb).max() < 1e-12
    rgb32 = rgb.astype(np.float32)
    ycc32 = rgb_to_ycbcr(rgb32)
    assert ycc32.dtype == np.float32
    # float32: two 3x3 products of values <= 4, a few ulps of 4 (4.8e-7 each)
    assert np.abs(ycbcr_to_rgb(ycc32) - rgb32).max() < 1e-6


def test_ycbcr_known_values():
    # grey has no chroma; pure red has Cr = (1 - 0.299) / 1.402 = 0.5 by the BT.601 definition
    ycc = rgb_to_ycbcr(np.array([[0.5, 0.5, 0.5], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]))
    assert np.allclose(ycc[0], [0.5, 0.0, 0.0], atol=1e-12)
    assert np.allclose(ycc[1], [0.299, -0.299 / 1.772, 0.5], atol=1e-12)
    assert np.allclose(ycc[2], [0.114, 0.5, -0.114 / 1.402], atol=1e-12)
    assert np.allclose(RGB_FROM_YCBCR @ [1.0, 0.0, 0.0], 1.0)


def test_ycbcr_shape_error():
    with pytest.raises(ShapeError, match="last axis of 3"):
        rgb_to_ycbcr(np.zeros((4, 2)))


def _reduce_brute(img, taps):
    """Per-pixel reference of Eq. 2 with clamped borders (loops are fine on 5 x 7)."""
    offsets = range(-(len(taps) // 2), len(taps) // 2 + 1)
    h, w = img.shape[:2]
    out = np.zeros(((h + 1) // 2, (w + 1) // 2) + img.shape[2:])
    for i in range(out.shape[0]):
        for j in range(out.shape[1]):
            for a, wa in zip(offsets, taps, strict=True):
                for b, wb in zip(offsets, taps, strict=True):
                    y = min(max(2 * i + a, 0), h - 1)
                    x = min(max(2 * j + b, 0), w - 1)
                    out[i, j] += wa * wb * img[y, x]
    return out


@pytest.mark.parametrize(
    ("name", "taps"),
    [("box3", [1 / 3] * 3), ("gauss5", [1 / 16, 4 / 16, 6 / 16, 4 / 16, 1 / 16])],
)
def test_reduce_matches_brute_force(rng, name, taps):
    img = rng.random((5, 7, 2))
    assert np.allclose(reduce(img, name), _reduce_brute(img, taps), atol=1e-14)


def test_expand_is_nearest():
    img = np.arange(6.0).reshape(2, 3)
    up = expand(img, (3, 5))
    assert up.shape == (3, 5)
    assert np.array_equal(up[2], [3, 3, 4, 4, 5])
    with pytest.raises(ShapeError, match="expected parent"):
        expand(img, (5, 5))


@pytest.mark.parametrize("shape", [(1, 1), (1, 9), (5, 7), (13, 6), (16, 16), (33, 2)])
@pytest.mark.parametrize("name", ["box3", "gauss5"])
def test_collapse_is_exact_any_size(rng, shape, name):
    img = rng.random(shape + (4,))  # 4 "direction images"
    keep = img.copy()
    top = top_level_for(*shape, 1)  # as deep as it goes
    levels = build_pyramid(img, top, name)
    assert [lv.shape[:2] for lv in levels] == level_shapes(*shape, top + 1)
    assert levels[-1].shape[:2] == (1, 1) or top == 0
    # exact up to one float64 rounding per level
    assert np.abs(collapse(levels) - img).max() < 1e-14
    assert np.array_equal(img, keep)  # input untouched without overwrite


def test_collapse_float32_and_overwrite(rng):
    img = rng.random((9, 11, 3)).astype(np.float32)
    keep = img.copy()
    levels = build_pyramid(img, 3, overwrite=True)
    assert levels[0] is img  # level 0 computed in place
    # float32: one subtraction and one addition per level, values <= 1: a few ulps (6e-8)
    assert np.abs(collapse(levels) - keep).max() < 1e-6


def test_laplacian_of_constant_image_is_zero():
    img = np.full((6, 10, 2), 0.37)
    levels = build_pyramid(img, 2)
    assert np.abs(levels[0]).max() < 1e-15 and np.abs(levels[1]).max() < 1e-15
    assert np.allclose(levels[2], 0.37)


def test_top_level_rule_matches_seed():
    # 64 x 64 texels, n = 8: the seed's lambda_max = 4 (a 4 x 4 top level)
    assert top_level_for(64, 64, 16) == 4
    assert top_level_for(2, 2, 16) == 0  # fewer texels than 2n: no pyramid at all
    assert top_level_for(5, 7, 16) == 1  # 35 -> 3 x 4 = 12
    with pytest.raises(ShapeError):
        top_level_for(0, 3, 4)


def test_pyramid_errors():
    with pytest.raises(SettingsError, match="box3"):
        build_pyramid(np.zeros((4, 4)), 1, "bilinear")
    with pytest.raises(SettingsError, match="top_level"):
        build_pyramid(np.zeros((4, 4)), -1)
    with pytest.raises(ShapeError):
        build_pyramid(np.zeros(4), 1)
