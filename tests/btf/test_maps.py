"""End-to-end Laplacian BTF: build, reconstruct, Eq. 7 look-up, hard cases (seed 001)."""

import numpy as np
import pytest

from texelbake.btf.color import rgb_to_ycbcr
from texelbake.btf.compress import BTFSettings, build_btf_maps
from texelbake.btf.laplacian import build_pyramid, expand
from texelbake.btf.lod import lod_from_distance, lod_weights, reconstruct_btf
from texelbake.btf.lut import bonn_directions, build_lut, lookup_pairs
from texelbake.btf.render import btf_lookup, btf_lookup_texels
from texelbake.btf.report import btf_errors, compression_stats
from texelbake.btf.synthetic import synthetic_btf
from texelbake.errors import NumericalError, SettingsError, ShapeError

N_DIR = 6
ALL = (400, 400, 400)  # more components than any level has: nothing dropped


def _grid(n=N_DIR):
    dirs = bonn_directions()[:n]
    return np.repeat(dirs, n, axis=0), np.tile(dirs, (n, 1))


def _btf(rng, h=9, w=7, n=N_DIR):
    di, do = _grid(n)
    return rng.random((n * n, h, w, 3)).astype(np.float32), di, do


@pytest.mark.parametrize(("h", "w", "filt"), [(9, 7, "box3"), (16, 16, "box3"), (1, 1, "box3"),
                                              (2, 13, "box3"), (9, 7, "gauss5")])
def test_all_components_reconstruct_input(rng, h, w, filt):
    btf, di, do = _btf(rng, h, w)
    top = int(np.ceil(np.log2(max(h, w))))  # down to a 1 x 1 top level
    maps, info = build_btf_maps(btf, di, do, BTFSettings(n_components=ALL, top_level=top,
                                                           pyramid_filter=filt))
    assert maps.weights[-1].shape[:2] == (1, 1)
    rec = reconstruct_btf(maps)
    assert rec.shape == btf.shape
    assert np.abs(rec - btf).max() < 1e-5  # the acceptance bound (float32 maps)


def test_constant_images_and_fewer_texels_than_components(rng):
    di, do = _grid()
    values = rng.random((N_DIR * N_DIR, 1, 1, 3)).astype(np.float32)
    btf = np.broadcast_to(values, (N_DIR * N_DIR, 4, 6, 3)).copy()  # constant per image
    maps, info = build_btf_maps(btf, di, do, BTFSettings(n_components=(8, 2, 2), top_level=2))
    assert np.all(np.isfinite(maps.eigen))
    for k in range(2):  # Laplacian levels of constant images are zero
        assert np.abs(maps.weights[k]).max() < 1e-6
    assert any("non-zero" in n for n in info.notes)
    assert np.abs(reconstruct_btf(maps) - btf).max() < 1e-5  # top: 2 texels < 8 components


def test_zero_valued_directions_below_horizon(rng):
    btf, di, do = _btf(rng)
    do = do.copy()
    below = np.arange(0, do.shape[0], 5)
    do[below, 2] = -do[below, 2]
    do[below[0]] = [0.0, 0.0, -1.0]
    btf[below] = 0.0
    maps, info = build_btf_maps(btf, di, do, BTFSettings(n_components=(6, 2, 2)))
    assert any("below the horizon" in n for n in info.notes)
    assert maps.mean_models[0] == "phong"
    rec = reconstruct_btf(maps)
    assert np.all(np.isfinite(rec))
    # look-ups below the horizon return exactly zero
    n = below.size
    uv = np.full((n, 2), 0.5)
    out = btf_lookup(maps, uv, maps.dirs_i[below], maps.dirs_o[below], np.zeros(n))
    assert np.all(out == 0.0)
    err = btf_errors(btf, maps)
    assert set(err) == {"Y", "Cb", "Cr"} and err["Y"]["max"] >= err["Y"]["avg"] >= err["Y"]["min"]


def test_phong_fallback_keeps_table_and_stays_exact(rng):
    btf, di, do = _btf(rng)
    maps, info = build_btf_maps(btf, di, do, BTFSettings(n_components=ALL, fit_phong=False))
    assert maps.mean_models == ("table", "constant", "constant")
    assert "tabulated" in info.fit_message
    assert np.abs(reconstruct_btf(maps) - btf).max() < 1e-5


def test_adversarial_mean_triggers_fallback_in_build():
    di, do = _grid()
    btf = np.zeros((N_DIR * N_DIR, 4, 4, 3), np.float32)
    btf[0] = 1.0  # only the normal-incidence pair is lit: Phong would need alpha -> inf
    maps, info = build_btf_maps(btf, di, do, BTFSettings(n_components=(4, 2, 2)))
    assert maps.mean_models[0] == "table"
    assert any("Phong fit rejected" in n for n in info.notes)


def test_lookup_at_grid_equals_reconstruction_and_eq7_blend(rng):
    btf, di, do = _btf(rng, 10, 12)
    maps, _ = build_btf_maps(btf, di, do, BTFSettings(n_components=(5, 2, 2), top_level=2))
    n = 300
    rows = rng.integers(0, 10, n)
    cols = rng.integers(0, 12, n)
    pair = rng.integers(0, N_DIR * N_DIR, n)
    wi, wo = maps.dirs_i[pair].astype(np.float64), maps.dirs_o[pair].astype(np.float64)
    rec = {lam: reconstruct_btf(maps, lam) for lam in (0.0, 1.0, 2.0)}
    for interp in (False, True):
        got = btf_lookup_texels(maps, rows, cols, wi, wo, np.zeros(n), interp)
        assert np.abs(got - rec[0.0][pair, rows, cols]).max() < 1e-5
    # Eq. 7: lambda = 1.3 blends levels 1 (weight 0.7) and 2+ (weight 1):
    # R(1.3) = 0.7 R(1) + 0.3 R(2)
    got = btf_lookup_texels(maps, rows, cols, wi, wo, np.full(n, 1.3))
    want = 0.7 * rec[1.0][pair, rows, cols] + 0.3 * rec[2.0][pair, rows, cols]
    assert np.abs(got - want).max() < 1e-5
    # uv addressing: texel centres map to their texel (row 0 at v = 1)
    uv = np.stack([(cols + 0.5) / 12, 1.0 - (rows + 0.5) / 10], axis=1)
    assert np.array_equal(btf_lookup(maps, uv, wi, wo, np.zeros(n)),
                          btf_lookup_texels(maps, rows, cols, wi, wo, np.zeros(n)))


def test_lod_one_with_all_components_is_the_filtered_btf(rng):
    # independent truth: the pyramid's own level-1 low-pass image, nearest-upsampled
    btf, di, do = _btf(rng, 8, 6)
    maps, _ = build_btf_maps(btf, di, do, BTFSettings(n_components=ALL, top_level=2))
    ycc = np.moveaxis(rgb_to_ycbcr(btf.astype(np.float64)), 0, 2)  # (h, w, d, 3)
    f1 = build_pyramid(ycc, 1)[1]  # F_1, (4, 3, d, 3)
    want = expand(f1, (8, 6))  # (8, 6, d, 3)
    rec = reconstruct_btf(maps, 1.0)  # (d, 8, 6, 3) RGB
    got = np.moveaxis(rgb_to_ycbcr(rec.astype(np.float64)), 0, 2)
    assert np.abs(got - want).max() < 1e-5


def test_lod_weights_closed_form():
    w = lod_weights(np.array([0.0, 0.25, 1.0, 2.5, 9.0, -3.0]), 3)
    assert np.allclose(w[0], [1, 1, 1, 1])
    assert np.allclose(w[1], [0.75, 1, 1, 1])
    assert np.allclose(w[2], [0, 1, 1, 1])
    assert np.allclose(w[3], [0, 0, 0.5, 1])
    assert np.allclose(w[4], [0, 0, 0, 1])  # clamped to lambda_max
    assert np.allclose(w[5], [1, 1, 1, 1])
    assert np.allclose(lod_from_distance(np.array([0.5, 2.0, 8.0, 1e9]), 4), [0, 1, 3, 4])


def test_direction_lut_nearest_and_interpolated():
    dirs = bonn_directions()
    di, do = np.repeat(dirs, 81, axis=0), np.tile(dirs, (81, 1))
    lut = build_lut(di, do, resolution=64)
    assert lut.is_product and lut.pair_index.shape == (81, 81)
    # every sampled pair finds itself through the tables
    cols, w = lookup_pairs(lut, di, do)
    assert np.array_equal(cols[:, 0], np.arange(81 * 81)) and np.all(w == 1)
    # nearest through the table agrees with brute-force nearest for random directions
    rng = np.random.default_rng(0)
    q = rng.standard_normal((500, 3))
    q[:, 2] = np.abs(q[:, 2]) + 0.2
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    cols, _ = lookup_pairs(lut, q, q)
    li = np.argmax(q @ lut.light_dirs.T, axis=1)
    vi = np.argmax(q @ lut.view_dirs.T, axis=1)
    assert np.mean(cols[:, 0] == lut.pair_index[li, vi]) > 0.85
    # the table quantises directions to 64 x 64 cells of the equal-area disk (cell side 2/64,
    # at most ~0.07 rad across): a different answer is a near tie within two cell diameters
    got_i, got_o = lut.light_dirs[cols[:, 0] // 81], lut.view_dirs[cols[:, 0] % 81]
    for got, best in ((got_i, lut.light_dirs[li]), (got_o, lut.view_dirs[vi])):
        lag = np.arccos(np.clip(np.sum(q * got, 1), -1, 1)) - np.arccos(
            np.clip(np.sum(q * best, 1), -1, 1))
        assert lag.max() < 0.14
    cols, w = lookup_pairs(lut, q, q, interpolate=True)
    assert np.allclose(w.sum(axis=1), 1.0) and np.all(w >= 0)
    # continuity: a tiny move changes the interpolation weights by a tiny amount
    eps = 1e-7
    q2 = q + eps
    q2 /= np.linalg.norm(q2, axis=1, keepdims=True)
    c2, w2 = lookup_pairs(lut, q2, q2, interpolate=True)
    f = np.zeros(81 * 81)
    f[:] = np.arange(81 * 81) % 17
    assert np.abs((f[cols] * w).sum(1) - (f[c2] * w2).sum(1)).max() < 1e-3


def test_non_product_pairs_fall_back_to_nearest_pair(rng):
    di = bonn_directions()[rng.permutation(81)[:20]]
    do = bonn_directions()[rng.permutation(81)[:20]]
    lut = build_lut(di, do)
    assert not lut.is_product
    cols, w = lookup_pairs(lut, di, do)
    assert np.array_equal(cols[:, 0], np.arange(20))
    cols, w = lookup_pairs(lut, di, do, interpolate=True)
    assert np.allclose((cols * w).sum(1), np.arange(20))


def test_compression_ratio_matches_seed_accounting():
    # 64 x 64 texels, 81 x 81 pairs, (8, 2, 2), lambda_max = 4: the seed's 80,621,568 raw bytes
    # and maps of 1,574,640 + 5456 * 48 bytes. Checked on a cheap stand-in with the same
    # shapes (accounting only depends on the shapes).
    from texelbake.btf.compress import BTFMaps

    lut = build_lut(*_grid(2))
    maps = BTFMaps(
        eigen=np.zeros((5, 6561, 12), np.float32),
        weights=tuple(np.zeros((s, s, 12), np.float32) for s in (64, 32, 16, 8, 4)),
        n_components=(8, 2, 2), mean_models=("phong", "constant", "constant"),
        mean_params=np.zeros((3, 4)), mean_table=np.zeros((3, 6561), np.float32),
        dirs_i=np.zeros((6561, 3), np.float32), dirs_o=np.zeros((6561, 3), np.float32), lut=lut)
    s = compression_stats(maps)
    assert s["raw_bytes_8bit"] == 80_621_568
    assert s["compressed_bytes"] == 1_574_640 + 5456 * 48 + 4 * 6
    assert 43.85 < s["compression_ratio"] < 43.95


def test_synthetic_btf_is_deterministic_and_structured():
    dirs = bonn_directions()[::9]  # 9 directions
    a, di, do = synthetic_btf(16, dirs, dirs, seed=3)
    b, _, _ = synthetic_btf(16, dirs, dirs, seed=3)
    assert a.tobytes() == b.tobytes()
    assert a.shape == (81, 16, 16, 3) and 0 <= a.min() and a.max() <= 1
    assert np.allclose(di[:9], dirs[0]) and np.allclose(do[:9], dirs)
    # structured, not noise: 4 Y components of level 0 capture most of the energy
    maps, _ = build_btf_maps(a, di, do, BTFSettings(n_components=(4, 2, 2)))
    err = btf_errors(a, maps)
    assert err["Y"]["avg"] < 0.01


def test_input_errors(rng):
    btf, di, do = _btf(rng)
    with pytest.raises(ShapeError, match=r"\(d, h, w, 3\)"):
        build_btf_maps(btf[..., :2], di, do)
    with pytest.raises(ShapeError, match="dirs_i and dirs_o"):
        build_btf_maps(btf, di[:3], do)
    bad = btf.copy()
    bad[0, 0, 0, 0] = np.nan
    with pytest.raises(NumericalError, match="btf contains NaN"):
        build_btf_maps(bad, di, do)
    with pytest.raises(ShapeError, match="unit"):
        build_btf_maps(btf, di * 2, do)
    with pytest.raises(SettingsError, match="n_components"):
        BTFSettings(n_components=(0, 0, 0))
    with pytest.raises(SettingsError, match="pyramid_filter"):
        BTFSettings(pyramid_filter="lanczos")
    maps, _ = build_btf_maps(btf, di, do, BTFSettings(n_components=(2, 1, 1)))
    with pytest.raises(ShapeError, match="texel_uv"):
        btf_lookup(maps, np.zeros((3, 3)), di[:3], do[:3], np.zeros(3))
    with pytest.raises(NumericalError):
        btf_lookup(maps, np.zeros((1, 2)), di[:1], do[:1], np.array([np.nan]))
    assert btf_lookup(maps, np.zeros((0, 2)), np.zeros((0, 3)), np.zeros((0, 3)),
                      np.zeros(0)).shape == (0, 3)


def test_rebuild_is_byte_identical_with_randomized_pca(rng):
    btf, di, do = _btf(rng, 24, 20, n=8)  # 480 texels x 64 pairs at level 0
    s = BTFSettings(n_components=(4, 2, 2), pca_method="randomized", top_level=2)
    a, ia = build_btf_maps(btf, di, do, s)
    b, ib = build_btf_maps(btf.copy(), di, do, s)
    assert ia.pca_methods[0] == "randomized"
    assert a.eigen.tobytes() == b.eigen.tobytes()
    assert all(x.tobytes() == y.tobytes() for x, y in zip(a.weights, b.weights, strict=True))
    assert a.mean_params.tobytes() == b.mean_params.tobytes()
