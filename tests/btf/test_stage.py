"""BTF stage glue: texel arrays -> BTF images, bake_btf, the USD shader referencing the maps."""

import numpy as np
import pytest

from texelbake.btf.bake import author_btf_shader, bake_btf, btf_from_texels, fill_uncovered
from texelbake.btf.compress import BTFSettings
from texelbake.btf.lod import reconstruct_btf
from texelbake.btf.lut import bonn_directions
from texelbake.btf.maps_io import SHADER_BTF, read_btf_maps
from texelbake.btf.report import btf_errors
from texelbake.errors import ShapeError
from texelbake.usd.shaderdefs import shader_id


def _grid(n=4):
    dirs = bonn_directions()[:n]
    return np.repeat(dirs, n, axis=0), np.tile(dirs, (n, 1))


def test_btf_from_texels_scatters_by_flat_id(rng):
    fbar = rng.random((5, 16, 3)).astype(np.float32)
    ids = np.array([0, 7, 13, 35, 20])
    btf, covered = btf_from_texels(fbar, ids, 6)
    assert btf.shape == (16, 6, 6, 3) and covered.sum() == 5
    for t, i in enumerate(ids):
        r, c = divmod(int(i), 6)
        assert covered[r, c] and np.array_equal(btf[:, r, c], fbar[t])
    assert np.all(btf[:, ~covered] == 0)
    with pytest.raises(ShapeError, match="duplicates"):
        btf_from_texels(fbar, np.array([0, 0, 1, 2, 3]), 6)
    with pytest.raises(ShapeError, match="texel ids"):
        btf_from_texels(fbar, ids, 5)


def test_bake_btf_writes_maps_and_report(tmp_path, rng):
    di, do = _grid()
    btf = rng.random((16, 8, 8, 3)).astype(np.float32)
    maps, rep = bake_btf(btf, di, do, tmp_path, BTFSettings(n_components=(64, 64, 64)))
    assert set(rep["files"]) == {"eigen", "weights", "lut", "pairs"}
    assert all((tmp_path / f).is_file() for f in rep["files"].values())
    assert set(rep["mse"]) == {"Y", "Cb", "Cr"}
    assert rep["mse"]["Y"]["max"] < 1e-10  # all components kept: exact
    back = read_btf_maps(tmp_path)
    assert np.abs(reconstruct_btf(back) - btf).max() < 1e-5
    assert {"ycbcr", "pyramid", "mean_fit", "pca", "build_total"} <= set(rep["seconds"])


def test_author_btf_shader_resolves_next_to_layer(tmp_path, rng):
    from pxr import Usd, UsdShade, UsdValidation

    di, do = _grid()
    btf = rng.random((16, 6, 6, 3)).astype(np.float32)
    maps, rep = bake_btf(btf, di, do, tmp_path, BTFSettings(n_components=(4, 1, 1)))
    layer = tmp_path / "payload.usda"
    stage = Usd.Stage.CreateNew(str(layer))
    shader = author_btf_shader(stage, "/Looks/Baked", rep["files"], maps)
    stage.GetRootLayer().Save()
    assert shader_id(shader) == SHADER_BTF
    mat = UsdShade.Material(stage.GetPrimAtPath("/Looks/Baked"))
    src = mat.GetSurfaceOutput("texelbake_btf").GetConnectedSources()[0][0].source
    assert src.GetPath() == shader.GetPrim().GetPath()
    for part in ("eigen", "weights", "lut", "pairs"):
        asset = shader.GetInput(f"{part}Map").Get()
        assert (tmp_path / asset.path).is_file()
    assert shader.GetInput("topLevel").Get() == maps.top_level
    ctx = UsdValidation.ValidationContext(
        list(UsdValidation.ValidationRegistry().GetAllValidatorMetadata()), True)
    names = {e.GetName() for e in ctx.Validate(stage)}
    assert "UnresolvableDependency" not in names  # the maps resolve next to the layer
    with pytest.raises(ShapeError, match="lacks BTF parts"):
        author_btf_shader(stage, "/Looks/B2", {"eigen": "x.exr"}, maps)


def test_fill_uncovered_pull_push(rng):
    btf = rng.random((5, 7, 9, 3)).astype(np.float32)
    covered = rng.random((7, 9)) < 0.4
    out = fill_uncovered(btf, covered)
    assert np.array_equal(out[:, covered], btf[:, covered])  # data untouched
    lo = btf[:, covered].min(axis=1)  # (5, 3)
    hi = btf[:, covered].max(axis=1)
    # filled texels are averages of covered ones: inside their per-image range
    assert np.all(out[:, ~covered] >= lo[:, None] - 1e-6)
    assert np.all(out[:, ~covered] <= hi[:, None] + 1e-6)
    one = np.zeros((7, 9), bool)
    one[3, 4] = True  # a single covered texel fills the whole map with its value
    assert np.allclose(fill_uncovered(btf, one), btf[:, 3:4, 4:5], atol=1e-6)
    with pytest.raises(ShapeError):
        fill_uncovered(btf, covered[:3])


def test_masked_errors_match_brute_force(tmp_path, rng):
    di, do = _grid()
    btf = rng.random((16, 6, 5, 3)).astype(np.float32)
    maps, _ = bake_btf(btf, di, do, tmp_path, BTFSettings(n_components=(2, 1, 1)))
    mask = rng.random((6, 5)) < 0.5
    got = btf_errors(btf, maps, texel_mask=mask, value_scale=2.0)
    from texelbake.btf.color import rgb_to_ycbcr

    diff = rgb_to_ycbcr(reconstruct_btf(maps).astype(np.float64)) - rgb_to_ycbcr(
        btf.astype(np.float64))  # (d, h, w, 3)
    per = (diff[:, mask] ** 2).mean(axis=1) * 4.0  # (d, 3), value_scale**2 = 4
    for c, name in enumerate(("Y", "Cb", "Cr")):
        assert np.isclose(got[name]["avg"], per[:, c].mean(), rtol=1e-5)
        assert np.isclose(got[name]["max"], per[:, c].max(), rtol=1e-5)


def test_default_value_scale_ignores_a_spike(rng):
    from texelbake.btf.report import default_value_scale

    btf = rng.random((20, 10, 10, 3)).astype(np.float32)  # uniform [0, 1): p99.9 ~ 0.999
    btf[3, 2, 2, 0] = 100.0  # one specular spike must not set the white point
    assert 1.0 < default_value_scale(btf) < 1.01
    mask = np.zeros((10, 10), bool)
    mask[:5] = True
    btf[:, 5:] *= 10.0  # outside the mask: ignored
    assert 1.0 < default_value_scale(btf, mask) < 1.01
    assert default_value_scale(np.zeros((2, 3, 3, 3))) == 1.0
