"""Surface reflectance fields, item 1: synthetic capture with `gt`, import of a measured
field, the chunked block store, per-block PCA (seed 002 §3, §6)."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from tests.helpers.srf import sphere_asset
from texelbake.errors import AssetError, SettingsError
from texelbake.io.images import write_exr, write_png
from texelbake.srf import pca
from texelbake.srf.capture import capture, unit_light
from texelbake.srf.measured import import_measured
from texelbake.srf.rig import camera_to_json, project, sphere_cameras, sphere_directions
from texelbake.srf.store import SrfWriter, open_store, sample_bilinear
from texelbake.trace.org import render_model


@pytest.fixture(scope="module")
def small_capture(tmp_path_factory):
    out = tmp_path_factory.mktemp("srf") / "cap"
    return capture(sphere_asset(1), out, n_cameras=3, n_lights=2, size=12, spp=1)


def test_capture_blocks_are_gt_images_under_one_unit_light(small_capture):
    st = small_capture
    assert (st.n_cameras, st.n_lights, st.width, st.height) == (3, 2, 12, 12)
    files = sorted((st.path / "blocks").glob("*.npy"))
    assert len(files) == 6  # one block per reflectance image
    asset = sphere_asset(1)
    for c, j in ((0, 0), (2, 1)):
        one = dataclasses.replace(asset, lights=(unit_light(st.light_dirs[j], j),))
        ref = render_model(one, st.cameras[c], spp=1, seed=0).image
        np.testing.assert_array_equal(st.image(c, j).astype(np.float32), ref)
        assert ref.max() > 0.05  # the object is lit and seen


def test_capture_is_byte_identical_on_rerun(small_capture, tmp_path):
    again = capture(sphere_asset(1), tmp_path / "again", n_cameras=3, n_lights=2, size=12,
                    spp=1)
    for a in sorted(small_capture.path.rglob("*.npy")):
        b = again.path / a.relative_to(small_capture.path)
        assert a.read_bytes() == b.read_bytes()
    ma = json.loads((small_capture.path / "srf.json").read_text())
    mb = json.loads((again.path / "srf.json").read_text())
    ma.pop("source"), mb.pop("source")
    assert ma == mb


def test_rig_directions_and_projection():
    d = sphere_directions(200)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-12)
    assert abs(d.mean(axis=0)).max() < 0.02  # evenly spread: centroid near 0
    cams = sphere_cameras(np.array([[-1.0, -1, -1], [1, 1, 1]]), 5, 16)
    for cam in cams:  # the centre projects to the image centre
        xy, front = project(cam, np.zeros((1, 3)))
        assert front[0]
        np.testing.assert_allclose(xy[0], [8.0, 8.0], atol=1e-9)
    with pytest.raises(SettingsError, match="count"):
        sphere_directions(0)


def test_bilinear_lookup_hits_pixel_centres_and_blends_between():
    rng = np.random.default_rng(0)
    img = rng.random((5, 7, 3)).astype(np.float32)
    from texelbake.srf.store import RawBlock

    blk = RawBlock(img)
    iy, ix = np.divmod(np.arange(35), 7)
    got = sample_bilinear(blk, ix + 0.5, iy + 0.5, 7, 5)
    np.testing.assert_array_equal(got, img[iy, ix].astype(np.float64))
    mid = sample_bilinear(blk, np.array([2.0]), np.array([1.5]), 7, 5)
    np.testing.assert_allclose(mid[0], 0.5 * (img[1, 1] + img[1, 2]), rtol=1e-6)


def test_pca_error_is_the_discarded_singular_energy():
    rng = np.random.default_rng(1)
    img = rng.random((16, 12, 3))
    for k in (1, 4, 47):
        flat = pca.encode(img, 4, k)
        dec = pca.decode_image(flat, 16, 12, 4, k)
        vec = img.reshape(4, 4, 3, 4, 3).transpose(0, 2, 1, 3, 4).reshape(12, -1)
        s = np.linalg.svd(vec - vec.mean(axis=0), compute_uv=False)
        # Eckart–Young: the rank-k error of the centred tiles (float32 storage: 1e-5)
        np.testing.assert_allclose(np.sum((dec - img) ** 2), np.sum(s[k:] ** 2),
                                   rtol=1e-4, atol=1e-8)


def test_pca_with_more_components_than_tiles_is_exact():
    img = np.random.default_rng(2).random((3, 3, 3))  # one padded tile, k > T
    dec = pca.decode_image(pca.encode(img, 4, 6), 3, 3, 4, 6)
    np.testing.assert_allclose(dec, img, atol=1e-6)


def test_pca_store_compresses_and_reports(tmp_path):
    cams = sphere_cameras(np.array([[-1.0, -1, -1], [1, 1, 1]]), 2, 64)
    w = SrfWriter(tmp_path / "p", cams, sphere_directions(2), encoding="pca", tile=8,
                  components=4)
    rng = np.random.default_rng(3)
    base = rng.random((64, 64, 3))
    for c in range(2):
        for j in range(2):
            w.write(c, j, base * (1 + c + j))
    st = w.close()
    # 64² x 3 floats against 192 (4 + 1) + 64 tiles x 4: the seed's >= 10x
    assert st.meta["stats"]["compression_ratio"] == pytest.approx(12288 / 1216)
    assert st.meta["stats"]["pca_snr_db"] > 0
    assert st.image(1, 1).shape == (64, 64, 3)
    assert st.block_path(0, 0).stat().st_size < 64 * 64 * 3 * 4 / 9.5


def test_writer_refuses_bad_input(tmp_path):
    cams = sphere_cameras(np.array([[-1.0, -1, -1], [1, 1, 1]]), 1, 8)
    w = SrfWriter(tmp_path / "s", cams, [[0, 0, 1.0]])
    with pytest.raises(Exception, match=r"\(8, 8, 3\)"):
        w.write(0, 0, np.zeros((4, 4, 3)))
    with pytest.raises(AssetError, match="NaN"):
        w.write(0, 0, np.full((8, 8, 3), np.nan))
    with pytest.raises(SettingsError, match="not written"):
        w.close()
    with pytest.raises(SettingsError, match="encoding"):
        SrfWriter(tmp_path / "t", cams, [[0, 0, 1.0]], encoding="zip")
    with pytest.raises(AssetError, match="srf.json"):
        open_store(tmp_path / "nothing")


def _measured_rig(tmp_path, n_cams=2, n_lights=2):
    cams = sphere_cameras(np.array([[-1.0, -1, -1], [1, 1, 1]]), n_cams, 10)
    rng = np.random.default_rng(4)
    images, truth = [], {}
    for c in range(n_cams):
        row = []
        for j in range(n_lights):
            img = rng.random((10, 10, 3)).astype(np.float32)
            if j % 2:  # an LDR image: sRGB PNG
                name = f"c{c}_l{j}.png"
                write_png(tmp_path / name, img)
                from texelbake.io.images import read_image, srgb_to_linear

                truth[c, j] = srgb_to_linear(read_image(tmp_path / name))
            else:
                name = f"c{c}_l{j}.exr"
                write_exr(tmp_path / name, img * 4.0)
                truth[c, j] = img * 2.0  # irradiance 2
            row.append(name)
        images.append(row)
    truth = {k: (v if k[1] % 2 == 0 else v / 2.0) for k, v in truth.items()}
    desc = {"cameras": [camera_to_json(c) for c in cams],
            "lights": [{"direction": list(d)} for d in sphere_directions(n_lights)],
            "images": images, "irradiance": 2.0}
    (tmp_path / "rig.json").write_text(json.dumps(desc))
    return desc, truth


def test_import_measured_reads_hdr_and_ldr(tmp_path):
    desc, truth = _measured_rig(tmp_path)
    mask = np.zeros((10, 10, 1))
    mask[2:7, 3:8] = 1.0
    write_exr(tmp_path / "m.exr", np.repeat(mask, 3, axis=2))
    desc = dict(desc, masks=["m.exr", "m.exr"], bounds=[[-1, -1, -1], [1, 1, 1]])
    (tmp_path / "rig.json").write_text(json.dumps(desc))
    st = import_measured(tmp_path / "rig.json", tmp_path / "store")
    assert (st.n_cameras, st.n_lights) == (2, 2)
    for (c, j), ref in truth.items():
        np.testing.assert_allclose(st.image(c, j), ref, rtol=1e-6, atol=1e-7)
    np.testing.assert_array_equal(st.silhouette(1), mask[:, :, 0])
    assert st.meta["bounds"] == [[-1, -1, -1], [1, 1, 1]]


def test_import_measured_names_the_bad_file_or_field(tmp_path):
    desc, _ = _measured_rig(tmp_path)
    bad = dict(desc, images=[desc["images"][0], ["missing.exr", desc["images"][1][1]]])
    (tmp_path / "bad.json").write_text(json.dumps(bad))
    with pytest.raises(AssetError, match="missing.exr"):
        import_measured(tmp_path / "bad.json", tmp_path / "o1")
    write_exr(tmp_path / "small.exr", np.zeros((4, 4, 3)))
    bad = dict(desc, images=[["small.exr", desc["images"][0][1]], desc["images"][1]])
    (tmp_path / "bad2.json").write_text(json.dumps(bad))
    with pytest.raises(AssetError, match="small.exr"):
        import_measured(tmp_path / "bad2.json", tmp_path / "o2")
    cams = [dict(desc["cameras"][0]), desc["cameras"][1]]
    del cams[0]["width"]
    (tmp_path / "bad3.json").write_text(json.dumps(dict(desc, cameras=cams)))
    with pytest.raises(SettingsError, match=r"cameras\[0\].*width"):
        import_measured(tmp_path / "bad3.json", tmp_path / "o3")


def test_subset_store_keeps_the_chosen_blocks(small_capture, tmp_path):
    from texelbake.srf.store import subset

    sub = subset(small_capture, [2, 0], [1], tmp_path / "sub")
    assert (sub.n_cameras, sub.n_lights) == (2, 1)
    np.testing.assert_array_equal(sub.image(0, 0), small_capture.image(2, 1))
    np.testing.assert_array_equal(sub.image(1, 0), small_capture.image(0, 1))
    np.testing.assert_allclose(sub.cameras[0].position, small_capture.cameras[2].position)
