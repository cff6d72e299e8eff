"""The viewer/inspector extraction (`services.viewer_data`) on a small baked plane with BTF
maps: meshes, texel arrays and BTF maps come out as the baked USD and the EXR maps hold them,
and the a_vis grid of a flat unoccluded texel is its closed form, a_vis / A = cos(theta)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from services.viewer_data import AVIS_PHI, AVIS_THETA, CORNER_FLOATS, extract, polar_dirs
from tests.helpers.render import write_plane_usd


@pytest.fixture(scope="module")
def baked(tmp_path_factory) -> Path:
    from schemas.settings import BakeSettings
    from texelbake.pipeline.run import bake

    d = tmp_path_factory.mktemp("viewer_plane")
    src = write_plane_usd(d / "plane.usda")
    settings = BakeSettings(atlas_resolution=16, shard_texels=16, samples_per_texel=4,
                            n_light_dirs=8, n_view_dirs=8, n_heldout=4, c_max=4,
                            avis_resolution=4, mesh_levels=1, btf=True)  # fmt: skip
    return Path(bake(src, d / "baked", settings, progress=False))


@pytest.fixture(scope="module")
def out(baked, tmp_path_factory) -> Path:
    o = tmp_path_factory.mktemp("viewer")
    extract(baked, o)
    return o


def f32(path: Path, shape) -> np.ndarray:  # noqa: ANN001
    return np.frombuffer(path.read_bytes(), dtype="<f4").reshape(shape)


def test_meshes_and_texels_are_the_baked_ones(baked, out):
    from texelbake.usd.read import read_baked

    b = read_baked(baked)
    man = json.loads((out / "manifest.json").read_text())
    assert man["atlas"] == 16 and len(man["lods"]) == len(b.meshes)
    for lod, m in zip(man["lods"], b.meshes, strict=True):
        corners = f32(out / lod["file"], (-1, CORNER_FLOATS))
        assert corners.shape[0] == lod["vertices"] == 3 * m.faces.shape[0]
        np.testing.assert_allclose(corners[:, :3], m.vertices[m.faces].reshape(-1, 3), atol=1e-6)
        np.testing.assert_allclose(corners[:, 3:5], m.corner_uvs.reshape(-1, 2), atol=1e-6)
        # the face normal (from the positions, independently), then an orthonormal t, b
        tri = m.vertices[m.faces]
        fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        fn /= np.linalg.norm(fn, axis=1, keepdims=True)
        np.testing.assert_allclose(corners[:, 5:8], np.repeat(fn, 3, axis=0), atol=1e-5)
        t, bt = corners[:, 8:11], corners[:, 11:14]
        np.testing.assert_allclose(np.sum(t * corners[:, 5:8], axis=1), 0.0, atol=1e-5)
        np.testing.assert_allclose(np.abs(np.sum(np.cross(t, bt) * corners[:, 5:8], axis=1)), 1.0,
                                   atol=1e-5)  # fmt: skip
    tex = json.loads((out / "texels.json").read_text())
    lvl = b.levels[0]
    assert tex["points"] == np.diff(lvl["texel_offsets"]).tolist()
    assert tex["valid"] == lvl["texel_valid"].tolist()
    snr = np.array([np.nan if v is None else v for v in tex["snr_heldout_db"]])
    ref = lvl["texel_snr_heldout"].astype(np.float64)
    assert np.array_equal(np.isnan(snr), ~np.isfinite(ref))
    np.testing.assert_allclose(snr[np.isfinite(ref)], ref[np.isfinite(ref)], atol=1e-4)
    assert (out / "albedo.png").read_bytes()[:4] == b"\x89PNG"


def test_avis_grid_of_a_flat_texel_is_cos_theta(baked, out):
    """A flat, unoccluded texel of area A shows A cos(theta) to a view at theta from its
    normal (the projected area): the grid, divided by A, is cos(theta) at every cell centre."""
    from texelbake.usd.read import read_baked

    lvl = read_baked(baked).levels[0]
    avis = f32(out / "avis.bin", (-1, AVIS_THETA, AVIS_PHI))
    full = np.flatnonzero(lvl["avis:texel_area"] > 0)
    assert full.size > 0.5 * avis.shape[0]
    cos_t = polar_dirs()[..., 2]
    np.testing.assert_allclose(avis[full], np.broadcast_to(cos_t, avis[full].shape), atol=1e-6)
    empty = np.flatnonzero(lvl["avis:texel_area"] <= 0)
    assert np.all(avis[empty] == 0.0)


def test_btf_maps_come_out_as_stored(baked, out):
    from texelbake.btf import read_btf_maps

    maps = read_btf_maps(baked.parent, "btf")
    btf = json.loads((out / "manifest.json").read_text())["btf"]
    assert btf["n_components"] == list(maps.n_components) and btf["top_level"] == maps.top_level
    eigen = f32(out / "btf_eigen.bin", btf["eigen"]["shape"])
    assert np.array_equal(eigen, maps.eigen.astype(np.float32))
    canvas = f32(out / "btf_weights.bin", btf["weights"]["shape"])
    for w, (h, wd), (y, x) in zip(maps.weights, btf["levels"], btf["weight_offsets"], strict=True):
        assert np.array_equal(canvas[y : y + h, x : x + wd], w.astype(np.float32))
    lut = f32(out / "btf_lut.bin", btf["lut"]["shape"])
    assert np.array_equal(lut[..., 0], maps.lut.light_table)
    assert np.array_equal(lut[..., 1], maps.lut.view_table)
    pairs = f32(out / "btf_pair_index.bin", btf["pair_index"]["shape"])
    assert np.array_equal(pairs, maps.lut.pair_index)
