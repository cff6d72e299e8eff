"""The bake's estimate prices the classed levels on a sample of their texels
(`texelbake.pipeline.estimate.sampled_fitted_shares`): each classed level's share of texels left to
the fit, from CLASS_SAMPLE texels, against the share over every texel of the level (the
classes of the whole level, a second run of the classifier)."""

from __future__ import annotations

import numpy as np

from schemas.settings import BakeSettings
from texelbake import stages
from texelbake.cpm.dense import LevelPass, dense_of
from texelbake.cpm.level_by_need import classes_bounded
from texelbake.pipeline.estimate import CLASS_SAMPLE, sampled_fitted_shares
from texelbake.testscenes import write_scene


def test_the_sampled_share_matches_the_whole_level(tmp_path):
    """The small cylinder at 16^2: a level of at most CLASS_SAMPLE occupied texels is sampled
    whole (the share is exact); a larger one within 3 standard errors of a sample of 16
    drawn without replacement. texel_classes "points" prices no class."""
    scene = write_scene("cylinder", tmp_path / "c.usda", "small")
    s = BakeSettings(atlas_resolution=16, samples_per_texel=16, n_light_dirs=16, n_view_dirs=16)
    ctx = stages.StageContext.create(tmp_path / "w", scene, s)
    stages.run_ingest(ctx, 0)
    stages.run_geometry(ctx, 0)
    sampled = sampled_fitted_shares(ctx)
    assert sampled is not None and len(sampled.shares) == s.classed_levels
    got = sampled.shares
    src, geo = ctx.fit_inputs(), ctx.geometry()
    whole_sampled = False
    for level, phi in enumerate(got):
        n_l = 16 >> level
        occ = np.unique((geo["sample_row"] >> level) * n_l + (geo["sample_col"] >> level))
        lp = LevelPass.of(src, level)
        dense, dseg = dense_of(lp, occ)
        cls = classes_bounded(lp, occ, dense, dseg)
        truth = float(np.mean(~(cls.exact | cls.grouped)))
        if occ.size <= CLASS_SAMPLE:
            assert phi == truth, level
            whole_sampled = True
        else:
            fpc = (occ.size - CLASS_SAMPLE) / (occ.size - 1)
            se = np.sqrt(max(truth * (1 - truth), 1.0 / CLASS_SAMPLE) / CLASS_SAMPLE * fpc)
            assert abs(phi - truth) <= 3 * se, (level, phi, truth)
    assert whole_sampled
    points = stages.StageContext.create(tmp_path / "w", scene,
                                        s.model_copy(update={"texel_classes": "points"}))
    assert sampled_fitted_shares(points) is None


def test_the_lobe_class_is_priced_on_the_same_sample(tmp_path):
    """lobe_class "validated" on the small cloisonne (curved, one material a cell) at 16^2:
    the share of level 0's texels the lobe class tries and the share it leaves to the fit
    are each within 3 standard errors of the same shares over the whole level (the classes
    and the lobes of every occupied texel, a second run); without the class, nothing is
    tried."""
    from texelbake.cpm.classify import REASONS
    from texelbake.cpm.lobe_class import lobes_bounded

    scene = write_scene("cloisonne", tmp_path / "c.usda", "small")
    s = BakeSettings(atlas_resolution=16, samples_per_texel=16, n_light_dirs=16, n_view_dirs=16,
                     lobe_class="validated", classed_levels=1)
    ctx = stages.StageContext.create(tmp_path / "w", scene, s)
    stages.run_ingest(ctx, 0)
    stages.run_geometry(ctx, 0)
    sampled = sampled_fitted_shares(ctx)
    assert sampled is not None and sampled.lobe_tried is not None
    src, geo = ctx.fit_inputs(), ctx.geometry()
    occ = np.unique(geo["sample_row"] * 16 + geo["sample_col"])
    assert occ.size > CLASS_SAMPLE
    lp = LevelPass.of(src, 0)
    dense, dseg = dense_of(lp, occ)
    cls = classes_bounded(lp, occ, dense, dseg)
    fit = ~(cls.exact | cls.grouped)
    tried = fit & (cls.reason != REASONS["empty"]) & (cls.reason != REASONS["cut"])
    lob = lobes_bounded(lp, occ, dense, dseg, tried)
    fpc = (occ.size - CLASS_SAMPLE) / (occ.size - 1)
    for got, truth in ((sampled.lobe_tried, float(np.mean(tried))),
                       (sampled.shares[0], float(np.mean(fit & ~lob.lobe)))):
        se = np.sqrt(max(truth * (1 - truth), 1.0 / CLASS_SAMPLE) / CLASS_SAMPLE * fpc)
        assert abs(got - truth) <= 3 * se, (got, truth)
    off = stages.StageContext.create(tmp_path / "w", scene,
                                     s.model_copy(update={"lobe_class": "off"}))
    assert sampled_fitted_shares(off).lobe_tried is None
