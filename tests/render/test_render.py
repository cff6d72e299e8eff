"""Renderer truths (issue 4 acceptance): a Lambertian plane, a sphere against its closed form,
a shadow edge cast by a second plane, and cpm against gt on a baked flat plane."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from tests.helpers.render import RHO, distant, icosphere, model, psnr_object, quad, write_plane_usd
from texelbake.errors import SettingsError, ShapeError
from texelbake.render import metrics
from texelbake.trace import camera as cam_mod
from texelbake.trace.org import OrgScene, render_model, shade_org

LIGHT = np.array([0.3, 0.2, 0.9]) / np.linalg.norm([0.3, 0.2, 0.9])
E = 3.0


def _centre_rays(cam):
    off = np.full((1, cam.width * cam.height, 2), 0.5)
    return cam_mod.eye_rays(cam, off)


def test_lambertian_plane_matches_rho_over_pi_e_cos():
    p, f = quad(-1.0, 1.0, -1.0, 1.0, 0.0)
    asset = model(p, f, lights=[distant(LIGHT, E)])
    # a camera 3 above the plane whose field of view stays inside it: every pixel hits
    cam = cam_mod.look_at((0.1, -0.1, 3.0), (0.1, -0.1, 0.0), 32, 32, fov_deg=30.0)
    res = render_model(asset, cam, spp=4, seed=3)
    expected = RHO / np.pi * E * LIGHT[2]  # (3,)
    assert res.image.shape == (32, 32, 3) and res.image.dtype == np.float32
    # float32 output of values ~0.5: exact up to rounding (2^-24 relative), bound 1e-4
    assert np.max(np.abs(res.image - expected)) < 1e-4
    assert res.rays_cast == 2 * 32 * 32 * 4  # one eye ray and one shadow ray per sample


def test_plane_seen_from_behind_or_lit_from_below_is_black():
    p, f = quad(-1.0, 1.0, -1.0, 1.0, 0.0)
    lit_below = model(p, f, lights=[distant(-LIGHT, E)])
    cam = cam_mod.look_at((0.0, 0.0, 3.0), (0.0, 0.0, 0.0), 8, 8, fov_deg=30.0)
    assert np.all(render_model(lit_below, cam, spp=1).image == 0.0)
    behind = cam_mod.look_at((0.0, 0.0, -3.0), (0.0, 0.0, 0.0), 8, 8, fov_deg=30.0)
    assert np.all(render_model(model(p, f, lights=[distant(LIGHT, E)]), behind, 1).image == 0)


def test_sphere_matches_closed_form():
    pts, faces = icosphere(5)  # 20480 faces, edge ~0.035 rad
    asset = model(pts, faces, normals=pts, lights=[distant(LIGHT, E)])
    cam = cam_mod.look_at((0.5, 1.0, 4.0), (0.0, 0.0, 0.0), 48, 48, fov_deg=36.0)
    o, d = _centre_rays(cam)
    rad, _, _ = shade_org(OrgScene(asset), o, d)
    # closed form: the ray's hit on the exact unit sphere, L = rho/pi E (n.l)+
    b = np.einsum("ij,ij->i", o, d)
    disc = b * b - (np.einsum("ij,ij->i", o, o) - 1.0)
    hit = disc > 0
    t = -b - np.sqrt(np.where(hit, disc, 0.0))
    n = o + t[:, None] * d
    cos_l = n @ LIGHT
    truth = RHO[None, :] / np.pi * E * np.clip(cos_l, 0.0, None)[:, None] * hit[:, None]
    # away from the silhouette and the terminator, where the polyhedron and the sphere
    # disagree on hit / horizon, the only difference is the interpolated normal and the
    # polyhedron's sagitta: O(edge^2) ~ 1e-3 rad of normal -> < 2e-3 * rho E / pi.
    inner = hit & (np.einsum("ij,ij->i", n, -d) > 0.3) & (np.abs(cos_l) > 0.1)
    assert inner.sum() > 400
    err = np.abs(rad[inner] - truth[inner]).max()
    assert err < 2e-3 * (RHO.max() * E / np.pi)
    # misses are black, the unlit side is black
    assert np.all(rad[~hit & (disc < -0.05)] == 0.0)
    assert np.all(rad[inner & (cos_l < -0.1)] == 0.0)


def test_shadow_edge_of_an_occluding_plane():
    h, a = 0.5, 0.5
    g_p, g_f = quad(-3.0, 3.0, -3.0, 3.0, 0.0)
    o_p, o_f = quad(-a, a, -a, a, h)
    pts = np.concatenate([g_p, o_p])
    faces = np.concatenate([g_f, o_f + len(g_p)])
    light = np.array([1.0, 0.5, 1.0]) / np.linalg.norm([1.0, 0.5, 1.0])
    asset = model(pts, faces, lights=[distant(light, E)])
    cam = cam_mod.look_at((0.05, 0.03, 6.0), (0.05, 0.03, 0.0), 64, 64, fov_deg=28.0)
    o, d = _centre_rays(cam)
    rad, _, _ = shade_org(OrgScene(asset), o, d)
    lit = RHO / np.pi * E * light[2]
    # rays that reach the ground (miss the occluder)
    t_occ = (h - o[:, 2]) / d[:, 2]
    q = o + t_occ[:, None] * d
    through = (np.abs(q[:, 0]) > a) | (np.abs(q[:, 1]) > a)
    t_g = -o[:, 2] / d[:, 2]
    g = o + t_g[:, None] * d
    # the ground point is in shadow iff its ray toward the light crosses the occluder square
    s = g[:, :2] + h * light[:2] / light[2]
    margin = np.minimum(np.abs(np.abs(s[:, 0]) - a), np.abs(np.abs(s[:, 1]) - a))
    shadow = (np.abs(s[:, 0]) < a) & (np.abs(s[:, 1]) < a)
    clear = through & (margin > 1e-3)  # float32 Embree: stay 1e-3 off the edge
    assert (clear & shadow).sum() > 100 and (clear & ~shadow).sum() > 100
    np.testing.assert_allclose(rad[clear & shadow], 0.0, atol=0.0)
    np.testing.assert_allclose(rad[clear & ~shadow], np.broadcast_to(lit, rad[clear & ~shadow]
                                                                     .shape), rtol=1e-9)
    # the edge is where the prediction puts it: pixels right next to it exist on both sides
    near = through & (margin < 0.05) & (margin > 1e-3)
    assert np.any(near & shadow) and np.any(near & ~shadow)
    # the occluder's top is lit
    top = ~through & (np.maximum(np.abs(q[:, 0]), np.abs(q[:, 1])) < a - 1e-3)
    np.testing.assert_allclose(rad[top], np.broadcast_to(lit, rad[top].shape), rtol=1e-9)


def test_stratified_offsets_stay_in_their_strata():
    off = cam_mod.sample_offsets(8, 5, seed=1)
    nx, ny = cam_mod.strata(8)
    assert (nx, ny) == (2, 4)
    cell = np.floor(off * np.array([nx, ny])).astype(int)
    s = np.arange(8)
    np.testing.assert_array_equal(cell[..., 0], np.broadcast_to((s % nx)[:, None], (8, 5)))
    np.testing.assert_array_equal(cell[..., 1], np.broadcast_to((s // nx)[:, None], (8, 5)))
    # a pass of samples 2..5 is the same whatever the pass: reproducible by (seed, start)
    np.testing.assert_array_equal(cam_mod.sample_offsets(8, 5, 1, 2, 6),
                                  cam_mod.sample_offsets(8, 5, 1, 2, 6))
    with pytest.raises(SettingsError):
        cam_mod.strata(0)


@pytest.mark.parametrize("share", [0.01, 0.2, 0.6])
def test_a_frames_pixels_get_the_whole_frames_offsets(share):
    """A frame that traces only some pixels (the box's rectangle) draws the span of the stream
    that holds them, skipping the rest; it must be the whole frame's there, bit for bit
    (sparse and dense sets, a rectangle, the first and last pixels, none, every pass)."""
    rng = np.random.default_rng(3)
    n = 4000
    pixels = np.flatnonzero(rng.random(n) < share)
    rect = (np.arange(10, 20)[:, None] * 100 + np.arange(40, 47)[None, :]).reshape(-1)
    for pix in (pixels, rect, np.array([0, n - 1]), np.zeros(0, np.int64)):
        for start, stop in ((0, 8), (2, 6), (7, 8)):
            np.testing.assert_array_equal(
                cam_mod.sample_offsets(8, n, 11, start, stop, pix),
                cam_mod.sample_offsets(8, n, 11, start, stop)[:, pix])


@pytest.mark.parametrize("bad", [[3, 2], [1, 1], [-1, 4], [5, 400]])
def test_offsets_refuse_pixels_out_of_order_or_range(bad):
    with pytest.raises(ShapeError, match="pixels"):
        cam_mod.sample_offsets(4, 400, 0, pixels=np.array(bad))


def test_centre_pixel_ray_is_the_view_direction():
    cam = cam_mod.look_at((1.0, 2.0, 3.0), (0.0, 0.0, 0.0), 33, 33, fov_deg=40.0)
    o, d = _centre_rays(cam)
    np.testing.assert_allclose(d[16 * 33 + 16], cam.forward, atol=1e-12)
    np.testing.assert_allclose(o[0], (1.0, 2.0, 3.0))
    # the corner pixel's ray leans by the half field of view (minus half a pixel)
    x = (2.0 * 0.5 / 33 - 1.0) * cam.tan_half_x
    cos = 1.0 / np.sqrt(1.0 + x * x + x * x)
    assert abs(float(d[0] @ cam.forward) - cos) < 1e-12


def test_render_is_deterministic():
    p, f = quad(-1.0, 1.0, -1.0, 1.0, 0.0)
    o_p, o_f = quad(-0.3, 0.3, -0.3, 0.3, 0.3)
    asset = model(np.concatenate([p, o_p]), np.concatenate([f, o_f + 4]),
                  lights=[distant(LIGHT, E)])
    cam = cam_mod.look_at((0.4, 0.2, 3.0), (0.0, 0.0, 0.0), 16, 16)
    a = render_model(asset, cam, spp=4, seed=7).image
    b = render_model(asset, cam, spp=4, seed=7).image
    assert a.tobytes() == b.tobytes()


@pytest.fixture(scope="module")
def baked_plane(tmp_path_factory) -> Path:
    from schemas.settings import BakeSettings
    from texelbake.pipeline.run import bake

    d = tmp_path_factory.mktemp("plane")
    src = write_plane_usd(d / "plane.usda")
    # the smallest bake that still has every level (a flat plane needs one point per texel)
    settings = BakeSettings(atlas_resolution=16, shard_texels=16, samples_per_texel=4,
                            n_light_dirs=4, n_view_dirs=4, n_heldout=4, c_max=4,
                            avis_resolution=4, mesh_levels=1)
    return bake(src, d / "baked", settings, progress=False)


def test_cpm_matches_gt_on_a_flat_plane(baked_plane):
    from texelbake.render import render

    # auto-framed at 3x the fitting distance: the plane's finest texels are smaller than a
    # pixel, so every sample takes the CPM path (no fallback to M_org)
    kw = {"width": 32, "height": 32, "spp": 4, "camera": 3.0, "seed": 1}
    gt = render(baked_plane, "gt", **kw)
    cpm = render(baked_plane, "cpm", **kw)
    assert cpm.extras["fallback_fraction"] == 0.0
    assert np.nanmin(cpm.extras["level"]) >= 0.0
    assert gt.image.max() > 0.1
    assert psnr_object(cpm, gt) >= 50.0  # over the plane's pixels, not the black frame
    # and the fallback path (closer than the finest level) is M_org exactly
    near = {**kw, "camera": None}
    gt_n = render(baked_plane, "gt", **near)
    cpm_n = render(baked_plane, "cpm", **near)
    assert cpm_n.extras["fallback_fraction"] > 0.5
    assert psnr_object(cpm_n, gt_n) >= 50.0


def test_normalmap_and_equal_time_on_a_flat_plane(baked_plane, tmp_path):
    from texelbake.render import render

    kw = {"width": 24, "height": 24, "spp": 4, "camera": 2.0, "seed": 2}
    gt = render(baked_plane, "gt", **kw)
    nm = render(baked_plane, "normalmap", **kw, out_dir=tmp_path)
    # a flat plane's normal map is (0, 0, 1) up to 8-bit quantisation; albedo exact to 8 bits
    assert psnr_object(nm, gt) >= 40.0
    assert (tmp_path / "normalmap.exr").is_file() and (tmp_path / "normalmap.png").is_file()
    eq = render(baked_plane, "equal-time", **kw, budget_seconds=0.0)
    assert eq.spp == 1  # no budget: the first pass only, one sample per pixel
    assert eq.extras["mean_spp"] == 1.0 and eq.coverage is not None
    for bad in (-1.0, float("nan")):  # a budget that is not a time is refused, named
        with pytest.raises(SettingsError, match="budget_seconds"):
            render(baked_plane, "equal-time", **kw, budget_seconds=bad)
    with pytest.raises(SettingsError):
        render(baked_plane, "nope", **kw)


def test_previews_and_report(baked_plane, tmp_path, monkeypatch):
    import json

    from texelbake.render import report as api

    monkeypatch.setitem(api.PREVIEW_SIZES, "tiny", {
        "px": 24, "ref_spp": 16, "gt_sweep": (1, 4), "cpm_sweep": (1,), "spp": 4})
    files = api.render_previews(baked_plane, tmp_path, size="tiny")
    names = {p.name for p in files}
    for mode in ("gt", "cpm", "normalmap", "equal-time"):
        assert {f"{mode}.png", f"{mode}.exr", f"far_{mode}.png", f"diff_{mode}.png"} <= names
    assert {"mip_levels.png", "far_mip_levels.png", "cp_density_atlas.png",
            "cp_density_model.png", "render_report.json", "speed_error.png"} <= names
    rep = json.loads((tmp_path / "render_report.json").read_text())
    for view in (rep, rep["far"]):
        for mode in ("gt", "cpm", "normalmap", "equal-time"):
            e = view["modes"][mode]
            assert e["seconds"] > 0 and e["rays_cast"] > 0 and e["spp"] >= 1
            assert isinstance(e["psnr_db"], float) or e["psnr_db"] == "inf"
        assert {e["spp"] for e in view["sweep"] if e["mode"] == "gt"} >= {1, 4}
    # the far view uses the characteristic point maps, flat plane: cpm = gt to >= 50 dB
    # over the object's pixels (the same eye rays and outline; a flat Lambertian texel's
    # radiance is the plane's)
    from scipy.ndimage import binary_erosion

    from texelbake.io.images import read_image

    assert rep["far"]["modes"]["cpm"]["fallback_fraction"] < 0.5
    far_gt, far_cpm = (read_image(tmp_path / f"far_{m}.exr") for m in ("gt", "cpm"))
    mask = metrics.object_mask(far_gt.max(axis=2) > 0, far_cpm.max(axis=2) > 0)
    assert mask.sum() == rep["far"]["modes"]["cpm"]["object_pixels"] > 0
    assert metrics.psnr_db(far_cpm[mask], far_gt[mask], far_gt.max()) >= 50.0
    # the gt image at 4 spp against the 16-spp reference of a flat, evenly lit plane: only
    # the plane's border pixels differ (interior pixels agree to float32 rounding)
    gt4, ref16 = (read_image(tmp_path / f"{m}.exr") for m in ("gt", "gt_reference"))
    differs = np.abs(gt4 - ref16).max(axis=2) > 1e-5 * ref16.max()
    interior = binary_erosion(ref16.max(axis=2) > 0, structure=np.ones((3, 3), bool))
    assert differs.any() and not (differs & interior).any()
    for view in (rep, rep["far"]):  # every mode's figures are over the object's pixels
        for mode in ("gt", "cpm", "normalmap", "equal-time"):
            e = view["modes"][mode]
            assert 0 < e["object_pixels"] < 24 * 24
            assert e["psnr_db_object"] < e["psnr_db"]  # the black frame no longer helps
            assert 0.0 <= e["flip_mean"] <= 1.0 and e["delta_e_p95"] >= 0.0
    # the report's ratio is equal-time's seconds over cpm's (both rounded to 1e-4 s in the
    # report, so the quotient of the rounded values may differ by that rounding)
    et = rep["equal_time"]
    a, b = et["equal_time_seconds"], et["cpm_seconds"]
    assert et["ratio"] == pytest.approx(a / b, abs=5e-5 / b * (1 + a / b) + 1e-4)
    assert (a, b) == (rep["modes"]["equal-time"]["seconds"], rep["modes"]["cpm"]["seconds"])
    with pytest.raises(SettingsError):
        api.render_previews(baked_plane, tmp_path, size="huge")


def test_well_stratified_is_the_largest_balanced_count():
    from texelbake.trace.tracer import well_stratified

    def balanced(m):
        nx, ny = cam_mod.strata(m)
        return ny <= 2 * nx

    for n in range(1, 300):  # brute force over every count
        m = well_stratified(n)
        assert m <= n and balanced(m)
        assert not any(balanced(k) for k in range(m + 1, n + 1))


def test_render_report_writes_the_modes_asked_for(baked_plane, tmp_path):
    import json

    from texelbake.render import render_report

    path = render_report(baked_plane, tmp_path, modes="gt,cpm", width=16, height=16, spp=1,
                         ref_spp=4, camera=3.0)
    rep = json.loads(path.read_text())
    assert set(rep["modes"]) == {"gt", "cpm"}
    assert rep["reference"]["spp"] == 4
    assert (tmp_path / "cpm.exr").is_file() and (tmp_path / "speed_error.png").is_file()
    with pytest.raises(SettingsError):
        render_report(baked_plane, tmp_path, modes="gt,bogus", width=8, height=8)


def test_diagnostic_colours_and_density(baked_plane):
    from matplotlib import colormaps

    from texelbake.render import diagnostics as api
    from texelbake.render.scene import load_scene

    lv = np.array([[np.nan, -1.0], [0.0, 1.5]])
    c = api.level_colours(lv, n_levels=3)
    pal = np.asarray(colormaps["tab10"](np.arange(10)))[:, :3]
    np.testing.assert_array_equal(c[0, 0], 0.0)  # background
    np.testing.assert_array_equal(c[0, 1], 1.0)  # M_org fallback
    np.testing.assert_allclose(c[1, 0], pal[0])
    np.testing.assert_allclose(c[1, 1], 0.5 * (pal[1] + pal[2]))
    scene = load_scene(baked_plane)
    dens = api.density_atlas(scene, 0)
    counts = np.diff(scene.baked.levels[0]["texel_offsets"])
    assert dens.shape == (16, 16) and dens.sum() == counts.sum() > 0
    np.testing.assert_array_equal(dens.ravel(), counts)
    cam = cam_mod.look_at((0.0, 0.0, 3.0), (0.0, 0.0, 0.0), 12, 12, fov_deg=20.0)
    img = api.density_on_model(scene, cam)
    assert img.shape == (12, 12, 3) and img.max() > 0  # the plane fills the view


def test_cpm_looks_up_each_sample_at_its_own_footprint(baked_plane):
    """footprint='sample': each of the spp eye rays of a pixel reads the maps at a 1/spp
    share of the pixel's footprint, ½ log2 spp levels finer (at least the finest level);
    which samples fall back to M_org is still decided by the pixel's footprint. At 1 spp
    the two agree exactly."""
    from texelbake.render import render

    kw = {"width": 32, "height": 32, "camera": 8.0, "seed": 1}
    px1 = render(baked_plane, "cpm", spp=1, footprint="pixel", **kw)
    s1 = render(baked_plane, "cpm", spp=1, footprint="sample", **kw)
    assert np.array_equal(px1.image, s1.image)
    # at 2 spp the samples read half a level finer; from this distance the plane's pixels
    # sit at λ 0-1.07 (16 x 16 atlas), so most read level 0.5 finer and a few clip at 0
    px = render(baked_plane, "cpm", spp=2, footprint="pixel", **kw)
    s = render(baked_plane, "cpm", spp=2, footprint="sample", **kw)
    lp, ls = px.extras["level"], s.extras["level"]
    deep = np.isfinite(lp) & (lp >= 0.55)  # every sample of the pixel at λ >= 0.5
    assert deep.sum() >= 8
    np.testing.assert_allclose(ls[deep], lp[deep] - 0.5, atol=1e-5)
    shallow = np.isfinite(lp) & (lp <= 0.45)
    assert (ls[shallow] == 0.0).all()
    assert s.extras["fallback_fraction"] == px.extras["fallback_fraction"]
    with pytest.raises(SettingsError, match="footprint"):
        render(baked_plane, "cpm", spp=1, footprint="texel", **kw)


def test_progressive_renders_any_sample_count_unbiased():
    """Equal-time's time-budgeted loop (`tracer.progressive`): a zero budget gives exactly
    one sample per pixel; a larger budget adds samples (not a square count, not the same in
    every pixel) whose mean converges to the many-sample image — closer than one sample."""
    from texelbake.trace.tracer import progressive

    v, f = icosphere(2)
    asset = model(v, f, lights=[distant(LIGHT, E)])
    scene = OrgScene(asset)
    cam = cam_mod.look_at((0.0, 0.0, 3.5), (0.0, 0.0, 0.0), 24, 24, fov_deg=40.0)
    ref = render_model(asset, cam, spp=256, seed=9)
    mask = metrics.object_mask(ref.coverage)

    def shade(o, d):
        return shade_org(scene, o, d)

    one, rays1, cov1, spp1, _ = progressive(cam, 0, shade, 0.0)
    assert spp1 == 1.0 and rays1 >= 24 * 24
    assert np.all((cov1 == 0) | (cov1 == 1))  # one sample: hit or miss
    img, _, cov, mean_spp, secs = progressive(cam, 0, shade, 0.3)
    assert mean_spp > 2.0 and secs > 0
    assert np.all((cov >= 0) & (cov <= 1))
    err1 = metrics.psnr_db(one[mask], ref.image[mask], ref.image.max())
    errn = metrics.psnr_db(img[mask], ref.image[mask], ref.image.max())
    assert errn > err1 + 3.0  # more samples, less noise (≥ 2x the samples: ≥ 3 dB)
    # silhouette coverage agrees with the reference's within a sampling tolerance
    assert abs(cov.sum() - ref.coverage.sum()) < 0.05 * ref.coverage.sum()
    # a frame of fewer pixels than the smallest chunk still gets more than one pass
    tiny = cam_mod.look_at((0.0, 0.0, 3.5), (0.0, 0.0, 0.0), 8, 8, fov_deg=40.0)
    assert progressive(tiny, 0, shade, 0.2)[3] > 2.0


def test_a_lightless_asset_is_lit_by_the_default_rig():
    """Studios ship assets without lights (the Teapot): the renderer lights them with a key and
    a fill from the viewer's side, and says so, instead of rendering black."""
    from texelbake.asset.lights import DEFAULT_KEY_IRRADIANCE, default_light_rig

    v, f = icosphere(2)
    asset = model(v, f)  # no lights
    scene = OrgScene(asset)
    assert scene.default_lights
    assert [light.path for light in scene.lights] == ["/texelbake:defaultRig/Key",
                                                      "/texelbake:defaultRig/Fill"]
    from texelbake.render.scene import describe_camera

    assert describe_camera(scene, None) == "auto-framed (the asset has none)"  # no camera
    cam = cam_mod.look_at((0.0, 0.0, 3.5), (0.0, 0.0, 0.0), 24, 24, fov_deg=40.0)
    img = render_model(asset, cam, spp=1).image
    assert img.max() > 0.0
    # both lights come from the viewer's side, the key from above (+Y up), unit directions
    view = np.array([0.0, 0.0, 1.0])
    key, fill = default_light_rig(view, "Y")
    for light in (key, fill):
        assert abs(np.linalg.norm(light.direction) - 1.0) < 1e-12 and light.kind == "distant"
        assert light.direction @ view > 0.3
    assert key.direction[1] > 0.3 and np.allclose(key.radiance_scale, DEFAULT_KEY_IRRADIANCE)
    assert default_light_rig(view, "Z")[0].direction[2] > 0.3  # Z-up: the key is above in Z
    with pytest.raises(Exception, match="view direction"):
        default_light_rig(np.zeros(3))
    # an asset with lights keeps them
    lit = OrgScene(model(v, f, lights=[distant(LIGHT, E)]))
    assert not lit.default_lights and len(lit.lights) == 1
