"""Identical candidate columns fitted as one (`texelbake.cpm.gram.identical`, issue 15 item 3): the
grouping against a brute-force comparison of every pair of columns, Table 2's probabilities of
the merged columns against the seed's summed over each group (from full SVDs, not the Gram
route), and fit_many's merged fits against Eq. 7 over every candidate."""

from __future__ import annotations

import numpy as np
import pytest

from texelbake.cpm.column_sampling import column_probabilities, energy_rank
from texelbake.cpm.fit import channel_correlation
from texelbake.cpm.gram.fit import GramTexel, fit_many
from texelbake.cpm.gram.identical import PRINT_TAPS, identical_columns
from texelbake.cpm.matrix import snr_db
from texelbake.cpm.texel_fit import FitCounts, FitParams

KW = {"psi": 0.97, "eps_db": 30.0, "c_max": 24, "n_trials": 3, "weights": "nnls",
      "colour": "auto", "decorrelation_threshold": 0.9}


def _fit_many(Fs, valids, corrs, seeds, counts=None, **params):
    """`fit_many` of texels given as parallel lists, FitParams from keywords."""
    texels = [GramTexel(F, v, c, s) for F, v, c, s in zip(Fs, valids, corrs, seeds, strict=True)]
    return fit_many(texels, FitParams(**params), counts)


def _duplicated(rng, d, u, m, rank=6):
    """F (3, m, d) whose m columns are copies of u distinct ones (each used at least once),
    in shuffled order, and the group of each column."""
    U = rng.random((d, rank))
    V = rng.random((rank, u, 1)) * np.array([0.7, 0.5, 0.3]) + 0.02 * rng.random((rank, u, 3))
    R = np.einsum("dk,kuc->cud", U, V) + 1e-3 * rng.random((3, u, d))
    group = rng.permutation(np.r_[np.arange(u), rng.integers(0, u, m - u)])
    return np.ascontiguousarray(R[:, group]), group


def _brute_groups(F):
    """Partition of the columns by exact equality, pair by pair (the independent method)."""
    m = F.shape[1]
    label = -np.ones(m, np.int64)
    for j in range(m):  # loop over columns: a test's brute force
        if label[j] < 0:
            eq = np.all(F == F[:, j:j + 1], axis=(0, 2))
            label[eq & (label < 0)] = j
    return label


def test_identical_columns_are_the_exact_partition():
    rng = np.random.default_rng(1)
    F, _ = _duplicated(rng, 256, 30, 90)
    # a column equal to another at every fingerprint tap but not elsewhere: never merged
    taps = np.unique(np.linspace(0, 255, PRINT_TAPS).astype(np.int64))
    off = np.setdiff1d(np.arange(256), taps)[7]
    F = np.concatenate([F, F[:, :1].copy()], axis=1)
    F[1, -1, off] += 1e-9
    merge = identical_columns(F, seed=4)
    assert merge is not None
    label = _brute_groups(F)
    assert merge.rep.size == np.unique(label).size == 31
    assert merge.count.sum() == F.shape[1]
    firsts = np.unique(label)  # groups in order of their first member
    for g, (rep, k) in enumerate(zip(merge.rep, merge.count, strict=True)):
        assert label[rep] == firsts[g]
        assert k == np.count_nonzero(label == label[rep])
    again = identical_columns(F, seed=4)
    np.testing.assert_array_equal(again.rep, merge.rep)
    other = identical_columns(F, seed=5)  # another texel's seed: other members, same groups
    np.testing.assert_array_equal(label[other.rep], label[merge.rep])
    assert identical_columns(np.random.default_rng(2).random((3, 40, 64)), seed=0) is None


def test_merged_probabilities_are_the_seeds_summed_over_each_group():
    """Table 2 on the merged columns sqrt(k) f (SVD of the merged selection matrix) equals the
    seed's probabilities on every candidate (SVD of the full one) summed over each group, and
    the psi rank is the same: the draws of groups are distributed as the seed's."""
    rng = np.random.default_rng(3)
    F, _ = _duplicated(rng, 300, 25, 80)
    lw = np.array([0.2126, 0.7152, 0.0722])
    S = np.tensordot(lw, F, axes=(0, 0)).T  # (d, m)
    merge = identical_columns(F, seed=0)
    Su = S[:, merge.rep] * merge.scale
    label = _brute_groups(F)
    for M in (S, Su):
        assert np.isfinite(M).all()
    U, s, Vt = np.linalg.svd(S, full_matrices=False)
    Uu, su, Vtu = np.linalg.svd(Su, full_matrices=False)
    k = energy_rank(s, 0.9999, float((S * S).sum()))
    assert k == energy_rank(su, 0.9999, float((Su * Su).sum())) >= 2
    p = column_probabilities(U, s, Vt, k, col_energy=(S * S).sum(axis=0))
    pu = column_probabilities(Uu, su, Vtu, k, col_energy=(Su * Su).sum(axis=0))
    summed = np.array([p[label == label[r]].sum() for r in merge.rep])
    # the residual term ||f||^2 - ||(R_k)_j||^2 cancels: two SVDs agree to ~1e-8 there, not 1e-15
    np.testing.assert_allclose(pu, summed, rtol=1e-6, atol=1e-12)


@pytest.mark.parametrize("decorrelate", [False, True])
def test_merged_fit_reproduces_eq7_over_every_candidate(decorrelate):
    rng = np.random.default_rng(7)
    F, _ = _duplicated(rng, 300, 40, 120)
    if decorrelate:
        F[1] *= 1.0 + 2.0 * rng.random((1, 300))
    valid = np.ones(300, bool)
    valid[:3] = False
    F[:, :, :3] = 0.0
    R = F.transpose(2, 1, 0)
    counts = FitCounts()
    got = _fit_many([F], [valid], [channel_correlation(R)], [9], counts, identical="merge", **KW)
    again = _fit_many([F], [valid], [channel_correlation(R)], [9], counts, identical="merge",
                      **KW)
    assert counts.merged_columns == 2 * 80 and counts.merged_texels == 2
    (fit, skip), (fit2, _) = got[0], again[0]
    assert skip == "" and fit.c >= 1
    np.testing.assert_array_equal(fit.columns, fit2.columns)
    np.testing.assert_array_equal(fit.weights, fit2.weights)
    label = _brute_groups(F)
    assert np.unique(label[fit.columns]).size == fit.c  # no point stored twice
    target = F.sum(axis=1).T  # (d, ch): Eq. 7 over every candidate
    approx = np.stack([fit.weights[:, c].astype(np.float64) @ F[c, fit.columns]
                       for c in range(3)], axis=1)
    assert fit.snr_db_insample == pytest.approx(snr_db(target, approx, valid), abs=1e-9)


def test_a_texel_of_few_distinct_columns_keeps_them_all_exactly():
    """small="all" counts distinct columns: 60 candidates of 10 distinct ones (c_max 24) keep
    the 10, each at its group's size, which is Eq. 7 exactly (not a 24-point fit)."""
    rng = np.random.default_rng(11)
    F, _ = _duplicated(rng, 200, 10, 60, rank=10)
    valid = np.ones(200, bool)
    R = F.transpose(2, 1, 0)
    (fit, skip), = _fit_many([F], [valid], [channel_correlation(R)], [3], identical="merge", small="all", **KW)
    label = _brute_groups(F)
    assert skip == "all" and fit.c == 10
    sizes = np.array([np.count_nonzero(label == label[j]) for j in fit.columns])
    np.testing.assert_array_equal(fit.weights, np.repeat(sizes[:, None], 3, 1))
    assert fit.snr_db_insample > 120.0
    (kept, _), = _fit_many([F], [valid], [channel_correlation(R)], [3], identical="keep", small="all", **KW)
    assert kept.c <= KW["c_max"]  # the seed's route fits 60 > c_max columns


def test_no_identical_columns_is_the_seeds_fit_bit_for_bit():
    rng = np.random.default_rng(17)
    F = rng.random((3, 50, 200))
    valid = np.ones(200, bool)
    R = F.transpose(2, 1, 0)
    a = _fit_many([F], [valid], [channel_correlation(R)], [2], identical="merge", **KW)[0][0]
    b = _fit_many([F], [valid], [channel_correlation(R)], [2], **KW)[0][0]
    np.testing.assert_array_equal(a.columns, b.columns)
    np.testing.assert_array_equal(a.weights, b.weights)


def test_a_merged_level_stores_eq7_where_it_reports_it_exact(tmp_path):
    """A level fitted with identical_columns="merge" on a scene with flat, unoccluded caps: it
    merges, records what it merged, and a texel it reports exact on the grid (every distinct
    column kept, or a fit at >= 100 dB) stores points whose weighted R (rebuilt from the stored
    sample ids, `build_R`) is the R of every candidate summed, to float32 rounding."""
    from schemas.settings import BakeSettings
    from texelbake import stages
    from texelbake.cpm import level_batched as lb
    from texelbake.cpm.build_r import build_R
    from texelbake.cpm.dense import LevelPass
    from texelbake.cpm.level import direction_sets, level_candidates, tile_texels
    from texelbake.testscenes import write_scene

    scene = write_scene("cylinder", tmp_path / "cyl.usda", "small")
    s = BakeSettings(atlas_resolution=16, shard_texels=8, samples_per_texel=16, n_light_dirs=16,
                     n_view_dirs=16, n_heldout=16, c_max=12, n_trials=2, mesh_levels=1,
                     identical_columns="merge", small_texels="all")
    ctx = stages.StageContext.create(tmp_path / "work", scene, s)
    stages.run_ingest(ctx, 0)
    stages.run_geometry(ctx, 0)
    src = ctx.fit_inputs()
    texels = tile_texels(16, 8, 0, 0)
    cands = level_candidates(src, 0, texels, None)
    out = lb.fit_level_batched(src, 0, texels, cands)
    again = lb.fit_level_batched(src, 0, texels, cands)
    for k in out:
        np.testing.assert_array_equal(out[k], again[k], err_msg=k)
    merged = out["merged"]
    assert merged.sum() > 0
    dirs = direction_sets(s)
    frames = src.geo["frames_L0"]
    checked = 0
    for i in np.flatnonzero(out["valid"] & (merged > 0) & (out["snr_in"] >= 100.0)):
        mine = np.flatnonzero(cands.texel == out["texel"][i])
        R_all = build_R(LevelPass(src, 0, frames, dirs, 1 << 26), cands.take(mine)).sum(axis=1)
        a, b = out["offsets"][i], out["offsets"][i + 1]
        pts = out["point_sample"][a:b]
        order = np.argsort(cands.sample[mine])  # the stored points among the candidates
        at = order[np.searchsorted(cands.sample[mine][order], pts)]
        assert np.array_equal(cands.sample[mine][at], pts)
        R_pts = build_R(LevelPass(src, 0, frames, dirs, 1 << 26), cands.take(mine[at]))
        alpha = out["point_weight"][a:b].astype(np.float64) / cands.weight[mine[at]]
        approx = np.einsum("cpd,pc->cd", R_pts, alpha)
        np.testing.assert_allclose(approx, R_all, rtol=1e-5, atol=1e-6 * np.abs(R_all).max())
        assert b - a < len(mine)  # fewer points than candidates
        checked += 1
    assert checked >= 3


def test_the_report_counts_what_was_merged_by_hand():
    from texelbake.cpm.assemble import _merged

    data = {"merged": np.array([0, 5, 0, 2, 7], np.int32),
            "snr_ho": np.array([10.0, 20.0, 30.0, np.inf, 40.0], np.float32)}
    valid = np.array([True, True, True, True, False])
    got = _merged(data, valid)
    assert got["texels"] == 2 and got["candidates"] == 7
    assert got["snr_heldout_db"]["n"] == 2 and got["snr_heldout_db"]["max"] > 100.0
    assert _merged({"snr_ho": data["snr_ho"]}, valid) == {}
