"""Cut-outs in gt (UsdPreviewSurface opacity below opacityThreshold): a card above a plane,
its opacity from a texture's alpha, cut on its half toward -x. The cut half neither shows nor
casts a shadow; the opaque half does both. Truth: a Lambertian plane under a distant light of
irradiance E at cos θ to its normal has radiance ρ E cos θ / π, and 0 in an umbra."""

from __future__ import annotations

import numpy as np
import pytest

from tests.helpers.render import RHO, write_plane_usd

LIGHT = (0.8, 0.0, 0.6)  # from +x, cos θ = 0.6: a shadow falls 0.4 toward -x of the card
CARD = (0.0, 0.4, -0.2, 0.2, 0.3)  # x in [0, 0.2] cut, x in [0.2, 0.4] opaque


def test_gt_sees_through_and_casts_no_shadow_from_the_cut_half(tmp_path):
    from texelbake.asset import load_asset
    from texelbake.trace.camera import eye_rays, look_at
    from texelbake.trace.org import render_model

    src = write_plane_usd(tmp_path / "card.usda", light_dir=LIGHT, occluder=CARD,
                          occluder_cutout=True)
    asset = load_asset(src)
    # straight down from above the card: x, y of each pixel centre's ray is the pixel's
    cam = look_at((0.0, 0.0, 3.0), (0.0, 0.0, 0.0), 48, 48, fov_deg=20.0)
    res = render_model(asset, cam, spp=1)
    o, d = eye_rays(cam, np.full((1, 48 * 48, 2), 0.5))
    hit = o - (o[:, 2] / d[:, 2])[:, None] * d  # where each ray meets z = 0
    x, y = hit[:, 0].reshape(48, 48), hit[:, 1].reshape(48, 48)
    lum = res.image.mean(axis=2)
    lit = float(np.mean(RHO)) * 3.0 * 0.6 / np.pi
    band = np.abs(y) < 0.15
    # under the cut half (x in [0.03, 0.17], away from the alpha's filtered band): the plane,
    # lit (its shadow would fall 0.4 further toward -x)
    seen_through = band & (x > 0.03) & (x < 0.17)
    # the cut half's shadow region x - 0.4: lit; the opaque half's: the umbra
    no_shadow = band & (x > -0.37) & (x < -0.23)
    umbra = band & (x > -0.17) & (x < -0.03)
    for region in (seen_through, no_shadow, umbra):
        assert region.sum() >= 10
    np.testing.assert_allclose(lum[seen_through], lit, rtol=1e-4)
    np.testing.assert_allclose(lum[no_shadow], lit, rtol=1e-4)
    assert lum[umbra].max() == 0.0


@pytest.mark.slow  # a bake (~1 min on a loaded 2-core machine)
def test_cpm_sees_through_and_is_shadowed_by_the_card_as_gt(tmp_path):
    # the same card baked (32² atlas, light fit): the cut half's samples weigh nothing and the
    # visibility rays of the fit and a_vis pass through it, so the cpm image of the plane
    # under and beside it is the lit plane's, and the umbra of the opaque half stays dark.
    # Bounds: a flat Lambertian texel reproduces the lit value to the fit's precision (1 %
    # seen: 0.2577 vs 0.2578, and 0.244 beside the umbra where the bilinear texel filter
    # reaches the shadow's edge: 6 %, hence 10 %); the umbra's mean within 10 % of the lit
    # value (0.015 / 0.258 = 6 % seen: the filter's reach into the umbra at 32²)
    from schemas.settings import BakeSettings
    from texelbake.pipeline.run import bake
    from texelbake.render import render
    from texelbake.render.scene import load_scene, resolve_camera
    from texelbake.trace.camera import eye_rays

    src = write_plane_usd(tmp_path / "card.usda", light_dir=LIGHT, occluder=CARD,
                          occluder_cutout=True)
    settings = BakeSettings(atlas_resolution=32, shard_texels=32, samples_per_texel=16,
                            n_light_dirs=16, n_view_dirs=16, n_heldout=4, c_max=16,
                            avis_resolution=16, mesh_levels=1)
    root = bake(src, tmp_path / "baked", settings, progress=False)
    cam = resolve_camera(load_scene(root), "lod", 64, 64)
    kw = {"width": 64, "height": 64, "spp": 4, "camera": cam, "seed": 3}
    gt, cpm = render(root, "gt", **kw), render(root, "cpm", **kw)
    assert np.isfinite(cpm.image).all()
    o, d = eye_rays(cam, np.full((1, 64 * 64, 2), 0.5))
    hit = o - (o[:, 2] / d[:, 2])[:, None] * d
    x, y = hit[:, 0].reshape(64, 64), hit[:, 1].reshape(64, 64)
    band = np.abs(y) < 0.15
    y_gt, y_cpm = gt.image.mean(axis=2), cpm.image.mean(axis=2)
    lit = float(np.mean(RHO)) * 3.0 * 0.6 / np.pi
    for region in (band & (x > 0.03) & (x < 0.17), band & (x > -0.37) & (x < -0.23)):
        assert region.sum() >= 8
        np.testing.assert_allclose(y_gt[region], lit, rtol=1e-4)
        np.testing.assert_allclose(y_cpm[region].mean(), lit, rtol=0.10)
    umbra = band & (x > -0.17) & (x < -0.03)
    assert y_gt[umbra].max() == 0.0 and y_cpm[umbra].mean() <= 0.10 * lit
    # the LOD's own fallback as a viewer shows it (`preview-surface`): its opacity map cuts
    # the card for eye and shadow rays alike. Without the cut the card's cut half hides the
    # plane (its averaged colour, lit at cos 0.8 from above, not the plane's) and shadows
    # the strip beside the umbra. Bounds: the plane's fallback is the averaged Lambertian
    # (exact to the 8-bit texture, < 1 %) but the opacity map is filtered over 1/32 of the
    # page: pixels within that of the cut's edge are left out by the regions' margins, so
    # the lit value within 5 % and the umbra dark as in cpm
    pre = render(root, "preview-surface", **kw).image.mean(axis=2)
    for region in (band & (x > 0.03) & (x < 0.17), band & (x > -0.37) & (x < -0.23)):
        np.testing.assert_allclose(pre[region].mean(), lit, rtol=0.05)
    assert pre[umbra].mean() <= 0.10 * lit
