"""The a_vis stage's level 0 by need (BakeSettings.avis_level0) inside a real tile."""

import numpy as np

from schemas.settings import BakeSettings
from texelbake.stages.avis import run_avis_tile
from texelbake.stages.context import StageContext
from texelbake.stages.geometry import run_geometry
from texelbake.testscenes import write_scene

SMALL = {"atlas_resolution": 16, "shard_texels": 8, "mesh_levels": 1}


def test_by_need_tile_casts_fewer_rays_and_keeps_the_level(tmp_path):
    """The same tile of the small cylinder with each avis_level0: its own artifact, the same
    closed texels, texel areas and closed-form terms at every level, far fewer rays, and
    maps near the dense ones in total (area-weighted strata: the total over a tile's
    texels within 5 %)."""
    src = write_scene("cylinder", tmp_path / "cylinder.usda", "small")
    out = {}
    for mode in ("dense", "by_need"):
        ctx = StageContext.create(tmp_path / "work", src, BakeSettings(**SMALL,
                                                                       avis_level0=mode))
        run_geometry(ctx)
        key = run_avis_tile(ctx, 0)
        out[mode] = (key, ctx.store.read_arrays(key))
    (kd, d), (kn, n) = out["dense"], out["by_need"]
    assert kd != kn
    for name in d:
        if name.endswith(("closed", "bounded", "texel_area", "cf_normals", "cf_areas")):
            assert np.array_equal(d[name], n[name]), name
    assert n["rays"][0] * 2 < d["rays"][0]  # K_SAMPLES = 16 of ~64 samples: at most 4x
    md, mn = d["L00_ray_maps"], n["L00_ray_maps"]
    assert md.shape == mn.shape and md.shape[0] > 0
    assert abs(mn.sum() - md.sum()) <= 0.05 * md.sum()
