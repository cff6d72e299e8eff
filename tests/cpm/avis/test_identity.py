"""The a_vis table the renderer reads meets the height-field identity (issue 11, item 1):
summed over a level's texels, a_vis(w) = A cos(theta) (A = 1 here: the unit square). Checked
through `AvisTable.evaluate` (bilinear, compressed at the default kept fraction) at every
level, on a random bumpy field and on V-grooves seen along and across the grooves, against the
seed's plain per-face Haar table (`correct_sum=False`)."""

from __future__ import annotations

import numpy as np
import pytest

from schemas.settings import BakeSettings
from tests.helpers.avis_scenes import grid_mesh, periodic_height, sample_faces, texel_of_xy, tile3x3
from texelbake.cpm.avis import avis_level, coarsen_level, compress_level
from texelbake.cpm.avis.correction import apply_correction, sum_correction
from texelbake.geometry.raycast import RayCaster

KEEP = BakeSettings().avis_keep_fraction
RES = BakeSettings().avis_resolution


def _levels(height, k=64, n_side=16, res=RES):
    pts, faces = grid_mesh(k, height)
    # every occluder of a ray leaving the centre tile below 80 deg lies in the 3x3 tiling
    assert np.ptp(pts[:, 2]) < np.tan(np.radians(10.0))
    tp, tf = tile3x3(pts, faces)
    pos, nrm, ar, _ = sample_faces(pts, faces, 2, seed=2)
    lvl = avis_level(pos, nrm, ar, texel_of_xy(pos, n_side), n_side, res,
                     RayCaster(tp, tf).occluded, tp, max_terms=1024)
    out = [lvl]
    while out[-1].n_side > 1:
        out.append(coarsen_level(out[-1]))
    return out


def _total(level, w, correct, keep=KEEP):
    """sum over the level's texels of a_vis(w), the table compressed at `keep`: (m,) for
    w (m, 3); one evaluate call over every (texel, direction) pair."""
    n = level.n_side ** 2
    table = compress_level(level, np.broadcast_to(np.eye(3), (n, 3, 3)).copy(), keep,
                           correct_sum=correct)
    m = w.shape[0]
    a = table.evaluate(np.repeat(np.arange(n), m), np.tile(w, (n, 1)))[0]  # (n * m,)
    return a.reshape(n, m).sum(axis=0)


def _dirs(rng, n=300, max_deg=75.0, phi=None):
    cos_t = rng.uniform(np.cos(np.radians(max_deg)), 1.0, n)
    ph = rng.uniform(0, 2 * np.pi, n) if phi is None else np.full(n, phi)
    s = np.sqrt(1 - cos_t ** 2)
    return np.column_stack([s * np.cos(ph), s * np.sin(ph), cos_t]), cos_t


@pytest.fixture(scope="module")
def bumpy():
    return _levels(periodic_height(0.05, seed=1))


@pytest.fixture(scope="module")
def grooves():
    period = 1.0 / 8  # grooves along y; walls at atan(0.06 * 2 / period) = 44 deg
    return _levels(lambda x, y: 0.06 * np.abs((x / period) % 1.0 - 0.5))


@pytest.mark.slow  # ray-casts a 64² field at res 32 (the module fixture)
def test_bumpy_field_identity_at_every_level(bumpy, rng):
    w, cos_t = _dirs(rng)
    for i, level in enumerate(bumpy):
        rel = np.abs(_total(level, w, True) - cos_t) / cos_t
        # measured 0.15 % at res 32 (0.6 % at 16): the bilinear look-up's own error, which the
        # lossless table has too
        assert rel.max() < 0.01, (i, rel.max())
    # without the sum correction the coarse levels' texels err alike and add up: measured
    # 0.9 %, 1.4 %, 2.5 %, 15 %, 16 % at levels 0-4 (why the correction exists)
    plain = max(float(np.max(np.abs(_total(level, w, False) - cos_t) / cos_t))
                for level in bumpy)
    assert plain > 0.05, plain


@pytest.mark.slow  # the V-groove field: ray-cast at res 32
@pytest.mark.parametrize("phi", [np.pi / 2, 0.0], ids=["along", "across"])
def test_v_grooves_along_and_across(grooves, rng, phi):
    w, cos_t = _dirs(rng, n=60, max_deg=75.0, phi=phi)
    w75 = np.array([[np.sin(np.radians(75)) * np.cos(phi), np.sin(np.radians(75)) * np.sin(phi),
                     np.cos(np.radians(75))]])
    for i, level in enumerate(grooves):
        rel = np.abs(_total(level, w, True) - cos_t) / cos_t
        # measured at res 32: 0.16 % at level 0, where every texel is a single wall. With the
        # look-up clamped to U(w) (before 2026-11-27) level 0 was 1.4 % off (4 % at res 16):
        # the clamp cut a wall's overshoot past its horizon but not the undershoot of the wall
        # it uncovers
        assert rel.max() < 0.01, (i, rel.max())
        if phi == np.pi / 2:  # along the grooves nothing is masked: the fraction is 1
            frac = _total(level, w75, True)[0] / np.cos(np.radians(75))
            assert abs(frac - 1.0) < 0.01, (i, frac)


def test_sum_correction_is_exact_and_keeps_the_bounds(rng):
    shape = (40, 6, 4, 4)
    f = rng.uniform(0, 1, shape) * (rng.uniform(size=shape) > 0.2)  # some fully masked
    f[0] = 1.0  # a fully visible texel
    u = rng.uniform(0.1, 1.0, shape)
    approx = np.clip(f + rng.normal(0.0, 0.05, shape) + 0.03, 0.0, 1.0) * (f > 0)
    approx[0] = 1.0  # reconstructed as fully visible: must stay so
    g = sum_correction(f, approx, u, bounded=True)
    fixed = apply_correction(approx, np.broadcast_to(g, shape), bounded=True)
    np.testing.assert_allclose((u * fixed).sum(axis=0), (u * f).sum(axis=0), rtol=1e-6)
    assert fixed.min() >= 0.0 and fixed.max() <= 1.0
    assert np.all(fixed[approx == 0] == 0.0) and np.allclose(fixed[0], 1.0, atol=1e-12)
    # direct texels (a_vis itself): multiplicative, exact, zero stays zero
    a = rng.uniform(0, 2, shape) * (rng.uniform(size=shape) > 0.3)
    a_approx = np.maximum(a * rng.uniform(0.9, 1.05, shape), 0.0)
    m = sum_correction(a, a_approx, np.ones(shape), bounded=False)
    got = apply_correction(a_approx, np.broadcast_to(m, shape), bounded=False)
    np.testing.assert_allclose(got.sum(axis=0), a.sum(axis=0), rtol=1e-6)
    assert np.all(got[a_approx == 0] == 0.0)


def _stored_and_errors(levels, keep, selection):
    """(stored bytes / dense float32 bytes over every level, worst texel's relative L2 error of
    the table the renderer reads against the uncompressed maps, over every level)."""
    from texelbake.cpm.avis.compress import texel_rel_errors
    from texelbake.cpm.avis.table import AvisTable

    nbytes, dense, worst = 0, 0.0, 0.0
    for lv in levels:
        n = lv.n_side ** 2
        table = compress_level(lv, np.broadcast_to(np.eye(3), (n, 3, 3)).copy(), keep,
                               selection=selection)
        # what the renderer reads: the payload arrays back into a table
        read = AvisTable.from_arrays(table.to_arrays())
        np.testing.assert_array_equal(read.haar.values, table.haar.values)
        nbytes += table.stored_bytes()
        dense += 4.0 * n * 6 * lv.res ** 2
        if lv.ray_texels.size:
            worst = max(worst, float(texel_rel_errors(read.ray_texel_maps(), lv.ray_maps).max()))
    return nbytes / dense, worst


@pytest.mark.slow  # ray-casts two 64² fields at res 32 (module fixtures)
def test_texel_budget_beats_the_seeds_per_face_quota(bumpy, grooves):
    # at the default resolution (32) the per-level texel budget stores about half of the
    # per-face quota at keep 0.06 for about its worst texel (measured: bumpy 1.31 % at 3.80 %
    # against 1.37 % at 7.6 %, V-grooves 1.40 % against 1.37 %; at res 16 the texel budget's
    # worst texel was the better one on both fields, 3.2 % against 3.8 % and 1.2 % against 8.5 %)
    for levels in (bumpy, grooves):
        st_t, worst_t = _stored_and_errors(levels, KEEP, "texel")
        st_f, worst_f = _stored_and_errors(levels, 0.06, "face")
        assert st_t <= 0.04 < st_f, (st_t, st_f)
        assert worst_t <= 0.02 and worst_t < 1.1 * worst_f, (worst_t, worst_f)


@pytest.mark.slow
@pytest.mark.parametrize("field", ["bumpy", "v-grooves"])
def test_every_texel_within_2_percent_at_4_percent_storage_res32(field, rng, request):
    # issue 11, item 1, at avis_resolution 32 (the default since 2026-11-27; 16 keeps too few
    # coefficients per texel, 3.2 % worst on the bumpy field), keep 0.03: measured worst texel
    # 1.3 % (bumpy) and 1.4 % (V-grooves) at 3.80 % storage, the identity within 0.16 % at
    # every level. Before 2026-11-27 the V-grooves' level 0 was 1.2-1.4 % off the identity
    # (the look-up's clamp to U(w)) and level 2 1.1 % (the power correction could not lower
    # texels reconstructed as fully visible)
    period = 1.0 / 8
    height = (periodic_height(0.05, seed=1) if field == "bumpy"
              else (lambda x, y: 0.06 * np.abs((x / period) % 1.0 - 0.5)))
    # at the default resolution the module's fields are these very levels (same mesh,
    # samples and rays): reused rather than ray-cast again
    levels = (request.getfixturevalue("bumpy" if field == "bumpy" else "grooves") if RES == 32
              else _levels(height, res=32))
    stored, worst = _stored_and_errors(levels, 0.03, "texel")
    assert stored <= 0.04, stored
    assert worst <= 0.02, worst
    w, cos_t = _dirs(rng, n=120)
    for i, level in enumerate(levels):
        tot = _total(level, w, True, keep=0.03)  # compress_level's default: correct_sum
        assert np.max(np.abs(tot - cos_t) / cos_t) < 0.01, i
