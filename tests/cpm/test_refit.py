"""Coarse levels refitted to the dense Eq. 7 (issue 11, item 3; `texelbake.cpm.refit`): the
refitted weights against an independent brute-force Eq. 7 built with the per-texel path's
functions (`level.brdf_grid`, `level.visibility_cos`), not the batched R the refit uses."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.optimize import nnls as scipy_nnls

from schemas.settings import BakeSettings
from texelbake import stages
from texelbake.cpm.level import (
    brdf_grid,
    direction_sets,
    level_candidates,
    texel_ids,
    tile_texels,
    visibility_cos,
    world_dirs,
)
from texelbake.cpm.level_batched import fit_level
from texelbake.cpm.matrix import avis_floor, filtered_reflectance, snr_db
from texelbake.cpm.refit import (
    POOL_TEXELS,
    SHRINK_ALPHAS,
    SHRINK_FOLDS,
    dense_nnls,
    pooled_alpha,
    refit_generalizes,
    refit_to_dense,
    shrink_errors,
    shrunk_refit,
    shrunk_weights,
    validation_fold,
)
from texelbake.scenes import write_scene


@pytest.fixture(scope="module")
def two_levels(tmp_path_factory):
    d = tmp_path_factory.mktemp("refit")
    scene = write_scene("cylinder", d / "cyl.usda", "small")
    # identical_columns "keep": the tile whose pooled strength the tests below measured (0.01)
    s = BakeSettings(atlas_resolution=16, shard_texels=8, samples_per_texel=16, n_light_dirs=16,
                     n_view_dirs=16, n_heldout=64, c_max=12, n_trials=2, mesh_levels=1,
                     identical_columns="keep")
    ctx = stages.StageContext.create(d / "work", scene, s)
    stages.run_ingest(ctx, 0)
    stages.run_geometry(ctx, 0)
    src = ctx.fit_inputs()
    t0 = tile_texels(16, 8, 0, 0)
    children = fit_level(src, 0, t0, level_candidates(src, 0, t0, None))
    t1 = tile_texels(16, 8, 0, 1)
    fit = fit_level(src, 1, t1, level_candidates(src, 1, t1, children))
    return src, fit, refit_to_dense(src, 1, fit)


def _dense_system(src, texel, samples):
    """The level-1 texel's refit system from the per-texel functions (`level.brdf_grid` over
    every dense sample): (A (3, d, c) each point's Eq. 7 term over a_vis, f_ref (d, 3) the
    dense Eq. 7 over a_vis, ok (d,) rows with a_vis above its floor)."""
    dirs = direction_sets(src.settings)
    frames = src.geo["frames_L1"]
    dense = np.flatnonzero(texel_ids(src.geo, 16, 1) == texel)
    area = src.geo["sample_area"][dense]
    tex = np.full(dense.size, texel)
    wi, wo = world_dirs(frames, tex, dirs["dirs_i"]), world_dirs(frames, tex, dirs["dirs_o"])
    vi = visibility_cos(src, dense, wi)
    vo = visibility_cos(src, dense, wo, "geometric")
    live = (vi.T[:, None, :] > 0) & (vo.T[None, :, :] > 0)
    f = brdf_grid(src, dense, wi, wo, live)  # (A, B, m, 3)
    ref = np.einsum("abmc,am,bm,m->abc", f, vi.T, vo.T, area).reshape(-1, 3)
    pos = np.searchsorted(dense, samples)
    terms = np.einsum("abmc,am,bm->cabm", f[:, :, pos], vi[pos].T, vo[pos].T)
    rows = np.tile(vo.T @ area, len(dirs["dirs_i"]))
    f_ref, ok = filtered_reflectance(ref, rows, avis_floor(float(area.sum())))
    inv = np.where(ok, 1.0 / np.where(ok, rows, 1.0), 0.0)
    A = terms.reshape(3, -1, pos.size) * inv[None, :, None]
    return A, f_ref, ok


def _dense_snr(src, texel, samples, weights):
    """In-sample SNR of points (samples, weights (c, 3)) against the brute-force Eq. 7 of the
    level-1 texel on the training grid (`_dense_system`)."""
    A, f_ref, ok = _dense_system(src, texel, samples)
    return snr_db(f_ref, np.einsum("kdc,ck->dk", A, weights), ok)


def test_refit_weights_against_an_independent_dense_eq7(two_levels):
    src, fit, refit = two_levels
    v = np.flatnonzero(fit["valid"])
    assert v.size >= 4
    np.testing.assert_array_equal(refit["point_sample"], fit["point_sample"])  # same points
    assert np.all(refit["point_weight"] >= 0)
    for t in v:  # loop over a handful of texels
        a, b = fit["offsets"][t], fit["offsets"][t + 1]
        smp = fit["point_sample"][a:b]
        order = np.argsort(smp)
        before = _dense_snr(src, fit["texel"][t], smp[order],
                            fit["point_weight"][a:b][order].astype(np.float64))
        after = _dense_snr(src, fit["texel"][t], smp[order],
                           refit["point_weight"][a:b][order].astype(np.float64))
        # the reported in-sample SNR is against the dense Eq. 7 (float32 weights: 0.05 dB)
        # (an exact fit reads 150-300 dB, rounding noise: compared up to 80 dB)
        assert abs(min(after, 80.0) - min(float(refit["snr_in"][t]), 80.0)) < 0.05, (
            t, after, refit["snr_in"][t])
        # NNLS on the dense target is optimal among non-negative weights: never worse
        assert min(after, 80.0) >= min(before, 80.0) - 0.05, (t, before, after)


def test_refit_raises_the_held_out_median(two_levels):
    _, fit, refit = two_levels
    v = fit["valid"]
    # measured on the full-size bake: level 4 of the small cylinder 10.8 -> 22.9 dB
    assert np.median(refit["snr_ho"][v]) >= np.median(fit["snr_ho"][v])


def test_validation_fold_is_the_light_direction_mod_folds():
    fold = validation_fold(4, 3, 2)  # rows i * 3 + o
    assert fold.tolist() == [0] * 3 + [1] * 3 + [0] * 3 + [1] * 3
    assert validation_fold(5, 1, 4).tolist() == [0, 1, 2, 3, 0]


def _grid_problem(noise: bool):
    """A 3-channel problem on an 8 x 4 grid: column 0 is a smooth term (1 on every row), the
    other columns are one-hot on the training rows only (points that matter on the grid's
    even light directions and nowhere between them)."""
    n_i, n_o = 8, 4
    fold = validation_fold(n_i, n_o, 2)
    train = np.flatnonzero(fold == 0)
    d = n_i * n_o
    col = np.zeros((d, 1 + train.size))
    col[:, 0] = 1.0
    col[train, 1 + np.arange(train.size)] = 1.0
    A = np.repeat(col[None], 3, axis=0)  # (3, d, c)
    f = np.ones((d, 3))
    if noise:  # the dense target deviates on the training rows only
        f[train] += np.random.default_rng(0).uniform(0.1, 0.4, (train.size, 3))
    return A, f, np.ones(d, bool), fold


def test_refit_guard_refuses_weights_that_only_fit_the_grid():
    A, f, ok, fold = _grid_problem(noise=True)
    old = np.zeros((A.shape[2], 3))
    old[0] = 1.0  # the smooth term alone: exact between the grid's directions
    new = dense_nnls(A, f, ok)
    # in-sample the refit wins (it matches the training rows exactly) ...
    assert snr_db(f, np.einsum("kdc,ck->dk", A, new), ok) > snr_db(
        f, np.einsum("kdc,ck->dk", A, old), ok)
    # ... but weights fitted without the odd light directions do no better there: refused
    assert not refit_generalizes(A, f, ok, old, fold)


def test_refit_guard_accepts_weights_that_hold_between_directions():
    A, f, ok, fold = _grid_problem(noise=False)
    old = np.zeros((A.shape[2], 3))
    old[0] = 0.5  # half the smooth term: wrong everywhere
    assert refit_generalizes(A, f, ok, old, fold)
    assert refit_generalizes(A, f, ok, old, np.zeros_like(fold))  # one fold: no training rows


def test_refit_without_validation_differs_only_where_it_was_refused(two_levels):
    src, fit, plain = two_levels
    guarded = refit_to_dense(dataclasses.replace(src, settings=src.settings.model_copy(
        update={"refit_validation": True})), 1, fit)
    rej = guarded["refit_rejected"]
    assert "refit_rejected" in plain and not plain["refit_rejected"].any()
    for t in range(len(fit["texel"])):  # loop over the texels of one tile
        a, b = fit["offsets"][t], fit["offsets"][t + 1]
        want = fit["point_weight"][a:b] if rej[t] else plain["point_weight"][a:b]
        np.testing.assert_array_equal(guarded["point_weight"][a:b], want)
    # both branches are exercised on this tile (measured: 4 of 13 refused)
    assert 0 < rej.sum() < fit["valid"].sum(), (rej.sum(), fit["valid"].sum())


def _random_problem(seed: int, d_i: int = 16, n_o: int = 6, c: int = 9, noise: float = 0.05):
    """A (3, d, c) non-negative problem whose target is a positive combination of its columns
    plus noise, and a fit's weights w0 that are close to, not at, the best ones."""
    rng = np.random.default_rng(seed)
    d = d_i * n_o
    A = rng.uniform(0.0, 1.0, (3, d, c)) ** 3
    w = rng.uniform(0.0, 1.0, (c, 3)) * (rng.uniform(size=(c, 1)) < 0.7)
    f = np.einsum("kdc,ck->dk", A, w) + rng.normal(0.0, noise, (d, 3))
    w0 = np.abs(w + rng.normal(0.0, 0.2, w.shape))
    ok = rng.uniform(size=d) < 0.9
    return A, f, ok, w0, validation_fold(d_i, n_o, SHRINK_FOLDS)


def _stacked_nnls(a, f, w0, lam):
    """The shrunk least squares solved independently: scipy's NNLS on the stacked rows
    [a; sqrt(lam) I] against [f; sqrt(lam) w0]."""
    c = a.shape[1]
    M = np.vstack([a, np.sqrt(lam) * np.eye(c)])
    return scipy_nnls(M, np.concatenate([f, np.sqrt(lam) * w0]), maxiter=50 * c)[0]


# (seed, noise, view directions): measured to choose 0, 1e-3, 1e-2, 1 and inf (the fit's weights)
@pytest.mark.parametrize("seed,noise,n_o", [(0, 0.05, 6), (1, 0.05, 6), (5, 0.05, 6),
                                             (0, 0.5, 2), (1, 0.5, 2), (5, 2.0, 2)])
def test_shrunk_refit_against_a_brute_force_cross_validation(seed, noise, n_o):
    """`shrunk_refit` works in Gram space (c x c); here every fold's fit is scipy's NNLS on the
    stacked rows and every error is summed over the held-out rows themselves. The chosen
    strength must be the brute force's (its errors differ by more than the solvers'
    ~1e-9 relative disagreement, checked) and the weights equal to 1e-6 of their scale."""
    A, f, ok, w0, fold = _random_problem(seed, n_o=n_o, noise=noise)
    alphas = (*SHRINK_ALPHAS, np.inf)
    err = np.zeros(len(alphas))
    for k in np.unique(fold):  # loop over folds
        tr, va = ok & (fold != k), ok & (fold == k)
        for ch in range(3):  # loop over colour channels
            lam0 = np.mean(np.sum(A[ch][tr] ** 2, axis=0))
            for n, alpha in enumerate(alphas):  # loop over strengths
                w = w0[:, ch] if np.isinf(alpha) else _stacked_nnls(
                    A[ch][tr], f[tr, ch], w0[:, ch], alpha * lam0)
                err[n] += np.sum((A[ch][va] @ w - f[va, ch]) ** 2)
    want = len(alphas) - 1 - int(np.argmin(err[::-1]))
    gap = np.sort(err)[1] - np.sort(err)[0]
    assert gap > 1e-6 * err.min()  # a clear winner: the comparison below is not a coin toss
    got_w, got_alpha = shrunk_refit(A, f, ok, w0, fold)
    assert got_alpha == alphas[want], (got_alpha, err)
    for ch in range(3):  # loop over colour channels
        lam0 = np.mean(np.sum(A[ch][ok] ** 2, axis=0))
        w = w0[:, ch] if np.isinf(alphas[want]) else _stacked_nnls(
            A[ch][ok], f[ok, ch], w0[:, ch], alphas[want] * lam0)
        np.testing.assert_allclose(got_w[:, ch], w, atol=1e-6 * max(1.0, np.abs(w).max()))


def test_shrunk_refit_keeps_the_fit_where_the_refit_only_fits_the_grid():
    """The guard's toy (points that matter on the even light directions only, a target that
    deviates there only): the unshrunk refit fits the deviations; the cross-validation, which
    sees the odd light directions, keeps the smooth term's weight and leaves the one-hot
    points near zero (the plain refit gives them the deviations, 0.1-0.4)."""
    A, f, ok, _ = _grid_problem(noise=True)
    fold = validation_fold(8, 4, SHRINK_FOLDS)
    old = np.zeros((A.shape[2], 3))
    old[0] = 1.0
    w, alpha = shrunk_refit(A, f, ok, old, fold)
    plain = dense_nnls(A, f, ok)
    assert alpha > 0  # not the plain refit
    assert np.abs(w[1:]).max() < 0.5 * np.abs(plain[1:]).max(), (alpha, w[1:].max())


def test_pooled_alpha_sums_the_texels_relative_errors():
    """By hand: texel 1 alone prefers alpha 0, texel 2 alone 1e-1; summed, 1e-2 wins. Ties go
    to the stronger shrink (the fit's weights first), and so does an empty pool."""
    inf = np.inf
    e = np.array([[0.10, 0.20, 0.30, 0.40, 0.50, 0.60],
                  [0.90, 0.80, 0.25, 0.20, 0.60, 0.70]])  # sums 1.0 1.0 0.55 0.6 1.1 1.3
    assert (pooled_alpha(e[:1]), pooled_alpha(e[1:]), pooled_alpha(e)) == (0.0, 0.1, 0.01)
    assert pooled_alpha(np.full((1, 6), 0.5)) == inf
    tie = np.array([[0.3, 0.3, 0.3, 0.2, 0.2, 0.9]])
    assert pooled_alpha(tie) == 1.0
    assert pooled_alpha(np.zeros((0, 6))) == inf


def test_refit_shrink_and_refit_validation_are_exclusive():
    with pytest.raises(ValueError, match="refit_shrink and refit_validation"):
        BakeSettings(coarse_target="dense", refit_shrink=True, refit_validation=True)


def test_shrunk_refit_in_the_stage_raises_the_dense_in_sample_snr(two_levels):
    """On a real level: the shrunk weights' in-sample SNR against the brute-force dense Eq. 7
    (`_dense_snr`, the per-texel functions) is never below the fit's weights' (the penalty is
    0 at the fit's weights), a texel whose strength is infinite keeps the fit's weights
    exactly, and the points do not move."""
    src, fit, _ = two_levels
    shrunk = refit_to_dense(dataclasses.replace(src, settings=src.settings.model_copy(
        update={"refit_shrink": True})), 1, fit)
    np.testing.assert_array_equal(shrunk["point_sample"], fit["point_sample"])
    alpha = shrunk["refit_alpha"]
    v = np.flatnonzero(fit["valid"] & (np.diff(fit["offsets"]) > 0))
    assert np.all(np.isin(alpha[v], np.float32((*SHRINK_ALPHAS, np.inf))))
    assert len(v) <= POOL_TEXELS and np.unique(alpha[v]).size == 1  # one pool: one strength
    for t in v:  # loop over the texels of one tile
        a, b = fit["offsets"][t], fit["offsets"][t + 1]
        pts = fit["point_sample"][a:b]
        before = _dense_snr(src, fit["texel"][t], pts, fit["point_weight"][a:b])
        after = _dense_snr(src, fit["texel"][t], pts, shrunk["point_weight"][a:b])
        assert after >= before - 1e-3, (t, before, after)
        if np.isinf(alpha[t]):
            np.testing.assert_array_equal(shrunk["point_weight"][a:b], fit["point_weight"][a:b])


def test_the_stage_pools_its_texels_strength_as_an_independent_computation(two_levels):
    """The stage's two passes against one computation from the per-texel functions: every
    texel's cross-validation errors from its brute-force system (`_dense_system`), pooled by
    `pooled_alpha`, must choose the stage's strength, and the weights that strength gives on the
    brute-force system must reach the stage's in-sample SNR (0.05 dB: float32 weights)."""
    src, fit, _ = two_levels
    shrunk = refit_to_dense(dataclasses.replace(src, settings=src.settings.model_copy(
        update={"refit_shrink": True})), 1, fit)
    v = np.flatnonzero(fit["valid"] & (np.diff(fit["offsets"]) > 0))
    fold = validation_fold(*(len(direction_sets(src.settings)[k]) for k in ("dirs_i", "dirs_o")),
                           SHRINK_FOLDS)
    systems, errors = {}, []
    for t in v:  # loop over the texels of one tile
        a, b = fit["offsets"][t], fit["offsets"][t + 1]
        systems[t] = _dense_system(src, fit["texel"][t], fit["point_sample"][a:b])
        A, f_ref, ok = systems[t]
        if ok.any():
            errors.append(shrink_errors(A, f_ref, ok, fit["point_weight"][a:b].astype(np.float64),
                                        fold))
    alpha = pooled_alpha(np.array(errors))
    assert np.isfinite(alpha)  # measured 0.01 on this tile: the weights move
    np.testing.assert_array_equal(shrunk["refit_alpha"][v], np.float32(alpha))
    for t in v:  # loop over the texels of one tile
        a, b = fit["offsets"][t], fit["offsets"][t + 1]
        A, f_ref, ok = systems[t]
        old = fit["point_weight"][a:b].astype(np.float64)
        w = shrunk_weights(A, f_ref, ok, old, alpha)
        want = max(snr_db(f_ref, np.einsum("kdc,ck->dk", A, w), ok),
                   snr_db(f_ref, np.einsum("kdc,ck->dk", A, old), ok))  # the stage keeps the better
        got = snr_db(f_ref, np.einsum("kdc,ck->dk", A, shrunk["point_weight"][a:b]
                                      .astype(np.float64)), ok)
        assert abs(min(got, 80.0) - min(want, 80.0)) < 0.05, (t, got, want)


def test_the_level_report_counts_texels_per_strength():
    """report.json's `refit_alpha` per level: texels per chosen strength, by hand; texels not
    shrunk (nan) are not counted."""
    from texelbake.cpm.assemble import _alpha_counts

    a = np.float32([0.01, np.inf, 0.01, np.nan, 0.0, 1e-3])
    assert _alpha_counts(a) == {"0": 1, "0.001": 1, "0.01": 2, "inf": 1}
    assert _alpha_counts(np.float32([np.nan])) == {}
