"""Each LOD's fallback textures at its own size (`texelbake.stages.lod_textures`): the
area-weighted box means against a loop over texels, the fill of texels nothing covers, and
where a viewer's mip of the page would differ."""

from __future__ import annotations

import numpy as np
import pytest

from texelbake.stages.lod_textures import box_down


def _brute(img, area, level):
    n = img.shape[0]
    f = 1 << level
    m = n // f
    out = np.full((m, m, img.shape[2]), np.nan)
    for r in range(m):  # the reference: one coarse texel at a time
        for c in range(m):
            w = area[r * f:(r + 1) * f, c * f:(c + 1) * f]
            if w.sum() > 0:
                v = (img[r * f:(r + 1) * f, c * f:(c + 1) * f] * w[..., None]).sum(axis=(0, 1))
                out[r, c] = v / w.sum()
    return out


@pytest.mark.parametrize("level", [1, 2, 3])
def test_box_down_is_the_area_weighted_mean_of_covered_texels(rng, level):
    n = 16
    img = rng.random((n, n, 3)).astype(np.float32)
    area = rng.random((n, n)) * (rng.random((n, n)) > 0.6)  # charts and empty page
    area[:8, :8] = 0.0  # a corner of the page no chart reaches, at every level
    got = box_down(img, area, level)
    want = _brute(img.astype(np.float64), area, level)
    seen = ~np.isnan(want[..., 0])
    assert 0 < seen.sum() < seen.size
    np.testing.assert_allclose(got[seen], want[seen], rtol=1e-6, atol=1e-7)
    # a texel nothing covers holds a covered one's value (no background in any level)
    covered = {tuple(np.round(v, 6)) for v in got[seen]}
    assert all(tuple(np.round(v, 6)) in covered for v in got[~seen])


def test_level_zero_is_the_map(rng):
    img = rng.random((8, 8, 3)).astype(np.float32)
    assert box_down(img, np.ones((8, 8)), 0) is img


def test_a_coarse_texel_takes_only_its_own_chart():
    # two charts side by side with padding between: the viewer's mip (a plain box mean of the
    # filled page) mixes the padding in at a chart's border; the LOD's own texture does not
    n = 8
    img = np.zeros((n, n, 1), np.float32)
    area = np.zeros((n, n))
    img[:, :3], area[:, :3] = 1.0, 1.0  # chart A, value 1, texels 0-2
    img[:, 3:], area[:, 5:] = 0.5, 1.0  # padding (filled from B) and chart B, value 0.5
    got = box_down(img, area, 2)[..., 0]
    mip = img[..., 0].reshape(2, 4, 2, 4).mean(axis=(1, 3))
    assert np.all(got[:, 0] == 1.0) and np.all(got[:, 1] == 0.5)
    assert np.all(mip[:, 0] == 0.875)  # a quarter of chart A's coarse texel is B's padding
