"""Shading networks as studios author them: material inputs driven by UsdPrimvarReader nodes
are evaluated on the bound mesh; MaterialX surface shaders are read as UsdPreviewSurface
(issue 11, item 4; texelbake.asset.primvars). Expected values are computed here from the
authored arrays, not through texelbake."""

from __future__ import annotations

import numpy as np
import pytest
from pxr import Sdf, UsdGeom, UsdShade, Vt

from tests.helpers.usd_stages import bind, grid_mesh, new_stage
from texelbake.asset import load_asset
from texelbake.geometry.subdivision import refinement_levels


def _display_color_material(stage, path, reader_id="UsdPrimvarReader_float3", fallback=None,
                            varname="displayColor"):
    """UsdPreviewSurface whose diffuseColor reads a primvar (the Teapot's network shape)."""
    mat = UsdShade.Material.Define(stage, path)
    surf = UsdShade.Shader.Define(stage, f"{path}/Surface")
    surf.CreateIdAttr("UsdPreviewSurface")
    surf.CreateInput("roughness", Sdf.ValueTypeNames.Float).Set(0.3)
    reader = UsdShade.Shader.Define(stage, f"{path}/Reader")
    reader.CreateIdAttr(reader_id)
    reader.CreateInput("varname", Sdf.ValueTypeNames.String).Set(varname)
    if fallback is not None:
        reader.CreateInput("fallback", Sdf.ValueTypeNames.Float3).Set(tuple(fallback))
    out = reader.CreateOutput("result", Sdf.ValueTypeNames.Float3)
    surf.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).ConnectToSource(out)
    mat.CreateSurfaceOutput().ConnectToSource(surf.ConnectableAPI(), "surface")
    return mat


def _color(mesh, values, interp):
    pv = UsdGeom.PrimvarsAPI(mesh).CreatePrimvar("displayColor", Sdf.ValueTypeNames.Color3fArray,
                                                 interp)
    pv.Set(Vt.Vec3fArray.FromNumpy(np.asarray(values, np.float32)))


def _diffuse_per_triangle(asset):
    return np.stack([np.asarray(asset.materials[i].params["diffuseColor"])
                     for i in asset.face_material])


def test_constant_primvar_per_mesh_and_inherited(tmp_path):
    stage = new_stage(tmp_path / "a.usda")
    mat = _display_color_material(stage, "/Root/Looks/M")
    a = grid_mesh(stage, "/Root/A", 1, 1)
    grp = UsdGeom.Xform.Define(stage, "/Root/G")
    b = grid_mesh(stage, "/Root/G/B", 1, 1, z=1.0)
    _color(a, [(0.9, 0.1, 0.2)], UsdGeom.Tokens.constant)
    _color(grp, [(0.1, 0.7, 0.3)], UsdGeom.Tokens.constant)  # inherited by B
    bind(a, mat)
    bind(b, mat)
    stage.Save()
    asset = load_asset(tmp_path / "a.usda")
    got = _diffuse_per_triangle(asset)
    by_mesh = {p: got[asset.face_mesh == i] for i, p in enumerate(asset.mesh_paths)}
    np.testing.assert_allclose(by_mesh["/Root/A"], [[0.9, 0.1, 0.2]] * 2, rtol=1e-6)
    np.testing.assert_allclose(by_mesh["/Root/G/B"], [[0.1, 0.7, 0.3]] * 2, rtol=1e-6)
    assert {m.path for m in asset.materials} == {"/Root/Looks/M"}  # one material, two values
    assert not any("unsupported node" in w for w in asset.warnings)


def test_uniform_and_vertex_primvars(tmp_path):
    stage = new_stage(tmp_path / "a.usda")
    mat = _display_color_material(stage, "/Root/Looks/M")
    u = grid_mesh(stage, "/Root/U", 2, 1)  # two quads -> four triangles
    v = grid_mesh(stage, "/Root/V", 1, 1, z=1.0)
    uni = [(1.0, 0.0, 0.0), (0.0, 0.0, 1.0)]
    _color(u, uni, UsdGeom.Tokens.uniform)
    vert = np.array([(0.0, 0.0, 0.0), (1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)])
    _color(v, vert, UsdGeom.Tokens.vertex)
    bind(u, mat)
    bind(v, mat)
    stage.Save()
    asset = load_asset(tmp_path / "a.usda")
    got = _diffuse_per_triangle(asset)
    mesh_u = asset.mesh_paths.index("/Root/U")
    # the fan triangulation keeps each quad's two triangles on its face: per face, exact
    np.testing.assert_allclose(got[asset.face_mesh == mesh_u], np.repeat(uni, 2, axis=0),
                               rtol=1e-6)
    # vertex colours: a face takes the mean of its four corners (documented)
    mesh_v = asset.mesh_paths.index("/Root/V")
    np.testing.assert_allclose(got[asset.face_mesh == mesh_v], [vert.mean(axis=0)] * 2,
                               rtol=1e-6)
    assert any("/Root/V" in w and "corners' mean" in w for w in asset.warnings)


def test_missing_primvar_gives_the_readers_fallback(tmp_path):
    stage = new_stage(tmp_path / "a.usda")
    with_fb = _display_color_material(stage, "/Root/Looks/F", fallback=(0.2, 0.4, 0.6))
    without = _display_color_material(stage, "/Root/Looks/Z")
    a = grid_mesh(stage, "/Root/A", 1, 1)
    b = grid_mesh(stage, "/Root/B", 1, 1, z=1.0)
    bind(a, with_fb)
    bind(b, without)
    stage.Save()
    asset = load_asset(tmp_path / "a.usda")
    got = _diffuse_per_triangle(asset)
    np.testing.assert_allclose(got[asset.face_mesh == asset.mesh_paths.index("/Root/A")],
                               [[0.2, 0.4, 0.6]] * 2, rtol=1e-6)
    # the UsdPrimvarReader spec: no primvar and no fallback -> zeros
    np.testing.assert_allclose(got[asset.face_mesh == asset.mesh_paths.index("/Root/B")], 0.0)


def test_many_distinct_values_are_bounded(tmp_path):
    from texelbake.asset.primvars import MAX_VARIANTS

    stage = new_stage(tmp_path / "a.usda")
    mat = _display_color_material(stage, "/Root/Looks/M")
    m = grid_mesh(stage, "/Root/A", 20, 10)  # 200 faces
    rng = np.random.default_rng(0)
    _color(m, rng.uniform(size=(200, 3)), UsdGeom.Tokens.uniform)
    bind(m, mat)
    stage.Save()
    asset = load_asset(tmp_path / "a.usda")
    assert len(asset.materials) <= MAX_VARIANTS
    assert any("distinct primvar values" in w for w in asset.warnings)


def test_subdivision_mesh_is_baked_from_its_limit_surface(tmp_path):
    # a flat 4 x 2 grid, catmullClark, UVs = xy face-varying, two materials by GeomSubset;
    # the same grid as a loop surface, and one with its scheme unauthored
    stage = new_stage(tmp_path / "a.usda")
    m = grid_mesh(stage, "/Root/A", 4, 2)
    m.GetSubdivisionSchemeAttr().Set(UsdGeom.Tokens.catmullClark)
    pts = np.asarray(m.GetPointsAttr().Get(), dtype=np.float64)
    idx = np.asarray(m.GetFaceVertexIndicesAttr().Get())
    st = UsdGeom.PrimvarsAPI(m).CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray,
                                               UsdGeom.Tokens.faceVarying)
    st.Set(Vt.Vec2fArray.FromNumpy(pts[idx, :2].astype(np.float32)))
    red = _display_color_material(stage, "/Root/Looks/Red")
    blue = _display_color_material(stage, "/Root/Looks/Blue")
    for name, faces, mat in (("left", [0, 1, 4, 5], red), ("right", [2, 3, 6, 7], blue)):
        subset = UsdGeom.Subset.CreateGeomSubset(m, name, UsdGeom.Tokens.face, faces,
                                                 UsdShade.Tokens.materialBind)
        bind(subset, mat)
    loop = grid_mesh(stage, "/Root/L", 1, 1, z=5.0)
    loop.GetSubdivisionSchemeAttr().Set(UsdGeom.Tokens.loop)
    plain = grid_mesh(stage, "/Root/P", 1, 1, z=9.0)
    plain.GetSubdivisionSchemeAttr().Clear()  # UsdGeom's fallback: catmullClark
    stage.Save()
    with pytest.warns(UserWarning, match="'loop'.*control cage"):
        asset = load_asset(tmp_path / "a.usda")
    assert any("/Root/P: subdivisionScheme not authored" in w for w in asset.warnings)
    on_a = asset.face_mesh == 0
    # 8 quads refined until 4096 quads (refinement_levels: 32 corners, five levels); the
    # loop cage and the unauthored one as authored (2 triangles each)
    assert on_a.sum() == 2 * 32 * 4 ** (refinement_levels(np.full(8, 4)) - 1) == 16384
    assert (asset.face_mesh == 1).sum() == (asset.face_mesh == 2).sum() == 2
    tri = asset.points[asset.faces[on_a]]  # (t, 3, 3)
    # a flat cage stays flat, and its outline: the limit of a planar grid is the grid's
    # rectangle (boundary curves of collinear points, corners kept)
    np.testing.assert_allclose(tri[..., 2], 0.0, atol=1e-6)
    np.testing.assert_allclose([tri[..., 0].min(), tri[..., 0].max(), tri[..., 1].min(),
                                tri[..., 1].max()], [0, 4, 0, 2], atol=1e-6)
    # UVs linear in xy stay so on the refined flat grid (bilinear face-varying refinement)
    np.testing.assert_allclose(asset.corner_uvs[on_a], tri[..., :2], atol=1e-6)
    # each refined triangle keeps its cage face's material: left half red, right half blue
    centre_x = tri[..., 0].mean(axis=1)
    mats = asset.face_material[on_a]
    assert len(set(mats[centre_x < 2].tolist())) == 1
    assert len(set(mats[centre_x > 2].tolist())) == 1
    assert mats[centre_x < 2][0] != mats[centre_x > 2][0]
    # smooth shading: normals computed from the refined surface, +z everywhere on the flat grid
    np.testing.assert_allclose(asset.corner_normals[on_a][..., 2], 1.0, atol=1e-9)


def test_time_sampled_subdivision_mesh_is_refined_at_every_time(tmp_path):
    # points authored at t = 0 and t = 1 (lifted by 0.5): each frame is refined by the same
    # operator, so the refined frames differ by the same lift (refinement is affine-invariant)
    stage = new_stage(tmp_path / "a.usda")
    m = grid_mesh(stage, "/Root/A", 2, 2)
    m.GetSubdivisionSchemeAttr().Set(UsdGeom.Tokens.catmullClark)
    pts = np.asarray(m.GetPointsAttr().Get(), dtype=np.float64)
    pts[4, 2] = 0.3  # a bump in the middle, so the refined surface is not flat
    for t, lift in ((0.0, 0.0), (1.0, 0.5)):
        m.GetPointsAttr().Set(Vt.Vec3fArray.FromNumpy((pts + [0, 0, lift]).astype(np.float32)),
                              t)
    stage.Save()
    asset = load_asset(tmp_path / "a.usda")
    frames = asset.points_over_time
    assert frames.shape == (2, asset.points.shape[0], 3) and asset.points.shape[0] > 9
    np.testing.assert_allclose(frames[0], asset.points, atol=1e-6)
    np.testing.assert_allclose(frames[1] - frames[0], np.tile([0, 0, 0.5], (frames.shape[1], 1)),
                               atol=1e-6)
    assert 0.0 < asset.points[:, 2].max() < 0.3  # the bump, smoothed


# ---- MaterialX surface shaders (texelbake.asset.mtlx) ---------------------------------------


def _mtlx_material(stage, path, inputs, *, universal=False, driven=None):
    mat = UsdShade.Material.Define(stage, path)
    sh = UsdShade.Shader.Define(stage, f"{path}/SR")
    sh.CreateIdAttr("ND_standard_surface_surfaceshader")
    for name, (type_name, value) in inputs.items():
        sh.CreateInput(name, type_name).Set(value)
    if driven is not None:
        node = UsdShade.Shader.Define(stage, f"{path}/Image")
        node.CreateIdAttr("ND_image_color3")
        out = node.CreateOutput("out", Sdf.ValueTypeNames.Color3f)
        sh.CreateInput(driven, Sdf.ValueTypeNames.Color3f).ConnectToSource(out)
    surf = sh.CreateOutput("out", Sdf.ValueTypeNames.Token)
    mat.CreateSurfaceOutput("mtlx").ConnectToSource(surf)
    if universal:
        mat.CreateSurfaceOutput().ConnectToSource(surf)
    return mat


def test_materialx_standard_surface_maps_to_preview_surface(tmp_path):
    f, c3 = Sdf.ValueTypeNames.Float, Sdf.ValueTypeNames.Color3f
    stage = new_stage(tmp_path / "a.usda")
    a = grid_mesh(stage, "/Root/A", 1, 1)
    b = grid_mesh(stage, "/Root/B", 1, 1, z=1.0)
    bind(a, _mtlx_material(stage, "/Root/Looks/Metal", {
        "base": (f, 0.5), "base_color": (c3, (1.0, 0.5, 0.25)), "metalness": (f, 1.0),
        "specular_roughness": (f, 0.3), "opacity": (c3, (0.5, 0.5, 1.0)),
        "sheen": (f, 0.2)}))
    bind(b, _mtlx_material(stage, "/Root/Looks/Tex", {"specular_IOR": (f, 1.33)},
                           universal=True, driven="base_color"))
    stage.Save()
    asset = load_asset(tmp_path / "a.usda")
    by = {m.path: m for m in asset.materials}
    metal = by["/Root/Looks/Metal"]
    assert metal.model == "preview"
    np.testing.assert_allclose(metal.params["diffuseColor"], [0.5, 0.25, 0.125])
    assert metal.params["metallic"] == 1.0 and metal.params["roughness"] == pytest.approx(0.3)
    assert metal.params["opacity"] == pytest.approx(2.0 / 3.0)
    tex = by["/Root/Looks/Tex"]  # unauthored inputs: the Standard Surface defaults
    np.testing.assert_allclose(tex.params["diffuseColor"], [0.8, 0.8, 0.8])
    assert tex.params["ior"] == pytest.approx(1.33) and tex.params["roughness"] == 0.2
    text = " ".join(asset.warnings)
    assert "sheen" in text and "base_color is driven by a node" in text


def test_a_texture_reads_the_uv_set_it_names(tmp_path):
    from tests.helpers.usd_stages import preview_material, write_png

    write_png(tmp_path / "t.png", np.zeros((2, 2, 3), np.uint8))
    stage = new_stage(tmp_path / "a.usda")
    m = grid_mesh(stage, "/Root/A", 1, 1)
    api = UsdGeom.PrimvarsAPI(m)
    st = np.array([[0, 0], [1, 0], [0, 1], [1, 1]], np.float32)
    api.CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.vertex).Set(
        Vt.Vec2fArray.FromNumpy(st))
    api.CreatePrimvar("lightmap", Sdf.ValueTypeNames.TexCoord2fArray,
                      UsdGeom.Tokens.vertex).Set(Vt.Vec2fArray.FromNumpy(st * 0.5 + 0.25))
    bind(m, preview_material(stage, "/Root/Looks/M", texture="./t.png", varname="lightmap"))
    stage.Save()
    asset = load_asset(tmp_path / "a.usda")
    # the texture names primvars:lightmap, so the mesh carries that set, not st
    assert asset.corner_uvs.min() >= 0.25 - 1e-6 and asset.corner_uvs.max() <= 0.75 + 1e-6
    assert not any("UV" in w for w in asset.warnings)
