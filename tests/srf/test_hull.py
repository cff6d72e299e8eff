"""Surface reflectance fields, item 2 (the seed's impostor): the visual hull carved from
the captured silhouettes, as a cuberille mesh sampled into surfels."""

from __future__ import annotations

import numpy as np
import pytest

from tests.helpers.render import icosphere
from tests.helpers.srf import sphere_asset
from texelbake.errors import AssetError, SettingsError
from texelbake.render.metrics import psnr_db
from texelbake.srf.capture import capture, unit_light
from texelbake.srf.deferred import render_srf
from texelbake.srf.hull import carve, cuberille, visual_hull
from texelbake.srf.store import SrfWriter
from texelbake.srf.surfels import surfels_from_mesh


def _signed_volume(v, f):
    t = v[f]
    return float(np.einsum("ij,ij->i", t[:, 0], np.cross(t[:, 1], t[:, 2])).sum() / 6.0)


def test_cuberille_is_closed_and_outward():
    occ = np.zeros((3, 3, 3), bool)
    occ[1, 1, 1] = True
    v, f = cuberille(occ, np.zeros(3), 0.5)
    assert v.shape == (8, 3) and f.shape == (12, 3)
    assert _signed_volume(v, f) == pytest.approx(0.125)
    occ[1, 1, 2] = occ[2, 1, 1] = True  # an L of three voxels
    v, f = cuberille(occ, np.zeros(3), 1.0)
    assert _signed_volume(v, f) == pytest.approx(3.0)
    edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    assert np.all(counts % 2 == 0)  # closed: every edge shared by an even number of faces


@pytest.fixture(scope="module")
def sphere_store(tmp_path_factory):
    return capture(sphere_asset(2), tmp_path_factory.mktemp("hull") / "s", n_cameras=12,
                   n_lights=2, size=32, spp=2)


def test_visual_hull_encloses_the_object_and_is_near_it(sphere_store):
    occ, lo, edge = carve(sphere_store, 32)
    pts, faces = icosphere(3)
    vox = np.floor((pts - lo) / edge).astype(int)
    assert occ[vox[:, 0], vox[:, 1], vox[:, 2]].all()  # conservative: nothing carved away
    vol = occ.sum() * edge ** 3
    assert 4.19 < vol < 2.5 * 4.19  # the unit sphere's 4π/3, and a 12-view hull's excess
    v, f = visual_hull(sphere_store, 32)
    assert _signed_volume(v, f) == pytest.approx(vol)


def test_hull_surfels_render_capture_views(sphere_store):
    v, f = visual_hull(sphere_store, 32)
    surf = surfels_from_mesh(v, f)
    for c in (0, 7):
        res = render_srf(sphere_store, surf, sphere_store.cameras[c],
                         [unit_light(sphere_store.light_dirs[1], 0)])
        assert psnr_db(res.image, sphere_store.image(c, 1)) >= 40.0


def test_carving_errors(sphere_store, tmp_path):
    with pytest.raises(SettingsError, match="resolution"):
        carve(sphere_store, 1)
    w = SrfWriter(tmp_path / "nosil", sphere_store.cameras[:1], [[0, 0, 1.0]])
    w.write(0, 0, np.zeros((32, 32, 3)))
    st = w.close({"bounds": [[-1, -1, -1], [1, 1, 1]]})
    with pytest.raises(AssetError, match="silhouette"):
        carve(st, 8)
    w.write_silhouette(0, np.zeros((32, 32)))  # the camera sees nothing: all carved
    st = w.close({"bounds": [[-1, -1, -1], [1, 1, 1]]})
    with pytest.raises(SettingsError, match="carve every voxel"):
        visual_hull(st, 8, bounds=[[-0.1, -0.1, -0.1], [0.1, 0.1, 0.1]])
