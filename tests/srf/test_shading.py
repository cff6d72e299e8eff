"""Surface reflectance fields, items 3-4: ULR over cameras and lights (seed 002 §5.2) and
deferred, cache-sorted shading operations (§5.3, Table 2)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import map_coordinates

from tests.helpers.render import quad
from texelbake.errors import SettingsError
from texelbake.geometry.raycast import RayCaster
from texelbake.srf.cache import BlockCache, shade
from texelbake.srf.ops import build_ops, naive_order, sorted_order
from texelbake.srf.rig import sphere_cameras, sphere_directions
from texelbake.srf.store import SrfWriter
from texelbake.srf.ulr import camera_weights, light_weights, ulr_weights
from texelbake.trace import camera as cam_mod


def test_ulr_weights_closed_form():
    pen = np.array([[0.3, 0.1, 0.2, 0.5]])
    idx, w, valid = ulr_weights(pen, 2)
    assert valid[0] and list(idx[0]) == [1, 2]
    t = 0.3  # the (k+1)-th penalty
    raw = np.array([(1 - 0.1 / t) / 0.1, (1 - 0.2 / t) / 0.2])
    np.testing.assert_allclose(w[0], raw / raw.sum(), rtol=1e-12)


def test_ulr_weights_hard_cases():
    # the capture ray itself: weight exactly 1
    idx, w, _ = ulr_weights(np.array([[0.4, 0.0, 0.2]]), 2)
    assert idx[0, 0] == 1 and w[0, 0] == 1.0 and w[0, 1] == 0.0
    # fewer usable than k + 1: threshold pi, all usable ones weigh
    _, w, valid = ulr_weights(np.array([[0.2, np.inf, 0.4]]), 3)
    assert valid[0] and np.count_nonzero(w[0]) == 2 and w.shape == (1, 3)
    # none usable: no weight, no NaN
    _, w, valid = ulr_weights(np.array([[np.inf, np.inf]]), 2)
    assert not valid[0] and np.all(w == 0)
    # ties at the threshold share equally
    _, w, valid = ulr_weights(np.array([[0.3, 0.3, 0.3]]), 2)
    np.testing.assert_allclose(w[0], [0.5, 0.5])
    with pytest.raises(SettingsError, match="'k'"):
        ulr_weights(np.zeros((1, 2)), 0)


def test_lights_as_cameras_at_infinity():
    cap = sphere_directions(20)
    idx, w, valid = light_weights(cap[[3, 7]], cap, 3)
    assert valid.all() and list(idx[:, 0]) == [3, 7] and np.all(w[:, 0] == 1.0)
    between = cap[3] + cap[4]
    _, w, _ = light_weights(between[None] / np.linalg.norm(between), cap, 3)
    assert np.isclose(w.sum(), 1.0) and w[0].max() < 1.0


def test_camera_visibility_excludes_occluded_cameras():
    cams = [cam_mod.look_at((0, 0, 5), (0, 0, 0), 16, 16),
            cam_mod.look_at((5, 0, 0.5), (0, 0, 0), 16, 16),
            cam_mod.look_at((0.5, 5, 0), (0, 0, 0), 16, 16)]
    v, f = quad(-1, 1, -1, 1, 2.0)  # a blocker between the point and the +z camera
    occ = RayCaster(v, f)
    p = np.zeros((1, 3))
    view = np.array([[0.0, 0.0, 1.0]])  # asks for the +z camera's ray
    cam, w, xy, valid = camera_weights(cams, p, view, 2, None, 1e-4)
    assert cam[0, 0] == 0 and w[0, 0] == 1.0
    np.testing.assert_allclose(xy[0, 0], [8, 8], atol=1e-9)
    cam, w, _, valid = camera_weights(cams, p, view, 2, occ, 1e-4)
    assert valid[0] and 0 not in cam[0][w[0] > 0]


@pytest.fixture(scope="module")
def rand_store(tmp_path_factory):
    root = tmp_path_factory.mktemp("ops")
    cams = sphere_cameras(np.array([[-1.0, -1, -1], [1, 1, 1]]), 4, 9)
    rng = np.random.default_rng(5)
    stores = {}
    for enc in ("raw", "pca"):
        w = SrfWriter(root / enc, cams, sphere_directions(3), encoding=enc, tile=4,
                      components=3)
        for c in range(4):
            for j in range(3):
                w.write(c, j, rng.random((9, 9, 3)))
        stores[enc] = w.close()
    return stores


def _random_ops(n_points, rng, s=2, kc=3, kl=2):
    ci = np.stack([rng.permutation(4)[:kc] for _ in range(n_points)])
    cw = rng.random((n_points, kc))
    xy = rng.uniform(-0.5, 9.5, (n_points, kc, 2))
    li = rng.integers(0, 3, (s, n_points, kl))
    lw = rng.random((s, n_points, kl))
    rad = rng.random((s, n_points, 3))
    return build_ops(ci, cw, xy, li, lw, rad), (ci, cw, xy, li, lw, rad)


@pytest.mark.parametrize("enc", ["raw", "pca"])
def test_sorted_and_naive_are_bit_identical_and_match_brute_force(rand_store, enc):
    st = rand_store[enc]
    rng = np.random.default_rng(6)
    ops, (ci, cw, xy, li, lw, rad) = _random_ops(200, rng)
    assert len(ops) == 200 * 2 * 3 * 2
    a, sa = shade(st, ops, 200, "sorted")
    b, sb = shade(st, ops, 200, "naive")
    assert np.array_equal(a, b)  # bit-identical
    assert sa.block_reads == len({(c, j) for c, j in zip(ops.camera, ops.light, strict=True)})
    assert sb.block_reads > 10 * sa.block_reads
    assert sa.peak_resident_bytes <= 3 * st.block_nbytes()
    # brute force: every point, light, camera, capture light with scipy's bilinear sampling
    imgs = {(c, j): st.image(c, j) for c in range(4) for j in range(3)}
    ref = np.zeros((200, 3))
    for p in range(0, 200, 37):  # a few points, looped (the independent truth)
        for s in range(2):
            for kc in range(3):
                for kl in range(2):
                    img = imgs[ci[p, kc], li[s, p, kl]]
                    val = [map_coordinates(img[:, :, ch], [[xy[p, kc, 1] - 0.5],
                                                           [xy[p, kc, 0] - 0.5]],
                                           order=1, mode="nearest")[0] for ch in range(3)]
                    ref[p] += cw[p, kc] * lw[s, p, kl] * rad[s, p] * np.array(val)
        np.testing.assert_allclose(a[p], ref[p], rtol=1e-9, atol=1e-12)


def test_orders_and_cache_errors(rand_store):
    rng = np.random.default_rng(7)
    ops, _ = _random_ops(30, rng)
    so = sorted_order(ops)
    assert sorted(so.tolist()) == naive_order(ops).tolist()
    key = ops.camera[so] * 3 + ops.light[so]
    assert np.all(np.diff(key) >= 0)
    with pytest.raises(SettingsError, match="executor"):
        shade(rand_store["raw"], ops, 30, "random")
    with pytest.raises(SettingsError, match="cache_blocks"):
        BlockCache(rand_store["raw"], 0)
    # zero-weight operations are never generated
    ci = np.zeros((2, 1), np.int64)
    ops0 = build_ops(ci, np.array([[1.0], [0.0]]), np.full((2, 1, 2), 4.0),
                     np.zeros((1, 2, 1), np.int64), np.ones((1, 2, 1)), np.ones((1, 2, 3)))
    assert len(ops0) == 1 and ops0.target[0] == 0


def test_environment_map_as_lights_conserves_energy_and_places_a_sun():
    from texelbake.srf.environment import environment_lights, latlong_directions

    lights = environment_lights(np.full((32, 64, 3), 0.5), 40)
    total = np.sum([lt.radiance_scale for lt in lights], axis=0)
    np.testing.assert_allclose(total, 4 * np.pi * 0.5, rtol=2e-3)  # Σ L ΔΩ = 4π L
    assert len(lights) == 40
    env = np.zeros((32, 64, 3))
    env[5, 20] = 100.0  # one bright pixel: all its energy in the nearest light
    d, dw = latlong_directions(32, 64)
    sun = d[5 * 64 + 20]
    lights = environment_lights(env, 40)
    assert len(lights) == 1
    np.testing.assert_allclose(lights[0].radiance_scale, 100.0 * dw[5 * 64 + 20])
    assert float(lights[0].direction @ sun) > 0.8
    with pytest.raises(SettingsError, match="up"):
        environment_lights(env, 4, up="X")


def test_camera_weights_do_not_depend_on_the_batch_size(monkeypatch):
    import texelbake.srf.ulr as ulr_mod

    cams = sphere_cameras(np.array([[-1.0, -1, -1], [1, 1, 1]]), 20, 16)
    rng = np.random.default_rng(8)
    p, v = 0.3 * rng.normal(size=(500, 3)), rng.normal(size=(500, 3))
    whole = camera_weights(cams, p, v, 3, None, 1e-3)
    monkeypatch.setattr(ulr_mod, "PAIR_BATCH", 20 * 37)  # 14 batches
    parts = camera_weights(cams, p, v, 3, None, 1e-3)
    assert all(np.array_equal(a, b) for a, b in zip(whole, parts, strict=True))
