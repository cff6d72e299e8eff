"""The fitted fallback as the export writes it: per LOD its specular-workflow UsdPreviewSurface
with its own textures at its switch size's level, the normal texture decoded as the
validator checks, chart padding, the residual per texel in the report and as a map, stock
validation, reruns byte-identical (every file)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from pxr import Usd, UsdShade

SMALL = {"samples_per_texel": 4, "n_light_dirs": 4, "n_view_dirs": 4, "n_heldout": 4,
         "c_max": 4, "avis_resolution": 4, "mesh_levels": 2, "atlas_resolution": 16,
         "shard_texels": 8, "lod_switch_px": (32.0, 8.0)}


def _bake(src: Path, out: Path, workdir: Path | None = None, **over) -> Path:
    from schemas.settings import BakeSettings
    from texelbake.pipeline.run import bake

    return bake(src, out, BakeSettings(**{**SMALL, **over}), progress=False, workdir=workdir)


@pytest.fixture(scope="module")
def cylinder(tmp_path_factory) -> dict:
    from texelbake.testscenes import write_scene

    d = tmp_path_factory.mktemp("fitted")
    src = write_scene("cylinder", d / "cylinder.usda", "small")
    return {"src": src, "dir": d, "fitted": _bake(src, d / "fitted", fallback="fitted"),
            "averaged": _bake(src, d / "averaged", fallback="averaged")}


def _materials(root: Path) -> dict:
    """LOD -> {input: (texture shader, its inputs) or constant}."""
    stage = Usd.Stage.Open(str(root))
    out = {}
    for prim in stage.Traverse():
        if not prim.GetName().startswith("LOD") or prim.GetTypeName() != "Mesh":
            continue
        mat, _ = UsdShade.MaterialBindingAPI(prim).ComputeBoundMaterial()
        surf = mat.ComputeSurfaceSource()[0]
        inputs = {}
        for inp in surf.GetInputs():
            src = inp.GetConnectedSources()[0]
            if src:
                tex = UsdShade.Shader(src[0].source.GetPrim())
                inputs[inp.GetBaseName()] = {i.GetBaseName(): i.Get() for i in tex.GetInputs()
                                             if i.GetBaseName() != "st"}
            else:
                inputs[inp.GetBaseName()] = inp.Get()
        out[prim.GetName()] = inputs
    return out


def test_fitted_material_per_lod(cylinder):
    import numpy as np

    from texelbake.io.images import read_pixels

    root = cylinder["fitted"]
    mats = _materials(root)
    avg = _materials(cylinder["averaged"])
    report = json.loads((root.parent / "report.json").read_text())
    assert set(mats) == {"LOD1", "LOD2"}
    res = report["fallback_resolution"]
    for lod, inputs in mats.items():
        # the averaged inputs' workflow, constants, roughness and normal; its own diffuse
        def authored(mat: dict) -> dict:  # asset paths as authored (relative)
            return {k: ({i: getattr(x, "path", x) for i, x in v.items()}
                        if isinstance(v, dict) else v)
                    for k, v in mat.items() if k != "diffuseColor"}

        assert authored(inputs) == authored(avg[lod])
        assert inputs["diffuseColor"]["sourceColorSpace"] == "sRGB"
        assert inputs["diffuseColor"]["file"].path.endswith(f"_diffuse_lod{lod[-1]}.png")
        px = read_pixels(str(root.parent / inputs["diffuseColor"]["file"].path))[0]
        assert px.shape[:2] == (res, res), lod
    fit = report["fallback"]["fit"]
    assert report["fallback"]["mode"] == "fitted"
    assert len(fit["gain"]) == 2
    for i, g in enumerate(fit["gain"], start=1):
        # the held-out choice: the gain is never worse than none there
        assert g["heldout_vs_averaged"] is None or 0.0 < g["heldout_vs_averaged"] <= 1.0
        assert g["lambda"] is None or g["lambda"] >= 0.0
        # the residual per texel of the gain's level: in the report and as a map, NaN where
        # no sample had a target, finite and non-negative where one did
        r = g["residual"]
        side = res >> g["gain_level"]
        assert r["side"] == side and 0 < r["texels"] <= side * side
        assert 0.0 <= r["fitted"]["p50"] <= r["fitted"]["p95"] <= r["fitted"]["max"]
        assert 0.0 <= r["target_noise"]["p50"] <= r["target_noise"]["max"]
        assert r["texels_above_flag"] == 0 or r["worst"][0]["residual"] > r["flag"]
        img = read_pixels(str(root.parent / f"cylinder_fit_residual_lod{i}.exr"))[0]
        assert img.shape == (side, side, 1)
        seen = np.isfinite(img)
        assert seen.sum() == r["texels"] and (img[seen] >= 0.0).all()
        assert abs(float(np.max(img[seen])) - r["fitted"]["max"]) < 1e-4


def test_chart_padding_holds_covered_values_only(cylinder):
    # every texel of the fallback page that no sample fell in holds a covered texel's value
    # (the nearest one's), so every mip level a viewer builds (box means) is a mean of chart
    # values: no level blends the page's background into a chart
    import numpy as np

    from schemas.settings import BakeSettings
    from texelbake.pipeline.run import default_workdir
    from texelbake.stages.context import StageContext
    from texelbake.stages.filtered import fallback_maps, fallback_samples, filtered_levels

    ctx = StageContext.create(default_workdir(), cylinder["src"],
                              BakeSettings(**SMALL, fallback="averaged"))
    fb = fallback_maps(ctx, filtered_levels(ctx))
    res = fb["resolution"]
    fs = fallback_samples(ctx, res)
    cov = np.bincount(fs["row"] * res + fs["col"], minlength=res * res) > 0
    assert 0 < cov.sum() < cov.size  # charts and page between them
    maps = {"base": fb["base"], "occlusion": fb["occlusion"], "normal": fb["normal"]}
    for i, r in enumerate(fb["roughness"]):  # each at its LOD's level
        n = r.shape[0]
        f = res // n
        maps[f"roughness{i}"] = (r, cov.reshape(n, f, n, f).any(axis=(1, 3)).ravel())
    for name, img in maps.items():
        c = cov
        if isinstance(img, tuple):
            img, c = img
        flat = np.asarray(img).reshape(c.size, -1)
        inside = {row.tobytes() for row in flat[c]}
        assert all(row.tobytes() in inside for row in flat[~c]), name


def test_no_mip_a_lod_reads_mixes_two_charts(cylinder):
    # the page's padding is filled from the nearest covered texel, and charts are packed
    # `padding_texels` atlas texels apart (a 32x wider gutter on a 512² page of a 16² atlas):
    # every box-mip block a viewer reads up to LOD2's switch level (a texel a pixel where
    # LOD2 switches in) takes its texels from one chart only
    import numpy as np
    from scipy.ndimage import distance_transform_edt, label

    from schemas.settings import BakeSettings
    from texelbake.geometry.atlas import rasterize_atlas
    from texelbake.pipeline.run import default_workdir
    from texelbake.stages.context import StageContext
    from texelbake.stages.filtered import fallback_resolution, fallback_samples

    s = BakeSettings(**SMALL, fallback="averaged")
    ctx = StageContext.create(default_workdir(), cylinder["src"], s)
    res = fallback_resolution(ctx)
    geo = ctx.geometry()
    chart, n_charts = label((rasterize_atlas(geo["m1_corner_uvs"], res)[0] >= 0
                             ).reshape(res, res))
    assert n_charts > 1
    fs = fallback_samples(ctx, res)
    cov = np.zeros(res * res, bool)
    cov[fs["row"] * res + fs["col"]] = True
    cov = cov.reshape(res, res)
    # the chart each page texel's value comes from: every texel belongs to its nearest
    # chart, and its value is its nearest covered texel's
    near = distance_transform_edt(chart == 0, return_distances=False, return_indices=True)
    chart_of = chart[near[0], near[1]]
    idx = distance_transform_edt(~cov, return_distances=False, return_indices=True)
    src = chart_of[idx[0], idx[1]]
    lod2_level = int(np.log2(s.lod_switch_px[0] / s.lod_switch_px[1]))
    assert lod2_level >= 2
    for lvl in range(1, lod2_level + 1):  # the blocks a look-up inside a chart reads
        f = 1 << lvl

        def blocks(a, f=f):
            return a.reshape(res // f, f, res // f, f).transpose(0, 2, 1, 3).reshape(-1, f * f)

        b, inside = blocks(src), blocks(chart).max(axis=1) > 0
        assert np.all(b[inside].min(axis=1) == b[inside].max(axis=1)), lvl


def test_averaged_stays_an_option(cylinder):
    mats = _materials(cylinder["averaged"])
    for inputs in mats.values():
        assert "specularColor" not in inputs or not isinstance(inputs["specularColor"], dict)
        assert isinstance(inputs["diffuseColor"], dict)
    report = json.loads((cylinder["averaged"].parent / "report.json").read_text())
    assert report["fallback"] == {"mode": "averaged"}


def test_fitted_bake_passes_stock_validation(cylinder, tmp_path):
    from tests.helpers.usd_validation import stock_errors
    from texelbake.usd.export import export_lod

    root = cylinder["fitted"]
    outs = [export_lod(root, n, tmp_path / f"lod{n}{suffix}")
            for n in (1, 2) for suffix in (".usda", ".usdz")]
    assert stock_errors(root, *outs) == {str(p): [] for p in (root, *outs)}


def test_rerun_in_a_fresh_store_is_byte_identical(cylinder, tmp_path):
    again = _bake(cylinder["src"], tmp_path / "again", workdir=tmp_path / "store",
                  fallback="fitted")
    files = sorted(p.name for p in cylinder["fitted"].parent.iterdir()
                   if p.suffix in (".png", ".exr", ".usdc"))
    assert any("diffuse_lod2" in f for f in files)
    assert any("fit_residual_lod2" in f for f in files)
    # the maps and the payload (the root layer names the source by a path relative to it)
    for name in files:
        a = (cylinder["fitted"].parent / name).read_bytes()
        assert (again.parent / name).read_bytes() == a, name


def test_shading_variant_selected_is_the_one_baked(tmp_path):
    # an asset with a `shadingVariant` set: the bake composes the stage as authored, so each
    # LOD's fallback (and the CPM maps) are of the selected variant; the others are not baked
    from pxr import Gf, Sdf

    from tests.helpers.render import write_plane_usd
    from texelbake.usd.read import read_baked

    src = write_plane_usd(tmp_path / "plane.usda", rho=(0.7, 0.1, 0.1))
    stage = Usd.Stage.Open(str(src))
    blue = UsdShade.Material.Define(stage, "/Root/Looks/Blue")
    sh = UsdShade.Shader.Define(stage, "/Root/Looks/Blue/Surface")
    sh.CreateIdAttr("texelbake:lambert")
    sh.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(0.1, 0.1, 0.7))
    blue.CreateSurfaceOutput("texelbake").ConnectToSource(
        sh.CreateOutput("surface", Sdf.ValueTypeNames.Token))
    plane = stage.GetPrimAtPath("/Root/Plane")
    plane.RemoveProperty("material:binding")  # the variants carry the binding
    vset = plane.GetVariantSets().AddVariantSet("shadingVariant")
    for name, mat in (("red", "/Root/Looks/Lambert"), ("blue", "/Root/Looks/Blue")):
        vset.AddVariant(name)
        vset.SetVariantSelection(name)
        with vset.GetVariantEditContext():
            UsdShade.MaterialBindingAPI.Apply(plane).Bind(
                UsdShade.Material(stage.GetPrimAtPath(mat)))
    vset.SetVariantSelection("blue")
    stage.GetRootLayer().Save()
    root = _bake(src, tmp_path / "out", mesh_levels=1, lod_switch_px=(32.0,), fallback="fitted")
    diffuse = read_baked(root).fallback["materials"][0]["textures"]["diffuseColor"]
    mean = diffuse.reshape(-1, 3).mean(axis=0)
    assert mean[2] > 0.5 and mean[0] < 0.2, mean  # the selected variant's blue, not red
