"""The cpm mode reads widened characteristic points (BakeSettings.point_lobe="widened",
`texelbake.cpm.lobe`): a bake of the small cylinder (its blue Phong lobe) carries each point's
lobe variance in the payload, and Eq. 12 evaluates each point's BRDF with it: a texel whose
points all keep their own lobe (variance 0) shades exactly as the narrow reading, a texel
with a widened point does not."""

from __future__ import annotations

import numpy as np
import pytest


@pytest.fixture(scope="module")
def baked_widened(tmp_path_factory):
    from schemas.settings import BakeSettings
    from texelbake.pipeline.run import bake
    from texelbake.testscenes import write_scene

    d = tmp_path_factory.mktemp("widened")
    src = write_scene("cylinder", d / "cyl.usda", "small")
    settings = BakeSettings(atlas_resolution=16, shard_texels=16, samples_per_texel=16,
                            n_light_dirs=16, n_view_dirs=16, n_heldout=16, c_max=12,
                            n_trials=2, avis_resolution=16, mesh_levels=1,
                            point_lobe="widened")
    return bake(src, d / "baked", settings, progress=False)


def test_eq12_reads_each_points_lobe_variance(baked_widened):
    from texelbake.cpm.brdf_product import WIDENED_MODELS
    from texelbake.render.scene import load_scene, resolve_camera
    from texelbake.render.texel_radiance import texel_radiance

    scene = load_scene(baked_widened)
    assert "point_var" in scene.baked.levels[0]  # written to the payload and read back
    cam = resolve_camera(scene, "lod", 64, 64)
    changed = 0
    for level in range(len(scene.baked.levels)):  # loop over the few levels
        pts = scene.points(level)
        var = pts["var"]
        assert var is not None and var.shape == pts["weight"].shape[:1]
        assert np.all(var >= 0)
        rad, avis, _, _ = texel_radiance(scene, level, cam.position)
        pts["var"] = None  # the same points read with their own lobes
        try:
            rad0, avis0, _, _ = texel_radiance(scene, level, cam.position)
        finally:
            pts["var"] = var
        np.testing.assert_array_equal(avis, avis0)  # a_vis does not depend on the lobes
        offsets = scene.baked.levels[level]["texel_offsets"]
        tex = np.repeat(np.arange(len(offsets) - 1), np.diff(offsets))
        # a widened point of a material with a lobe to widen (a Lambert one has none)
        lobed = np.array([m.model in WIDENED_MODELS for m in scene.materials])
        on = (var > 0) & lobed[pts["material"]]
        wide = np.bincount(tex, weights=on, minlength=len(offsets) - 1) > 0
        np.testing.assert_array_equal(rad[~wide], rad0[~wide])
        # (a widened point the camera or the light does not see adds nothing either way)
        changed += int(np.sum(np.abs(rad[wide] - rad0[wide]).sum(axis=1) > 1e-9))
    assert changed > 0  # the scene exercises the widened path
