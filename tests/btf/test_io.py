"""Measured-BTF import (UBO2003 names, JSON/CSV directions) and the EXR maps round trip."""

import json

import numpy as np
import OpenImageIO as oiio
import pytest

from texelbake.btf.compress import BTFSettings, build_btf_maps
from texelbake.btf.lut import bonn_angles, bonn_directions, dirs_from_degrees
from texelbake.btf.maps_io import read_btf_maps, write_btf_maps
from texelbake.btf.measured import (
    load_measured_btf,
    parse_ubo2003_name,
    read_directions_file,
    srgb_to_linear,
)
from texelbake.errors import AssetError, AssetPathError


def _write(path, pixels, fmt):
    h, w, c = pixels.shape
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), oiio.ImageSpec(w, h, c, fmt))
    assert out.write_image(pixels)
    out.close()


def test_parse_ubo2003_names():
    assert parse_ubo2003_name("00042 tl015 pl060 tv030 pv120.jpg") == (15.0, 60.0, 30.0, 120.0)
    assert parse_ubo2003_name("/x/y/tl075_pl345_tv000_pv000.png") == (75.0, 345.0, 0.0, 0.0)
    assert parse_ubo2003_name("TL45 PL7.5 TV60 PV300.exr") == (45.0, 7.5, 60.0, 300.0)
    with pytest.raises(AssetError, match="UBO2003"):
        parse_ubo2003_name("img_0001.png")
    with pytest.raises(AssetError, match="tl=95"):
        parse_ubo2003_name("tl095 pl000 tv000 pv000.jpg")


def test_bonn_sampling():
    theta, phi = bonn_angles()
    assert theta.shape == (81,)
    assert [int((theta == t).sum()) for t in (0, 15, 30, 45, 60, 75)] == [1, 6, 12, 18, 20, 24]
    d = bonn_directions()
    assert np.allclose(np.linalg.norm(d, axis=1), 1.0)
    assert np.allclose(d[theta == 0], [0, 0, 1])
    assert np.allclose(dirs_from_degrees([90.0], [90.0]), [[0, 1, 0]], atol=1e-15)


def test_load_ubo2003_folder_png(tmp_path, rng):
    pairs = [(0, 0, 0, 0), (15, 60, 30, 120), (75, 345, 45, 20)]
    imgs = {}
    for k, (tl, pl, tv, pv) in enumerate(pairs):
        px = rng.integers(0, 256, (4, 5, 3), dtype=np.uint8)
        name = f"{k:05d} tl{tl:03d} pl{pl:03d} tv{tv:03d} pv{pv:03d}.png"
        _write(tmp_path / name, px, oiio.UINT8)
        imgs[name] = px
    m = load_measured_btf(tmp_path)
    assert m.btf.shape == (3, 4, 5, 3) and m.btf.dtype == np.float32
    assert m.files == tuple(sorted(imgs))
    for k, f in enumerate(m.files):  # 8-bit PNG is sRGB: decoded to linear
        assert np.allclose(m.btf[k], srgb_to_linear(imgs[f] / 255.0), atol=1e-6)
    assert np.allclose(m.angles, pairs)
    jpg = tmp_path / "jpg"
    jpg.mkdir()
    _write(jpg / "tl030 pl090 tv045 pv180.jpg", np.full((4, 5, 3), 128, np.uint8), oiio.UINT8)
    mj = load_measured_btf(jpg)
    # JPEG is 8-bit sRGB: a flat 128 decodes to 0.2158 linear (JPEG may shift a level or two)
    assert np.allclose(mj.btf, srgb_to_linear(128 / 255.0), atol=0.01)
    assert np.allclose(mj.angles, [[30, 90, 45, 180]])
    assert np.allclose(m.dirs_i[2], dirs_from_degrees(75.0, 345.0))
    assert np.allclose(m.dirs_o[1], dirs_from_degrees(30.0, 120.0))


def test_srgb_curve_closed_form():
    # IEC 61966-2-1: linear segment below 0.04045, 1 -> 1, 0.5 -> 0.21404
    assert np.allclose(srgb_to_linear([0.0, 0.04, 0.5, 1.0]),
                       [0.0, 0.04 / 12.92, 0.214041, 1.0], atol=1e-6)


def test_json_and_csv_directions_with_exr(tmp_path, rng):
    names = ["a.exr", "b.exr"]
    angles = [(10.0, 20.0, 30.0, 40.0), (50.0, 60.0, 70.0, 80.0)]
    data = {}
    for n in names:
        px = rng.random((3, 2, 3)).astype(np.float32) * 5.0  # HDR, linear
        _write(tmp_path / n, px, oiio.FLOAT)
        data[n] = px
    (tmp_path / "dirs.json").write_text(json.dumps({"images": [
        {"file": n, "theta_i": a[0], "phi_i": a[1], "theta_o": a[2], "phi_o": a[3]}
        for n, a in zip(names, angles, strict=True)]}))
    (tmp_path / "dirs.csv").write_text(
        "file,theta_i,phi_i,theta_o,phi_o\n"
        + "".join(f"{n},{a[0]},{a[1]},{a[2]},{a[3]}\n" for n, a in zip(names, angles, strict=True)))
    from_json = read_directions_file(tmp_path / "dirs.json")
    assert from_json == read_directions_file(tmp_path / "dirs.csv")
    for table in ("dirs.json", "dirs.csv"):
        m = load_measured_btf(tmp_path, tmp_path / table)
        assert np.array_equal(m.btf[0], data["a.exr"])  # EXR is linear: taken as is
        assert np.allclose(m.dirs_i[1], dirs_from_degrees(50.0, 60.0))
        assert np.allclose(m.dirs_o[0], dirs_from_degrees(30.0, 40.0))
    crop = load_measured_btf(tmp_path, tmp_path / "dirs.csv", crop=(1, 0, 2, 1))
    assert np.array_equal(crop.btf[1], data["b.exr"][1:3, 0:1])
    with pytest.raises(AssetError, match="crop"):
        load_measured_btf(tmp_path, tmp_path / "dirs.csv", crop=(2, 0, 2, 1))


def test_import_errors(tmp_path, rng):
    with pytest.raises(AssetPathError):
        load_measured_btf(tmp_path / "missing")
    (tmp_path / "bad.json").write_text(json.dumps([{"file": "x.png", "theta_i": "a"}]))
    with pytest.raises(AssetError, match="entry 0"):
        read_directions_file(tmp_path / "bad.json")
    (tmp_path / "esc.json").write_text(json.dumps([{"file": "../x.png", "theta_i": 0,
                                                    "phi_i": 0, "theta_o": 0, "phi_o": 0}]))
    with pytest.raises(AssetPathError, match="outside"):
        load_measured_btf(tmp_path, tmp_path / "esc.json")
    sub = tmp_path / "sizes"
    sub.mkdir()
    _write(sub / "tl000 pl000 tv000 pv000.png", rng.integers(0, 255, (4, 4, 3), np.uint8),
           oiio.UINT8)
    _write(sub / "tl015 pl000 tv000 pv000.png", rng.integers(0, 255, (4, 5, 3), np.uint8),
           oiio.UINT8)
    with pytest.raises(AssetError, match="differs"):
        load_measured_btf(sub)


def _small_maps(rng, **kw):
    dirs = bonn_directions()[:6]
    di, do = np.repeat(dirs, 6, axis=0), np.tile(dirs, (6, 1))
    btf = rng.random((36, 9, 7, 3)).astype(np.float32)
    return build_btf_maps(btf, di, do, BTFSettings(**kw))[0]


@pytest.mark.parametrize("fit_phong", [True, False])
def test_exr_maps_round_trip_identical(tmp_path, rng, fit_phong):
    maps = _small_maps(rng, n_components=(5, 2, 1), fit_phong=fit_phong, lut_resolution=16)
    paths = write_btf_maps(maps, tmp_path / "a")
    back = read_btf_maps(tmp_path / "a")
    assert back.n_components == maps.n_components
    assert back.mean_models == maps.mean_models
    assert back.mean_params.tobytes() == maps.mean_params.tobytes()
    for name in ("eigen", "mean_table", "dirs_i", "dirs_o"):
        a, b = getattr(maps, name), getattr(back, name)
        assert a.dtype == b.dtype and a.tobytes() == b.tobytes(), name
    assert len(back.weights) == len(maps.weights)
    for a, b in zip(maps.weights, back.weights, strict=True):
        assert a.tobytes() == b.tobytes()
    for name in ("light_dirs", "view_dirs", "pair_index", "light_table", "view_table"):
        assert np.array_equal(getattr(maps.lut, name), getattr(back.lut, name)), name
    assert back.notes == maps.notes
    # rewriting the same maps gives byte-identical files
    again = write_btf_maps(back, tmp_path / "b")
    for part, p in paths.items():
        assert p.read_bytes() == again[part].read_bytes(), part


def test_read_maps_errors(tmp_path, rng):
    with pytest.raises(AssetError, match="not found"):
        read_btf_maps(tmp_path)
    maps = _small_maps(rng, n_components=(2, 1, 1))
    write_btf_maps(maps, tmp_path)
    (tmp_path / "btf_lut.exr").unlink()
    with pytest.raises(AssetError):
        read_btf_maps(tmp_path)


def test_half_storage_round_trip_and_error(tmp_path, rng):
    from texelbake.btf.lod import reconstruct_btf

    full = _small_maps(rng, n_components=(36, 36, 36))
    rng2 = np.random.default_rng(12345)  # same input as `full`
    half = _small_maps(rng2, n_components=(36, 36, 36), storage="float16")
    assert half.storage == "float16"
    assert np.array_equal(half.eigen, half.eigen.astype(np.float16).astype(np.float32))
    assert half.compressed_bytes() < 0.51 * full.compressed_bytes() + 64
    write_btf_maps(half, tmp_path)
    back = read_btf_maps(tmp_path)
    assert back.storage == "float16" and back.eigen.tobytes() == half.eigen.tobytes()
    assert all(a.tobytes() == b.tobytes() for a, b in zip(half.weights, back.weights,
                                                           strict=True))
    # half precision: relative 2^-11 per stored value, values in [0, 1], a few dozen terms
    err = np.abs(reconstruct_btf(back) - reconstruct_btf(full)).max()
    assert 0 < err < 5e-3
