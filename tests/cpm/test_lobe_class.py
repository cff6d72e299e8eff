"""The lobe class (`texelbake.cpm.lobe_class`, BakeSettings.lobe_class="validated"): a curved
glossy texel stored as a few widened lobes without the seed's fit, measured on the held-out
pairs (brute-force Eq. 7 over its dense samples); and each hard case's behaviour: a shadow
edge, two materials, normals past 90 degrees, a single sample, a flat texel (exact before),
the memory chunks, the coarser level that reads the lobes' variances, and the setting off.

The scenes are test_classify's 2 x 2 square, its normals turned about y as a cylinder's strip
(`_strip`), 64 samples per texel."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from schemas.settings import BakeSettings
from tests.cpm.test_classify import SETTINGS, _grid_samples, _inputs, _walled
from texelbake.cpm.classify import REASONS
from texelbake.cpm.dense import LevelPass, dense_of
from texelbake.cpm.level import FitInputs, level_candidates
from texelbake.cpm.level_batched import fit_level_batched
from texelbake.cpm.level_by_need import EXACT_SKIP, LOBE_SKIP, fit_level_by_need
from texelbake.cpm.lobe_class import lobe_texels, lobes_bounded
from texelbake.model import Material

GLOSS = Material("/m/gloss", "preview", {"diffuseColor": (0.2, 0.2, 0.2), "roughness": 0.3})
RED = Material("/m/red", "preview", {"diffuseColor": (0.8, 0.1, 0.1), "roughness": 0.3})
TEXELS = np.arange(4, dtype=np.int64)


def _strip(turn: float, mesh=None, materials=(GLOSS,), mat=None, lobes: str = "validated",
           **update) -> FitInputs:
    """The square with its shading and geometric normals turning about y by `turn` rad across
    it (a cylinder's strip seen flat), 64 samples per texel in 8 columns of one normal each:
    with c_max 4 more facets than a grouped texel may hold, as a smooth-shaded mesh's."""
    pos = _grid_samples(8)
    a = turn * (pos[:, 0] - 0.5)
    nrm = np.stack([np.sin(a), np.zeros_like(a), np.cos(a)], axis=1)
    kw = {} if mesh is None else {"mesh": mesh}
    src = _inputs(pos, nrm, materials=materials, mat=mat, **kw)
    return dataclasses.replace(src, settings=SETTINGS.model_copy(update={
        "lobe_class": lobes, "c_max": 4, **update}))


def _by_need(src: FitInputs) -> dict[str, np.ndarray]:
    return fit_level_by_need(src, 0, TEXELS, level_candidates(src, 0, TEXELS, None),
                             lambda t, c: fit_level_batched(src, 0, t, c))


def _lobes(src: FitInputs, tried=None):
    lp = LevelPass.of(src, 0)
    dense, dseg = dense_of(lp, TEXELS)
    return lobe_texels(lp, TEXELS, dense, dseg,
                       np.ones(4, bool) if tried is None else tried)


def test_curved_glossy_texels_are_lobes_measured_on_the_held_out_pairs():
    """A gently curved strip (0.1 rad across the square, 0.05 rad across a texel) of a glossy
    dielectric: every texel is a lobe of at most 16 points, fewer than its 64 samples, with
    widened lobes (variance > 0) and non-negative weights; the held-out pairs, which neither
    the weights' fit pairs nor the validation pairs share, measure each at least 25 dB (the
    validation threshold eps_db, 30 dB, less 5 dB: 8 x 8 validation pairs are a small sample
    of the directions; measured 34.5 and 44.0 dB)."""
    src = _strip(0.1)
    lob = _lobes(src)
    assert lob.lobe.all()
    counts = np.diff(lob.offsets)
    assert np.all((counts >= 1) & (counts <= 16))
    assert np.all(lob.var > 0) and np.all(lob.weights >= 0)
    assert np.all(lob.snr_val >= src.settings.eps_db)
    out = _by_need(src)
    assert np.all(out["skip"] == LOBE_SKIP)
    assert np.array_equal(out["c"], counts) and "point_var" in out
    np.testing.assert_array_equal(out["point_var"], lob.var.astype(np.float32))
    assert np.all(out["snr_ho"] >= 25.0)


def test_strong_curvature_goes_to_the_fit():
    """Normals turning 1 rad across the square (0.5 rad, 29 degrees, across a texel) are not a
    few lobes to eps_db on the validation pairs: those texels are fitted (tried, validation
    SNR below eps_db, not stored)."""
    src = _strip(1.0)
    lob = _lobes(src)
    assert not lob.lobe.any()
    assert np.all(lob.snr_val < src.settings.eps_db)
    out = _by_need(src)
    assert not np.any(out["skip"] == LOBE_SKIP) and out["valid"].all()


def test_a_shadow_edge_is_not_a_lobe():
    """A tall wall at x = 0.3 splits texels 0 and 2 into samples that see the -x half of the
    sky and samples that do not: the visibility-pattern rule refuses them on its own (half
    the light's directions split, found by the samples' own rays), and their lobes miss
    eps_db on the fit pairs anyway; texels 1 and 3, all right of the wall, have one pattern
    and are lobes."""
    from texelbake.cpm.lobe_class import _one_pattern

    src = _strip(0.1, mesh=_walled(100.0, -100.0, 100.0))
    lob = _lobes(src)
    assert list(lob.lobe) == [False, True, False, True]
    assert np.all(lob.snr_val[[0, 2]] < src.settings.eps_db)
    lp = LevelPass.of(src, 0)
    dense, dseg = dense_of(lp, TEXELS)
    mean = np.tile([0.0, 0.0, 1.0], (4, 1))
    assert list(_one_pattern(lp, TEXELS, dense, dseg, np.ones(4, bool), mean)) == \
        [False, True, False, True]
    out = _by_need(src)
    assert list(out["skip"] == LOBE_SKIP) == [False, True, False, True]


def test_a_grazing_shadow_edge_is_allowed_and_weighed_by_its_light():
    """A low wall (0.1 high) beyond the square at x = -0.5 shadows the samples nearest it on
    the grid's view direction 6 degrees above the horizon toward -x, and not the far ones:
    texels 0 and 2 hold two visibility patterns there (counted here direction by direction
    with the samples' own rays), but that direction's share of their light (sum of
    (n_mean . w)+ over the split directions against over all the grid's) is under
    10^(-eps_db/20): the texels are still tried, and the validation pairs decide (the wall
    shadows some of those too, near the horizon: texels 0 and 2 measure 26.7 dB there and are
    fitted, 1 and 3 are kept)."""
    from texelbake.cpm.level import visibility_cos, world_dirs
    from texelbake.cpm.lobe_class import _one_pattern

    p, f = _walled(0.1, -100.0, 100.0)
    p = p.copy()
    p[4:, 0] = -0.5
    src = _strip(0.1, mesh=(p, f))
    lp = LevelPass.of(src, 0)
    dense, dseg = dense_of(lp, TEXELS)
    mean = np.tile([0.0, 0.0, 1.0], (4, 1))
    share = np.zeros(4)
    for t in range(4):  # loop over texels and directions: the reference count
        smp = dense[dseg == t]
        split, total = 0.0, 0.0
        for key, cosine in (("dirs_i", "shading"), ("dirs_o", "geometric")):
            for d in lp.dirs[key]:
                w = world_dirs(lp.frames, np.array([t]), d[None])[0, 0]
                lit = visibility_cos(src, smp, np.tile(w, (len(smp), 1, 1)), cosine)[:, 0] > 0
                above = src.geo["sample_nrm"][smp] @ w > 0
                split += max(w[2], 0.0) * float(lit.any() and (above & ~lit).any())
                total += max(w[2], 0.0)
        share[t] = split / total
    assert share[0] > 0 and share[2] > 0
    assert np.all(share < 10 ** (-src.settings.eps_db / 20))
    assert _one_pattern(lp, TEXELS, dense, dseg, np.ones(4, bool), mean).all()
    lob = _lobes(src)
    assert np.isfinite(lob.snr_val).all()
    np.testing.assert_array_equal(lob.lobe, lob.snr_val >= src.settings.eps_db)
    assert list(lob.lobe) == [False, True, False, True]


def test_two_materials_and_a_single_sample():
    """A texel holding two materials is not a lobe (each would need its own); a texel of one
    sample holds one normal and one facet: exact, never tried as a lobe."""
    pos = _grid_samples(8)
    mat = ((pos[:, 0] > 0.25) & (pos[:, 0] < 0.5) & (pos[:, 1] < 0.5)).astype(np.int64)
    src = _strip(0.1, materials=(GLOSS, RED), mat=mat)
    lob = _lobes(src)
    assert list(lob.lobe) == [False, True, True, True]
    assert np.isnan(lob.snr_val[0])
    one = _inputs(np.array([[0.25, 0.25, 0.0]]), np.array([[0.0, 0.0, 1.0]]),
                  materials=(GLOSS,))
    one = dataclasses.replace(one, settings=SETTINGS.model_copy(
        update={"lobe_class": "validated"}))
    out = fit_level_by_need(one, 0, np.zeros(1, np.int64),
                            level_candidates(one, 0, np.zeros(1, np.int64), None),
                            lambda t, c: fit_level_batched(one, 0, t, c))
    assert list(out["skip"]) == [EXACT_SKIP]


def test_normals_past_90_degrees_are_not_tried(monkeypatch):
    """A texel whose samples' normals turn past 90 degrees from their mean (a quarter of them
    facing down: a fold back on itself) is fitted without a lobe tried, before any ray: its
    slope is unbounded."""
    from texelbake.cpm import lobe_class

    pos = _grid_samples(8)
    nrm = np.tile([0.0, 0.0, 1.0], (len(pos), 1))
    nrm[(pos[:, 0] < 0.1) & (pos[:, 1] < 0.5)] = [0.0, 0.0, -1.0]
    src = _inputs(pos, nrm, materials=(GLOSS,))
    src = dataclasses.replace(src, settings=SETTINGS.model_copy(
        update={"lobe_class": "validated", "c_max": 1}))
    seen = []
    inner = lobe_class._one_pattern
    monkeypatch.setattr(lobe_class, "_one_pattern",
                        lambda *a: seen.append(a[4].copy()) or inner(*a))
    lob = _lobes(src, tried=np.array([True, True, False, False]))
    assert not lob.lobe[0] and np.isnan(lob.snr_val[0])
    assert list(seen[0]) == [False, True, False, False]  # texel 1 (flat) goes on


def test_flat_texels_stay_exact_and_the_setting_off_fits_curved_ones():
    """A flat texel is exact before any lobe is tried; with lobe_class "off" the curved strip
    is fitted and, with the seed's narrow lobes, the level carries no lobe variance."""
    flat = _strip(0.0)
    assert np.all(_by_need(flat)["skip"] == EXACT_SKIP)
    off = _by_need(_strip(0.1, lobes="off", point_lobe="narrow"))
    assert not np.any(off["skip"] == LOBE_SKIP) and "point_var" not in off


def test_lobes_do_not_depend_on_the_memory_chunks(monkeypatch):
    """`lobes_bounded` with one texel per chunk gives the lobes of one chunk, bit for bit."""
    from texelbake.cpm import lobe_class

    src = _strip(0.1, mesh=_walled(100.0, -100.0, 100.0))
    lp = LevelPass.of(src, 0)
    dense, dseg = dense_of(lp, TEXELS)
    tried = np.ones(4, bool)
    whole = lobes_bounded(lp, TEXELS, dense, dseg, tried)
    monkeypatch.setattr(lobe_class, "BYTES_PER_LOBE_ENTRY", 10**12)
    parts = lobes_bounded(lp, TEXELS, dense, dseg, tried)
    for f in dataclasses.fields(whole):
        np.testing.assert_array_equal(getattr(whole, f.name), getattr(parts, f.name))
    assert whole.lobe.sum() == 2


def test_the_coarser_level_reads_the_lobes_variances():
    """Level 1 (the square's one texel, fitted: classed_levels 1) takes its children's points
    as candidates with their lobe variances: its points keep the variance of the child point
    they are, and its held-out SNR is measured. Classed (classed_levels 2), it holds no
    lobe: only the finest level is tried."""
    src = _strip(0.1, classed_levels=1)
    from texelbake.stages.cpm import fit_level

    fine = fit_level(src, 0, TEXELS, level_candidates(src, 0, TEXELS, None))
    assert np.all(fine["skip"] == LOBE_SKIP)
    one = np.zeros(1, np.int64)
    cands = level_candidates(src, 1, one, fine)
    assert cands.var is not None and np.all(cands.var > 0)
    coarse = fit_level(src, 1, one, cands)
    assert "point_var" in coarse and coarse["valid"].all()
    var_of = dict(zip(fine["point_sample"].tolist(), fine["point_var"].tolist(), strict=True))
    assert [var_of[int(p)] for p in coarse["point_sample"]] == coarse["point_var"].tolist()
    assert np.isfinite(coarse["snr_ho"]).all()
    # a classed coarser level is not tried: only the finest level holds lobes
    src2 = _strip(0.1, classed_levels=2)
    classed = fit_level(src2, 1, one, level_candidates(src2, 1, one, fine))
    assert "classed" in classed and not np.any(classed["skip"] == LOBE_SKIP)


def test_lobes_need_the_batched_classed_fit():
    """The lobe class is a class of the classed texels of the batched fit: other settings are
    refused, naming the fields."""
    with pytest.raises(ValueError, match="lobe_class 'validated' needs fit_method 'batched'"):
        BakeSettings(lobe_class="validated", fit_method="per_texel")
    with pytest.raises(ValueError, match="texel_classes 'by_need'"):
        BakeSettings(lobe_class="validated", texel_classes="points")
    assert REASONS["exact"] == 0


def test_the_report_counts_the_lobe_class():
    """The level's report entry counts the lobe texels with their mean points and held-out
    SNR, and the cost model's fitted share leaves them out (no fit); a level without lobe
    texels (lobe_class off) has no such entry."""
    from texelbake.cpm.assemble import _classes as report_classes
    from texelbake.cpm.assemble import fitted_shares

    out = _by_need(_strip(0.1))
    rep = report_classes(out, out["valid"].astype(bool))
    assert rep["lobe"]["texels"] == 4 and rep["points"]["texels"] == 0
    assert rep["lobe"]["points_mean"] == float(np.mean(out["c"]))
    assert rep["lobe"]["snr_heldout_db"]["p50"] >= 25.0
    assert fitted_shares([out]) == [0.0]
    off = _by_need(_strip(0.1, lobes="off"))
    assert "lobe" not in report_classes(off, off["valid"].astype(bool))
    assert fitted_shares([off]) == [1.0]


def test_a_texel_not_tried_among_tried_ones_raises_no_floating_point_warning():
    """A chunk's texel that is not tried and holds no sample has a zero mean normal, hence no
    tangent frame: its rows are never read, and building the chunk's frames must not divide
    0 by 0 (a RuntimeWarning per chunk before)."""
    import warnings

    from texelbake.cpm.lobe_class import _quadrant_points

    mean = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 0.0]])
    nrm = np.array([[0.1, 0.0, 0.995], [0.0, 0.1, 0.995]])
    dseg = np.zeros(2, np.int64)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        pts, cell = _quadrant_points(nrm, mean, nrm, mean, dseg, np.arange(2), np.arange(2))
    assert pts.size == 2 and np.isfinite(cell).all()
