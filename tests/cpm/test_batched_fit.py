"""The batched CPM fit (issue 15) against the per-texel path, its second method: the Gram-space
fit of many texels (`gram.fit.fit_many`) against `fit.fit_texel` on R itself, the product BRDF
grid against `level.brdf_grid`, a level fitted batched against the per-texel loop, the memory
bound not changing a result."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from schemas.settings import BakeSettings
from texelbake import stages
from texelbake.cpm import level_batched as lb
from texelbake.cpm.brdf_product import brdf_product
from texelbake.cpm.build_r import build_R
from texelbake.cpm.fit import channel_correlation, fit_texel
from texelbake.cpm.gram import linalg as gram_linalg
from texelbake.cpm.gram.fit import GramTexel, fit_many
from texelbake.cpm.gram.linalg import batched_eigh
from texelbake.cpm.level import (
    brdf_grid,
    direction_sets,
    level_candidates,
    texel_dirs,
    tile_texels,
    visibility_cos,
    world_dirs,
)
from texelbake.cpm.level_batched import chunk_bounds, fit_level_batched
from texelbake.cpm.level_per_texel import fit_level_per_texel
from texelbake.cpm.texel_fit import FitParams
from texelbake.testscenes import write_scene

KW = {"psi": 0.97, "eps_db": 30.0, "c_max": 24, "n_trials": 3, "weights": "nnls", "colour": "auto",
          "decorrelation_threshold": 0.9}


def _fit_many(Fs, valids, corrs, seeds, counts=None, **params):
    """`fit_many` of texels given as parallel lists, FitParams from keywords."""
    texels = [GramTexel(F, v, c, s) for F, v, c, s in zip(Fs, valids, corrs, seeds, strict=True)]
    return fit_many(texels, FitParams(**params), counts)


def _fit_texel(R, avis, seed=0, texel_area=None, rows="eq7", **params):
    """`fit_texel` with FitParams from keywords."""
    return fit_texel(R, avis, FitParams(**params), seed=seed, texel_area=texel_area, rows=rows)


def _texel(rng, d, m, rank, decorrelate):
    U = rng.random((d, rank))
    V = rng.random((rank, m, 1)) * np.array([0.7, 0.5, 0.3]) + 0.02 * rng.random((rank, m, 3))
    R = np.einsum("dk,kmc->dmc", U, V) + 1e-3 * rng.random((d, m, 3))
    if decorrelate:
        R[:, :, 1] *= rng.random((1, m)) * 3
    avis = 0.5 + rng.random(d)
    avis[:3] = 0.0  # masked rows: excluded from fit and SNR on both paths
    return R, avis


def _F(R, avis):
    valid = avis > 1e-9
    inv = np.where(valid, 1.0 / np.where(valid, avis, 1.0), 0.0)
    return np.ascontiguousarray((R * inv[:, None, None]).transpose(2, 1, 0)), valid


@pytest.mark.parametrize("decorrelate", [False, True])
def test_gram_fit_of_many_texels_equals_fit_texel(decorrelate):
    """Second method: fit_texel selects and fits on R (d x m) itself; fit_many only sees the
    texels' Grams, stacked with texels of other sizes. Same draws (same seed), same bisection:
    same points, weights equal to rounding (float32 storage), same in-sample SNR."""
    rng = np.random.default_rng(3)
    texels = [_texel(rng, 300, m, r, decorrelate) for m, r in ((40, 6), (25, 4), (40, 9), (60, 12))]
    Fs, valids = zip(*[_F(R, a) for R, a in texels], strict=True)
    got = _fit_many(list(Fs), list(valids), [channel_correlation(R) for R, _ in texels],
                   [11, 12, 13, 14], **KW)
    for (R, avis), seed, (fit, skip) in zip(texels, [11, 12, 13, 14], got, strict=True):
        ref = _fit_texel(R, avis, seed=seed, texel_area=1.0, **KW)
        assert skip == ""
        assert fit.colour_mode == ref.colour_mode == ("per_channel" if decorrelate else "luminance")
        np.testing.assert_array_equal(fit.columns, ref.columns)
        np.testing.assert_allclose(fit.weights, ref.weights, rtol=1e-5, atol=0)
        assert fit.k == ref.k and fit.c == ref.c
        assert abs(fit.snr_db_insample - ref.snr_db_insample) < 1e-6


@pytest.mark.parametrize("decorrelate", [False, True])
def test_top_eigenpairs_fit_equals_fit_texel(decorrelate, monkeypatch):
    """The selection Grams' top eigenpairs only (`top_eighs`, LAPACK dsyevr on a subset),
    forced on every texel: the same points and weights as fit_texel's full SVD of R, whatever
    K it needed (a texel of rank 40 with psi 0.999 outgrows the first K = 8)."""
    monkeypatch.setattr(gram_linalg, "SUBSET_MIN_M", 4)
    monkeypatch.setattr(gram_linalg, "SUBSET_START", 8)
    rng = np.random.default_rng(5)
    texels = [_texel(rng, 500, m, r, decorrelate) for m, r in ((40, 6), (90, 40), (70, 3))]
    kw = {**KW, "psi": 0.999}
    Fs, valids = zip(*[_F(R, a) for R, a in texels], strict=True)
    got = _fit_many(list(Fs), list(valids), [channel_correlation(R) for R, _ in texels],
                   [31, 32, 33], **kw)
    ks = []
    for (R, avis), seed, (fit, _) in zip(texels, [31, 32, 33], got, strict=True):
        ref = _fit_texel(R, avis, seed=seed, texel_area=1.0, **kw)
        np.testing.assert_array_equal(fit.columns, ref.columns)
        np.testing.assert_allclose(fit.weights, ref.weights, rtol=1e-5, atol=0)
        assert fit.k == ref.k and abs(fit.snr_db_insample - ref.snr_db_insample) < 1e-6
        ks.append(fit.k)
    assert max(ks) > 8  # the growth of K was exercised


def test_top_eighs_are_the_top_of_the_full_decomposition():
    """`top_eighs` against numpy's full eigh: the top K eigenvalues to 1e-12 of the largest,
    their eigenvectors up to sign, K > the psi-rank (or K = m); narrow matrices complete."""
    rng = np.random.default_rng(9)
    mats = []
    for m, decay in ((200, 0.5), (300, 0.97), (170, 0.999), (50, 0.9)):
        Q, _ = np.linalg.qr(rng.normal(size=(m, m)))
        mats.append((Q * decay ** np.arange(m)) @ Q.T)
    sizes = []
    for G, (lam, V) in zip(mats, gram_linalg.top_eighs(mats, 0.97), strict=True):
        m, K = G.shape[0], lam.shape[0]
        sizes.append(K)
        full_lam, full_V = np.linalg.eigh(G)
        s, _ = gram_linalg.spectrum((full_lam, full_V))
        k = gram_linalg.energy_rank(s, 0.97, float(np.trace(G)))
        assert K == m or K > k
        np.testing.assert_allclose(lam, full_lam[m - K:], rtol=0, atol=1e-12 * full_lam[-1])
        top = min(k + 1, K)  # distinct eigenvalues: vectors equal up to sign
        dots = np.abs(np.einsum("ij,ij->j", V[:, K - top:], full_V[:, m - top:]))
        np.testing.assert_allclose(dots, 1.0, atol=1e-8)
    # fast decay: the first K; slow: K grew; flat: all of it; narrow: the full eigh
    assert sizes == [gram_linalg.SUBSET_START, 128, 170, 50]


@pytest.mark.parametrize("decorrelate", [False, True])
def test_split_of_a_wide_texel_equals_fit_texel_batches(decorrelate):
    """A texel wider than n_batch: fit_many's split (Grams of <= n_batch columns) against
    fit_texel's batches on R with the same n_batch (`search.select_batched` on both)."""
    rng = np.random.default_rng(8)
    R, avis = _texel(rng, 400, 90, 10, decorrelate)
    F, valid = _F(R, avis)
    (fit, skip), = _fit_many([F], [valid], [channel_correlation(R)], [21], n_batch=32, **KW)
    ref = _fit_texel(R, avis, seed=21, texel_area=1.0, n_batch=32, **KW)
    assert skip == "split"
    np.testing.assert_array_equal(fit.columns, ref.columns)
    np.testing.assert_allclose(fit.weights, ref.weights, rtol=1e-5, atol=0)
    assert abs(fit.snr_db_insample - ref.snr_db_insample) < 1e-6


def test_batched_eigh_does_not_depend_on_the_stack():
    """A texel's eigendecomposition is the same alone or stacked with others (farm tiling and
    the memory bound regroup texels)."""
    rng = np.random.default_rng(0)
    mats = [(lambda X: X @ X.T)(rng.random((m, 50))) for m in (7, 12, 7, 7, 12)]
    together = batched_eigh(mats)
    for g, (lam, V) in zip(mats, together, strict=True):
        lam1, V1 = batched_eigh([g])[0]
        np.testing.assert_array_equal(lam, lam1)
        np.testing.assert_array_equal(V, V1)
        np.testing.assert_allclose(V @ np.diag(lam) @ V.T, g, atol=1e-10 * np.abs(g).max())


def test_chunk_bounds_cover_and_respect_the_cap():
    sizes = np.array([3, 4, 10, 1, 1, 1, 6])
    b = chunk_bounds(sizes, 6)
    assert b[0][0] == 0 and b[-1][1] == len(sizes)
    assert all(x[1] == y[0] for x, y in zip(b, b[1:], strict=False))
    for a, e in b:
        assert sizes[a:e].sum() <= 6 or e - a == 1


@pytest.fixture(scope="module")
def small_scene(tmp_path_factory):
    d = tmp_path_factory.mktemp("batched")
    scene = write_scene("cylinder", d / "cyl.usda", "small")
    s = BakeSettings(atlas_resolution=16, shard_texels=8, samples_per_texel=16, n_light_dirs=16,
                     n_view_dirs=16, n_heldout=16, c_max=12, n_trials=2, mesh_levels=1)
    ctx = stages.StageContext.create(d / "work", scene, s)
    stages.run_ingest(ctx, 0)
    stages.run_geometry(ctx, 0)
    return ctx


def test_brdf_product_equals_brdf_grid_on_live_entries(small_scene):
    src = small_scene.fit_inputs()
    texels = tile_texels(16, 8, 0, 0)
    cands = level_candidates(src, 0, texels, None)
    dirs = direction_sets(src.settings)
    frames = src.geo["frames_L0"]
    wi = world_dirs(frames, cands.texel, dirs["dirs_i"])
    wo = world_dirs(frames, cands.texel, dirs["dirs_o"])
    live = (wi[..., 2].T[:, None, :] > -2)  # every entry: the grid evaluates all of them
    live = np.broadcast_to(live, (wi.shape[1], wo.shape[1], len(cands.sample))).copy()
    ref = brdf_grid(src, cands.sample, wi, wo, live)  # (A, B, p, 3)
    got = brdf_product(src.geo, src.materials, cands.sample, wi, wo, live)  # (3, p, A, B)
    np.testing.assert_array_equal(got.transpose(2, 3, 1, 0), ref)
    # a sparse live mask (occluded samples): the gathered path, equal on live entries
    sparse = live & (np.random.default_rng(0).random(live.shape) < 0.3)
    got = brdf_product(src.geo, src.materials, cands.sample, wi, wo, sparse)
    ref = brdf_grid(src, cands.sample, wi, wo, sparse)
    np.testing.assert_array_equal(got.transpose(2, 3, 1, 0)[sparse], ref[sparse])


def test_directions_shared_by_a_texels_samples_equal_their_own(small_scene):
    """`texel_dirs` gives each run of a texel's samples one row of world directions, equal bit
    for bit to `world_dirs` per sample (grouped texels, and texels that recur out of order),
    and `visibility_cos` on those rows equals it on every sample's own directions (the same
    rays: its occlusion is a step function of them)."""
    src = small_scene.fit_inputs()
    cands = level_candidates(src, 0, tile_texels(16, 8, 0, 0), None)
    dirs = direction_sets(src.settings)
    frames = src.geo["frames_L0"]
    for order in (np.arange(len(cands.sample)),
                  np.random.default_rng(2).permutation(len(cands.sample))):
        tex, smp = cands.texel[order], cands.sample[order]
        for key, cosine in (("dirs_i", "shading"), ("dirs_o", "geometric")):
            per = world_dirs(frames, tex, dirs[key])
            shared = texel_dirs(frames, tex, dirs[key])
            np.testing.assert_array_equal(shared.per_sample, per)
            assert len(shared.rows) == 1 + np.count_nonzero(tex[1:] != tex[:-1])
            want = visibility_cos(src, smp, per, cosine)
            assert 0 < np.count_nonzero(want == 0) < want.size
            np.testing.assert_array_equal(visibility_cos(src, smp, shared, cosine), want)
    empty = texel_dirs(frames, np.zeros(0, np.int64), dirs["dirs_o"])
    assert empty.rows.shape == (0, len(dirs["dirs_o"]), 3) and empty.row.shape == (0,)


def test_batched_level_against_per_texel_loop_and_memory_bound(small_scene):
    """The whole level (every texel fitted: small_texels "fit"): the same
    texels valid, in-sample SNR equal to rounding, held-out SNR median no lower than the
    per-texel loop's minus 0.5 dB; a 64 MiB memory bound (many chunks) gives the same arrays
    byte for byte as the default."""
    src = small_scene.fit_inputs()
    texels = tile_texels(16, 8, 1, 0)
    cands = level_candidates(src, 0, texels, None)
    # identical_columns "keep" and narrow lobes: the per-texel loop is the seed's fit, column
    # for column
    src = dataclasses.replace(src, settings=src.settings.model_copy(
        update={"small_texels": "fit", "identical_columns": "keep", "point_lobe": "narrow"}))
    ref = fit_level_per_texel(src, 0, texels, cands)
    got = fit_level_batched(src, 0, texels, cands)
    np.testing.assert_array_equal(got["valid"], ref["valid"])
    v = ref["valid"]
    assert v.sum() > 5
    # equal fits up to ties: collinear samples (one facet) give the same residual with
    # different points, and rounding decides which; the in-sample SNR is the same
    assert np.all(got["skip"][v] == 0)
    np.testing.assert_allclose(got["snr_in"][v], ref["snr_in"][v], atol=0.05)
    assert np.abs(got["c"][v].astype(int) - ref["c"][v]).max() <= 4
    assert np.median(got["snr_ho"][v]) >= np.median(ref["snr_ho"][v]) - 0.5
    small = dataclasses.replace(src, settings=src.settings.model_copy(
        update={"worker_memory_mb": 64}))
    # a 64 MiB bound with 16 x 16 pairs still fits a tile: force single-texel chunks too
    old = lb.BYTES_PER_R_ENTRY
    try:
        lb.BYTES_PER_R_ENTRY = 10**7
        tiny = fit_level_batched(small, 0, texels, cands)
    finally:
        lb.BYTES_PER_R_ENTRY = old
    for k in got:
        np.testing.assert_array_equal(tiny[k], got[k], err_msg=k)


def test_reduced_system_cholesky_and_eigh_against_the_residual():
    """The trials' reduced least squares: pivoted Cholesky (batched path) and the
    eigendecomposition (per-texel algebra) both reproduce ||M a - target||^2 for any a, with
    duplicate, collinear and zero columns (one facet's samples)."""
    from texelbake.cpm.gram.linalg import normalised_gram, reduced_system, reduced_system_eigh

    rng = np.random.default_rng(2)
    M = rng.random((500, 12)) @ rng.random((12, 30))  # rank 12
    M[:, 5] = M[:, 3] * 2.5  # collinear
    M[:, 7] = 0.0  # zero column
    M[:, 9] = M[:, 2]  # duplicate
    G = M.T @ M
    _, scale = normalised_gram(G)
    for target in (M.sum(axis=1), rng.random(500)):
        b, tt = M.T @ target, float(target @ target)
        A1, t1, r1 = reduced_system(G, scale, b, tt)
        A2, t2, r2 = reduced_system_eigh(G, batched_eigh([G / np.outer(scale, scale)])[0],
                                         scale, b, tt)
        assert A1.shape[0] <= 13
        for a in (np.zeros(30), rng.random(30), rng.random(30) * 10):
            exact = float(np.sum((M @ a - target) ** 2))
            for A, t, r in ((A1, t1, r1), (A2, t2, r2)):
                assert float(np.sum((A @ a - t) ** 2)) + r == pytest.approx(exact, rel=1e-7,
                                                                             abs=1e-9 * tt)


def test_small_texels_keep_every_candidate_on_both_paths():
    """small="all" on the Gram path: a texel of m <= c_max columns whose fit is not exact on
    the grid keeps every column at weight 1 instead (skip "all", the in-sample SNR of round-off
    only, the fit's rank reported) and equals fit_texel's with the same setting; a wider texel
    is fitted exactly as with small="fit"."""
    rng = np.random.default_rng(5)
    texels = [_texel(rng, 300, m, r, False) for m, r in ((20, 6), (40, 9))]
    Fs, valids = zip(*[_F(R, a) for R, a in texels], strict=True)
    corrs = [channel_correlation(R) for R, _ in texels]
    kw = dict(KW, c_max=24)
    got = _fit_many(list(Fs), list(valids), corrs, [1, 2], small="all", **kw)
    seed_fit = _fit_many(list(Fs), list(valids), corrs, [1, 2], **kw)
    (small, skip_small), (wide, skip_wide) = got
    assert skip_small == "all" and skip_wide == ""
    assert small.c == 20 and np.array_equal(small.columns, np.arange(20))
    assert np.all(small.weights == 1.0) and small.snr_db_insample > 250.0
    ref = _fit_texel(*texels[0], seed=1, texel_area=1.0, small="all", **kw)
    assert np.array_equal(ref.columns, small.columns) and ref.c == small.c
    np.testing.assert_array_equal(wide.columns, seed_fit[1][0].columns)
    np.testing.assert_array_equal(wide.weights, seed_fit[1][0].weights)
    assert seed_fit[0][0].c < 20  # the seed's bisection stops short of every column
    assert small.k == seed_fit[0][0].k  # the rank the fit found, reported as it is


def test_a_wide_texel_read_by_blocks_is_fitted_as_if_held(small_scene, monkeypatch):
    """Texels wider than n_batch (16 here: most level-0 texels of this scene) are fitted from
    `Columns` built a block of n_batch candidates at a time (one texel's F does not grow with
    its width). Held whole instead (its F built in one `build_R` call and wrapped
    by `Columns.of_array`), every array of the level is the same bit for bit: a block's
    columns are those of the whole F, and sums go by the same blocks."""
    src = small_scene.fit_inputs()
    src = dataclasses.replace(src, settings=src.settings.model_copy(update={"n_batch": 16}))
    texels = tile_texels(16, 8, 0, 0)
    cands = level_candidates(src, 0, texels, None)
    counts = np.bincount(np.searchsorted(np.sort(texels), cands.texel), minlength=len(texels))
    assert (counts > 16).sum() >= 5 and counts.max() > 3 * 16
    built = []

    def held(lp, cset, rows, cseg, inv_o, s1, s2):
        F, s1[rows], s2[rows] = build_R(lp, cset.take(rows), inv_o, cseg[rows])
        built.append(F.shape[1])
        return lb.Columns.of_array(F, lp.src.settings.n_batch)

    lazy = fit_level_batched(src, 0, texels, cands)
    monkeypatch.setattr(lb, "_wide_columns", held)
    whole = fit_level_batched(src, 0, texels, cands)
    assert len(built) == (counts > 16).sum()
    assert lazy["valid"].sum() >= 5
    for k in lazy:
        np.testing.assert_array_equal(lazy[k], whole[k], err_msg=k)


def test_segment_sum_adds_each_segments_terms_in_their_order():
    """`segment_sum` against a loop that adds every term to its segment's row in input
    order, bit for bit: along a middle axis and the first, ids ascending with empty
    segments, ids unsorted (a segment's terms still in their order), and no terms."""
    from texelbake.cpm.level import segment_sum

    rng = np.random.default_rng(4)
    seg = np.sort(rng.integers(0, 9, 300))
    seg = seg[seg != 4]  # an empty segment inside, and 9..11 empty at the end
    v = rng.normal(size=(3, seg.size, 4, 5)) * 10.0 ** rng.integers(-8, 8, (3, seg.size, 1, 1))
    for ids in (seg, rng.permutation(seg)):
        want = np.zeros((3, 12, 4, 5))
        for j, s in enumerate(ids):  # the reference: one term at a time
            want[:, s] += v[:, j]
        assert np.array_equal(segment_sum(v, ids, 12, 1), want)
        assert np.array_equal(segment_sum(v[1], ids, 12, 0), want[1])
    assert segment_sum(np.zeros((0, 2)), np.zeros(0, np.int64), 3, 0).shape == (3, 2)
