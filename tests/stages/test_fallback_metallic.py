"""The fallback of an asset whose metallic and roughness vary per texel (an ARM-style texture:
roughness from its green channel, metallic from its blue, as glTF-converted assets bind them):
a metallic map in the metallic workflow, the roughness read per sample, each checked texel by
texel against the source texture's values at the dense samples' uvs; stock validation."""

from __future__ import annotations

import numpy as np
from pxr import Sdf, Usd, UsdShade

#: the ARM texture: metal (blue 1) and rough 0.2 (green) where s < 0.5, dielectric and 0.8
#: elsewhere; 64 px wide so a sample farther than 2/64 from the seam reads one side
W = 64


def _arm_plane(tmp_path):
    from tests.helpers.render import write_plane_usd
    from tests.helpers.usd_stages import uv_texture, write_png

    src = write_plane_usd(tmp_path / "plane.usda")
    px = np.zeros((8, W, 3), np.uint8)
    px[:, :W // 2, 1], px[:, W // 2:, 1] = 51, 204  # roughness 0.2 | 0.8
    px[:, :W // 2, 2] = 255  # metallic 1 | 0
    write_png(tmp_path / "arm.png", px)
    stage = Usd.Stage.Open(str(src))
    mat = UsdShade.Material.Define(stage, "/Root/Looks/Arm")
    surf = UsdShade.Shader.Define(stage, "/Root/Looks/Arm/Surface")
    surf.CreateIdAttr("UsdPreviewSurface")
    surf.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).Set((0.9, 0.6, 0.2))
    mat.CreateSurfaceOutput().ConnectToSource(surf.ConnectableAPI(), "surface")
    tex = uv_texture(stage, "/Root/Looks/Arm", "Texture", "./arm.png", "g")
    tex.CreateOutput("b", Sdf.ValueTypeNames.Float)
    for name, ch in (("roughness", "g"), ("metallic", "b")):
        surf.CreateInput(name, Sdf.ValueTypeNames.Float).ConnectToSource(tex.ConnectableAPI(),
                                                                         ch)
    UsdShade.MaterialBindingAPI.Apply(stage.GetPrimAtPath("/Root/Plane")).Bind(mat)
    stage.RemovePrim("/Root/Looks/Lambert")  # the helper's, texelbake's own shader: unused
    stage.GetRootLayer().Save()
    return src


def test_metallic_and_roughness_textures_reach_the_fallback(tmp_path):
    from schemas.settings import BakeSettings
    from tests.helpers.usd_validation import stock_errors
    from texelbake.pipeline.run import bake
    from texelbake.stages.context import StageContext
    from texelbake.stages.filtered import fallback_samples
    from texelbake.usd.read import read_baked

    src = _arm_plane(tmp_path)
    s = BakeSettings(samples_per_texel=4, n_light_dirs=4, n_view_dirs=4, n_heldout=4, c_max=4,
                     avis_resolution=4, mesh_levels=1, atlas_resolution=16, shard_texels=8,
                     lod_switch_px=(32.0,))
    work = tmp_path / "store"
    root = bake(src, tmp_path / "out", s, progress=False, workdir=work)
    mat = read_baked(root).fallback["materials"][0]
    assert int(mat["constants"]["useSpecularWorkflow"]) == 0
    assert "metallic" not in mat["constants"]  # the map says it
    met, rough = mat["textures"]["metallic"][..., 0], mat["textures"]["roughness"][..., 0]
    res = met.shape[0]
    # the expectation: per texel the area mean over the dense samples of each side's value
    ctx = StageContext.create(work, src, s)
    fs = fallback_samples(ctx, res)
    t0 = fs["row"].astype(np.int64) * res + fs["col"]
    u = fs["smp"].uv[:, 0]
    metal = u < 0.5
    area = np.bincount(t0, weights=fs["smp"].area, minlength=res * res)
    want_m = np.bincount(t0, weights=fs["smp"].area * metal, minlength=res * res)
    want_a2 = np.bincount(t0, weights=fs["smp"].area * np.where(metal, 0.2, 0.8) ** 4,
                          minlength=res * res)
    # bilinear reads blend within a texel of the seam and, wrapping, of the edges s = 0, 1
    near = (np.abs(u - 0.5) < 2.0 / W) | (u < 2.0 / W) | (u > 1.0 - 2.0 / W)
    far = np.bincount(t0, weights=near.astype(float), minlength=res * res) == 0
    ok = (area > 0) & far
    assert ok.sum() > 0.5 * (area > 0).sum()
    want_m, want_r = want_m[ok] / area[ok], (want_a2[ok] / area[ok]) ** 0.25
    # 8-bit PNGs: half a step; the roughness texture's 0.2/0.8 are 51/255 and 204/255 exactly
    assert np.abs(met.reshape(-1)[ok] - want_m).max() < 0.6 / 255
    assert np.abs(rough.reshape(-1)[ok] - want_r).max() < 0.6 / 255 + 1e-3
    assert (want_m > 0.99).any() and (want_m < 0.01).any()  # both sides are checked
    from texelbake.usd.export import export_lod

    outs = [export_lod(root, 1, tmp_path / f"lod1{suffix}") for suffix in (".usda", ".usdz")]
    assert stock_errors(root, *outs) == {str(p): [] for p in (root, *outs)}


def test_material_metallic_per_sample():
    from texelbake.baselines.filtered_maps import material_metallic
    from texelbake.model import Material

    mats = [Material("/a", "preview", {"metallic": 0.7}),
            Material("/b", "preview", {"metallic": 1.0, "useSpecularWorkflow": 1}),
            Material("/c", "lambert", {}),
            Material("/d", "preview", {"metallic": 3.0})]
    got = material_metallic(mats, np.array([0, 1, 2, 3, 0]), np.zeros((5, 2)))
    np.testing.assert_array_equal(got, [0.7, 0.0, 0.0, 1.0, 0.7])


def test_the_fitted_gains_model_takes_each_texels_metallic(rng):
    # `fallback="fitted"` with a metallic map: L(g) = L0 + g ΔL with ΔL = (1 − m) ΔL_dielectric
    # + m ΔL_metal. At m = 1 and m = 0 it is the constant workflow's model bit for bit (the
    # metal's lobe, the dielectric's diffuse), and ΔL is affine in m between them
    from texelbake.stages.fallback import _model_terms

    t = 4
    nrm = np.c_[0.2 * rng.standard_normal((t, 2)), np.ones(t)]
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    base = rng.uniform(0.2, 0.9, (t, 3))
    rough = rng.uniform(0.3, 0.8, t)
    for m, const in ((1.0, {"metallic": 1.0}), (0.0, {"metallic": 0.0})):
        got = _model_terms({}, np.full(t, m), base, rough, nrm)
        want = _model_terms(const, m == 1.0, base, rough, nrm)
        for a, b in zip(got, want, strict=True):
            np.testing.assert_array_equal(a, b)
    d0, d1 = (_model_terms({}, np.full(t, m), base, rough, nrm)[1] for m in (0.0, 1.0))
    half = _model_terms({}, np.full(t, 0.5), base, rough, nrm)[1]
    np.testing.assert_allclose(half, 0.5 * (d0 + d1), rtol=1e-12, atol=1e-15)
