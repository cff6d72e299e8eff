"""Assets as studios ship them: the stage as composed with its variant selections, MaterialX
documents referenced from a layer, missing textures, and UsdUVTexture read as a renderer reads
it (wrap modes, colour space, the st primvar). Each case is built by tests.helpers.studio_assets;
the reference values are computed here from the bytes written (the sRGB formula on 8-bit
swatches), not by texelbake."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from pxr import Sdf, Usd, UsdGeom, UsdShade, Vt

from tests.helpers.studio_assets import (
    KIT_FACES,
    KIT_SWATCHES,
    KIT_UV,
    MTLX_DOC,
    box_mesh,
    kit_asset,
    mtlx_asset,
    texture_material,
    textured_box,
    wheel_variants_asset,
)
from tests.helpers.usd_stages import bind, new_stage, write_png
from texelbake import brdf
from texelbake.asset import AssetWarning, check_asset_paths, load_asset
from texelbake.asset.paths import scan_asset_paths
from texelbake.errors import AssetError, AssetPathError


def _srgb(byte: float) -> float:
    """The sRGB decode (IEC 61966-2-1) of an 8-bit value: the independent reference."""
    c = byte / 255.0
    return c / 12.92 if c <= 0.04045 else ((c + 0.055) / 1.055) ** 2.4


# ------------------------------------------------------------------------------------------
# variants: what the selections do not reach is not read
# ------------------------------------------------------------------------------------------


def test_unselected_variant_escaping_the_folder_is_not_read_but_listed(tmp_path):
    root, outside = wheel_variants_asset(tmp_path)
    assert Sdf.Layer.Find(str(outside)) is None  # the builder released it
    with pytest.warns(AssetWarning, match="only by unselected variants"):
        asset = load_asset(root)
    # the selected variant's wheel is baked beside the body; the others are not
    assert sorted(asset.mesh_paths) == ["/Root/Body", "/Root/Wheels/W"]
    assert Sdf.Layer.Find(str(outside)) is None  # never opened, not even by the check
    assert [p.split("'")[1] for p in asset.unreachable_paths] == [
        "../../../wheels/wheelVariants.usda", "./parts/racing_wheels.usda"]
    assert all("{wheels=" in p for p in asset.unreachable_paths)
    assert str(outside) not in check_asset_paths(root)


@pytest.mark.parametrize("variant, match", [("sport", "escapes"), ("racing", "does not exist")])
def test_selected_variant_reading_outside_or_missing_is_refused(tmp_path, variant, match):
    root, outside = wheel_variants_asset(tmp_path)
    stage = Usd.Stage.Open(str(root))
    stage.GetPrimAtPath("/Root").GetVariantSet("wheels").SetVariantSelection(variant)
    stage.Save()
    del stage
    with pytest.raises(AssetPathError, match=match) as err:
        load_asset(root)
    assert f"{{wheels={variant}}}Wheels" in str(err.value)
    assert Sdf.Layer.Find(str(outside)) is None


def test_a_selection_authored_in_a_stronger_layer_decides(tmp_path):
    # the root selects `stock` itself; a stronger layer over it selects `sport`: now the
    # escaping reference is what the bake would read
    root, _ = wheel_variants_asset(tmp_path)
    shot = new_stage(root.parent / "shot.usda")
    shot.GetRootLayer().subLayerPaths.append("./root.usda")
    shot.OverridePrim("/Root").GetVariantSet("wheels").SetVariantSelection("sport")
    shot.Save()
    del shot
    with pytest.raises(AssetPathError, match="escapes"):
        scan_asset_paths(root.parent / "shot.usda")


def test_unselected_variant_unsafe_texture_and_nested_layer(tmp_path):
    # a texture escaping the folder and an absolute sublayer, both only in an unselected
    # variant's file: the file is in the bundle, its contents are not read by the bake
    (tmp_path / "looks").mkdir()
    alt = new_stage(tmp_path / "looks" / "alt.usda")
    alt.GetRootLayer().subLayerPaths.append("/proc/self/environ")
    mesh = box_mesh(alt, "/Root/Alt")
    bind(mesh, texture_material(alt, "/Root/Looks/Alt", "../../secret.png", st_varname="st"))
    alt.Save()
    stage = new_stage(tmp_path / "a.usda")
    box_mesh(stage, "/Root/Body")
    vset = stage.GetPrimAtPath("/Root").GetVariantSets().AddVariantSet("look")
    vset.AddVariant("plain")
    vset.AddVariant("alt")
    vset.SetVariantSelection("alt")
    with vset.GetVariantEditContext():
        stage.DefinePrim("/Root/Look").GetReferences().AddReference("./looks/alt.usda")
    vset.SetVariantSelection("plain")
    stage.Save()
    scan = scan_asset_paths(tmp_path / "a.usda")
    assert str((tmp_path / "looks" / "alt.usda").resolve()) in scan.files
    assert {p.split("'")[1] for p in scan.unreachable} == {
        "./looks/alt.usda", "/proc/self/environ", "../../secret.png"}
    stage = Usd.Stage.Open(str(tmp_path / "a.usda"))
    stage.GetPrimAtPath("/Root").GetVariantSet("look").SetVariantSelection("alt")
    stage.Save()
    del stage
    with pytest.raises(AssetPathError, match="is absolute|escapes"):
        scan_asset_paths(tmp_path / "a.usda")


# ------------------------------------------------------------------------------------------
# MaterialX documents
# ------------------------------------------------------------------------------------------


def test_materialx_reference_reads_standard_surface_with_its_image(tmp_path):
    path = mtlx_asset(tmp_path)
    asset = load_asset(path)
    (mat,) = asset.materials
    assert mat.path == "/Root/Looks/Rook" and mat.model == "preview"
    assert mat.params["roughness"] == pytest.approx(0.6) and mat.params["metallic"] == 0.0
    tex = mat.textures["diffuseColor"]
    assert tex.path == str(tmp_path / "textures" / "rook_color.png")
    assert (tex.wrap_s, tex.wrap_t, tex.source_color_space) == ("repeat", "repeat", "sRGB")
    # the checker's two colours, sRGB-decoded (colorspace="srgb_texture" in the document)
    got = {tuple(np.round(c, 6)) for c in tex.pixels.reshape(-1, 3).tolist()}
    want = {tuple(np.round([_srgb(b) for b in rgb], 6)) for rgb in ((220, 180, 40),
                                                                     (40, 90, 160))}
    assert got == want
    # the document and its texture are files of the asset (its hash, its upload)
    files = check_asset_paths(path)
    assert str(tmp_path / "Rook_mat.mtlx") in files
    assert str(tmp_path / "textures" / "rook_color.png") in files
    # the layer on disk is as authored afterwards (the swap lives only while composing)
    assert "Rook_mat.mtlx@" in Sdf.Layer.FindOrOpen(str(path)).ExportToString()


def test_materialx_texture_escaping_the_folder_is_refused(tmp_path):
    path = mtlx_asset(tmp_path, texture="../../../etc/secret.png")
    with pytest.raises(AssetPathError, match="escapes") as err:
        load_asset(path)
    assert "Rook_mat.mtlx" in str(err.value)


def test_materialx_document_that_does_not_parse(tmp_path):
    path = mtlx_asset(tmp_path)
    (tmp_path / "Rook_mat.mtlx").write_text(MTLX_DOC[:120])
    with pytest.raises(AssetError, match="MaterialX") as err:
        load_asset(path)
    assert "Rook_mat.mtlx" in str(err.value)


# ------------------------------------------------------------------------------------------
# UsdUVTexture as a renderer reads it
# ------------------------------------------------------------------------------------------


def test_kit_uvs_far_outside_unit_square_tile_their_swatches(tmp_path):
    # no st input, no wrap modes, UVs in -37.8..37.8 under primvars:map1: the swatch colour
    # everywhere (useMetadata without metadata tiles); read as "black" it baked 1.4/255
    with pytest.warns(AssetWarning, match="map1"):
        asset = load_asset(kit_asset(tmp_path))
    assert np.abs(asset.corner_uvs).max() == pytest.approx(KIT_UV, rel=1e-6)
    by_name = {m.path.rsplit("/", 1)[1]: i for i, m in enumerate(asset.materials)}
    for name, rgb in KIT_SWATCHES.items():
        i = by_name[name]
        tex = asset.materials[i].textures["diffuseColor"]
        assert (tex.wrap_s, tex.wrap_t, tex.st_primvar) == ("repeat", "repeat", "st")
        sel = asset.face_material == i
        assert sel.sum() == 2 * len(KIT_FACES[name])  # two triangles per quad
        # every point of the faces, not only the corners: a 9x9 barycentric grid
        b = np.stack(np.meshgrid(np.linspace(0, 1, 9), np.linspace(0, 1, 9)), -1).reshape(-1, 2)
        b = b[b.sum(1) <= 1]
        bary = np.concatenate([1 - b.sum(1, keepdims=True), b], axis=1)  # (k, 3)
        uv = np.einsum("kc,fcd->fkd", bary, asset.corner_uvs[sel]).reshape(-1, 2)
        got = brdf.diffuse_albedo(asset.materials[i], uv)
        np.testing.assert_allclose(got, np.broadcast_to([_srgb(c) for c in rgb], got.shape),
                                   atol=1e-6)


@pytest.mark.parametrize("mode, inside, outside", [
    ("repeat", 1.0, 1.0), ("clamp", 1.0, 1.0), ("mirror", 1.0, 1.0), ("black", 1.0, 0.0),
    ("useMetadata", 1.0, 1.0)])
def test_authored_wrap_modes(tmp_path, mode, inside, outside):
    write_png(tmp_path / "white.png", np.full((4, 4, 3), 255, np.uint8))
    stage = new_stage(tmp_path / "a.usda")
    mesh = box_mesh(stage, "/Root/Box")
    mat = texture_material(stage, "/Root/Looks/W", "./white.png", st_varname="st")
    tex = UsdShade.Shader(stage.GetPrimAtPath("/Root/Looks/W/Texture"))
    for key in ("wrapS", "wrapT"):
        tex.CreateInput(key, Sdf.ValueTypeNames.Token).Set(mode)
    bind(mesh, mat)
    stage.Save()
    m = load_asset(tmp_path / "a.usda").materials[0]
    got = brdf.diffuse_albedo(m, np.array([[0.5, 0.5], [3.5, -2.5]]))[:, 0]
    np.testing.assert_allclose(got, [inside, outside], atol=1e-6)


def test_non_st_varname_is_the_uv_set(tmp_path):
    stage = new_stage(tmp_path / "a.usda")
    mesh = box_mesh(stage, "/Root/Box", "uvA", (0.0, 0.5))
    UsdGeom.PrimvarsAPI(mesh).CreatePrimvar(  # a decoy st the material does not read
        "st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.faceVarying).Set(
        Vt.Vec2fArray.FromNumpy(np.full((24, 2), 0.9, np.float32)))
    write_png(tmp_path / "t.png", np.full((2, 2, 3), 90, np.uint8))
    bind(mesh, texture_material(stage, "/Root/Looks/T", "./t.png", st_varname="uvA"))
    stage.Save()
    asset = load_asset(tmp_path / "a.usda")
    assert asset.materials[0].textures["diffuseColor"].st_primvar == "uvA"
    assert asset.corner_uvs.max() == pytest.approx(0.5)  # uvA's values, not the decoy's 0.9


def test_auto_colour_space_decodes_colours_only(tmp_path):
    # 8-bit RGB: decoded on diffuseColor, linear on roughness (a data map), as Blender reads it
    write_png(tmp_path / "rgb.png", np.full((2, 2, 3), 128, np.uint8))
    write_png(tmp_path / "grey.png", np.full((2, 2, 1), 128, np.uint8))
    stage = new_stage(tmp_path / "a.usda")
    mesh = box_mesh(stage, "/Root/Box")
    mat = texture_material(stage, "/Root/Looks/M", "./rgb.png", st_varname="st")
    surface = UsdShade.Shader(stage.GetPrimAtPath("/Root/Looks/M/Surface"))
    for name, file, out in (("roughness", "./rgb.png", "g"), ("metallic", "./grey.png", "r")):
        t = UsdShade.Shader.Define(stage, f"/Root/Looks/M/{name}")
        t.CreateIdAttr("UsdUVTexture")
        t.CreateInput("file", Sdf.ValueTypeNames.Asset).Set(file)
        t.CreateOutput(out, Sdf.ValueTypeNames.Float)
        surface.CreateInput(name, Sdf.ValueTypeNames.Float).ConnectToSource(
            t.ConnectableAPI(), out)
    bind(mesh, mat)
    stage.Save()
    m = load_asset(tmp_path / "a.usda").materials[0]
    np.testing.assert_allclose(m.textures["diffuseColor"].pixels, _srgb(128), atol=1e-6)
    np.testing.assert_allclose(m.textures["roughness"].pixels, 128 / 255, atol=1e-6)
    np.testing.assert_allclose(m.textures["metallic"].pixels, 128 / 255, atol=1e-6)


def test_missing_texture_takes_its_fallback_and_the_bundle_is_accepted(tmp_path):
    path = textured_box(tmp_path, "./gone.png", fallback=(0.2, 0.4, 0.6, 1.0))
    files = check_asset_paths(path)  # not refused
    assert files == [str(path)]
    with pytest.warns(AssetWarning, match="gone.png.*fallback"):
        asset = load_asset(path)
    np.testing.assert_allclose(asset.materials[0].params["diffuseColor"], [0.2, 0.4, 0.6],
                               atol=1e-7)
    assert not asset.materials[0].textures and len(asset.missing_paths) == 1


def test_materialx_in_an_unselected_variant_is_not_read(tmp_path):
    # the selected look is a UsdPreviewSurface; the other names a document that does not
    # parse and one that is missing: neither is read, both listed
    path = textured_box(tmp_path)
    (tmp_path / "broken.mtlx").write_text("<materialx")
    stage = Usd.Stage.Open(str(path))
    vset = stage.GetPrimAtPath("/Root").GetVariantSets().AddVariantSet("look")
    vset.AddVariant("print")
    vset.AddVariant("mtlx")
    vset.SetVariantSelection("mtlx")
    with vset.GetVariantEditContext():
        stage.DefinePrim("/Root/Alt").GetReferences().AddReference(
            "./broken.mtlx", "/MaterialX/Materials/Rook")
        stage.DefinePrim("/Root/Alt2").GetReferences().AddReference("./gone.mtlx")
    vset.SetVariantSelection("print")
    stage.Save()
    del stage
    asset = load_asset(path)
    assert {p.split("'")[1] for p in asset.unreachable_paths} == {"./broken.mtlx", "./gone.mtlx"}
    assert asset.materials[0].textures["diffuseColor"].pixels.shape == (16, 16, 3)


def test_transform2d_between_reader_and_texture(tmp_path):
    # a glTF-style texture transform: st -> UsdTransform2d -> UsdUVTexture. Reference: the
    # same image sampled by hand at R(30°)·diag(2, 0.5)·st + (0.25, -0.1) (the Sdr order)
    pixels = (np.arange(8 * 8 * 3) * 5 % 256).astype(np.uint8).reshape(8, 8, 3)
    write_png(tmp_path / "t.png", pixels)
    stage = new_stage(tmp_path / "a.usda")
    mesh = box_mesh(stage, "/Root/Box", "uvA")
    mat = texture_material(stage, "/Root/Looks/T", "./t.png", st_varname="uvA")
    tex = UsdShade.Shader(stage.GetPrimAtPath("/Root/Looks/T/Texture"))
    tex.CreateInput("sourceColorSpace", Sdf.ValueTypeNames.Token).Set("raw")
    xf = UsdShade.Shader.Define(stage, "/Root/Looks/T/Transform")
    xf.CreateIdAttr("UsdTransform2d")
    xf.CreateInput("in", Sdf.ValueTypeNames.Float2).ConnectToSource(
        UsdShade.Shader(stage.GetPrimAtPath("/Root/Looks/T/StReader")).ConnectableAPI(),
        "result")
    xf.CreateInput("scale", Sdf.ValueTypeNames.Float2).Set((2.0, 0.5))
    xf.CreateInput("rotation", Sdf.ValueTypeNames.Float).Set(30.0)
    xf.CreateInput("translation", Sdf.ValueTypeNames.Float2).Set((0.25, -0.1))
    xf.CreateOutput("result", Sdf.ValueTypeNames.Float2)
    tex.GetInput("st").ConnectToSource(xf.ConnectableAPI(), "result")
    bind(mesh, mat)
    stage.Save()
    m = load_asset(tmp_path / "a.usda").materials[0]
    assert m.textures["diffuseColor"].st_primvar == "uvA"
    st = np.random.default_rng(3).uniform(0, 1, (50, 2))
    r = np.radians(30.0)
    rot = np.array([[np.cos(r), -np.sin(r)], [np.sin(r), np.cos(r)]])
    moved = (st * [2.0, 0.5]) @ rot.T + [0.25, -0.1]
    want = brdf.sample_texture(dataclasses.replace(
        m.textures["diffuseColor"], st_transform=(1.0, 0.0, 0.0, 0.0, 1.0, 0.0)), moved)
    # the authored parameters are float32: uv agrees to ~1e-8, the texels to ~1e-7
    np.testing.assert_allclose(brdf.diffuse_albedo(m, st), want, atol=1e-6)
    assert not np.allclose(want, brdf.sample_texture(dataclasses.replace(
        m.textures["diffuseColor"], st_transform=(1.0, 0.0, 0.0, 0.0, 1.0, 0.0)), st))


def test_varname_from_the_material_interface(tmp_path):
    # the exporters' pattern: the reader's varname (a string) connected to the material's
    # `inputs:frame:stPrimvarName`, whose value names the UV set
    stage = new_stage(tmp_path / "a.usda")
    mesh = box_mesh(stage, "/Root/Box", "UVMap", (0.0, 0.25))
    write_png(tmp_path / "t.png", np.full((2, 2, 3), 90, np.uint8))
    mat = texture_material(stage, "/Root/Looks/T", "./t.png", st_varname="st")
    frame = mat.CreateInput("frame:stPrimvarName", Sdf.ValueTypeNames.String)
    frame.Set("UVMap")
    reader = UsdShade.Shader(stage.GetPrimAtPath("/Root/Looks/T/StReader"))
    reader.GetPrim().RemoveProperty("inputs:varname")
    reader.CreateInput("varname", Sdf.ValueTypeNames.String).ConnectToSource(frame)
    bind(mesh, mat)
    stage.Save()
    asset = load_asset(tmp_path / "a.usda")
    assert asset.materials[0].textures["diffuseColor"].st_primvar == "UVMap"
    assert asset.corner_uvs.max() == pytest.approx(0.25)
    assert not any("as UVs" in w for w in asset.warnings)


MTLX_PREVIEW_DOC = """<?xml version="1.0"?>
<materialx version="1.38">
  <UsdPrimvarReader name="uv" type="vector2">
    <input name="varname" type="string" value="uvA" />
  </UsdPrimvarReader>
  <UsdUVTexture name="tex" type="color3">
    <input name="file" type="filename" value="tiles.png" />
    <input name="st" type="vector2" nodename="uv" />
    <input name="wrapS" type="string" value="mirror" />
    <input name="fallback" type="color4" value="0.1, 0.2, 0.3, 1.0" />
  </UsdUVTexture>
  <UsdPreviewSurface name="SR_plastic" type="surfaceshader">
    <input name="diffuseColor" type="color3" nodename="tex" />
    <input name="roughness" type="float" value="0.3" />
    <input name="metallic" type="float" value="0.0" />
  </UsdPreviewSurface>
  <surfacematerial name="Plastic" type="material">
    <input name="surfaceshader" type="surfaceshader" nodename="SR_plastic" />
  </surfacematerial>
</materialx>
"""


def test_materialx_usd_preview_surface_nodes(tmp_path):
    # MaterialX's own UsdPreviewSurface / UsdUVTexture / UsdPrimvarReader nodes; the layer
    # references the document's root (`</MaterialX>`) and binds below it
    write_png(tmp_path / "tiles.png", np.full((4, 4, 3), 200, np.uint8))
    (tmp_path / "plastic.mtlx").write_text(MTLX_PREVIEW_DOC)
    stage = new_stage(tmp_path / "a.usda")
    mesh = box_mesh(stage, "/Root/Box", "uvA")
    looks = stage.DefinePrim("/Root/MX")
    looks.GetReferences().AddReference("./plastic.mtlx", "/MaterialX")
    UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim()).GetDirectBindingRel().SetTargets(
        ["/Root/MX/Materials/Plastic"])
    stage.Save()
    (mat,) = load_asset(tmp_path / "a.usda").materials
    tex = mat.textures["diffuseColor"]
    assert mat.params["roughness"] == pytest.approx(0.3)
    assert (tex.wrap_s, tex.wrap_t, tex.st_primvar) == ("mirror", "repeat", "uvA")
    np.testing.assert_allclose(tex.pixels, _srgb(200), atol=1e-6)  # auto, 8-bit, a colour
    # without its file, the node's fallback stands in
    (tmp_path / "tiles.png").unlink()
    with pytest.warns(AssetWarning, match="fallback"):
        (mat,) = load_asset(tmp_path / "a.usda").materials
    np.testing.assert_allclose(mat.params["diffuseColor"], [0.1, 0.2, 0.3], atol=1e-7)
