"""Cut-outs in gt (UsdPreviewSurface opacity below opacityThreshold): a card above a plane,
its opacity from a texture's alpha, cut on its half toward -x. The cut half neither shows nor
casts a shadow; the opaque half does both. Truth: a Lambertian plane under a distant light of
irradiance E at cos θ to its normal has radiance ρ E cos θ / π, and 0 in an umbra."""

from __future__ import annotations

import numpy as np

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
