"""Blender reads the fallback material as it reads the source's (tests/blender/import_render.py,
Blender 5.0.1's USD importer at its defaults, Cycles): a gold metal sphere whose
UsdPreviewSurface (metallic workflow) is the source, and the same sphere with the fallback
texelbake authors for it (`author_preview_material` with `dominant_constants` of the source as
`load_asset` reads it, and constant textures of the source's values). The two must import to
the same Principled BSDF and render alike.

Blender's importer turns an authored `specularColor` into Specular Tint whatever the workflow;
for a metal that is the edge (F82) tint, so the fallback's old spec-default specularColor
(0, 0, 0) darkened every rim of a metal LOD (the bolt's LOD2 in benchmarks/fallback.py: mean
radiance 0.69 of the original's, 0.84 with only Specular Tint set white).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from tests.helpers.dcc import compare_renders, import_and_render, keep_artifacts, side_by_side
from tests.helpers.usd_stages import uv_texture

pytestmark = [pytest.mark.dcc, pytest.mark.slow]  # Blender and Cycles: not for test-fast

GOLD = (0.9, 0.6, 0.2)
ROUGHNESS = 0.3
# 64² at 16 spp, the harness's sun and dim world (the sphere covers ~1200 px); the fallback's
# textures are 8-bit (sRGB base colour, raw roughness). Measured: object MAD 0.0016 and mean
# ratio 0.992 as it is; with the metallic workflow's specularColor (0, 0, 0) authored (Specular
# Tint black) 0.016 and 0.948, the rims dark
MAD_MAX = 0.006
RATIO_TOL = 0.02


def _sphere(stage, path: str, n_lat: int = 24, n_lon: int = 48):
    """A unit UV sphere (vertex normals, `st` from longitude and latitude, seam duplicated)."""
    from pxr import Gf, Sdf, UsdGeom, Vt

    lat = np.linspace(0.0, math.pi, n_lat + 1)
    lon = np.linspace(0.0, 2.0 * math.pi, n_lon + 1)
    th, ph = np.meshgrid(lat, lon, indexing="ij")  # (n_lat + 1, n_lon + 1)
    pts = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], axis=-1)
    st = np.stack([ph / (2.0 * math.pi), 1.0 - th / math.pi], axis=-1)
    idx = np.arange(pts.shape[0] * pts.shape[1]).reshape(pts.shape[:2])
    a, b = idx[:-1, :-1], idx[:-1, 1:]
    c, d = idx[1:, 1:], idx[1:, :-1]
    # counter-clockwise seen from outside; triangles at the poles (two corners meet there)
    quads = np.stack([a, d, c, b], axis=-1)  # (n_lat, n_lon, 4)
    faces = ([q[[0, 1, 2]] for q in quads[0]] + [q for row in quads[1:-1] for q in row]
             + [q[[0, 1, 3]] for q in quads[-1]])
    mesh = UsdGeom.Mesh.Define(stage, path)
    flat = pts.reshape(-1, 3)
    mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(flat, dtype=np.float32)))
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray([len(f) for f in faces]))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray([int(i) for f in faces for i in f]))
    mesh.CreateNormalsAttr(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(flat, dtype=np.float32)))
    mesh.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    mesh.CreateExtentAttr([Gf.Vec3f(-1.0), Gf.Vec3f(1.0)])
    pv = UsdGeom.PrimvarsAPI(mesh).CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray,
                                                 UsdGeom.Tokens.vertex)
    pv.Set(Vt.Vec2fArray.FromNumpy(np.ascontiguousarray(st.reshape(-1, 2), dtype=np.float32)))
    return mesh


def _stage(path: Path):
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    root = UsdGeom.Xform.Define(stage, "/Sphere")
    stage.SetDefaultPrim(root.GetPrim())
    return stage, _sphere(stage, "/Sphere/Geom")


def _bind(mesh, mat) -> None:
    from pxr import UsdShade

    UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim()).Bind(mat)


def _source(path: Path) -> Path:
    from pxr import Gf, Sdf, UsdShade

    stage, mesh = _stage(path)
    mat = UsdShade.Material.Define(stage, "/Sphere/Looks/Gold")
    surf = UsdShade.Shader.Define(stage, "/Sphere/Looks/Gold/PreviewSurface")
    surf.CreateIdAttr("UsdPreviewSurface")
    surf.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(*GOLD))
    surf.CreateInput("metallic", Sdf.ValueTypeNames.Float).Set(1.0)
    surf.CreateInput("roughness", Sdf.ValueTypeNames.Float).Set(ROUGHNESS)
    mat.CreateSurfaceOutput().ConnectToSource(surf.CreateOutput("surface",
                                                                Sdf.ValueTypeNames.Token))
    _bind(mesh, mat)
    stage.Save()
    return path


def _constant_textures(d: Path) -> None:
    """4² textures of the source's own values beside the fallback layer: base colour (sRGB),
    a flat normal, roughness, no occlusion."""
    from texelbake.io.images import linear_to_srgb, write_pixels

    full = np.ones((4, 4, 1))
    write_pixels(d / "albedo.png", np.round(linear_to_srgb(full * GOLD) * 255).astype(np.uint8),
                 "uint8")
    write_pixels(d / "normal.png", np.round(full * (0.5, 0.5, 1.0) * 255).astype(np.uint8),
                 "uint8")
    write_pixels(d / "roughness.png", np.round(full * ROUGHNESS * 255).astype(np.uint8), "uint8")
    write_pixels(d / "occlusion.png", np.full((4, 4, 1), 255, dtype=np.uint8), "uint8")


def _fallback(src: Path, path: Path) -> Path:
    """The sphere with the fallback texelbake authors for `src`'s material: its carried
    constants and 4² textures of the source's own values (base colour, a flat normal,
    roughness, no occlusion)."""
    from texelbake.asset import load_asset
    from texelbake.baselines.filtered_maps import dominant_constants
    from texelbake.usd.fallback import author_preview_material

    d = path.parent
    const = dominant_constants(load_asset(src).materials, np.zeros(1, dtype=np.int64),
                               np.ones(1))
    _constant_textures(d)
    stage, mesh = _stage(path)
    mat = author_preview_material(stage, "/Sphere/Looks/Fallback", "./albedo.png", "./normal.png",
                                  "/Sphere/CPM", "./roughness.png", "./occlusion.png", const)
    _bind(mesh, mat)
    stage.Save()
    return path


@pytest.fixture(scope="module")
def gold(tmp_path_factory):
    d = tmp_path_factory.mktemp("dcc_fallback_material")
    src = _source(d / "source.usda")
    fb = _fallback(src, d / "fallback.usda")
    renders = d / "renders"
    got = import_and_render({"source": src, "fallback": fb}, renders, resolution=64, samples=16)
    pngs = [Path(got["files"][k]["png"]) for k in ("source", "fallback")]
    side_by_side(pngs, renders / "row.png")
    keep_artifacts(sorted(renders.glob("*.png")), "dcc/fallback_material")
    return got, pngs


def test_the_fallback_imports_to_the_source_principled_bsdf(gold):
    got, _ = gold
    src = next(iter(got["files"]["source"]["bsdf"].values()))
    fb = next(iter(got["files"]["fallback"]["bsdf"].values()))
    assert src["Metallic"] == fb["Metallic"] == 1.0
    # the source authors no specularColor: Blender's default tint (white) for both
    np.testing.assert_allclose(fb["Specular Tint"], src["Specular Tint"], atol=1e-6)
    assert fb["Base Color"] == fb["Roughness"] == "linked"  # the fallback's textures


def test_the_fallback_renders_as_the_source(gold):
    from texelbake.io.images import read_pixels, srgb_to_linear

    _, (src_png, fb_png) = gold
    cmp = compare_renders(src_png, fb_png)
    assert cmp["iou"] > 0.99 and cmp["mad"] < MAD_MAX, cmp
    means = []
    for p in (src_png, fb_png):
        px = read_pixels(p)[0].astype(np.float64)
        means.append(float(srgb_to_linear(px[..., :3])[px[..., 3] >= 0.5].mean()))
    assert abs(means[1] / means[0] - 1.0) < RATIO_TOL, means


# A sphere whose metallic comes from a texture (stripes of gold metal and gold-coloured
# dielectric in longitude): the fallback with a metallic map (`stages.filtered.fallback_metallic`)
# against the one the dominant material's constants gave before (a textured metallic dropped:
# metallic 0 everywhere). 16² textures, the seam at a texel edge.
HALF = 16


def _half_metal_png(d: Path) -> str:
    from texelbake.io.images import write_pixels

    px = np.zeros((HALF, HALF, 1), np.uint8)
    px[:, (np.arange(HALF) // 2) % 2 == 0] = 255  # 8 stripes in longitude: any view sees both
    write_pixels(d / "metallic.png", px, "uint8")
    return "./metallic.png"


def _half_metal_source(path: Path) -> Path:
    from pxr import Gf, Sdf, UsdShade

    stage, mesh = _stage(path)
    metallic = _half_metal_png(path.parent)
    mat = UsdShade.Material.Define(stage, "/Sphere/Looks/Half")
    surf = UsdShade.Shader.Define(stage, "/Sphere/Looks/Half/PreviewSurface")
    surf.CreateIdAttr("UsdPreviewSurface")
    surf.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(*GOLD))
    surf.CreateInput("roughness", Sdf.ValueTypeNames.Float).Set(ROUGHNESS)
    tex = uv_texture(stage, "/Sphere/Looks/Half", "Metallic", metallic, "r")
    surf.CreateInput("metallic", Sdf.ValueTypeNames.Float).ConnectToSource(
        tex.ConnectableAPI(), "r")
    mat.CreateSurfaceOutput().ConnectToSource(surf.CreateOutput("surface",
                                                                Sdf.ValueTypeNames.Token))
    _bind(mesh, mat)
    stage.Save()
    return path


def _half_metal_fallback(src: Path, path: Path, with_map: bool) -> Path:
    """The fallback texelbake authors: with the metallic map, the metallic workflow and no
    metallic constant (`fallback_maps`); without it, the dominant material's constants."""
    from texelbake.asset import load_asset
    from texelbake.baselines.filtered_maps import dominant_constants
    from texelbake.usd.fallback import author_preview_material

    d = path.parent
    const = dominant_constants(load_asset(src).materials, np.zeros(1, dtype=np.int64),
                               np.ones(1))
    if with_map:
        const = {**{k: v for k, v in const.items() if k != "metallic"}, "useSpecularWorkflow": 0}
    _constant_textures(d)
    stage, mesh = _stage(path)
    mat = author_preview_material(
        stage, "/Sphere/Looks/Fallback", "./albedo.png", "./normal.png", "/Sphere/CPM",
        "./roughness.png", "./occlusion.png", const,
        metallic_file=_half_metal_png(d) if with_map else None)
    _bind(mesh, mat)
    stage.Save()
    return path


def test_a_metallic_map_renders_as_the_source_in_blender(tmp_path):
    d = {k: tmp_path / k for k in ("source", "map", "constants")}
    for p in d.values():
        p.mkdir()
    src = _half_metal_source(d["source"] / "source.usda")
    files = {"source": src,
             "map": _half_metal_fallback(src, d["map"] / "fallback.usda", True),
             "constants": _half_metal_fallback(src, d["constants"] / "fallback.usda", False)}
    renders = tmp_path / "renders"
    got = import_and_render(files, renders, resolution=64, samples=16)
    pngs = {k: Path(got["files"][k]["png"]) for k in files}
    side_by_side(list(pngs.values()), renders / "row.png")
    keep_artifacts(sorted(renders.glob("*.png")), "dcc/fallback_metallic_map")
    bsdf = next(iter(got["files"]["map"]["bsdf"].values()))
    assert bsdf["Metallic"] == "linked"  # Blender reads the map
    with_map = compare_renders(pngs["source"], pngs["map"])
    without = compare_renders(pngs["source"], pngs["constants"])
    # the map renders as the source (the bar of the constant gold sphere above); the
    # constants, metallic 0 on the metal stripes, are far from it (measured: MAD 0.0029 and
    # 0.098)
    assert with_map["iou"] > 0.99 and with_map["mad"] < MAD_MAX, with_map
    assert without["mad"] > 3.0 * MAD_MAX, without
