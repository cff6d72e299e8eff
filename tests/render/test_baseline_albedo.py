"""The baselines keep a printed texture: a box printed with a 16x16 checker (4x4 texel cells,
two colours), baked at the 16² CPM atlas, rendered in ``normalmap``, ``toksvig`` and ``leadr``
against ``gt`` (M_org with its texture) from one camera.

At a 16² atlas over six faces a face gets about 5x5 texels: the atlas-resolution albedo
averages the print to one colour per face (the "plain body"). The baselines read the
fallback's finer base-colour page instead (`texelbake.render.albedo`). The box is flat, so the
normal and the roughness maps are exact; what remains against gt is the page's filtering of the
cells' edges, LEADR's lobe and the render noise at 4 spp. Measured: mean object-pixel |Δ|
(linear radiance, over the gt image's mean there) normalmap 0.073, toksvig 0.083, leadr 0.103
with the page; 0.51 each with the atlas albedo. The bar 0.15 sits between them with margin
both ways.
"""

from __future__ import annotations

import numpy as np
import pytest

from tests.helpers.studio_assets import textured_box

SMALL = {"atlas_resolution": 16, "shard_texels": 16, "samples_per_texel": 4,
         "n_light_dirs": 4, "n_view_dirs": 4, "n_heldout": 4, "c_max": 4,
         "avis_resolution": 4}
REL_MAD_MAX = 0.15


@pytest.fixture(scope="module")
def printed_box(tmp_path_factory):
    from schemas.settings import BakeSettings
    from texelbake.pipeline.run import bake
    from texelbake.render.scene import load_scene

    d = tmp_path_factory.mktemp("printed_box")
    root = bake(textured_box(d / "src"), d / "out", BakeSettings(**SMALL), progress=False)
    return load_scene(root)


@pytest.mark.parametrize("mode", ["normalmap", "toksvig", "leadr"])
def test_baselines_keep_the_printed_texture(printed_box, mode):
    from texelbake.render.frame import render_frame
    from texelbake.render.metrics import object_mask

    scene = printed_box
    assert scene.baked.fallback["materials"][0]["textures"]["diffuseColor"].shape[0] > scene.n0
    cam = scene.default_camera(64, 64)  # the box ~60 px across: an atlas texel ~6 px
    gt = render_frame(scene, "gt", cam, 4, 0)
    img = render_frame(scene, mode, cam, 4, 0)
    mask = object_mask(gt.coverage, img.coverage)
    diff = np.abs(img.image[..., :3] - gt.image[..., :3]).mean(axis=2)[mask]
    rel = float(diff.mean() / gt.image[..., :3].mean(axis=2)[mask].mean())
    assert rel <= REL_MAD_MAX, (mode, rel)
