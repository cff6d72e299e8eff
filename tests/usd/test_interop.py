"""USD that any tool opens cleanly (issue 11, item 5): generated scenes and baked results pass
pxr's stock validators in a process that never imported texelbake, and UsdLux light units
follow the schema's rules (tested against the formulas written out here)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from pxr import Gf, Sdf, Usd, UsdGeom, UsdLux, UsdShade

from tests.helpers.usd_validation import stock_check, stock_errors
from texelbake.model import SHADER_CELLULAR, SHADER_LAMBERT
from texelbake.usd.shaderdefs import (
    ALL_SHADER_INPUTS,
    DEFINITIONS_FILE,
    author_shader,
    shader_id,
    write_definitions,
)


@pytest.fixture(scope="module")
def scenes(tmp_path_factory) -> list[Path]:
    from texelbake.testscenes import write_scene

    out = tmp_path_factory.mktemp("scenes")
    return [write_scene(n, out / f"{n}.usda", "small")
            for n in ("cylinder", "wall", "bolt", "cloisonne")]


def test_generated_scenes_pass_stock_validation(scenes):
    errors = stock_errors(*scenes)
    assert errors == {str(p): [] for p in scenes}
    assert (scenes[0].parent / DEFINITIONS_FILE).is_file()


def test_texelbake_shaders_open_silently_and_type_check_when_a_tool_opts_in(tmp_path):
    # as authored, a stock pxr resolves no Sdr node for a texelbake shader: nothing is printed
    # (an asset-based node would print "Invalid prim name" per id) and nothing is an error.
    # A tool that opts in (implementationSource = sourceAsset over the shader) reads the
    # definitions beside the file: a wrong input type is then an error there, so the
    # definitions really are complete and found
    stage = Usd.Stage.CreateNew(str(tmp_path / "bad.usda"))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    mat = UsdShade.Material.Define(stage, "/Looks/M")
    stage.SetDefaultPrim(stage.GetPrimAtPath("/Looks"))
    sh = author_shader(stage, "/Looks/M/S", SHADER_CELLULAR)
    sh.CreateInput("seed", Sdf.ValueTypeNames.Float).Set(3.0)  # declared int
    mat.CreateSurfaceOutput("texelbake").ConnectToSource(
        sh.CreateOutput("surface", Sdf.ValueTypeNames.Token))
    stage.GetRootLayer().Save()
    assert (tmp_path / DEFINITIONS_FILE).is_file()
    assert stock_errors(tmp_path / "bad.usda") == {str(tmp_path / "bad.usda"): []}
    sh.GetImplementationSourceAttr().Set(UsdShade.Tokens.sourceAsset)
    stage.GetRootLayer().Save()
    errors, printed = stock_check(tmp_path / "bad.usda")
    errors = errors[str(tmp_path / "bad.usda")]
    assert any(e.startswith("MismatchedPropertyType") and "seed" in e for e in errors), errors
    assert not any(e.startswith(("MissingShaderIdInRegistry", "MissingSourceType")) for e in errors)
    assert "Invalid prim name" in printed  # why the opt-in is not the default


def test_definitions_file_is_deterministic_and_complete(tmp_path):
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    a, b = write_definitions(tmp_path / "a"), write_definitions(tmp_path / "b")
    assert a.read_bytes() == b.read_bytes()
    stage = Usd.Stage.Open(str(a))
    for sid, inputs in ALL_SHADER_INPUTS.items():
        prim = stage.GetPrimAtPath(f"/{sid.replace(':', '_')}")
        assert prim, sid
        shader = UsdShade.Shader(prim)
        assert shader.GetIdAttr().Get() == sid
        assert sorted(i.GetBaseName() for i in shader.GetInputs()) == sorted(n for n, _, _ in inputs)


def test_shader_id_reads_both_forms():
    stage = Usd.Stage.CreateInMemory()
    new = author_shader(stage, "/A", SHADER_LAMBERT)
    old = UsdShade.Shader.Define(stage, "/B")
    old.CreateIdAttr(SHADER_LAMBERT)  # files written before definitions by source asset
    plain = UsdShade.Shader.Define(stage, "/C")
    assert shader_id(new) == shader_id(old) == SHADER_LAMBERT
    assert shader_id(plain) is None
    assert new.GetPrim().GetAttribute("info:texelbake:sourceAsset").Get().path == \
        f"./{DEFINITIONS_FILE}"
    # no info:id and no authored implementation source: no tool asks Sdr for a node
    assert not new.GetIdAttr().HasAuthoredValue()
    assert not new.GetImplementationSourceAttr().HasAuthoredValue()
    # files written with implementationSource = sourceAsset still read
    opted = UsdShade.Shader.Define(stage, "/D")
    opted.SetSourceAsset(Sdf.AssetPath(f"./{DEFINITIONS_FILE}"), "texelbake")
    opted.SetSourceAssetSubIdentifier("texelbake_phong", "texelbake")
    assert shader_id(opted) == "texelbake:phong"


def test_ingest_reads_a_source_asset_shader_like_an_id_shader(scenes):
    from texelbake.asset import load_asset

    asset = load_asset(scenes[0])  # the cylinder: texelbake:lambert and texelbake:phong
    assert sorted(m.model for m in asset.materials) == ["lambert", "phong"]
    phong = next(m for m in asset.materials if m.model == "phong")
    assert float(np.asarray(phong.params["exponent"])) > 1.0  # authored, not the default 32
    assert not any("unsupported shader" in w for w in asset.warnings)


# ---- UsdLux light units -------------------------------------------------------------------


def _sun(stage, path, **attrs):
    light = UsdLux.DistantLight.Define(stage, path)
    light.AddRotateXOp().Set(-90.0)
    for name, value in attrs.items():
        getattr(light, f"Create{name[0].upper()}{name[1:]}Attr")(value)
    return light


def test_distant_light_units_follow_usdlux(tmp_path):
    from tests.helpers.usd_stages import grid_mesh, new_stage
    from texelbake.asset import load_asset

    stage = new_stage(tmp_path / "a.usda")
    grid_mesh(stage, "/Root/m", 1, 1)
    _sun(stage, "/Root/Fallbacks")  # nothing authored: intensity 50000, angle 0.53, normalize off
    _sun(stage, "/Root/Normalized", intensity=3.0, exposure=1.0, normalize=True, angle=10.0)
    _sun(stage, "/Root/Wide", intensity=2.0, angle=30.0)
    _sun(stage, "/Root/Delta", intensity=5.0, angle=0.0)
    _sun(stage, "/Root/Warm", intensity=1.0, normalize=True, enableColorTemperature=True,
         colorTemperature=3000.0, color=Gf.Vec3f(1.0, 0.5, 1.0))
    stage.Save()
    asset = load_asset(tmp_path / "a.usda")
    by = {light.path: light.radiance_scale for light in asset.lights}

    def omega(deg):  # solid angle of a disk of angular diameter deg
        return 2.0 * math.pi * (1.0 - math.cos(math.radians(deg) / 2.0))

    np.testing.assert_allclose(by["/Root/Fallbacks"], 50000.0 * omega(0.53), rtol=1e-6)
    assert 3.3 < by["/Root/Fallbacks"][0] < 3.4  # not 50000: the sun's disk is 6.7e-5 sr
    np.testing.assert_allclose(by["/Root/Normalized"], 3.0 * 2.0, rtol=1e-12)  # angle ignored
    np.testing.assert_allclose(by["/Root/Wide"], 2.0 * omega(30.0), rtol=1e-6)
    np.testing.assert_allclose(by["/Root/Delta"], 5.0, rtol=1e-12)
    rgb = np.asarray(UsdLux.BlackbodyTemperatureAsRgb(3000.0), dtype=np.float64)
    np.testing.assert_allclose(by["/Root/Warm"], np.array([1.0, 0.5, 1.0]) * rgb, rtol=1e-6)
    assert rgb[0] > rgb[2]  # warm
    assert any("/Root/Wide" in w and "hard" in w for w in asset.warnings)


def test_sphere_light_units_follow_usdlux(tmp_path):
    from tests.helpers.usd_stages import grid_mesh, new_stage
    from texelbake.asset import load_asset

    stage = new_stage(tmp_path / "a.usda")
    grid_mesh(stage, "/Root/m", 1, 1)
    for name, normalize in (("Plain", False), ("Norm", True)):
        bulb = UsdLux.SphereLight.Define(stage, f"/Root/{name}")
        bulb.AddTranslateOp().Set(Gf.Vec3d(0, 3, 0))
        bulb.CreateRadiusAttr(0.25)
        bulb.CreateIntensityAttr(8.0)
        bulb.CreateNormalizeAttr(normalize)
    stage.Save()
    by = {light.path: light.radiance_scale for light in load_asset(tmp_path / "a.usda").lights}
    # radiant intensity of a uniform sphere of luminance L: L * (its projected area pi r^2);
    # normalized, L is divided by the sphere's area 4 pi r^2 first
    np.testing.assert_allclose(by["/Root/Plain"], 8.0 * math.pi * 0.25 ** 2, rtol=1e-12)
    np.testing.assert_allclose(by["/Root/Norm"], 8.0 / 4.0, rtol=1e-12)


def test_generated_scenes_author_light_units_explicitly(scenes):
    for path in scenes:
        stage = Usd.Stage.Open(str(path))
        lights = [p for p in stage.Traverse() if p.HasAPI(UsdLux.LightAPI)]
        assert lights, path
        for prim in lights:
            api = UsdLux.LightAPI(prim)
            assert api.GetNormalizeAttr().HasAuthoredValue(), prim.GetPath()
            if prim.IsA(UsdLux.DistantLight):
                assert UsdLux.DistantLight(prim).GetAngleAttr().HasAuthoredValue()
                assert api.GetNormalizeAttr().Get() is True


def test_up_axis_and_units_reach_every_output(tmp_path):
    """A Z-up asset in centimetres keeps upAxis and metersPerUnit in the baked root, its payload
    and a one-LOD export (read back by stock pxr)."""
    from pxr import UsdGeom

    from schemas.settings import BakeSettings
    from texelbake.pipeline.run import bake
    from texelbake.testscenes import write_scene
    from texelbake.usd.export import export_lod

    src = write_scene("cylinder", tmp_path / "src" / "cyl.usda", "small")
    stage = Usd.Stage.Open(str(src))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, 0.01)
    stage.GetRootLayer().Save()
    settings = BakeSettings(samples_per_texel=4, n_light_dirs=4, n_view_dirs=4, n_heldout=4,
                            c_max=4, mesh_levels=2)
    root = bake(src, tmp_path / "out", settings, progress=False)
    lod1 = export_lod(root, 1, tmp_path / "lod1.usdc")
    payload = next(root.parent.glob("*_payload.usdc"))
    for path in (root, payload, lod1):
        st = Usd.Stage.Open(str(path))
        assert UsdGeom.GetStageUpAxis(st) == UsdGeom.Tokens.z, path
        assert UsdGeom.GetStageMetersPerUnit(st) == pytest.approx(0.01), path
