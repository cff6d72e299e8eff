"""Inter-object shadows in the cpm mode (issue 4; seed 000 §4.2): a quad floating above a
plane, both in one baked asset, casts its shadow on the plane's texels.

The renderer's answer to the seed's "shadow test on M_i, then intra-object visibility on
M_org": the characteristic points' shadow rays toward each light are cast once per frame
against the whole M_org (every object of the asset; `core.texel_radiance`), so a texel's
radiance already carries the shadows of other objects at the resolution of its points."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from tests.helpers.render import psnr_object, write_plane_usd

# the light comes from +x, 53.1 degrees from the zenith: the occluder (x in [0.0, 0.4],
# |y| <= 0.2, z = 0.3) throws its shadow 0.4 toward -x, onto x in [-0.4, 0.0], beside it in a
# top view
LIGHT = (0.8, 0.0, 0.6)
OCCLUDER = (0.0, 0.4, -0.2, 0.2, 0.3)


@pytest.fixture(scope="module")
def baked_shadow(tmp_path_factory) -> Path:
    from schemas.settings import BakeSettings
    from texelbake.pipeline.run import bake

    d = tmp_path_factory.mktemp("shadow")
    src = write_plane_usd(d / "shadow.usda", light_dir=LIGHT, occluder=OCCLUDER)
    settings = BakeSettings(atlas_resolution=64, shard_texels=32, samples_per_texel=16,
                            n_light_dirs=16, n_view_dirs=16, n_heldout=4, c_max=16,
                            avis_resolution=16, mesh_levels=1)
    return bake(src, d / "baked", settings, progress=False)


def test_cpm_carries_the_shadow_of_another_object(baked_shadow):
    from texelbake.render import render
    from texelbake.render.scene import load_scene, resolve_camera
    from texelbake.trace.camera import eye_rays

    # the asset's top view moved back until a finest texel spans 0.7 pixel: every plane
    # pixel takes the CPM path
    cam = resolve_camera(load_scene(baked_shadow), "lod", 64, 64)
    kw = {"width": 64, "height": 64, "spp": 4, "camera": cam, "seed": 3}
    gt = render(baked_shadow, "gt", **kw)
    cpm = render(baked_shadow, "cpm", **kw)
    assert cpm.extras["fallback_fraction"] == 0.0
    # where each pixel centre's ray meets the plane z = 0
    o, d = eye_rays(cam, np.full((1, 64 * 64, 2), 0.5))
    hit = o - (o[:, 2] / d[:, 2])[:, None] * d
    x, y = hit[:, 0].reshape(64, 64), hit[:, 1].reshape(64, 64)
    umbra = (x > -0.35) & (x < -0.05) & (np.abs(y) < 0.15)  # > 1.5 texels from the edges
    lit = (x > -0.45) & (x < -0.05) & (np.abs(y) > 0.28) & (np.abs(y) < 0.45)
    y_gt = gt.image.mean(axis=2)
    assert umbra.sum() >= 20 and lit.sum() >= 20, (umbra.sum(), lit.sum())
    assert y_gt[umbra].max() == 0.0 and y_gt[lit].min() > 0.05  # the scene is what we think
    y_cpm = cpm.image.mean(axis=2)
    # Without shadows from the other object the umbra would be as bright as the lit plane.
    # The texels inside it hold only shadowed points, so it is black up to the reach of the
    # texel filter: bilinear within a level and linear between levels, the coarser level's
    # texels are twice as wide (measured: 0 with these settings; 7 % at the edge of the
    # region with 4 x 4 training directions and c_max 4).
    assert y_cpm[umbra].mean() <= 0.02 * y_gt[lit].mean()
    assert y_cpm[umbra].max() <= 0.15 * y_gt[lit].mean()
    # The lit plane: a flat Lambertian texel reproduces rho/pi E cos exactly, but beside the
    # occluder a_vis toward the camera comes from the Haar-compressed table, into which the
    # occluder's masking of nearby directions leaks (measured with 16^2 cells per face and
    # 6 % of the coefficients: mean +0.4 %, max +6.1 % at one pixel when each eye ray reads
    # the finest level (footprint="sample"), +3.9 % when the pixel's footprint blends in
    # level 1; with 4^2 cells, +8 % and +19 %). The level's sum correction (a_vis summed over
    # the level's texels exact per direction) moves part of the occluder texels' error onto
    # their partly masked neighbours: max +7.6 % at one of the 99 pixels, mean unchanged.
    np.testing.assert_allclose(y_cpm[lit], y_gt[lit], rtol=0.08)
    assert abs(float(np.mean(y_cpm[lit] / y_gt[lit])) - 1.0) <= 0.01
    # the shadow's edges are blurred by the texel filter, nothing else differs much
    assert psnr_object(cpm, gt) >= 25.0


def test_texel_radiance_of_a_subset_equals_the_full_level(baked_shadow):
    """The cpm mode computes Eq. 12 only for the texels a frame looks up; each texel's value
    must not depend on which others are computed with it."""
    from texelbake.render.scene import load_scene, resolve_camera
    from texelbake.render.texel_radiance import texel_radiance

    scene = load_scene(baked_shadow)
    cam = resolve_camera(scene, "lod", 32, 32)
    for level in (0, 2):
        rad, avis, ex, rays = texel_radiance(scene, level, cam.position)
        assert ex.sum() > 10 and rad[ex].max() > 0
        rng = np.random.default_rng(level)
        sub = np.sort(rng.choice(rad.shape[0], size=rad.shape[0] // 3, replace=False))
        r2, a2, e2, rays2 = texel_radiance(scene, level, cam.position, sub)
        np.testing.assert_array_equal(e2, ex[sub])
        np.testing.assert_allclose(r2, rad[sub], rtol=1e-12, atol=1e-15)
        np.testing.assert_allclose(a2, avis[sub], rtol=1e-12, atol=1e-15)
        assert rays2 < rays
