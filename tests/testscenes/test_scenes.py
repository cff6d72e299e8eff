"""The USD test scenes: written, validated by pxr, counted independently, deterministic.

Counts here are taken from the written files with pxr alone (faceVertexCounts, prim types,
resolved bindings, UsdUVTexture file inputs), never from texelbake.testscenes' own arrays; the
geometry checks compare against closed forms (the ridged cylinder's volume, the bolt's
lattice) or a second computation (Newell face normals against the authored normals).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import OpenImageIO as oiio
import pytest
from pxr import Gf, Sdf, Sdr, Usd, UsdGeom, UsdLux, UsdShade, UsdValidation

from texelbake import testscenes as scenes
from texelbake.errors import SettingsError
from texelbake.model import SHADER_CELLULAR, SHADER_PREVIEW
from texelbake.testscenes import SCENE_NAMES, expected_counts, write_scene
from texelbake.usd.shaderdefs import SHADER_INPUTS, register_shader_definitions
from texelbake.usd.shaderdefs import shader_id as read_shader_id

CASES = [(n, s) for s in ("small", "full") for n in SCENE_NAMES]

# the texelbake:cellular inputs of texelbake.model's table, with their types
CELLULAR_TABLE = {
    "cellScale": "float", "seed": "int", "borderWidth": "float", "borderColor": "color3f",
    "borderRoughness": "float", "cellColorA": "color3f", "cellColorB": "color3f",
}


@pytest.fixture(scope="module")
def written(tmp_path_factory) -> dict[tuple[str, str], Path]:
    """Every scene at both sizes, written once into one folder (as `texelbake scenes` would)."""
    out = tmp_path_factory.mktemp("scenes")
    return {(n, s): write_scene(n, out / f"{n}_{s}.usda", s) for n, s in CASES}


def _validate(stage: Usd.Stage) -> list:
    ctx = UsdValidation.ValidationContext(
        list(UsdValidation.ValidationRegistry().GetAllValidatorMetadata()), True)
    return list(ctx.Validate(stage))


def _meshes(stage: Usd.Stage) -> list[UsdGeom.Mesh]:
    return [UsdGeom.Mesh(p) for p in stage.Traverse() if p.IsA(UsdGeom.Mesh)]


def _mesh_arrays(mesh: UsdGeom.Mesh) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    pts = np.asarray(mesh.GetPointsAttr().Get(), dtype=np.float64)
    counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get(), dtype=np.int64)
    idx = np.asarray(mesh.GetFaceVertexIndicesAttr().Get(), dtype=np.int64)
    return pts, counts, idx


def _fan(counts: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """(t, 3) triangles of a fan triangulation, written independently of texelbake.testscenes."""
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    face = np.repeat(np.arange(len(counts)), counts - 2)
    k = np.arange(len(face)) - np.repeat(np.cumsum(counts - 2) - (counts - 2), counts - 2)
    s = starts[face]
    return np.stack([idx[s], idx[s + k + 1], idx[s + k + 2]], axis=1)


def _newell(pts: np.ndarray, counts: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """(f, 3) unit face normals by Newell's method (sum over all edges of each polygon)."""
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    face = np.repeat(np.arange(len(counts)), counts)
    nxt = np.arange(len(idx)) + 1
    last = starts + counts - 1
    nxt[last] = starts
    a, b = pts[idx], pts[idx[nxt]]
    terms = np.stack([(a[:, 1] - b[:, 1]) * (a[:, 2] + b[:, 2]),
                      (a[:, 2] - b[:, 2]) * (a[:, 0] + b[:, 0]),
                      (a[:, 0] - b[:, 0]) * (a[:, 1] + b[:, 1])], axis=1)
    n = np.zeros((len(counts), 3))
    np.add.at(n, face, terms)
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def _signed_volume(pts: np.ndarray, tris: np.ndarray) -> float:
    a, b, c = pts[tris[:, 0]], pts[tris[:, 1]], pts[tris[:, 2]]
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


def _count(stage: Usd.Stage) -> dict[str, int]:
    meshes = _meshes(stage)
    faces = sum(int((np.asarray(m.GetFaceVertexCountsAttr().Get()) - 2).sum()) for m in meshes)
    bound = set()
    for m in meshes:
        targets = [m.GetPrim()] + [s.GetPrim() for s in UsdGeom.Subset.GetAllGeomSubsets(m)]
        for prim in targets:
            mat, _ = UsdShade.MaterialBindingAPI(prim).ComputeBoundMaterial()
            if mat:
                bound.add(str(mat.GetPath()))
    lights = [p for p in stage.Traverse() if p.HasAPI(UsdLux.LightAPI)]
    cameras = [p for p in stage.Traverse() if p.IsA(UsdGeom.Camera)]
    return {"meshes": len(meshes), "faces": faces, "materials": len(bound),
            "lights": len(lights), "cameras": len(cameras), "textures": len(_texture_files(stage))}


def _texture_files(stage: Usd.Stage) -> set[Path]:
    files = set()
    for prim in stage.Traverse():
        shader = UsdShade.Shader(prim)
        if shader and shader.GetShaderId() == "UsdUVTexture":
            files.add(Path(shader.GetInput("file").Get().resolvedPath))
    return files


@pytest.mark.parametrize(("name", "size"), CASES)
def test_scene_validates_and_has_expected_counts(written, name, size):
    path = written[(name, size)]
    stage = Usd.Stage.Open(str(path))
    assert stage, f"pxr cannot open {path}"
    results = _validate(stage)
    errors = [r for r in results if r.GetType() == UsdValidation.ValidationErrorType.Error]
    assert not errors, "\n".join(f"{r.GetName()}: {r.GetMessage()}" for r in errors)
    assert _count(stage) == expected_counts(name, size)
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.y
    assert stage.GetRootLayer().HasDefaultPrim() and stage.GetDefaultPrim().IsA(UsdGeom.Xform)
    assert Usd.ModelAPI(stage.GetDefaultPrim()).GetKind() == "component"
    assert UsdGeom.StageHasAuthoredMetersPerUnit(stage)


def test_cylinder_full_has_the_seeds_face_count():
    # seed 000, Table 3: the cylinder has 3072 faces
    assert expected_counts("cylinder", "full")["faces"] == 3072
    for name in ("wall", "bolt", "cloisonne"):
        assert 10_000 <= expected_counts(name, "full")["faces"] <= 100_000
    for name in SCENE_NAMES:
        assert 300 <= expected_counts(name, "small")["faces"] <= 2_000


@pytest.mark.parametrize(("name", "size"), CASES)
def test_authored_normals_and_st(written, name, size):
    stage = Usd.Stage.Open(str(written[(name, size)]))
    for mesh in _meshes(stage):
        pts, counts, idx = _mesh_arrays(mesh)
        assert mesh.GetSubdivisionSchemeAttr().Get() == UsdGeom.Tokens.none
        normals = np.asarray(mesh.GetNormalsAttr().Get(), dtype=np.float64)
        interp = mesh.GetNormalsInterpolation()
        face_n = np.repeat(_newell(pts, counts, idx), counts, axis=0)  # per corner
        corner_n = normals[idx] if interp == "vertex" else normals
        assert interp in ("vertex", "faceVarying") and len(corner_n) == len(idx)
        np.testing.assert_allclose(np.linalg.norm(corner_n, axis=1), 1.0, atol=1e-6)
        cos = np.einsum("ij,ij->i", corner_n, face_n)
        if interp == "faceVarying":
            # faceted meshes: the authored normal is the face's, up to float32 points
            assert cos.min() > 1.0 - 1e-5, f"{mesh.GetPath()}: min cos {cos.min()}"
        else:
            # smooth normals lean off the face but stay on its side (winding agrees)
            assert cos.min() > 0.3, f"{mesh.GetPath()}: min cos {cos.min()}"
        st = UsdGeom.PrimvarsAPI(mesh).GetPrimvar("st")
        assert st.GetTypeName() == Sdf.ValueTypeNames.TexCoord2fArray
        st_vals = np.asarray(st.Get(), dtype=np.float64)
        n_expected = {"vertex": len(pts), "faceVarying": len(idx)}[st.GetInterpolation()]
        assert st_vals.shape == (n_expected, 2)
        assert np.isfinite(st_vals).all() and st_vals.min() >= 0.0 and st_vals.max() <= 1.5
        extent = np.asarray(mesh.GetExtentAttr().Get())
        np.testing.assert_allclose(extent, [pts.min(0), pts.max(0)], rtol=0, atol=1e-6)


def test_cylinder_is_closed_with_the_closed_form_volume(written):
    stage = Usd.Stage.Open(str(written[("cylinder", "full")]))
    (mesh,) = _meshes(stage)
    pts, counts, idx = _mesh_arrays(mesh)
    p = scenes.SCENE_PARAMS["cylinder"]["full"]
    n, r0 = p["ridges"], scenes.params.CYLINDER["radius"]
    height = scenes.params.CYLINDER["height"]
    h = r0 * (math.pi / n) * math.tan(math.radians(scenes.params.CYLINDER["ridge_slope_deg"]))
    # a star prism: 2n triangles (centre, valley, peak) of area r0 (r0 + h) sin(pi/n) / 2
    truth = height * n * r0 * (r0 + h) * math.sin(math.pi / n)
    # float32 points: relative error ~1e-7 per coordinate, 1e-5 leaves room for the sum
    assert _signed_volume(pts, _fan(counts, idx)) == pytest.approx(truth, rel=1e-5)
    # watertight: every undirected edge is used by exactly two faces, once each way
    tris = _fan(counts, idx)
    e = np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]])
    _, c = np.unique(np.sort(e, axis=1), axis=0, return_counts=True)
    assert set(c.tolist()) == {2}
    assert len(np.unique(e, axis=0)) == len(e)  # no directed edge twice: consistent winding


def test_cylinder_facets_alternate_through_subsets(written):
    stage = Usd.Stage.Open(str(written[("cylinder", "small")]))
    (mesh,) = _meshes(stage)
    pts, counts, idx = _mesh_arrays(mesh)
    valid, why = UsdGeom.Subset.ValidateFamily(mesh, UsdGeom.Tokens.face, "materialBind")
    assert valid, why
    assert UsdGeom.Subset.GetFamilyType(mesh, "materialBind") == UsdGeom.Tokens.partition
    color = np.zeros((len(counts), 3))
    for subset in UsdGeom.Subset.GetAllGeomSubsets(mesh):
        mat, _ = UsdShade.MaterialBindingAPI(subset.GetPrim()).ComputeBoundMaterial()
        src = mat.ComputeSurfaceSource("texelbake")[0]
        color[np.asarray(subset.GetIndicesAttr().Get())] = src.GetInput("diffuseColor").Get()
    # classify side facets by angle alone: facet k spans phi in [k, k+1) * pi / n
    n = scenes.SCENE_PARAMS["cylinder"]["small"]["ridges"]
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    centroid = np.stack([pts[idx[starts + j]] for j in range(3)]).mean(axis=0)
    side = counts == 4
    phi = np.mod(np.arctan2(centroid[side, 2], centroid[side, 0]), 2 * math.pi)
    k = np.floor(phi / (math.pi / n)).astype(int)
    blue = color[side, 2] > color[side, 0]
    assert blue.sum() == side.sum() // 2
    np.testing.assert_array_equal(blue, k % 2 == 0)  # strictly alternating around the axis


def test_bolt_lattice_of_diamond_bumps(written):
    stage = Usd.Stage.Open(str(written[("bolt", "small")]))
    shaft = next(m for m in _meshes(stage) if m.GetPrim().GetName() == "Shaft")
    pts, _, _ = _mesh_arrays(shaft)
    p = scenes.SCENE_PARAMS["bolt"]["small"]
    r = scenes.params.BOLT["radius"]
    bump = scenes.params.BOLT["bump_ratio"] * 2 * math.pi * r / p["around"]
    rad = np.hypot(pts[:, 0], pts[:, 2])
    # one apex per cell, every other lattice point on the shaft, the cap centre on the axis
    assert np.sum(np.isclose(rad, r + bump, atol=1e-6)) == p["around"] * p["along"]
    on_shaft = np.sum(np.isclose(rad, r, atol=1e-6))
    assert on_shaft == 2 * p["around"] * (2 * p["along"] + 1) - p["around"] * p["along"]
    assert np.sum(rad < 1e-9) == 1


def test_cloisonne_material_convention(written):
    stage = Usd.Stage.Open(str(written[("cloisonne", "small")]))
    (mesh,) = _meshes(stage)
    mat, _ = UsdShade.MaterialBindingAPI(mesh.GetPrim()).ComputeBoundMaterial()
    own = mat.ComputeSurfaceSource("texelbake")[0]
    assert read_shader_id(own) == SHADER_CELLULAR
    inputs = {i.GetBaseName(): str(i.GetTypeName()) for i in own.GetInputs()}
    assert inputs == CELLULAR_TABLE
    universal = mat.ComputeSurfaceSource()[0]
    assert universal.GetShaderId() == SHADER_PREVIEW
    assert universal.GetPath() != own.GetPath()
    # closed, outward-facing blob
    pts, counts, idx = _mesh_arrays(mesh)
    assert _signed_volume(pts, _fan(counts, idx)) > 0.9 * 4 / 3 * math.pi * np.prod(
        scenes.params.CLOISONNE_SCALE)


def test_textures_exist_beside_the_layer_and_read(written):
    for (name, size), path in written.items():
        stage = Usd.Stage.Open(str(path))
        for prim in stage.Traverse():
            shader = UsdShade.Shader(prim)
            if shader and shader.GetShaderId() == "UsdUVTexture":
                asset = shader.GetInput("file").Get()
                assert asset.path.startswith("./"), asset.path  # relative, beside the layer
                assert Path(asset.resolvedPath).parent == path.parent
                assert Path(asset.path).name.startswith(f"{name}_{size}_")
        for file in _texture_files(stage):
            inp = oiio.ImageInput.open(str(file))
            assert inp is not None, oiio.geterror()
            spec = inp.spec()
            pixels = inp.read_image("uint8")
            inp.close()
            assert spec.nchannels == 3 and pixels.shape == (spec.height, spec.width, 3)
            assert pixels.std() > 1.0  # an image, not a flat fill
    # the wall's texture has the wall's aspect ratio, so st = (x / W, y / H) is undistorted
    stage = Usd.Stage.Open(str(written[("wall", "full")]))
    (file,) = _texture_files(stage)
    spec = oiio.ImageInput.open(str(file)).spec()
    lo, hi = np.asarray(UsdGeom.Mesh(stage.GetPrimAtPath("/Wall/Geom/Mortar")).GetExtentAttr()
                        .Get())
    assert spec.height == round(spec.width * (hi[1] - lo[1]) / (hi[0] - lo[0]))


@pytest.mark.parametrize("name", SCENE_NAMES)
def test_camera_frames_the_object_and_lights_face_it(written, name):
    stage = Usd.Stage.Open(str(written[(name, "small")]))
    cam_prim = next(p for p in stage.Traverse() if p.IsA(UsdGeom.Camera))
    gf_cam = UsdGeom.Camera(cam_prim).GetCamera(Usd.TimeCode.Default())
    frustum = gf_cam.frustum
    view_proj = frustum.ComputeViewMatrix() * frustum.ComputeProjectionMatrix()
    pts = np.concatenate([_mesh_arrays(m)[0] for m in _meshes(stage)])
    ndc = np.array([view_proj.Transform(Gf.Vec3d(*p)) for p in pts[:: max(1, len(pts) // 500)]])
    assert np.abs(ndc[:, :2]).max() < 1.0  # every point inside the image
    assert np.abs(ndc[:, 2]).max() < 1.0  # and inside the clipping range
    cam_pos = np.asarray(gf_cam.transform.ExtractTranslation())
    centre = 0.5 * (pts.min(0) + pts.max(0))
    for prim in stage.Traverse():
        if prim.IsA(UsdLux.DistantLight):
            xf = np.asarray(UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(0))
            toward = xf[2, :3] / np.linalg.norm(xf[2, :3])  # the light shines down -Z
            assert toward[1] > 0.3  # from above
            assert toward @ (cam_pos - centre) > 0  # from the camera's side
        if prim.IsA(UsdLux.SphereLight):
            pos = np.asarray(UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(0))[3, :3]
            assert np.any(pos < pts.min(0)) or np.any(pos > pts.max(0))  # outside the object


def test_deterministic_bytes(tmp_path):
    for name in SCENE_NAMES:
        a = write_scene(name, tmp_path / "a" / f"{name}.usda", "small")
        b = write_scene(name, tmp_path / "b" / f"{name}.usda", "small")
        assert a.read_bytes() == b.read_bytes()
    files_a = sorted(p.name for p in (tmp_path / "a").iterdir())
    assert files_a == sorted(p.name for p in (tmp_path / "b").iterdir())
    assert not [f for f in files_a if f.startswith(".")]  # no temp files left behind
    for f in files_a:
        assert (tmp_path / "a" / f).read_bytes() == (tmp_path / "b" / f).read_bytes()
    # rewriting in place replaces the files with identical bytes
    before = (tmp_path / "a" / "wall_small_albedo.png").read_bytes()
    write_scene("wall", tmp_path / "a" / "wall.usda", "small")
    assert (tmp_path / "a" / "wall_small_albedo.png").read_bytes() == before


def test_usdc_layer(tmp_path):
    path = write_scene("cylinder", tmp_path / "cyl.usdc", "small")
    stage = Usd.Stage.Open(str(path))
    assert stage.GetRootLayer().GetFileFormat().formatId == "usdc"
    assert _count(stage) == expected_counts("cylinder", "small")


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [({"name": "teapot"}, "name"), ({"size": "huge"}, "size"), ({"suffix": ".obj"}, "path")],
)
def test_bad_settings_name_the_field(tmp_path, kwargs, field):
    name = kwargs.get("name", "wall")
    size = kwargs.get("size", "small")
    with pytest.raises(SettingsError, match=f"field '{field}'") as info:
        write_scene(name, tmp_path / f"x{kwargs.get('suffix', '.usda')}", size)
    assert str(kwargs.get("name", kwargs.get("size", ".obj"))) in str(info.value)
    assert not list(tmp_path.iterdir())  # nothing written
    if field != "path":
        with pytest.raises(SettingsError, match=f"field '{field}'"):
            expected_counts(name, size)


def test_shader_definitions_register_and_type_check():
    register_shader_definitions()
    register_shader_definitions()  # idempotent
    for shader_id, inputs in SHADER_INPUTS.items():
        node = Sdr.Registry().GetShaderNodeByIdentifier(shader_id)
        assert node is not None, shader_id
        assert sorted(node.GetShaderInputNames()) == sorted(i[0] for i in inputs)
    node = Sdr.Registry().GetShaderNodeByIdentifier(SHADER_CELLULAR)
    declared = {n: str(node.GetShaderInput(n).GetTypeAsSdfType().GetSdfType())
                for n in node.GetShaderInputNames()}
    assert declared == CELLULAR_TABLE
    # the validator now checks texelbake shaders' input types: a wrong type is an error
    stage = Usd.Stage.CreateInMemory()
    shader = UsdShade.Shader.Define(stage, "/Looks/Bad")
    shader.CreateIdAttr(SHADER_CELLULAR)
    shader.CreateInput("seed", Sdf.ValueTypeNames.Float).Set(3.0)
    names = {r.GetName() for r in _validate(stage)
             if r.GetType() == UsdValidation.ValidationErrorType.Error}
    assert "MismatchedPropertyType" in names
    assert "MissingShaderIdInRegistry" not in names


def test_shader_definition_defaults_match_the_brdf_module():
    brdf = pytest.importorskip("texelbake.brdf")
    tables = {"texelbake:lambert": brdf.LAMBERT_DEFAULTS, "texelbake:phong": brdf.PHONG_DEFAULTS,
              "texelbake:cellular": brdf.CELLULAR_DEFAULTS}
    for shader_id, defaults in tables.items():
        ours = {n: d for n, _, d in SHADER_INPUTS[shader_id]}
        assert set(ours) == set(defaults)
        for k, v in defaults.items():
            np.testing.assert_allclose(np.asarray(ours[k], float), np.asarray(v, float))
