"""Bad assets: each case gets its typed error (or a warning and a defined fallback), and the
message names the prim path or the asset path."""

from __future__ import annotations

import numpy as np
import pytest
from pxr import Sdf, Usd, UsdGeom, UsdShade, Vt

from tests.helpers.usd_stages import (
    bind,
    grid_mesh,
    new_stage,
    preview_material,
    triangle_mesh,
    write_png,
)
from texelbake.asset import AssetWarning, check_asset_paths, load_asset
from texelbake.asset.paths import scan_asset_paths
from texelbake.errors import AssetError, AssetPathError, TexelbakeError
from texelbake.model import SHADER_MEASURED

# ------------------------------------------------------------------------------------------
# files and geometry
# ------------------------------------------------------------------------------------------


def test_missing_file(tmp_path):
    with pytest.raises(AssetError, match="nope.usda"):
        load_asset(tmp_path / "nope.usda")


def test_file_pxr_cannot_open(tmp_path):
    bad = tmp_path / "garbage.usda"
    bad.write_text("#usda 1.0\ndef Mesh \"m\" {\n  point3f[] points = [(0, 0\n")
    with pytest.raises(AssetError, match="garbage.usda") as err:
        load_asset(bad)
    assert not isinstance(err.value, AssetPathError)


def test_no_mesh(tmp_path):
    stage = new_stage(tmp_path / "a.usda")
    UsdGeom.Sphere.Define(stage, "/Root/ball")
    stage.Save()
    with (pytest.warns(AssetWarning, match="/Root/ball"),
          pytest.raises(AssetError, match="no UsdGeom.Mesh") as err):
        load_asset(tmp_path / "a.usda")
    assert "a.usda" in str(err.value) and "/Root" in str(err.value)


@pytest.mark.parametrize("bad_value", [np.nan, np.inf, -np.inf])
def test_non_finite_points(tmp_path, bad_value):
    stage = new_stage(tmp_path / "a.usda")
    mesh = grid_mesh(stage, "/Root/m", 1, 1)
    pts = np.array(mesh.GetPointsAttr().Get(), dtype=np.float32)
    pts[2, 1] = bad_value
    mesh.GetPointsAttr().Set(Vt.Vec3fArray.FromNumpy(pts))
    stage.Save()
    with pytest.raises(AssetError, match="NaN/Inf") as err:
        load_asset(tmp_path / "a.usda")
    assert "/Root/m" in str(err.value) and "index 2" in str(err.value)


def test_non_finite_points_at_a_time_sample(tmp_path):
    stage = new_stage(tmp_path / "a.usda")
    mesh = grid_mesh(stage, "/Root/m", 1, 1)
    pts = np.array(mesh.GetPointsAttr().Get(), dtype=np.float32)
    mesh.GetPointsAttr().Set(Vt.Vec3fArray.FromNumpy(pts), 1.0)
    pts[3, 0] = np.nan
    mesh.GetPointsAttr().Set(Vt.Vec3fArray.FromNumpy(pts), 2.0)
    stage.Save()
    with pytest.raises(AssetError, match="time 2") as err:
        load_asset(tmp_path / "a.usda")
    assert "/Root/m" in str(err.value) and "index 3" in str(err.value)


@pytest.mark.parametrize("bad_index", [4, 99, -1])
def test_out_of_range_face_indices(tmp_path, bad_index):
    stage = new_stage(tmp_path / "a.usda")
    triangle_mesh(stage, "/Root/m", [(0, 0, 0), (1, 0, 0), (0, 1, 0), (1, 1, 0)],
                  [0, 1, 2, 1, bad_index, 2])
    stage.Save()
    with pytest.raises(AssetError, match="out of range") as err:
        load_asset(tmp_path / "a.usda")
    msg = str(err.value)
    assert "/Root/m" in msg and f"= {bad_index}" in msg and "4 points" in msg


def test_face_counts_do_not_match_indices(tmp_path):
    stage = new_stage(tmp_path / "a.usda")
    mesh = grid_mesh(stage, "/Root/m", 1, 1)
    mesh.GetFaceVertexCountsAttr().Set([5])
    stage.Save()
    with pytest.raises(AssetError, match="faceVertexCounts") as err:
        load_asset(tmp_path / "a.usda")
    assert "/Root/m" in str(err.value)


def test_degenerate_faces_dropped_with_warning(tmp_path):
    stage = new_stage(tmp_path / "a.usda")
    pts = [(0, 0, 0), (1, 0, 0), (0, 1, 0), (2, 0, 0), (3, 0, 0), (4, 0, 0)]
    # one good triangle, one collinear (zero area), one with a repeated vertex
    triangle_mesh(stage, "/Root/m", pts, [0, 1, 2, 3, 4, 5, 0, 0, 1])
    two = UsdGeom.Mesh.Define(stage, "/Root/two")  # a 2-gon and a good triangle
    two.CreatePointsAttr([(0, 0, 1), (1, 0, 1), (0, 1, 1)])
    two.CreateFaceVertexCountsAttr([2, 3])
    two.CreateFaceVertexIndicesAttr([0, 1, 0, 1, 2])
    two.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    stage.Save()
    with pytest.warns(AssetWarning) as record:
        asset = load_asset(tmp_path / "a.usda")
    assert asset.num_faces == 2 and asset.dropped_faces == 3
    texts = [str(r.message) for r in record]
    assert any("/Root/m" in t and "dropped 2" in t for t in texts)
    assert any("/Root/two" in t and "fewer than 3" in t for t in texts)
    assert set(texts) <= set(asset.warnings)
    np.testing.assert_array_equal(asset.faces, [[0, 1, 2], [6, 7, 8]])  # the good ones survive


def test_tiny_face_below_relative_threshold_is_dropped(tmp_path):
    # area 5e-17 against a bbox diagonal of ~1.4: below TOL.zero_area * diag^2 = 2e-14
    stage = new_stage(tmp_path / "a.usda")
    pts = [(0, 0, 0), (1, 0, 0), (0, 1, 0), (0.5, 0.5, 0), (0.5 + 1e-8, 0.5, 0),
           (0.5, 0.5 + 1e-8, 0)]
    triangle_mesh(stage, "/Root/m", np.array(pts, dtype=np.float64), [0, 1, 2, 3, 4, 5])
    stage.Save()
    with pytest.warns(AssetWarning, match="/Root/m"):
        asset = load_asset(tmp_path / "a.usda")
    assert asset.dropped_faces == 1 and asset.num_faces == 1


def test_all_faces_degenerate(tmp_path):
    stage = new_stage(tmp_path / "a.usda")
    triangle_mesh(stage, "/Root/flat", [(0, 0, 0), (1, 0, 0), (2, 0, 0)], [0, 1, 2])
    stage.Save()
    with (pytest.warns(AssetWarning), pytest.raises(AssetError, match="every face is degenerate")
          as err):
        load_asset(tmp_path / "a.usda")
    assert "/Root/flat" in str(err.value)


def test_mesh_without_faces(tmp_path):
    stage = new_stage(tmp_path / "a.usda")
    UsdGeom.Mesh.Define(stage, "/Root/empty")
    stage.Save()
    with pytest.raises(AssetError, match="no faces") as err:
        load_asset(tmp_path / "a.usda")
    assert "/Root/empty" in str(err.value)


def test_geomsubset_index_out_of_range(tmp_path):
    stage = new_stage(tmp_path / "a.usda")
    mesh = grid_mesh(stage, "/Root/m", 1, 1)
    subset = UsdGeom.Subset.CreateGeomSubset(mesh, "bad", UsdGeom.Tokens.face, Vt.IntArray([0, 7]),
                                             UsdShade.Tokens.materialBind)
    bind(subset, preview_material(stage, "/Root/Looks/M"))
    stage.Save()
    with pytest.raises(AssetError, match="face index 7") as err:
        load_asset(tmp_path / "a.usda")
    assert "/Root/m/bad" in str(err.value)


def test_changing_topology_over_time(tmp_path):
    stage = new_stage(tmp_path / "a.usda")
    mesh = grid_mesh(stage, "/Root/m", 1, 1)
    pts = np.array(mesh.GetPointsAttr().Get(), dtype=np.float32)
    mesh.GetPointsAttr().Set(Vt.Vec3fArray.FromNumpy(pts), 1.0)
    mesh.GetPointsAttr().Set(Vt.Vec3fArray.FromNumpy(np.vstack([pts, pts[:1]])), 2.0)
    stage.Save()
    with pytest.raises(AssetError, match="changing topology") as err:
        load_asset(tmp_path / "a.usda")
    assert "/Root/m" in str(err.value)


# ------------------------------------------------------------------------------------------
# asset paths
# ------------------------------------------------------------------------------------------


def _textured(tmp_path, texture_path: str):
    stage = new_stage(tmp_path / "a.usda")
    mesh = grid_mesh(stage, "/Root/m", 1, 1)
    bind(mesh, preview_material(stage, "/Root/Looks/M", texture=texture_path))
    stage.Save()
    return tmp_path / "a.usda"


def _assert_names(err, *needles):
    msg = str(err.value)
    for needle in needles:
        assert needle in msg, (needle, msg)


def test_missing_texture(tmp_path):
    # a renderer's reading: warned, the material's constant (no `fallback` authored), listed
    path = _textured(tmp_path, "./textures/missing.png")
    with pytest.warns(AssetWarning, match=r"missing\.png.*/Root/Looks/M/Texture"):
        asset = load_asset(path)
    assert "diffuseColor" not in asset.materials[0].textures
    np.testing.assert_allclose(asset.materials[0].params["diffuseColor"], [0.5] * 3)
    assert len(asset.missing_paths) == 1 and "./textures/missing.png" in asset.missing_paths[0]
    # the node's own fallback wins over the constant, reduced to the output's channels
    stage = Usd.Stage.Open(str(path))
    UsdShade.Shader(stage.GetPrimAtPath("/Root/Looks/M/Texture")).CreateInput(
        "fallback", Sdf.ValueTypeNames.Float4).Set((0.1, 0.2, 0.3, 0.4))
    stage.Save()
    with pytest.warns(AssetWarning, match="using its fallback"):
        asset = load_asset(path)
    np.testing.assert_allclose(asset.materials[0].params["diffuseColor"], [0.1, 0.2, 0.3],
                               atol=1e-7)


def test_absolute_texture_path(tmp_path):
    write_png(tmp_path / "tex.png", np.zeros((1, 1, 3), np.uint8))
    absolute = str((tmp_path / "tex.png").resolve())  # exists, but absolute is refused
    path = _textured(tmp_path, absolute)
    with pytest.raises(AssetPathError, match="is absolute") as err:
        load_asset(path)
    _assert_names(err, absolute, "/Root/Looks/M/Texture")


@pytest.mark.parametrize("url", ["http://example.com/tex.png", "s3://bucket/tex.png",
                                 "file:///etc/passwd"])
def test_url_texture_path(tmp_path, url):
    path = _textured(tmp_path, url)
    with pytest.raises(AssetPathError, match="URL") as err:
        check_asset_paths(path)
    _assert_names(err, url, "/Root/Looks/M/Texture")


def test_dotdot_escaping_reference_is_never_opened(tmp_path):
    inner = tmp_path / "asset"
    inner.mkdir()
    outside = tmp_path / "hostile.usda"
    hostile = new_stage(outside)
    grid_mesh(hostile, "/Root/m", 1, 1)
    hostile.Save()
    del hostile
    stage = new_stage(inner / "a.usda")
    stage.GetPrimAtPath("/Root").GetReferences().AddReference("../hostile.usda")
    stage.Save()
    del stage
    assert Sdf.Layer.Find(str(outside)) is None  # not in the layer registry before
    with pytest.raises(AssetPathError, match="escapes") as err:
        load_asset(inner / "a.usda")
    _assert_names(err, "../hostile.usda", "/Root", "a.usda")
    assert Sdf.Layer.Find(str(outside)) is None  # and still never opened


def test_dotdot_inside_the_folder_is_fine(tmp_path):
    (tmp_path / "sub").mkdir()
    write_png(tmp_path / "tex.png", np.zeros((1, 1, 3), np.uint8))
    path = _textured(tmp_path, "./sub/../tex.png")
    asset = load_asset(path)
    assert asset.materials[0].textures["diffuseColor"].pixels.shape == (1, 1, 3)


def test_symlink_escaping_the_folder(tmp_path):
    inner = tmp_path / "asset"
    inner.mkdir()
    write_png(tmp_path / "secret.png", np.zeros((1, 1, 3), np.uint8))
    (inner / "tex.png").symlink_to(tmp_path / "secret.png")
    path = _textured(inner, "./tex.png")
    with pytest.raises(AssetPathError, match="escapes") as err:
        load_asset(path)
    _assert_names(err, "./tex.png", "/Root/Looks/M/Texture")


def test_reference_to_a_file_pxr_cannot_read(tmp_path):
    (tmp_path / "model.obj").write_text("v 0 0 0\n")
    stage = new_stage(tmp_path / "a.usda")
    grid_mesh(stage, "/Root/m", 1, 1)
    stage.DefinePrim("/Root/prop").GetReferences().AddReference("./model.obj")
    stage.Save()
    with pytest.raises(AssetError, match="cannot open") as err:
        check_asset_paths(tmp_path / "a.usda")
    assert not isinstance(err.value, AssetPathError)
    _assert_names(err, "model.obj")


def test_missing_sublayer(tmp_path):
    stage = new_stage(tmp_path / "a.usda")
    grid_mesh(stage, "/Root/m", 1, 1)
    stage.GetRootLayer().subLayerPaths.append("./layers/gone.usda")
    stage.Save()
    with pytest.raises(AssetPathError, match="does not exist") as err:
        load_asset(tmp_path / "a.usda")
    _assert_names(err, "./layers/gone.usda", "subLayers")


@pytest.mark.parametrize("selected", [True, False])
def test_absolute_payload_in_a_variant(tmp_path, selected):
    other = new_stage(tmp_path / "other.usda")
    grid_mesh(other, "/Root/m", 1, 1)
    other.Save()
    stage = new_stage(tmp_path / "a.usda")
    grid_mesh(stage, "/Root/m", 1, 1)
    root = stage.GetPrimAtPath("/Root")
    vset = root.GetVariantSets().AddVariantSet("LOD")
    vset.AddVariant("LOD1")
    vset.SetVariantSelection("LOD1")
    with vset.GetVariantEditContext():
        stage.DefinePrim("/Root/heavy").GetPayloads().AddPayload(str(tmp_path / "other.usda"))
    if not selected:
        vset.ClearVariantSelection()
    stage.Save()
    if selected:  # the bake would read it: refused, naming the variant's spec
        with pytest.raises(AssetPathError, match="is absolute") as err:
            check_asset_paths(tmp_path / "a.usda")
        _assert_names(err, "other.usda", "/Root{LOD=LOD1}heavy")
        return
    # unselected: composition never reads it, so the check does not refuse it; listed instead
    scan = scan_asset_paths(tmp_path / "a.usda")
    assert len(scan.unreachable) == 1 and "/Root{LOD=LOD1}heavy" in scan.unreachable[0]
    assert str(tmp_path / "other.usda") not in scan.files


def test_path_expression_rejected(tmp_path):
    path = _textured(tmp_path, '`"./{TEX}.png"`')
    with pytest.raises(AssetPathError, match="expression"):
        check_asset_paths(path)


def test_usdz_member_escaping_the_package(tmp_path):
    layer = tmp_path / "root.usda"
    stage = new_stage(layer)
    mesh = grid_mesh(stage, "/Root/m", 1, 1)
    bind(mesh, preview_material(stage, "/Root/Looks/M", texture="../tex.png"))
    stage.Save()
    write_png(tmp_path / "tex.png", np.zeros((1, 1, 3), np.uint8))
    pkg_dir = tmp_path / "pkg"
    pkg_dir.mkdir()
    writer = Sdf.ZipFileWriter.CreateNew(str(pkg_dir / "a.usdz"))
    writer.AddFile(str(layer), "root.usda")
    writer.Save()
    with pytest.raises(AssetPathError, match="escapes the .usdz package") as err:
        load_asset(pkg_dir / "a.usdz")
    _assert_names(err, "../tex.png", "/Root/Looks/M/Texture", "a.usdz[root.usda]")


def test_missing_merl_file(tmp_path):
    stage = new_stage(tmp_path / "a.usda")
    mesh = grid_mesh(stage, "/Root/m", 1, 1)
    mat = preview_material(stage, "/Root/Looks/Gold")
    sh = UsdShade.Shader.Define(stage, "/Root/Looks/Gold/Merl")
    sh.CreateIdAttr(SHADER_MEASURED)
    sh.CreateInput("file", Sdf.ValueTypeNames.Asset).Set("./gold.binary")
    mat.CreateSurfaceOutput("texelbake").ConnectToSource(sh.ConnectableAPI(), "surface")
    bind(mesh, mat)
    stage.Save()
    with pytest.raises(AssetPathError, match="does not exist") as err:
        load_asset(tmp_path / "a.usda")
    _assert_names(err, "./gold.binary", "/Root/Looks/Gold/Merl")
    # present but not a MERL table: AssetError naming the file and the shader prim
    (tmp_path / "gold.binary").write_bytes(np.array([10, 10, 10], "<i4").tobytes())
    with pytest.raises(AssetError, match="MERL") as err:
        load_asset(tmp_path / "a.usda")
    _assert_names(err, "gold.binary", "/Root/Looks/Gold/Merl")


# ------------------------------------------------------------------------------------------
# unsupported shader networks: warning naming the prim, constant values
# ------------------------------------------------------------------------------------------


def test_unsupported_node_feeding_an_input(tmp_path):
    stage = new_stage(tmp_path / "a.usda")
    mesh = grid_mesh(stage, "/Root/m", 1, 1)
    mat = preview_material(stage, "/Root/Looks/M", (0.3, 0.6, 0.9))
    noise = UsdShade.Shader.Define(stage, "/Root/Looks/M/Noise")
    noise.CreateIdAttr("ND_noise2d_color3")
    noise.CreateOutput("out", Sdf.ValueTypeNames.Color3f)
    UsdShade.Shader(stage.GetPrimAtPath("/Root/Looks/M/Surface")).GetInput(
        "diffuseColor").ConnectToSource(noise.ConnectableAPI(), "out")
    bind(mesh, mat)
    stage.Save()
    with pytest.warns(AssetWarning, match="/Root/Looks/M/Noise"):
        asset = load_asset(tmp_path / "a.usda")
    m = asset.materials[0]
    assert m.model == "preview" and not m.textures
    np.testing.assert_allclose(m.params["diffuseColor"], [0.3, 0.6, 0.9], atol=1e-7)
    assert any("/Root/Looks/M/Noise" in w for w in asset.warnings)


def test_unsupported_surface_shader_falls_back_to_constants(tmp_path):
    stage = new_stage(tmp_path / "a.usda")
    mesh = grid_mesh(stage, "/Root/m", 1, 1)
    mat = UsdShade.Material.Define(stage, "/Root/Looks/X")
    sh = UsdShade.Shader.Define(stage, "/Root/Looks/X/Std")
    sh.CreateIdAttr("StudioX_surface")  # a shader texelbake does not know (MaterialX is read)
    sh.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).Set((0.1, 0.2, 0.3))
    sh.CreateInput("metallic", Sdf.ValueTypeNames.Float).Set(1.0)
    sh.CreateInput("base_color", Sdf.ValueTypeNames.Color3f).Set((1, 1, 1))  # not a preview input
    mat.CreateSurfaceOutput().ConnectToSource(sh.ConnectableAPI(), "surface")
    bind(mesh, mat)
    stage.Save()
    with pytest.warns(AssetWarning, match="/Root/Looks/X/Std"):
        asset = load_asset(tmp_path / "a.usda")
    m = asset.materials[0]
    assert m.path == "/Root/Looks/X" and m.model == "preview"
    np.testing.assert_allclose(m.params["diffuseColor"], [0.1, 0.2, 0.3], atol=1e-7)
    assert m.params["metallic"] == 1.0 and m.params["roughness"] == 0.5  # the rest: defaults


def test_udim_texture_falls_back_to_constant(tmp_path):
    write_png(tmp_path / "tex.1001.png", np.zeros((1, 1, 3), np.uint8))
    path = _textured(tmp_path, "./tex.<UDIM>.png")
    assert check_asset_paths(path) == sorted(  # the tile is part of the bundle
        str((tmp_path / n).resolve()) for n in ("a.usda", "tex.1001.png"))
    with pytest.warns(AssetWarning, match="UDIM"):
        asset = load_asset(path)
    assert not asset.materials[0].textures
    (tmp_path / "tex.1001.png").unlink()  # no tile at all: a missing texture, listed
    scan = scan_asset_paths(path)
    assert len(scan.missing) == 1 and "tex.<UDIM>.png" in scan.missing[0]


def test_material_without_surface(tmp_path):
    stage = new_stage(tmp_path / "a.usda")
    mesh = grid_mesh(stage, "/Root/m", 1, 1)
    bind(mesh, UsdShade.Material.Define(stage, "/Root/Looks/Empty"))
    stage.Save()
    with pytest.warns(AssetWarning, match="/Root/Looks/Empty"):
        asset = load_asset(tmp_path / "a.usda")
    np.testing.assert_allclose(asset.materials[0].params["diffuseColor"], [0.18] * 3)


def test_every_error_is_a_texelbake_error(tmp_path):
    path = _textured(tmp_path, "http://x.org/t.png")
    with pytest.raises(TexelbakeError):
        load_asset(path)


def test_orthographic_camera_warns(tmp_path):
    stage = new_stage(tmp_path / "a.usda")
    grid_mesh(stage, "/Root/m", 1, 1)
    UsdGeom.Camera.Define(stage, "/Root/Ortho").CreateProjectionAttr(UsdGeom.Tokens.orthographic)
    stage.Save()
    with pytest.warns(AssetWarning, match="/Root/Ortho"):
        asset = load_asset(tmp_path / "a.usda")
    assert [c.path for c in asset.cameras] == ["/Root/Ortho"]
