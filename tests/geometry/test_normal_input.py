"""A material's `normal` input on M_org (`texelbake.geometry.normal_input`): decoded in the
surface's MikkTSpace frames into the dense samples' shading normals and the ground truth's,
each checked against the closed form of a flat quad whose uvs are turned or mirrored (T and B
are then known directions), and a normal map read per sample."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from pxr import Gf, Sdf, UsdGeom, UsdLux, UsdShade, Vt

TILT = np.array([0.5, 0.0, np.sqrt(0.75)])  # 30° toward the tangent


def _quad(path: Path, uv_map: str, normal=None, texture: str | None = None) -> Path:
    """A unit quad in z = 0 facing +z (two triangles) whose st maps u along `uv_map`'s axis
    ("x": u = x, v = y; "y": u = y, v = -x, turned; "-x": u = -x, v = y, mirrored), with a
    UsdPreviewSurface (diffuse, specular workflow, specularColor 0) whose normal is the
    constant `normal` or a texture; a distant light straight down +z."""
    from tests.helpers.usd_stages import new_stage

    stage = new_stage(path)
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    mesh = UsdGeom.Mesh.Define(stage, "/Root/Quad")
    pts = np.array([[-0.5, -0.5, 0], [0.5, -0.5, 0], [0.5, 0.5, 0], [-0.5, 0.5, 0]], np.float32)
    mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(pts))
    mesh.CreateFaceVertexCountsAttr([3, 3])
    mesh.CreateFaceVertexIndicesAttr([0, 1, 2, 0, 2, 3])
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    mesh.CreateExtentAttr([(-0.5, -0.5, 0.0), (0.5, 0.5, 0.0)])
    x, y = pts[:, 0].astype(float), pts[:, 1].astype(float)
    u, v = {"x": (x, y), "y": (y, -x), "-x": (-x, y)}[uv_map]
    st = np.stack([u + 0.5, v + 0.5], axis=1)[[0, 1, 2, 0, 2, 3]].astype(np.float32)
    UsdGeom.PrimvarsAPI(mesh).CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray,
                                            UsdGeom.Tokens.faceVarying).Set(
        Vt.Vec2fArray.FromNumpy(st))
    mat = UsdShade.Material.Define(stage, "/Root/Looks/M")
    surf = UsdShade.Shader.Define(stage, "/Root/Looks/M/Surface")
    surf.CreateIdAttr("UsdPreviewSurface")
    surf.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(0.5, 0.5, 0.5))
    surf.CreateInput("useSpecularWorkflow", Sdf.ValueTypeNames.Int).Set(1)
    surf.CreateInput("specularColor", Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(0.0, 0.0, 0.0))
    if normal is not None:
        surf.CreateInput("normal", Sdf.ValueTypeNames.Normal3f).Set(Gf.Vec3f(*map(float, normal)))
    if texture is not None:
        from tests.helpers.usd_stages import uv_texture

        tex = uv_texture(stage, "/Root/Looks/M", "NormalMap", texture, "rgb",
                         scale=(2, 2, 2, 1), bias=(-1, -1, -1, 0))
        surf.CreateInput("normal", Sdf.ValueTypeNames.Normal3f).ConnectToSource(
            tex.ConnectableAPI(), "rgb")
    mat.CreateSurfaceOutput().ConnectToSource(surf.ConnectableAPI(), "surface")
    UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim()).Bind(mat)
    light = UsdLux.DistantLight.Define(stage, "/Root/Sun")  # shines down its -z: onto +z
    light.CreateIntensityAttr(1.0)
    light.CreateNormalizeAttr(True)
    stage.GetRootLayer().Save()
    return path


def _samples(src: Path):
    from texelbake.asset.load import load_asset
    from texelbake.brdf.evaluate import shading_normal
    from texelbake.geometry.normal_input import mapped_normals
    from texelbake.geometry.sampling import sample_surface

    a = load_asset(src)
    ni = mapped_normals(a, shading_normal)
    return a, ni, sample_surface(a.points, a.faces, 64, 0, corner_normals=a.corner_normals,
                                 corner_uvs=a.corner_uvs, face_material=a.face_material,
                                 normal_input=ni)


@pytest.mark.parametrize(("uv_map", "want"), [
    ("x", TILT),  # T = +x, B = +y
    ("y", TILT[[1, 0, 2]]),  # u along +y: T = +y
    ("-x", TILT * [-1.0, 1.0, 1.0]),  # mirrored: T = -x (B = +y: the sign keeps it)
])
def test_a_constant_normal_turns_with_the_uv_frame(tmp_path, uv_map, want):
    _, ni, smp = _samples(_quad(tmp_path / "q.usda", uv_map, normal=TILT))
    assert ni is not None and smp.normals.shape[0] >= 64
    np.testing.assert_allclose(smp.normals, np.broadcast_to(want, smp.normals.shape),
                               atol=1e-6)


def test_no_normal_input_leaves_everything_as_it_was(tmp_path):
    a, ni, smp = _samples(_quad(tmp_path / "q.usda", "x"))
    assert ni is None
    np.testing.assert_array_equal(smp.normals, np.tile([0.0, 0.0, 1.0], (smp.normals.shape[0], 1)))


def test_a_normal_map_is_read_per_sample_and_by_the_ground_truth(tmp_path):
    # left half of the map tilted 30° toward +u, right half toward -u (8-bit, raw)
    from tests.helpers.usd_stages import write_png
    from texelbake.trace.org import OrgScene, shade_org

    px = np.zeros((4, 16, 3), np.uint8)
    enc = np.round((TILT * 0.5 + 0.5) * 255).astype(np.uint8)
    px[:, :8] = enc
    px[:, 8:] = np.round((TILT * [-1, 1, 1] * 0.5 + 0.5) * 255).astype(np.uint8)
    write_png(tmp_path / "nrm.png", px)
    a, ni, smp = _samples(_quad(tmp_path / "q.usda", "x", texture="./nrm.png"))
    decoded = (enc.astype(float) / 255.0) * 2.0 - 1.0
    decoded /= np.linalg.norm(decoded)
    u = smp.uv[:, 0]
    far = np.abs(u - 0.5) > 2.0 / 16  # away from the texels the bilinear read blends
    far &= (u > 2.0 / 16) & (u < 1.0 - 2.0 / 16)  # and from the wrap at the edges
    left, right = far & (u < 0.5), far & (u > 0.5)
    assert left.any() and right.any()
    np.testing.assert_allclose(smp.normals[left], np.broadcast_to(decoded, (left.sum(), 3)),
                               atol=1e-6)
    np.testing.assert_allclose(smp.normals[right], np.broadcast_to(
        decoded * [-1, 1, 1], (right.sum(), 3)), atol=1e-6)
    # the ground truth shades with the same normals: straight-down light on a diffuse quad,
    # radiance ∝ n·l = cos 30° on both halves (the unmapped quad: 1)
    scene = OrgScene(a)
    xs = np.array([-0.35, 0.35])
    o = np.stack([xs, np.zeros(2), np.full(2, 2.0)], axis=1)
    d = np.tile([0.0, 0.0, -1.0], (2, 1))
    rad, _, hit = shade_org(scene, o, d)
    assert hit.all()
    flat = OrgScene(a)
    flat.normal_input = None
    rad_flat, _, _ = shade_org(flat, o, d)
    np.testing.assert_allclose(rad / rad_flat, np.sqrt(0.75), rtol=2e-2)
