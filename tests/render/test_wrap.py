"""An asset of many parts (the small wall: 13 blocks on a mortar plane) gets a wrapped M1, and
the cpm mode takes its outline from M_org (coverage), not from the wrap's rounded rim."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest


@pytest.fixture(scope="module")
def baked_wall(tmp_path_factory) -> Path:
    from schemas.settings import BakeSettings
    from texelbake.pipeline.run import bake
    from texelbake.testscenes import write_scene

    d = tmp_path_factory.mktemp("wall")
    src = write_scene("wall", d / "wall_small.usda", "small")
    settings = BakeSettings(atlas_resolution=32, shard_texels=16, samples_per_texel=8,
                            n_light_dirs=8, n_view_dirs=8, n_heldout=4, c_max=8,
                            avis_resolution=8, mesh_levels=1,
                            lod_mode="atlas")  # the atlas-sized M1 (issue 22 keeps it)
    return bake(src, d / "baked", settings, progress=False)


def test_the_wall_gets_one_wrapped_m1(baked_wall):
    from texelbake.geometry.hierarchy import n_parts
    from texelbake.render.scene import load_scene

    scene = load_scene(baked_wall)
    m1 = scene.baked.meshes[0]
    assert n_parts(scene.asset.points, scene.asset.faces) == 14  # 13 blocks and the mortar
    assert n_parts(m1.vertices, m1.faces) == 1
    # tightened back onto the blocks, except at the rim's corners, where `enclose` caps a
    # vertex's move at the largest face offset (a corner meeting three planes would need
    # sqrt(3) of it): within sqrt(3) wrap offsets (bbox diagonal / 32) of M_org, measured 1.4
    offset = float(np.linalg.norm(np.ptp(scene.asset.points, axis=0))) / 32
    assert scene.lod_error[0] <= np.sqrt(3.0) * offset


def test_cpm_takes_its_outline_from_m_org(baked_wall):
    """Eye rays that hit the wrap but miss M_org see the background: every pixel whose eye
    rays all miss M_org is black in cpm (without the test, the wrap's rim lights a ring of
    them), and the image's total light comes closer to gt's."""
    from texelbake.render.frame import render_frame
    from texelbake.render.scene import load_scene
    from texelbake.trace import camera as cam_mod
    from texelbake.trace.camera import eye_rays, sample_offsets

    scene = load_scene(baked_wall)
    cam = cam_mod.auto_frame(scene.asset.bounds, 48, 32, distance=1.2)
    spp, seed = 4, 2
    on = render_frame(scene, "cpm", cam, spp, seed)
    off = render_frame(scene, "cpm", cam, spp, seed, coverage=False)
    gt = render_frame(scene, "gt", cam, 64, seed)
    # the eye rays of the cpm image, against M_org
    o, d = eye_rays(cam, sample_offsets(spp, cam.width * cam.height, seed, 0, spp))
    hit = scene.org.cast(o, d).hit.reshape(spp, cam.height, cam.width).any(axis=0)
    empty = ~hit
    assert empty.any() and hit.sum() > 200
    assert on.image[empty].max() == 0.0
    assert off.image[empty].max() > 0.05 * gt.image.max()  # the rim the test removes
    assert on.extras["fallback_fraction"] == off.extras["fallback_fraction"]
    err_on = abs(float(on.image.sum() / gt.image.sum()) - 1.0)
    err_off = abs(float(off.image.sum() / gt.image.sum()) - 1.0)
    assert err_on < err_off
