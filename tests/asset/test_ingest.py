"""USD ingest (texelbake.asset): every feature on small stages built with pxr, each checked
against an independent truth (hand-built matrices, brute-force loops, closed forms)."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
from pxr import Gf, Sdf, UsdGeom, UsdLux, UsdShade, UsdUtils, Vt

from tests.helpers.usd_stages import (
    bind,
    grid_mesh,
    new_stage,
    preview_material,
    triangle_mesh,
    write_png,
)
from texelbake.asset import (
    DEFAULT_MATERIAL,
    AssetWarning,
    check_asset_paths,
    describe,
    load_asset,
    srgb_to_linear,
)
from texelbake.geometry.mesh import face_normals, triangle_areas
from texelbake.model import SHADER_LAMBERT, SHADER_MEASURED, SHADER_PHONG, AssetModel

# Points are authored as float32; every comparison of positions uses the float32 inputs
# widened to float64, so exact transforms agree to float64 rounding of a few products.
ATOL_GEOM = 1e-9


def _srgb_reference(v: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1 decoding in float64, written independently of texelbake."""
    v = np.asarray(v, dtype=np.float64)
    out = np.empty_like(v)
    low = v <= 0.04045
    out[low] = v[low] / 12.92
    out[~low] = ((v[~low] + 0.055) / 1.055) ** 2.4
    return out


def _rot_row(axis: str, degrees: float) -> np.ndarray:
    """Row-vector rotation matrix (p' = p @ R), the transpose of the textbook column form."""
    a = math.radians(degrees)
    c, s = math.cos(a), math.sin(a)
    col = {
        "x": np.array([[1, 0, 0], [0, c, -s], [0, s, c]]),
        "y": np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]),
        "z": np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]),
    }[axis]
    return col.T


def _affine_row(lin: np.ndarray, t) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = lin
    m[3, :3] = t
    return m


# ------------------------------------------------------------------------------------------
# geometry
# ------------------------------------------------------------------------------------------


def test_ngon_fan_triangulation(tmp_path):
    stage = new_stage(tmp_path / "a.usda")
    # a convex pentagon and a quad sharing nothing; fan from each polygon's first corner
    pts = [(0, 0, 0), (2, 0, 0), (3, 1.5, 0), (1, 3, 0), (-1, 1.5, 0),
           (5, 0, 0), (6, 0, 0), (6, 1, 0), (5, 1, 0)]
    mesh = UsdGeom.Mesh.Define(stage, "/Root/m")
    mesh.CreatePointsAttr(pts)
    mesh.CreateFaceVertexCountsAttr([5, 4])
    mesh.CreateFaceVertexIndicesAttr([0, 1, 2, 3, 4, 5, 6, 7, 8])
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    stage.Save()
    asset = load_asset(tmp_path / "a.usda")
    assert isinstance(asset, AssetModel)
    expected = np.array([[0, 1, 2], [0, 2, 3], [0, 3, 4], [5, 6, 7], [5, 7, 8]])
    np.testing.assert_array_equal(asset.faces, expected)
    assert asset.faces.dtype == np.int64 and asset.corner_normals.shape == (5, 3, 3)
    # total area equals the shoelace area of each polygon (independent closed form)
    p = np.array(pts, dtype=float)

    def shoelace(idx):
        x, y = p[idx, 0], p[idx, 1]
        return 0.5 * abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))

    assert triangle_areas(asset.points, asset.faces).sum() == pytest.approx(shoelace([0, 1, 2, 3, 4]) + 1.0, rel=1e-12)
    np.testing.assert_array_equal(asset.face_mesh, np.zeros(5))
    np.testing.assert_allclose(face_normals(asset.points, asset.faces), np.tile([0, 0, 1.0], (5, 1)), atol=1e-12)


def test_left_handed_orientation_flips_winding(tmp_path):
    stage = new_stage(tmp_path / "a.usda")
    grid_mesh(stage, "/Root/right", 1, 1)
    left = grid_mesh(stage, "/Root/left", 1, 1)
    left.CreateOrientationAttr(UsdGeom.Tokens.leftHanded)
    stage.Save()
    asset = load_asset(tmp_path / "a.usda")
    fn = face_normals(asset.points, asset.faces)
    right_faces, left_faces = asset.face_mesh == 0, asset.face_mesh == 1
    np.testing.assert_allclose(fn[right_faces], np.tile([0, 0, 1.0], (2, 1)), atol=1e-12)
    np.testing.assert_allclose(fn[left_faces], np.tile([0, 0, -1.0], (2, 1)), atol=1e-12)
    # computed shading normals follow the flipped winding
    np.testing.assert_allclose(asset.corner_normals[left_faces], -1.0 * np.tile(
        [0, 0, 1.0], (2, 3, 1)), atol=1e-12)


def test_transforms_flattened_against_hand_built_matrices(tmp_path):
    stage = new_stage(tmp_path / "a.usda")
    a = UsdGeom.Xform.Define(stage, "/Root/A")
    a.AddTranslateOp().Set(Gf.Vec3d(1, 2, 3))
    a.AddRotateXYZOp().Set(Gf.Vec3f(30, 45, 60))
    a.AddScaleOp().Set(Gf.Vec3f(2, 0.5, 1.5))
    b = UsdGeom.Xform.Define(stage, "/Root/A/B")
    b.AddTranslateOp().Set(Gf.Vec3d(0.5, 0, 0))
    b.AddRotateZOp().Set(90.0)
    rng = np.random.default_rng(7)
    local = rng.normal(size=(6, 3)).astype(np.float32)
    triangle_mesh(stage, "/Root/A/B/m", local, [0, 1, 2, 3, 4, 5])
    stage.Save()
    asset = load_asset(tmp_path / "a.usda")
    # USD: xformOpOrder [translate, rotateXYZ, scale] applies scale first; rotateXYZ applies
    # X, then Y, then Z. Row vectors: p_parent = p @ S @ Rx @ Ry @ Rz @ T.
    m_a = _affine_row(np.diag([2, 0.5, 1.5]) @ _rot_row("x", 30) @ _rot_row("y", 45)
                      @ _rot_row("z", 60), [1, 2, 3])
    m_b = _affine_row(_rot_row("z", 90), [0.5, 0, 0])
    world = m_b @ m_a
    expected = np.c_[local.astype(np.float64), np.ones(6)] @ world
    np.testing.assert_allclose(asset.points, expected[:, :3], atol=ATOL_GEOM)


def test_authored_normals_follow_nonuniform_transform(tmp_path):
    stage = new_stage(tmp_path / "a.usda")
    xf = UsdGeom.Xform.Define(stage, "/Root/X")
    xf.AddRotateXYZOp().Set(Gf.Vec3f(10, 20, 30))
    xf.AddScaleOp().Set(Gf.Vec3f(3.0, 0.5, 1.0))
    # a tilted plane: two triangles, authored normal = its geometric normal in local space
    pts = np.array([[0, 0, 0], [1, 0, 1], [1, 1, 1], [0, 1, 0]], dtype=np.float32)
    mesh = triangle_mesh(stage, "/Root/X/m", pts, [0, 1, 2, 0, 2, 3])
    n_local = np.cross(pts[1] - pts[0], pts[2] - pts[0]).astype(np.float64)
    n_local /= np.linalg.norm(n_local)
    mesh.CreateNormalsAttr(Vt.Vec3fArray.FromNumpy(np.tile(n_local, (4, 1)).astype(np.float32)))
    mesh.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
    stage.Save()
    asset = load_asset(tmp_path / "a.usda")
    # independent truth: the world normal is perpendicular to the world triangle, i.e. the
    # cross product of transformed edges (float32 authored normal: ~1e-7 relative)
    geo = face_normals(asset.points, asset.faces)
    for c in range(3):
        np.testing.assert_allclose(asset.corner_normals[:, c], geo, atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(asset.corner_normals, axis=2), 1.0, atol=1e-12)


def test_primvars_normals_win_over_normals_attribute(tmp_path):
    stage = new_stage(tmp_path / "a.usda")
    mesh = grid_mesh(stage, "/Root/m", 1, 1)
    mesh.CreateNormalsAttr([(1, 0, 0)] * 4)
    pv = UsdGeom.PrimvarsAPI(mesh).CreatePrimvar("normals", Sdf.ValueTypeNames.Normal3fArray,
                                                 UsdGeom.Tokens.uniform)
    pv.Set([(0, 1, 0)])
    pv.SetIndices(Vt.IntArray([0]))
    stage.Save()
    asset = load_asset(tmp_path / "a.usda")
    np.testing.assert_allclose(asset.corner_normals, np.tile([0, 1.0, 0], (2, 3, 1)))


def test_computed_normals_area_weighted_brute_force(tmp_path):
    rng = np.random.default_rng(3)
    # an irregular octahedron: triangles of very different areas
    pts = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]],
                   dtype=np.float64) * rng.uniform(0.5, 2.0, size=(6, 1))
    tris = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4],
                     [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]])
    stage = new_stage(tmp_path / "a.usda")
    triangle_mesh(stage, "/Root/m", pts, tris)
    stage.Save()
    asset = load_asset(tmp_path / "a.usda")
    p = asset.points
    expected = np.zeros((8, 3, 3))
    for f, tri in enumerate(asset.faces):  # brute force: loop over faces around each vertex
        for c, v in enumerate(tri):
            acc = np.zeros(3)
            for other in asset.faces:
                if v in other:
                    acc += np.cross(p[other[1]] - p[other[0]], p[other[2]] - p[other[0]])
            expected[f, c] = acc / np.linalg.norm(acc)
    np.testing.assert_allclose(asset.corner_normals, expected, atol=1e-12)
    # and the result points outward (dot with the vertex position > 0)
    assert (np.einsum("fcj,fcj->fc", asset.corner_normals, p[asset.faces]) > 0).all()


def test_mirroring_transform_keeps_front_faces(tmp_path):
    stage = new_stage(tmp_path / "a.usda")
    xf = UsdGeom.Xform.Define(stage, "/Root/X")
    xf.AddScaleOp().Set(Gf.Vec3f(-1, 1, 1))
    mesh = grid_mesh(stage, "/Root/X/m", 1, 1)
    mesh.CreateNormalsAttr([(0, 0, 1)] * 4)
    mesh.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
    stage.Save()
    asset = load_asset(tmp_path / "a.usda")
    # the mirrored authored normal is still +z; the winding was flipped to agree with it
    np.testing.assert_allclose(asset.corner_normals[:, 0], np.tile([0, 0, 1.0], (2, 1)))
    np.testing.assert_allclose(face_normals(asset.points, asset.faces), np.tile([0, 0, 1.0], (2, 1)), atol=1e-12)


# ------------------------------------------------------------------------------------------
# UVs
# ------------------------------------------------------------------------------------------


def _uv_fn(xy: np.ndarray) -> np.ndarray:
    return np.stack([0.1 * xy[..., 0] + 0.05, 0.2 * xy[..., 1] - 0.3], axis=-1)


@pytest.mark.parametrize("interp", ["constant", "uniform", "vertex", "varying", "faceVarying",
                                    "faceVarying-indexed", "vertex-indexed"])
def test_uv_interpolations_expand_to_corners(tmp_path, interp):
    stage = new_stage(tmp_path / "a.usda")
    mesh = grid_mesh(stage, "/Root/m", 2, 1)  # 6 points, 2 quads, 8 corners
    pts = np.asarray(mesh.GetPointsAttr().Get(), dtype=np.float64)
    fvi = np.asarray(mesh.GetFaceVertexIndicesAttr().Get())
    base = interp.split("-")[0]
    if base == "constant":
        values = np.array([[0.25, 0.75]])
    elif base == "uniform":
        values = np.array([[0.0, 1.0], [1.0, 0.0]])
    elif base in ("vertex", "varying"):
        values = _uv_fn(pts[:, :2])
    else:  # per corner, different across faces sharing a vertex
        values = _uv_fn(pts[fvi, :2]) + np.repeat([[0.0, 0.0], [10.0, 10.0]], 4, axis=0)
    pv = UsdGeom.PrimvarsAPI(mesh).CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray, base)
    if interp.endswith("indexed"):
        uniq, inv = np.unique(values.astype(np.float32), axis=0, return_inverse=True)
        pv.Set(Vt.Vec2fArray.FromNumpy(uniq))
        pv.SetIndices(Vt.IntArray([int(i) for i in inv.reshape(-1)]))
    else:
        pv.Set(Vt.Vec2fArray.FromNumpy(values.astype(np.float32)))
    stage.Save()
    asset = load_asset(tmp_path / "a.usda")
    assert asset.corner_uvs.shape == (4, 3, 2) and asset.has_uvs.all()
    poly = np.array([0, 0, 1, 1])  # fan: two triangles per quad, in order
    corner_xy = asset.points[asset.faces][..., :2]  # (4, 3, 2)
    if base == "constant":
        expected = np.broadcast_to([0.25, 0.75], (4, 3, 2))
    elif base == "uniform":
        expected = np.repeat(values[poly][:, None, :], 3, axis=1)
    elif base in ("vertex", "varying"):
        expected = _uv_fn(corner_xy)
    else:
        expected = _uv_fn(corner_xy) + 10.0 * poly[:, None, None]
    np.testing.assert_allclose(asset.corner_uvs, expected, atol=1e-6)  # float32 storage


def test_missing_uvs_are_zero_and_flagged(tmp_path):
    stage = new_stage(tmp_path / "a.usda")
    grid_mesh(stage, "/Root/m", 1, 1)
    stage.Save()
    asset = load_asset(tmp_path / "a.usda")
    assert not asset.has_uvs.any() and not asset.corner_uvs.any()


# ------------------------------------------------------------------------------------------
# materials
# ------------------------------------------------------------------------------------------


def test_geomsubset_bindings_and_default_material(tmp_path):
    stage = new_stage(tmp_path / "a.usda")
    mesh = grid_mesh(stage, "/Root/m", 4, 1)  # 4 quads -> 8 triangles
    plain = grid_mesh(stage, "/Root/plain", 1, 1, z=1.0)
    mat_a = preview_material(stage, "/Root/Looks/A", (1, 0, 0))
    mat_b = preview_material(stage, "/Root/Looks/B", (0, 0, 1))
    bind(mesh, mat_a)
    subset = UsdGeom.Subset.CreateGeomSubset(mesh, "odd", UsdGeom.Tokens.face, Vt.IntArray([1, 3]),
                                             UsdShade.Tokens.materialBind)
    bind(subset, mat_b)
    assert plain
    stage.Save()
    asset = load_asset(tmp_path / "a.usda")
    paths = [m.path for m in asset.materials]
    assert paths == ["/Root/Looks/B", "/Root/Looks/A", ""]  # subsets first, then the mesh
    assert asset.materials[2] is DEFAULT_MATERIAL and asset.materials[2].model == "lambert"
    # fan order: polygon i -> triangles 2i, 2i + 1
    np.testing.assert_array_equal(asset.face_material[asset.face_mesh == 0],
                                  [1, 1, 0, 0, 1, 1, 0, 0])
    np.testing.assert_array_equal(asset.face_material[asset.face_mesh == 1], [2, 2])
    np.testing.assert_allclose(asset.materials[0].params["diffuseColor"], [0, 0, 1])
    assert asset.materials[1].params["roughness"] == pytest.approx(0.25)
    assert asset.materials[1].params["ior"] == pytest.approx(1.5)  # PREVIEW_DEFAULTS


def test_mesh_binding_hidden_by_subsets_is_not_listed(tmp_path):
    stage = new_stage(tmp_path / "a.usda")
    mesh = grid_mesh(stage, "/Root/m", 2, 1)
    bind(mesh, preview_material(stage, "/Root/Looks/Unused"))
    for i, name in enumerate(("L", "R")):
        sub = UsdGeom.Subset.CreateGeomSubset(mesh, name, UsdGeom.Tokens.face, Vt.IntArray([i]),
                                              UsdShade.Tokens.materialBind)
        bind(sub, preview_material(stage, f"/Root/Looks/{name}"))
    stage.Save()
    asset = load_asset(tmp_path / "a.usda")
    assert [m.path for m in asset.materials] == ["/Root/Looks/L", "/Root/Looks/R"]
    np.testing.assert_array_equal(asset.face_material, [0, 0, 1, 1])


def test_uv_texture_network_with_srgb_decode(tmp_path):
    rng = np.random.default_rng(11)
    pixels = rng.integers(0, 256, size=(4, 6, 3), dtype=np.uint8)
    pixels[0, 0] = (0, 10, 255)  # both branches of the sRGB curve
    write_png(tmp_path / "tex.png", pixels)
    stage = new_stage(tmp_path / "a.usda")
    mesh = grid_mesh(stage, "/Root/m", 1, 1)
    UsdGeom.PrimvarsAPI(mesh).CreatePrimvar(
        "uv0", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.vertex).Set(
        [(0, 0), (1, 0), (0, 1), (1, 1)])
    mat = preview_material(stage, "/Root/Looks/M", texture="./tex.png", varname="uv0")
    tex_shader = UsdShade.Shader(stage.GetPrimAtPath("/Root/Looks/M/Texture"))
    tex_shader.CreateInput("wrapS", Sdf.ValueTypeNames.Token).Set("clamp")
    tex_shader.CreateInput("wrapT", Sdf.ValueTypeNames.Token).Set("mirror")
    tex_shader.CreateInput("scale", Sdf.ValueTypeNames.Float4).Set(Gf.Vec4f(2, 3, 4, 5))
    tex_shader.CreateInput("bias", Sdf.ValueTypeNames.Float4).Set(Gf.Vec4f(0.1, 0.2, 0.3, 0.4))
    bind(mesh, mat)
    stage.Save()
    asset = load_asset(tmp_path / "a.usda")  # the reader names uv0: used, nothing to warn
    assert not any("uv0" in w for w in asset.warnings)
    material = asset.materials[0]
    tex = material.textures["diffuseColor"]
    assert tex.pixels.shape == (4, 6, 3) and tex.pixels.dtype == np.float32
    np.testing.assert_allclose(tex.pixels, _srgb_reference(pixels / 255.0), atol=1e-6)
    assert (tex.wrap_s, tex.wrap_t) == ("clamp", "mirror")
    assert tex.scale == (2, 3, 4, 1) and tex.bias == pytest.approx((0.1, 0.2, 0.3, 0.0))
    assert tex.st_primvar == "uv0" and tex.source_color_space == "auto"
    assert tex.path.endswith("tex.png")
    np.testing.assert_allclose(material.params["diffuseColor"], [0.5, 0.5, 0.5])  # constant kept
    assert asset.has_uvs.all()
    np.testing.assert_allclose(asset.corner_uvs, asset.points[asset.faces][..., :2], atol=1e-7)


def test_uv_texture_raw_single_channel_output(tmp_path):
    pixels = np.arange(12, dtype=np.uint8).reshape(2, 2, 3) * 20
    write_png(tmp_path / "rough.png", pixels)
    stage = new_stage(tmp_path / "a.usda")
    mesh = grid_mesh(stage, "/Root/m", 1, 1)
    mat = preview_material(stage, "/Root/Looks/M", texture="rough.png", color_space="raw",
                           output="g", connect_to="roughness")
    UsdShade.Shader(stage.GetPrimAtPath("/Root/Looks/M/Texture")).CreateInput(
        "scale", Sdf.ValueTypeNames.Float4).Set(Gf.Vec4f(1, 7, 1, 1))
    bind(mesh, mat)
    stage.Save()
    asset = load_asset(tmp_path / "a.usda")
    tex = asset.materials[0].textures["roughness"]
    # raw: no decode; output g: only the green channel, scale reordered to follow it
    np.testing.assert_allclose(tex.pixels[..., 0], pixels[..., 1] / 255.0, atol=1e-7)
    assert tex.pixels.shape == (2, 2, 1) and tex.scale == (7, 1, 1, 1)
    assert tex.wrap_s == "repeat"  # useMetadata with no wrap metadata in a PNG: tiles


def test_srgb_to_linear_matches_formula():
    v = np.linspace(0, 1, 1001, dtype=np.float32)
    np.testing.assert_allclose(srgb_to_linear(v), _srgb_reference(v), rtol=1e-6, atol=1e-8)


def test_texelbake_shader_ids_win_over_preview(tmp_path):
    stage = new_stage(tmp_path / "a.usda")
    meshes = [grid_mesh(stage, f"/Root/m{i}", 1, 1, z=float(i)) for i in range(3)]
    for i, (sid, inputs) in enumerate([
        (SHADER_LAMBERT, {"diffuseColor": (0.2, 0.4, 0.6)}),
        (SHADER_PHONG, {"specularColor": (0.3, 0.3, 0.3), "exponent": 64.0}),
        ("texelbake:unknownThing", {}),
    ]):
        mat = preview_material(stage, f"/Root/Looks/M{i}", (0.9, 0.8, 0.7))
        sh = UsdShade.Shader.Define(stage, f"/Root/Looks/M{i}/Own")
        sh.CreateIdAttr(sid)
        for name, value in inputs.items():
            vt = Sdf.ValueTypeNames.Color3f if isinstance(value, tuple) else Sdf.ValueTypeNames.Float
            sh.CreateInput(name, vt).Set(value)
        mat.CreateSurfaceOutput("texelbake").ConnectToSource(sh.ConnectableAPI(), "surface")
        bind(meshes[i], mat)
    stage.Save()
    with pytest.warns(AssetWarning, match="/Root/Looks/M2"):
        asset = load_asset(tmp_path / "a.usda")
    lam, pho, fallback = asset.materials
    assert lam.model == "lambert"
    np.testing.assert_allclose(lam.params["diffuseColor"], [0.2, 0.4, 0.6], atol=1e-7)
    assert pho.model == "phong" and pho.params["exponent"] == 64.0
    np.testing.assert_allclose(pho.params["specularColor"], [0.3] * 3, atol=1e-7)
    np.testing.assert_allclose(pho.params["diffuseColor"], [0.18] * 3)  # documented default
    assert fallback.model == "preview"  # unknown texelbake id -> the universal output
    np.testing.assert_allclose(fallback.params["diffuseColor"], [0.9, 0.8, 0.7], atol=1e-7)


def test_measured_brdf_merl_layout_and_scale(tmp_path):
    dims = (90, 90, 180)
    c, i, j, k = np.meshgrid(np.arange(3), np.arange(90), np.arange(90), np.arange(180),
                             indexing="ij", sparse=True)
    data = (c * 1e6 + i * 1e4 + j * 1e2 + k).astype(np.float64)  # exact in float64
    with open(tmp_path / "gold.binary", "wb") as fh:
        fh.write(np.array(dims, dtype="<i4").tobytes())
        fh.write(np.ascontiguousarray(data, dtype="<f8").tobytes())
    stage = new_stage(tmp_path / "a.usda")
    mesh = grid_mesh(stage, "/Root/m", 1, 1)
    mat = preview_material(stage, "/Root/Looks/Gold")
    sh = UsdShade.Shader.Define(stage, "/Root/Looks/Gold/Merl")
    sh.CreateIdAttr(SHADER_MEASURED)
    sh.CreateInput("file", Sdf.ValueTypeNames.Asset).Set("./gold.binary")
    sh.CreateInput("scale", Sdf.ValueTypeNames.Float).Set(2.0)
    mat.CreateSurfaceOutput("texelbake").ConnectToSource(sh.ConnectableAPI(), "surface")
    bind(mesh, mat)
    stage.Save()
    asset = load_asset(tmp_path / "a.usda")
    m = asset.materials[0]
    assert m.model == "merl" and m.params["scale"] == 2.0
    table = m.params["table"]
    assert table.shape == (3, 90, 90, 180) and table.dtype == np.float64
    scale = np.array([1 / 1500, 1.15 / 1500, 1.66 / 1500])
    rng = np.random.default_rng(5)
    for _ in range(20):
        cc, ii, jj, kk = (int(rng.integers(0, n)) for n in (3, 90, 90, 180))
        want = (cc * 1e6 + ii * 1e4 + jj * 1e2 + kk) * scale[cc]
        assert table[cc, ii, jj, kk] == pytest.approx(want, rel=1e-15)
    assert m.params["file"].endswith("gold.binary")


def test_texture_through_node_graph(tmp_path):
    write_png(tmp_path / "t.png", np.full((2, 2, 3), 200, np.uint8))
    stage = new_stage(tmp_path / "a.usda")
    mesh = grid_mesh(stage, "/Root/m", 1, 1)
    mat = preview_material(stage, "/Root/Looks/M")
    graph = UsdShade.NodeGraph.Define(stage, "/Root/Looks/M/Graph")
    tex = UsdShade.Shader.Define(stage, "/Root/Looks/M/Graph/Tex")
    tex.CreateIdAttr("UsdUVTexture")
    tex.CreateInput("file", Sdf.ValueTypeNames.Asset).Set("./t.png")
    tex.CreateOutput("rgb", Sdf.ValueTypeNames.Float3)
    graph.CreateOutput("color", Sdf.ValueTypeNames.Color3f).ConnectToSource(
        tex.ConnectableAPI(), "rgb")
    surf = UsdShade.Shader(stage.GetPrimAtPath("/Root/Looks/M/Surface"))
    surf.GetInput("diffuseColor").ConnectToSource(graph.ConnectableAPI(), "color")
    bind(mesh, mat)
    stage.Save()
    asset = load_asset(tmp_path / "a.usda")
    px = asset.materials[0].textures["diffuseColor"].pixels
    np.testing.assert_allclose(px, _srgb_reference(np.full((2, 2, 3), 200 / 255)), atol=1e-6)


# ------------------------------------------------------------------------------------------
# lights, cameras
# ------------------------------------------------------------------------------------------


def test_lights_directions_and_radiance(tmp_path):
    stage = new_stage(tmp_path / "a.usda")
    grid_mesh(stage, "/Root/m", 1, 1)
    sun = UsdLux.DistantLight.Define(stage, "/Root/Sun")
    sun.AddRotateXOp().Set(-90.0)  # local -Z (its shining direction) becomes world -Y
    sun.CreateIntensityAttr(3.0)
    sun.CreateExposureAttr(2.0)
    sun.CreateColorAttr(Gf.Vec3f(1, 0.5, 0.25))
    sun.CreateNormalizeAttr(True)  # UsdLux: the intensity is the irradiance
    grp = UsdGeom.Xform.Define(stage, "/Root/G")
    grp.AddScaleOp().Set(Gf.Vec3f(2, 2, 2))
    bulb = UsdLux.SphereLight.Define(stage, "/Root/G/Bulb")
    bulb.AddTranslateOp().Set(Gf.Vec3d(1, 2, 3))
    bulb.CreateRadiusAttr(0.5)
    bulb.CreateIntensityAttr(10.0)
    bulb.CreateExposureAttr(1.0)
    point = UsdLux.SphereLight.Define(stage, "/Root/Point")
    point.CreateRadiusAttr(0.5)
    point.CreateIntensityAttr(4.0)
    point.CreateTreatAsPointAttr(True)
    stage.Save()
    asset = load_asset(tmp_path / "a.usda")
    by_path = {light.path: light for light in asset.lights}
    s = by_path["/Root/Sun"]
    assert s.kind == "distant"
    np.testing.assert_allclose(s.direction, [0, 1, 0], atol=1e-12)  # toward the light
    np.testing.assert_allclose(s.radiance_scale, np.array([1, 0.5, 0.25]) * 3 * 4)
    b = by_path["/Root/G/Bulb"]
    assert b.kind == "sphere"
    np.testing.assert_allclose(b.position, [2, 4, 6], atol=1e-12)  # translate, then parent scale
    assert b.radius == pytest.approx(1.0)  # 0.5 scaled by 2
    np.testing.assert_allclose(b.radiance_scale, np.full(3, 10 * 2 * math.pi * 1.0 ** 2))
    p = by_path["/Root/Point"]
    assert p.radius == 0.0
    np.testing.assert_allclose(p.radiance_scale, np.full(3, 4.0))


def test_camera_world_transform(tmp_path):
    stage = new_stage(tmp_path / "a.usda")
    grid_mesh(stage, "/Root/m", 1, 1)
    cam = UsdGeom.Camera.Define(stage, "/Root/Cam")
    cam.AddTranslateOp().Set(Gf.Vec3d(0, 1, 5))
    cam.AddRotateYOp().Set(90.0)
    cam.CreateFocalLengthAttr(35.0)
    cam.CreateClippingRangeAttr(Gf.Vec2f(0.1, 100))
    stage.Save()
    asset = load_asset(tmp_path / "a.usda")
    (c,) = asset.cameras
    assert c.path == "/Root/Cam" and c.focal_length == pytest.approx(35.0)
    np.testing.assert_allclose(c.clipping, [0.1, 100], rtol=1e-6)
    expected = _affine_row(_rot_row("y", 90), [0, 1, 5]).T  # column-vector convention
    np.testing.assert_allclose(c.world_from_camera, expected, atol=1e-12)
    view_dir = c.world_from_camera[:3, :3] @ np.array([0, 0, -1.0])
    np.testing.assert_allclose(view_dir, [-1, 0, 0], atol=1e-12)  # -Z turned by +90 about Y


# ------------------------------------------------------------------------------------------
# time samples
# ------------------------------------------------------------------------------------------


def test_time_sampled_points_and_transforms(tmp_path):
    stage = new_stage(tmp_path / "a.usda")
    xf = UsdGeom.Xform.Define(stage, "/Root/X")
    op = xf.AddTranslateOp()
    op.Set(Gf.Vec3d(0, 0, 0), 1.5)
    op.Set(Gf.Vec3d(3, 0, 0), 3.0)
    mesh = grid_mesh(stage, "/Root/X/m", 1, 1)
    base = np.asarray(mesh.GetPointsAttr().Get(), dtype=np.float64)
    attr = mesh.GetPointsAttr()
    attr.Clear()
    attr.Set(Vt.Vec3fArray.FromNumpy(base.astype(np.float32)), 1.0)
    attr.Set(Vt.Vec3fArray.FromNumpy((base + [0, 0, 2]).astype(np.float32)), 2.0)
    grid_mesh(stage, "/Root/static", 1, 1, z=-1.0)
    stage.Save()
    asset = load_asset(tmp_path / "a.usda")
    np.testing.assert_array_equal(asset.time_codes, [1.0, 1.5, 2.0, 3.0])
    assert asset.has_deformation and asset.points_over_time.shape == (4, 8, 3)

    # USD holds values outside the sampled range and interpolates linearly inside it
    def z_lift(t):
        return 2.0 * np.clip(t - 1.0, 0.0, 1.0)

    def shift(t):
        return 3.0 * np.clip((t - 1.5) / 1.5, 0.0, 1.0)

    for ti, t in enumerate(asset.time_codes):
        want = base + [shift(t), 0, z_lift(t)]
        np.testing.assert_allclose(asset.points_over_time[ti, :4], want, atol=1e-6)
        np.testing.assert_allclose(asset.points_over_time[ti, 4:], asset.points[4:])
    np.testing.assert_allclose(asset.points, asset.points_over_time[0])  # earliest by default
    later = load_asset(tmp_path / "a.usda", time_code=2.0)
    np.testing.assert_allclose(later.points, asset.points_over_time[2])


def test_static_asset_has_no_deformation(tmp_path):
    stage = new_stage(tmp_path / "a.usda")
    grid_mesh(stage, "/Root/m", 1, 1)
    stage.Save()
    asset = load_asset(tmp_path / "a.usda")
    assert not asset.has_deformation
    assert asset.time_codes.shape == (0,) and asset.points_over_time.shape == (0, 4, 3)


# ------------------------------------------------------------------------------------------
# formats, bundle, describe
# ------------------------------------------------------------------------------------------


def _textured_scene(tmp_path):
    rng = np.random.default_rng(2)
    write_png(tmp_path / "tex.png", rng.integers(0, 256, size=(3, 5, 3), dtype=np.uint8))
    stage = new_stage(tmp_path / "a.usda")
    mesh = grid_mesh(stage, "/Root/m", 3, 2)
    UsdGeom.PrimvarsAPI(mesh).CreatePrimvar(
        "st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.vertex).Set(
        Vt.Vec2fArray.FromNumpy(rng.uniform(size=(12, 2)).astype(np.float32)))
    bind(mesh, preview_material(stage, "/Root/Looks/M", texture="./tex.png"))
    UsdLux.DistantLight.Define(stage, "/Root/Sun")
    stage.Save()
    return tmp_path / "a.usda"


def _assert_same_asset(a: AssetModel, b: AssetModel) -> None:
    for name in ("points", "faces", "corner_normals", "corner_uvs", "has_uvs", "face_material",
                 "face_mesh"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    assert a.mesh_paths == b.mesh_paths
    assert [m.path for m in a.materials] == [m.path for m in b.materials]
    np.testing.assert_array_equal(a.materials[0].textures["diffuseColor"].pixels,
                                  b.materials[0].textures["diffuseColor"].pixels)


def test_usdc_round_trip(tmp_path):
    usda = _textured_scene(tmp_path)
    # export the layer (Stage.Export would flatten and make asset paths absolute)
    assert Sdf.Layer.FindOrOpen(str(usda)).Export(str(tmp_path / "a.usdc"))
    _assert_same_asset(load_asset(usda), load_asset(tmp_path / "a.usdc"))


def test_usdz_round_trip(tmp_path):
    usda = _textured_scene(tmp_path)
    usdz = tmp_path / "pkg" / "a.usdz"
    usdz.parent.mkdir()
    assert UsdUtils.CreateNewUsdzPackage(Sdf.AssetPath(str(usda)), str(usdz))
    assert check_asset_paths(usdz) == [str(usdz.resolve())]
    from_zip = load_asset(usdz)
    _assert_same_asset(load_asset(usda), from_zip)
    assert "a.usdz[" in from_zip.materials[0].textures["diffuseColor"].path


def test_check_asset_paths_lists_the_bundle(tmp_path):
    (tmp_path / "sub").mkdir()
    write_png(tmp_path / "sub" / "t.png", np.zeros((1, 1, 3), np.uint8))
    part = new_stage(tmp_path / "sub" / "part.usda")
    m = grid_mesh(part, "/Root/m", 1, 1)
    bind(m, preview_material(part, "/Root/Looks/M", texture="./t.png"))  # relative to part
    part.Save()
    stage = new_stage(tmp_path / "a.usda")
    stage.GetPrimAtPath("/Root").GetReferences().AddReference("./sub/part.usda")
    stage.Save()
    files = check_asset_paths(tmp_path / "a.usda")
    assert files == sorted(str(p.resolve()) for p in (
        tmp_path / "a.usda", tmp_path / "sub" / "part.usda", tmp_path / "sub" / "t.png"))
    asset = load_asset(tmp_path / "a.usda")
    assert asset.materials[0].textures["diffuseColor"].path.endswith("t.png")


def test_describe_mentions_what_was_found(tmp_path):
    usda = _textured_scene(tmp_path)
    asset = load_asset(usda)
    text = describe(asset)
    for needle in ("/Root/m: 12 triangles", "/Root/Looks/M: preview", "tex.png", "textures: 1",
                   "lights: 1", "/Root/Sun", "cameras: 0", "bbox diagonal", "deformation: no",
                   "dropped faces: 0", "meshes: 1"):
        assert needle in text, needle


def test_loads_are_deterministic(tmp_path):
    usda = _textured_scene(tmp_path)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a clean asset raises no warning
        a, b = load_asset(usda), load_asset(usda)
    _assert_same_asset(a, b)
    assert describe(a).replace(str(usda), "") == describe(b).replace(str(usda), "")


def test_asset_model_is_immutable(tmp_path):
    asset = load_asset(_textured_scene(tmp_path))
    with pytest.raises(ValueError):
        asset.points[0, 0] = 1.0
    with pytest.raises(TypeError):
        asset.materials[0].params["x"] = 1  # type: ignore[index]
    with pytest.raises(ValueError):
        asset.materials[0].params["diffuseColor"][0] = 1.0
    with pytest.raises(ValueError):
        asset.materials[0].textures["diffuseColor"].pixels[0, 0, 0] = 1.0
    with pytest.raises(ValueError):
        DEFAULT_MATERIAL.params["diffuseColor"][0] = 1.0


# ------------------------------------------------------------------------------------------
# UsdSkel skinning, interface inputs, normalize, skipped prims
# ------------------------------------------------------------------------------------------


def _skinned_stage(path):
    from pxr import UsdSkel

    stage = new_stage(path)
    root = UsdSkel.Root.Define(stage, "/Root/Char")
    root.AddTranslateOp().Set(Gf.Vec3d(10, 0, 0))
    skel = UsdSkel.Skeleton.Define(stage, "/Root/Char/Skel")
    skel.CreateJointsAttr(["a", "a/b"])
    joint_b = Gf.Matrix4d().SetTranslate(Gf.Vec3d(1, 0, 0))
    skel.CreateBindTransformsAttr(Vt.Matrix4dArray([Gf.Matrix4d(1), joint_b]))
    skel.CreateRestTransformsAttr(Vt.Matrix4dArray([Gf.Matrix4d(1), joint_b]))
    anim = UsdSkel.Animation.Define(stage, "/Root/Char/Skel/Anim")
    anim.CreateJointsAttr(["a", "a/b"])
    anim.CreateTranslationsAttr(Vt.Vec3fArray([(0, 0, 0), (1, 0, 0)]))
    anim.CreateScalesAttr(Vt.Vec3hArray([(1, 1, 1), (1, 1, 1)]))
    rot = anim.CreateRotationsAttr()
    rot.Set(Vt.QuatfArray([Gf.Quatf(1), Gf.Quatf(1)]), 0.0)
    quarter = Gf.Quatf(Gf.Rotation(Gf.Vec3d(0, 0, 1), 90).GetQuat())
    rot.Set(Vt.QuatfArray([Gf.Quatf(1), quarter]), 1.0)
    UsdSkel.BindingAPI.Apply(skel.GetPrim()).CreateAnimationSourceRel().SetTargets(
        [anim.GetPath()])
    rest = np.array([(0, 0, 0), (1, 0, 0), (2, 0, 0), (2, 1, 0), (0, 1, 0)], dtype=np.float32)
    mesh = triangle_mesh(stage, "/Root/Char/Body", rest, [0, 1, 3, 1, 2, 3, 0, 3, 4])
    binding = UsdSkel.BindingAPI.Apply(mesh.GetPrim())
    binding.CreateSkeletonRel().SetTargets([skel.GetPath()])
    joints = np.array([[0, 1], [0, 1], [0, 1], [0, 1], [0, 1]])
    weights = np.array([[1, 0], [1, 0], [0.5, 0.5], [0, 1], [1, 0]], dtype=np.float32)
    binding.CreateJointIndicesPrimvar(False, 2).Set(Vt.IntArray(joints.ravel().tolist()))
    binding.CreateJointWeightsPrimvar(False, 2).Set(Vt.FloatArray(weights.ravel().tolist()))
    binding.CreateGeomBindTransformAttr(Gf.Matrix4d(1))
    stage.Save()
    return rest.astype(np.float64), weights.astype(np.float64)


def _lbs_reference(rest, weights, degrees):
    """Linear blend skinning written out: joint b at (1, 0, 0) turns by `degrees` about z;
    skinning matrix_j = inv(bind_j) @ skel_j (row vectors); the SkelRoot adds (10, 0, 0)."""
    bind_b = _affine_row(np.eye(3), [1, 0, 0])
    skel_b = _affine_row(_rot_row("z", degrees), [1, 0, 0])
    skin = [np.eye(4), np.linalg.inv(bind_b) @ skel_b]
    hom = np.c_[rest, np.ones(len(rest))]
    out = sum(weights[:, [j]] * (hom @ skin[j]) for j in range(2))
    return out[:, :3] + [10, 0, 0]


def test_usdskel_skinning_matches_linear_blend_reference(tmp_path):
    rest, weights = _skinned_stage(tmp_path / "a.usda")
    asset = load_asset(tmp_path / "a.usda")
    np.testing.assert_array_equal(asset.time_codes, [0.0, 1.0])
    assert asset.has_deformation
    # float32 skinning inside UsdSkel: ~1e-7 relative on unit-sized coordinates
    np.testing.assert_allclose(asset.points_over_time[0], _lbs_reference(rest, weights, 0),
                               atol=1e-5)
    np.testing.assert_allclose(asset.points_over_time[1], _lbs_reference(rest, weights, 90),
                               atol=1e-5)
    # between samples USD slerps the joint rotation: 45 degrees at t = 0.5
    half = load_asset(tmp_path / "a.usda", time_code=0.5)
    np.testing.assert_allclose(half.points, _lbs_reference(rest, weights, 45), atol=1e-5)
    # computed normals follow the skinned surface
    np.testing.assert_allclose(np.einsum("fcj,fj->fc", half.corner_normals,
                                         face_normals(half.points, half.faces))[0], 1.0, atol=1e-9)


def test_material_interface_input_drives_shader(tmp_path):
    stage = new_stage(tmp_path / "a.usda")
    mesh = grid_mesh(stage, "/Root/m", 1, 1)
    mat = preview_material(stage, "/Root/Looks/M", (0.5, 0.5, 0.5))
    tint = mat.CreateInput("tint", Sdf.ValueTypeNames.Color3f)
    tint.Set((0.9, 0.1, 0.2))
    UsdShade.Shader(stage.GetPrimAtPath("/Root/Looks/M/Surface")).GetInput(
        "diffuseColor").ConnectToSource(tint)
    bind(mesh, mat)
    stage.Save()
    asset = load_asset(tmp_path / "a.usda")
    np.testing.assert_allclose(asset.materials[0].params["diffuseColor"], [0.9, 0.1, 0.2],
                               atol=1e-7)


def test_sphere_light_normalize(tmp_path):
    stage = new_stage(tmp_path / "a.usda")
    grid_mesh(stage, "/Root/m", 1, 1)
    for name, radius in (("Small", 0.1), ("Big", 2.0)):
        light = UsdLux.SphereLight.Define(stage, f"/Root/{name}")
        light.CreateRadiusAttr(radius)
        light.CreateIntensityAttr(8.0)
        light.CreateNormalizeAttr(True)
    stage.Save()
    asset = load_asset(tmp_path / "a.usda")
    # normalize: radiance / (4 pi r^2), so intensity pi r^2 L = 8 / 4 whatever the radius
    for light in asset.lights:
        np.testing.assert_allclose(light.radiance_scale, np.full(3, 2.0))


def test_point_instancers_are_flattened_and_other_gprims_skipped_with_a_warning(tmp_path):
    stage = new_stage(tmp_path / "a.usda")
    grid_mesh(stage, "/Root/m", 1, 1)
    inst = UsdGeom.PointInstancer.Define(stage, "/Root/Scatter")
    grid_mesh(stage, "/Root/Scatter/Prototypes/leaf", 1, 1)
    inst.CreatePrototypesRel().SetTargets(["/Root/Scatter/Prototypes/leaf"])
    inst.CreateProtoIndicesAttr([0, 0])
    inst.CreatePositionsAttr([(0, 0, 0), (1, 0, 0)])
    UsdGeom.Sphere.Define(stage, "/Root/ball")
    stage.Save()
    with pytest.warns(AssetWarning) as record:
        asset = load_asset(tmp_path / "a.usda")
    # the instancer's two leaves are baked (tests/scene/test_instancing.py checks placement)
    assert asset.mesh_paths == ("/Root/m", "/Root/Scatter[leaf]")
    assert int(np.sum(asset.face_mesh == 1)) == 2 * int(np.sum(asset.face_mesh == 0))
    texts = " ".join(str(r.message) for r in record)
    assert "/Root/ball" in texts


def test_computed_normals_where_the_vertex_sum_cancels(tmp_path):
    # a two-sided triangle: both windings share all three vertices, so every vertex sum is 0;
    # each corner then takes its own triangle's normal
    stage = new_stage(tmp_path / "a.usda")
    triangle_mesh(stage, "/Root/m", [(0, 0, 0), (1, 0, 0), (0, 1, 0)], [0, 1, 2, 0, 2, 1])
    stage.Save()
    asset = load_asset(tmp_path / "a.usda")
    np.testing.assert_allclose(asset.corner_normals[0], np.tile([0, 0, 1.0], (3, 1)))
    np.testing.assert_allclose(asset.corner_normals[1], np.tile([0, 0, -1.0], (3, 1)))


@pytest.mark.parametrize("interp", ["constant", "uniform", "vertex", "faceVarying"])
def test_authored_normal_interpolations(tmp_path, interp):
    stage = new_stage(tmp_path / "a.usda")
    mesh = grid_mesh(stage, "/Root/m", 2, 1)  # 6 points, 2 quads, 8 corners
    count = {"constant": 1, "uniform": 2, "vertex": 6, "faceVarying": 8}[interp]
    rng = np.random.default_rng(count)
    values = rng.normal(size=(count, 3)) + [0, 0, 3]
    values /= np.linalg.norm(values, axis=1, keepdims=True)
    mesh.CreateNormalsAttr(Vt.Vec3fArray.FromNumpy(values.astype(np.float32)))
    mesh.SetNormalsInterpolation(interp)
    stage.Save()
    asset = load_asset(tmp_path / "a.usda")
    fvi = np.asarray(mesh.GetFaceVertexIndicesAttr().Get())
    # triangles of the fan: polygon p gives (s, s+1, s+2), (s, s+2, s+3), s = 4p
    corners = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]])
    poly = np.array([0, 0, 1, 1])
    if interp == "constant":
        expected = np.broadcast_to(values[0], (4, 3, 3))
    elif interp == "uniform":
        expected = np.repeat(values[poly][:, None], 3, axis=1)
    elif interp == "vertex":
        expected = values[fvi[corners]]
    else:
        expected = values[corners]
    np.testing.assert_array_equal(asset.faces, fvi[corners])
    np.testing.assert_allclose(asset.corner_normals, expected, atol=1e-6)  # float32 storage
