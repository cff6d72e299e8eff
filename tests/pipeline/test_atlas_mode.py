"""atlas_mode "lod1": the settings a bake runs with (`resolve_settings`), its plan and its
one-line note, on the small cylinder (no stage runs)."""

from __future__ import annotations

import pytest

from schemas.settings import BakeSettings
from texelbake.geometry.build import lod1_atlas
from texelbake.pipeline.plan import atlas_note, n_tiles, plan_bake, resolve_settings
from texelbake.stages.context import asset_of
from texelbake.testscenes import write_scene


@pytest.fixture(scope="module")
def cylinder(tmp_path_factory):
    return write_scene("cylinder", tmp_path_factory.mktemp("atlas") / "cyl.usda", "small")


def test_fixed_mode_is_the_settings_as_given(cylinder):
    s = BakeSettings(atlas_resolution=16)
    assert resolve_settings(cylinder, s) is s
    assert atlas_note(cylinder, s) == "atlas: 16x16 (atlas_mode fixed)"


def test_lod1_mode_bakes_the_need_within_the_cap(cylinder):
    a = asset_of(cylinder)
    _, need = lod1_atlas(a.points, a.faces, 256.0, 4096)
    assert need is not None and need >= 64
    # a cap above the need: the need itself
    big = resolve_settings(cylinder, BakeSettings(atlas_mode="lod1", atlas_cap=4096))
    assert big.atlas_resolution == need
    # the cap reached: the largest size it allows, shard_texels kept within it, the plan's
    # tiles from the resolved side, and the note says so
    s = BakeSettings(atlas_mode="lod1", atlas_cap=8, shard_texels=16)
    r = resolve_settings(cylinder, s)
    assert (r.atlas_resolution, r.shard_texels) == (8, 8)
    assert plan_bake(cylinder, s).stage("cpm").n_shards == n_tiles(r) == 1
    note = atlas_note(cylinder, s)
    assert "cap is reached" in note and f"{need}x{need}" in note and "8x8" in note
    # resolving is idempotent: every process of a bake resolves the same
    assert resolve_settings(cylinder, r) == r
    # tiles larger than the fixed atlas_resolution's default: lod1 mode keeps them within the
    # side it chooses; fixed mode refuses them
    wide = resolve_settings(cylinder, BakeSettings(atlas_mode="lod1", atlas_cap=4096,
                                                   shard_texels=32))
    assert (wide.atlas_resolution, wide.shard_texels) == (need, min(32, need))
    with pytest.raises(ValueError, match="must not exceed atlas_resolution"):
        BakeSettings(shard_texels=32)


def test_cap_must_be_a_power_of_two():
    with pytest.raises(ValueError, match="atlas_cap"):
        BakeSettings(atlas_cap=100)
