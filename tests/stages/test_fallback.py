"""The fitted fallback as the export writes it: per LOD its specular-workflow UsdPreviewSurface
with its own textures at its switch size's level, the normal texture decoded as the
validator checks, chart padding, the residual in the report, reruns byte-identical."""

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
    from texelbake.io.images import read_pixels

    root = cylinder["fitted"]
    mats = _materials(root)
    report = json.loads((root.parent / "report.json").read_text())
    assert set(mats) == {"LOD1", "LOD2"}
    res = report["fallback_resolution"]
    # LOD1's page is sized by its switch size; LOD2 switches in at a quarter of it: level 2
    assert report["fallback_levels"] == [0, 2]
    for lod, inputs in mats.items():
        assert inputs["useSpecularWorkflow"] == 1
        assert {"diffuseColor", "specularColor", "roughness", "normal", "occlusion"} <= set(
            inputs)
        assert "metallic" not in inputs  # the specular workflow ignores it: not authored
        # the normal texture as the validator checks it: raw, scale 2, bias -1 (alpha 1, 0)
        nrm = inputs["normal"]
        assert nrm["sourceColorSpace"] == "raw"
        assert tuple(nrm["scale"]) == (2.0, 2.0, 2.0, 1.0)
        assert tuple(nrm["bias"]) == (-1.0, -1.0, -1.0, 0.0)
        for colour in ("diffuseColor", "specularColor"):
            assert inputs[colour]["sourceColorSpace"] == "sRGB"
        side = res >> (0 if lod == "LOD1" else 2)
        for name in ("diffuseColor", "specularColor", "roughness"):
            px = read_pixels(str(root.parent / inputs[name]["file"].path))[0]
            assert px.shape[:2] == (side, side), (lod, name)
    fit = report["fallback"]["fit"]
    assert report["fallback"]["mode"] == "fitted"
    assert [r["texels"] > 0 for r in fit["residual"]] == [True, True]
    assert all(0.0 <= r["median"] <= r["p95"] <= r["max"] for r in fit["residual"])


def test_chart_padding_holds_covered_values_only(cylinder):
    # every texel no sample fell in holds a covered texel's value (the nearest one's), so no
    # mip level blends the page's background into a chart
    from schemas.settings import BakeSettings
    from texelbake.pipeline.run import default_workdir
    from texelbake.stages.context import StageContext
    from texelbake.stages.fallback import fitted_fallback

    report = json.loads((cylinder["fitted"].parent / "report.json").read_text())
    ctx = StageContext.create(default_workdir(), cylinder["src"],
                              BakeSettings(**SMALL, fallback="fitted"))
    fit = fitted_fallback(ctx, report["fallback_resolution"], 2)
    for lod in range(2):
        cov = fit["covered"][lod]
        assert 0 < cov.sum() < cov.size  # charts and page between them
        for name in ("diffuse", "specular", "roughness"):
            img = fit[name][lod].reshape(cov.size, -1)
            inside = {row.tobytes() for row in img[cov.ravel()]}
            assert all(row.tobytes() in inside for row in img[~cov.ravel()]), (lod, name)


def test_averaged_stays_an_option(cylinder):
    mats = _materials(cylinder["averaged"])
    for inputs in mats.values():
        assert "specularColor" not in inputs or not isinstance(inputs["specularColor"], dict)
        assert isinstance(inputs["diffuseColor"], dict)
    report = json.loads((cylinder["averaged"].parent / "report.json").read_text())
    assert report["fallback"] == {"mode": "averaged"}


def test_rerun_in_a_fresh_store_is_byte_identical(cylinder, tmp_path):
    again = _bake(cylinder["src"], tmp_path / "again", workdir=tmp_path / "store",
                  fallback="fitted")
    files = sorted(p.name for p in cylinder["fitted"].parent.glob("*.png"))
    assert any("specular_lod2" in f for f in files)
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
