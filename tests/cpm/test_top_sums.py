"""The top levels' dense sums made by the tile shards (issue 15, item 6): a coarse texel's a_vis
and held-out truth are sums over its dense samples, so the tiles' shares add up to the sums
over all of them, and the top shard fitted from the tiles' sums reads no sample and gives the
fit it gives when it reads every sample itself (its second method, kept as the fallback for
stores whose tiles have no sums)."""

from __future__ import annotations

import numpy as np
import pytest

from schemas.settings import BakeSettings
from texelbake import stages
from texelbake.cpm import dense as dense_mod
from texelbake.cpm import level_batched as lb
from texelbake.cpm.dense import DenseSums, dense_sums
from texelbake.cpm.level import PointSet, direction_sets, samples_in, tile_texels
from texelbake.stages import cpm as cpm_stage
from texelbake.testscenes import write_scene

#: a 32^2 atlas in 8^2 tiles: levels 0-3 inside a tile, levels 4-5 (2 x 2 texels, 1) above.
#: avis_coarse="dense": these tests are about the sums of every dense sample (a_vis among
#: them) and run the cpm stages alone; the children's maps need the a_vis stage first
#: (tests/pipeline/test_pipeline.py bakes with them)
SETTINGS = {"atlas_resolution": 32, "shard_texels": 8, "samples_per_texel": 8,
            "n_light_dirs": 12, "n_view_dirs": 12, "n_heldout": 16, "c_max": 12, "n_trials": 2,
            "mesh_levels": 1, "avis_coarse": "dense"}


def _ctx(root, scene, **extra):
    ctx = stages.StageContext.create(root, scene, BakeSettings(**{**SETTINGS, **extra}))
    stages.run_ingest(ctx, 0)
    stages.run_geometry(ctx, 0)
    return ctx


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    d = tmp_path_factory.mktemp("topsums")
    return write_scene("bolt", d / "bolt.usda", "small")


def test_tile_ancestors_hold_their_tiles(scene, tmp_path):
    """tile_ancestor against the texel ids of the tile's own samples at every top level."""
    ctx = _ctx(tmp_path, scene)
    geo = ctx.fit_inputs().geo
    n = ctx.settings.atlas_resolution
    last = ctx.tile_levels - 1
    assert ctx.n_levels - ctx.tile_levels == 2  # levels 4 (2 x 2 texels) and 5 (1)
    for tile in range(16):  # loop over the 16 tiles
        smp = samples_in(geo, n, last, tile_texels(n, 8, tile, last))
        for level in range(ctx.tile_levels, ctx.n_levels):
            ids = np.unique((geo["sample_row"][smp] >> level) * (n >> level)
                            + (geo["sample_col"][smp] >> level))
            if smp.size:
                assert ids.tolist() == [cpm_stage.tile_ancestor(ctx, tile, level)]


@pytest.mark.parametrize(("heldout_samples", "point_lobe", "avis_fit_samples"),
                         [(0, "narrow", 0), (64, "narrow", 16384), (64, "widened", 16384),
                          (0, "narrow", 100)])
def test_dense_sums_add_over_disjoint_samples(scene, tmp_path, heldout_samples, point_lobe,
                                              avis_fit_samples):
    """Sums over every sample of the coarse texels equal the tiles' shares added (same rays,
    same BRDF values; only the order of the floating-point sums differs: 1e-12 relative),
    also where the truth is summed over a seeded subset of a texel's samples (64 of its
    hundreds: each tile draws its share of the same subset, with the same weights), the
    validation pairs' truth of widened lobes with it, and a_vis cast from every k-th sample
    of a texel's Z-order run (100 of its hundreds: each tile casts its share of them, and
    the area they cover adds up with it)."""
    ctx = _ctx(tmp_path, scene, heldout_samples=heldout_samples, point_lobe=point_lobe,
               avis_fit_samples=avis_fit_samples)
    src = ctx.fit_inputs()
    level = ctx.tile_levels
    texels = np.arange((32 >> level) ** 2, dtype=np.int64)
    whole = dense_sums(src, level, texels)
    parts = DenseSums.zeros(len(texels), direction_sets(ctx.settings))
    last = ctx.tile_levels - 1
    for tile in range(16):  # loop over tiles
        smp = samples_in(src.geo, 32, last, tile_texels(32, 8, tile, last))
        anc = cpm_stage.tile_ancestor(ctx, tile, level)
        parts.add_row(anc, dense_sums(src, level, np.array([anc]), smp))
    np.testing.assert_array_equal(parts.count, whole.count)
    assert whole.count.sum() == len(src.geo["sample_area"])
    fields = ["area", "avis_o", "ref", "avis_h", "area_avis"]
    subset = whole.area_avis < whole.area * (1 - 1e-9)
    assert subset.all() if avis_fit_samples == 100 else not subset.any()
    if point_lobe == "widened":
        fields += ["val_ref", "val_avis", "val_area"]
        assert whole.val_ref.max() > 0
    else:
        assert whole.val_ref.size == 0 and not any(
            k.startswith("val_") for k in whole.to_arrays(""))  # stored as before
    for f in fields:
        a, b = getattr(parts, f), getattr(whole, f)
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12 * np.abs(b).max(), err_msg=f)
    assert whole.ref.max() > 0 and whole.avis_o.max() > 0


@pytest.mark.parametrize(("point_lobe", "avis_fit_samples"),
                         [("narrow", 16384), ("widened", 16384), ("narrow", 100)])
def test_top_shard_from_tile_sums_reads_no_sample(scene, tmp_path, monkeypatch, point_lobe,
                                                  avis_fit_samples):
    """The same bake's top shard twice: from the tiles' sums (with `samples_in` made to fail:
    it reads no dense sample) and, one tile's sums removed, from every sample itself. The sums
    differ by the order of their floating-point additions only, so the same points, weights
    to 1e-6 and held-out SNR to 1e-4 dB; with widened lobes the same choices (their lobes'
    variances equal) from the validation pairs' truth in the sums."""
    ctx = _ctx(tmp_path / "a", scene, point_lobe=point_lobe, avis_fit_samples=avis_fit_samples)
    for tile in range(16):  # the tile shards
        cpm_stage.run_cpm_tile(ctx, tile)
        assert ctx.store.exists(cpm_stage.sums_key(ctx, tile))
    assert cpm_stage.gathered_sums(ctx) is not None

    def no_samples(*a, **k):
        raise AssertionError("the top shard read the dense samples")

    with monkeypatch.context() as m:
        m.setattr(dense_mod, "samples_in", no_samples)  # where the batched fit reads samples
        cpm_stage.run_cpm_top(ctx, 0)
    from_sums = cpm_stage.cpm_levels(ctx)

    ctx_b = _ctx(tmp_path / "b", scene, point_lobe=point_lobe,
                 avis_fit_samples=avis_fit_samples)
    for tile in range(16):
        cpm_stage.run_cpm_tile(ctx_b, tile)
    ctx_b.store.path(cpm_stage.sums_key(ctx_b, 5)).unlink()  # one tile's sums missing
    assert cpm_stage.gathered_sums(ctx_b) is None
    cpm_stage.run_cpm_top(ctx_b, 0)
    read_all = cpm_stage.cpm_levels(ctx_b)
    widened = 0
    for level in range(ctx.tile_levels, ctx.n_levels):
        a, b = from_sums[level], read_all[level]
        for k in ("texel", "offsets", "point_sample", "k", "c", "valid", "mode"):
            np.testing.assert_array_equal(a[k], b[k], err_msg=f"L{level} {k}")
        if point_lobe == "widened":
            np.testing.assert_allclose(a["point_var"], b["point_var"], rtol=1e-6)
            widened += int(np.sum(a["point_var"] > 0))
        np.testing.assert_allclose(a["point_weight"], b["point_weight"], rtol=1e-6)
        v = a["valid"]
        assert v.any()
        np.testing.assert_allclose(a["snr_ho"][v], b["snr_ho"][v], atol=1e-4)
    assert (widened > 0) == (point_lobe == "widened")  # the top levels carry widened lobes


def test_rerun_tile_writes_missing_sums_only(scene, tmp_path):
    """A tile fitted before the sums existed (its sums removed) gets them on a rerun without
    refitting its levels (the level artifacts are not rewritten), byte-identical to the first."""
    ctx = _ctx(tmp_path, scene)
    cpm_stage.run_cpm_tile(ctx, 3)
    key = cpm_stage.sums_key(ctx, 3)
    first = ctx.store.path(key).read_bytes()
    lvl = ctx.store.path(cpm_stage.level_key(ctx, 0, 3))
    mtime = lvl.stat().st_mtime_ns
    ctx.store.path(key).unlink()
    cpm_stage.run_cpm_tile(ctx, 3)
    assert ctx.store.path(key).read_bytes() == first
    assert lvl.stat().st_mtime_ns == mtime


def test_sums_of_the_wrong_texels_are_refused(scene, tmp_path):
    """Samples outside the texels given, or sums of another texel count: a ShapeError that
    names the level, not a fit on misaligned rows."""
    from texelbake.errors import ShapeError

    ctx = _ctx(tmp_path, scene)
    src = ctx.fit_inputs()
    smp = samples_in(src.geo, 32, 3, tile_texels(32, 8, 0, 3))
    with pytest.raises(ShapeError, match="level 4"):
        dense_sums(src, 4, np.array([3]), smp)  # tile 0 lies under texel 0, not 3
    sums = dense_sums(src, 4, np.array([0]), smp)
    with pytest.raises(ShapeError, match="level 4"):
        lb.fit_level_batched(src, 4, np.arange(4), PointSet(
            np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0, np.int64)), sums)
