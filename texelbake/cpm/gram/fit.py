"""Characteristic points of one texel from its Gram matrices (seed 000 §3.3, §4.1; DMM06 Table 2),
the algorithm of `texelbake.cpm.fit.fit_texel` (rows="eq7") moved to m x m space so that the
expensive parts run batched over many texels (`texelbake.cpm.level_batched`).

Everything the fit needs from the d x m matrix F = diag(1/a_vis) R (rows with a_vis <= eps are
zero) is a Gram matrix (d = N_i N_o rows, m samples, d >> m):

- Table 2's probabilities need the top right singular vectors and the singular values of the
  selection matrix S (luminance S = F lw, or one channel): eigh(S^T S), exactly the Gram route
  of `column_sampling.svd_float64` with its floor on unresolved singular values;
- the trials solve min ||F_c[:, C] a - F_c 1|| (Eq. 10-11, NNLS); with G_c = F_c^T F_c =
  D V diag(lam) V^T D (D = column norms) that residual equals ||A a - t||^2 + rest with
  A = diag(sqrt lam) V^T D, t = diag(1/sqrt lam) V^T D^-1 G_c 1 and rest = 1^T G_c 1 - t^T t,
  the reduced system the per-texel path forms from F itself (same algebra, the products
  M^T t replaced by G 1);
- the SNR signal of Eq. 7 is sum_c 1^T G_c 1.

The Grams (one GEMM per matrix) and the eigendecompositions (`texelbake.cpm.gram.linalg`:
torch.linalg.eigh over stacks of equal-size matrices, or LAPACK's top eigenpairs of a wide one;
a texel's result never depends on which texels share its batch) are computed for many texels
at once (`fit_many`); per texel only the m-sized work remains: probabilities, the search on c
(`texelbake.cpm.search`, NNLS on r x c systems, r <= m), and the reported in-sample SNR,
recomputed in d space from F with the stored float32 weights (`texel_fit.assemble_fit`).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from texelbake.cpm.column_sampling import column_probabilities, energy_rank
from texelbake.cpm.gram.columns import Columns, SelectionRows
from texelbake.cpm.gram.identical import Merge, identical_columns, unmerge
from texelbake.cpm.gram.linalg import (
    needs_full_svd,
    normalised_gram,
    reduced_system,
    spectrum,
    top_eighs,
)
from texelbake.cpm.matrix import points_sum
from texelbake.cpm.search import reduced_trial, search_c, select_batched
from texelbake.cpm.texel_fit import (
    FitCounts,
    FitParams,
    GroupFit,
    TexelFit,
    all_points_fit,
    assemble_fit,
    needs_all_points,
)
from texelbake.tol import TOL


def correlation_from_sums(sx: np.ndarray, sxx: np.ndarray, n: int) -> float:
    """`fit.channel_correlation` from the entries' sums: sx (ch,) = sum x, sxx (ch, ch) = sum
    x x^T over the n = d m entries of R (same one-pass formula and constant-channel rule)."""
    ch = sx.shape[0]
    if ch < 2 or n < 2:
        return 1.0
    mu = sx / n
    cov = sxx - n * np.outer(mu, mu)
    var = np.diag(cov)
    ok = var > TOL.const_channel_var * np.diag(sxx)
    sd = np.where(ok, np.sqrt(np.where(ok, var, 1.0)), 1.0)
    corr = np.ones((ch, ch))
    both = ok[:, None] & ok[None, :]
    corr[both] = (cov / np.outer(sd, sd))[both]
    return float(np.clip(corr.min(), -1.0, 1.0))


@dataclass(frozen=True)
class GramTexel:
    """One texel for the batched fit: F (ch, m, d) float64 = diag(1/a_vis) R transposed per
    channel (rows under the a_vis floor zero; contiguous blocks), or `Columns` for a texel
    wider than n_batch; valid (d,) bool rows above the floor; corr its `channel_correlation`
    (`correlation_from_sums`); seed its rng seed."""

    F: np.ndarray | Columns
    valid: np.ndarray
    corr: float
    seed: int


@dataclass(frozen=True)
class GroupInput:
    """One selection group of a texel: its selection Gram's eigh and the channels it fits."""

    sel_eig: tuple[np.ndarray, np.ndarray]
    sel_diag: np.ndarray  # (m,) exact column energies of S
    sel_total: float  # ||S||_F^2
    chans: np.ndarray  # channel indices fitted by this group


@dataclass(frozen=True)
class GramProblem:
    """One texel's fit from Grams: F (ch, m, d) the columns it selects among (the merged ones
    when identical columns are merged), valid (d,) bool, Gc the ch Grams F_c F_c^T (m, m),
    groups its selection groups (one in luminance mode, one per channel otherwise), mode,
    corr, seed, and targets (ch, d): Eq. 7's row sums over every candidate when F holds merged
    columns (default F's own row sums F 1)."""

    F: np.ndarray
    valid: np.ndarray
    Gc: list[np.ndarray]
    groups: list[GroupInput]
    mode: str
    corr: float
    seed: int
    targets: np.ndarray | None = None


def fit_texel_gram(prob: GramProblem, params: FitParams, counts: FitCounts | None = None
                   ) -> tuple[TexelFit | None, str]:
    """One texel's fit from its Grams; returns (TexelFit, ""), or (None, "full_svd") when the
    Gram route cannot resolve span(V_k) (`top_singular` redoes a full SVD then; the caller
    fits that texel with `fit.fit_texel`). The caller handles m = 0, no valid row, all-zero R
    and non-finite input (`fit_texel`'s cases)."""
    F, targets, Gc = prob.F, prob.targets, prob.Gc
    ch, m, _ = F.shape
    rng = np.random.default_rng(prob.seed)
    # per channel F_c^T target and ||target||^2 (the signal of Eq. 7's SNR): of the given
    # targets, or of F's own row sums (then reduced_system forms G 1 itself)
    fits_of: list[tuple[np.ndarray | None, float | None]]
    if targets is None:
        fits_of = [(None, None)] * ch
        signals = [float(Gc[c].sum()) for c in range(ch)]
    else:
        signals = [float(targets[c] @ targets[c]) for c in range(ch)]
        fits_of = [(F[c] @ targets[c], signals[c]) for c in range(ch)]
    reds = []
    for c in range(ch):  # loop over <= 3 channels
        norms = np.sqrt(np.maximum(np.diag(Gc[c]), 0.0))
        reds.append(reduced_system(Gc[c], np.where(norms > 0, norms, 1.0), *fits_of[c]))
    specs = []
    for gi in prob.groups:  # loop over <= ch groups
        s, Vt = spectrum(gi.sel_eig)
        k = energy_rank(s, params.psi, gi.sel_total)
        if needs_full_svd(s, k, m):
            return None, "full_svd"
        specs.append((s, Vt, k))
    fits = []
    for gi, (s, Vt, k) in zip(prob.groups, specs, strict=True):  # loop over <= ch groups
        if k == 0:
            fits.append(GroupFit(np.zeros(0, np.int64), np.zeros((0, len(gi.chans))), 0, False))
            continue
        p = column_probabilities(np.zeros((0, 0)), s, Vt, k, col_energy=gi.sel_diag)
        signal = float(sum(signals[c] for c in gi.chans))
        trial = reduced_trial([reds[c] for c in gi.chans], signal, params.weights)
        cols, alpha, capped = search_c(p, k, trial, rng, params.c_max, params, counts)
        fits.append(GroupFit(cols, alpha, k, capped))
    ref = F.sum(axis=1).T if targets is None else targets.T  # (d, ch): Eq. 7, 1/a_vis in F
    return _assemble(F, prob.valid, fits, [gi.chans for gi in prob.groups], ref,
                     prob.mode, prob.corr, params), ""


def _assemble(F: np.ndarray | Columns, valid: np.ndarray, fits: list[GroupFit],
              chans: list[np.ndarray], ref: np.ndarray, mode: str, corr: float,
              params: FitParams) -> TexelFit:
    """`texel_fit.assemble_fit` with Eq. 7 of the points summed from F's columns."""
    def eq7(columns: np.ndarray, w: np.ndarray) -> np.ndarray:
        return points_sum(F, columns, w)  # (d, ch)

    return assemble_fit(fits, chans, F.shape[0], eq7, ref, valid, mode=mode, corr=corr,
                        params=params)


@dataclass(frozen=True)
class _Plan:
    """A texel's Grams and selection groups between `fit_many`'s two passes."""

    mode: str
    Gc: list[np.ndarray]
    groups: list[tuple[np.ndarray, np.ndarray]]
    first: int  # position of its first selection Gram in the stacked eigendecompositions
    targets: np.ndarray | None
    merge: Merge | None


def fit_many(texels: Sequence[GramTexel], params: FitParams, counts: FitCounts | None = None
             ) -> list[tuple[TexelFit | None, str]]:
    """Fits of many texels: Grams per texel, every eigendecomposition stacked (`top_eighs`),
    then `fit_texel_gram` per texel; returns per texel (TexelFit, skip) with skip "" (draws
    and trials), "split" (wider than n_batch, `fit_split`), "all" (every candidate kept:
    params.small="all" and a texel of m <= c_max whose fit is not exact on the grid,
    `needs_all_points`), or (None, "full_svd") for a texel the Gram route cannot resolve, which
    the caller fits over all its candidates.
    params.identical="merge": a texel's candidates with identical columns are fitted as one
    column (`texelbake.cpm.gram.identical`: the seed's fit in distribution, Grams of u^2 d for u
    distinct columns, no point stored twice; under small="all" a texel of m <= c_max candidates
    is not merged, one of more whose u distinct columns are <= c_max keeps them all).
    Texels must have m >= 1, d >= 2 min(m, n_batch), a valid row and a nonzero R
    (`fit_texel`'s cases)."""
    plans: list[_Plan | None] = []
    mats: list[np.ndarray] = []
    for tex in texels:  # loop over texels: Grams (GEMMs)
        F = tex.F
        ch = F.shape[0]
        if F.shape[1] > params.n_batch:
            plans.append(None)
            continue
        if isinstance(F, Columns):
            raise ValueError(f"Columns are for texels wider than n_batch ({params.n_batch}), "
                             f"got {F.shape[1]} columns")
        mode = params.colour_mode(ch, tex.corr)
        targets = merge = None
        if params.identical == "merge" and not needs_all_points(
                params.small, F.shape[1], params.c_max, -math.inf):
            # (a texel that keeps every candidate when its fit is not exact is not merged:
            # identical on the grid is not identical between its directions)
            merge = identical_columns(F, tex.seed)
            if merge is not None:
                if counts is not None:
                    counts.merged_texels += 1
                    counts.merged_columns += F.shape[1] - merge.rep.size
                targets = F.sum(axis=1)  # (ch, d): Eq. 7 over every candidate
                F = merge.columns(F)  # a copy, dropped after the Grams (memory)
        Gc = [F[c] @ F[c].T for c in range(ch)]
        groups = select_groups(F, Gc, mode, params)
        plans.append(_Plan(mode, Gc, groups, len(mats), targets, merge))
        mats += [g for g, _ in groups]
    eigs = top_eighs(mats, params.psi)
    out: list[tuple[TexelFit | None, str]] = []
    for tex, plan in zip(texels, plans, strict=True):  # loop over texels: the m-sized work
        if plan is None:
            out.append(_finish(tex, None, fit_split(tex, params, counts), params))
            continue
        F = tex.F
        assert not isinstance(F, Columns)  # narrowed in the first loop
        ginp = [GroupInput(eigs[plan.first + j], np.diag(g).copy(), float(np.trace(g)), chans)
                for j, (g, chans) in enumerate(plan.groups)]
        F_sel = F if plan.merge is None else plan.merge.columns(F)
        got = fit_texel_gram(GramProblem(F_sel, tex.valid, plan.Gc, ginp, plan.mode, tex.corr,
                                         tex.seed, plan.targets), params, counts)
        out.append(_finish(tex, plan, got, params))
    return out


def _finish(tex: GramTexel, plan: _Plan | None, got: tuple[TexelFit | None, str],
            params: FitParams) -> tuple[TexelFit | None, str]:
    """A texel's Gram fit as its candidates' fit: every candidate kept when the fit asks for
    it (`needs_all_points`), merged columns back to the texel's candidates (`unmerge`).
    plan : None for a texel fitted by `fit_split`."""
    fit, F = got[0], tex.F
    merge = targets = None
    if plan is not None:
        merge, targets = plan.merge, plan.targets
    if fit is None:
        return got
    m_fit = F.shape[1] if merge is None else merge.rep.size  # columns the fit saw
    if needs_all_points(params.small, m_fit, params.c_max, fit.snr_db_insample):
        ref = (F.sum(axis=1) if targets is None else targets).T  # (d, ch): Eq. 7, 1/a_vis in F
        if isinstance(F, Columns):  # every column at weight 1: the sum itself
            return all_points_fit(ref, ref, tex.valid, F.shape[1], tex.corr, params.eps_db,
                                  fit.k), "all"
        if merge is not None:  # every group at its size: the sum of its members
            cols, size = merge.groups()
            approx = points_sum(F, cols, size)
            fit = all_points_fit(ref, approx, tex.valid, F.shape[1], tex.corr, params.eps_db,
                                 fit.k, columns=cols, weights=size)
            return dataclasses.replace(fit, merged=merge.merged), "all"
        approx = points_sum(F, None, np.ones(F.shape[1]))  # every column at weight 1
        return all_points_fit(ref, approx, tex.valid, F.shape[1], tex.corr, params.eps_db,
                              fit.k), "all"
    if merge is not None:  # merged columns -> the texel's candidates
        assert not isinstance(F, Columns) and targets is not None  # what a merge implies
        return unmerge(fit, merge, F, targets, tex.valid, params.eps_db), got[1]
    return got


def fit_split(tex: GramTexel, params: FitParams, counts: FitCounts | None = None
              ) -> tuple[TexelFit | None, str]:
    """A texel wider than n_batch columns: the per-texel path's batches
    (`search.select_batched`) with every step from Grams of <= n_batch columns: Gram work
    m n_batch d instead of m^2 d, the same draws as `fit_texel` with the same n_batch.
    tex.F : the texel's F, held or as `Columns` (read a block of <= n_batch columns at a time:
    the memory of a step is n_batch d, whatever m).
    Returns (None, "full_svd") when a step needs the full SVD (see `fit_texel_gram`)."""
    F = tex.F if isinstance(tex.F, Columns) else Columns.of_array(tex.F, params.n_batch)
    ch, m, _ = F.shape
    mode = params.colour_mode(ch, tex.corr)
    rng = np.random.default_rng(tex.seed)
    sel_rows: list[tuple[SelectionRows, np.ndarray]]
    if mode == "luminance":
        sel_rows = [(SelectionRows(F, params.luma(ch)), np.arange(ch))]
    else:
        sel_rows = [(SelectionRows(F, None, c), np.array([c])) for c in range(ch)]
    fits = []
    for S, chans in sel_rows:  # loop over <= ch groups
        def direct(cand: np.ndarray, whole: np.ndarray, c_max: int, S=S, chans=chans
                   ) -> GroupFit | None:
            total = F.sum_over(whole)  # (ch, d)
            return _select_direct(F, S, chans, cand, [total[c] for c in chans], c_max, params,
                                  rng, counts)
        got = select_batched(np.arange(m, dtype=np.int64), params.c_max, params, direct)
        if got is None:
            return None, "full_svd"
        fits.append(got)
    return _assemble(F, tex.valid, fits, [chans for _, chans in sel_rows], F.sum(axis=1).T,
                     mode, tex.corr, params), "split"


def _select_direct(F: Columns, S: SelectionRows, chans: np.ndarray, cand: np.ndarray,
                   targets: list[np.ndarray], c_max: int, params: FitParams,
                   rng: np.random.Generator, counts: FitCounts | None) -> GroupFit | None:
    """The selection among columns cand against the given targets (d,) per channel, from
    Grams; None when it needs the full SVD."""
    Sc = S[cand]
    G_sel = Sc @ Sc.T
    eig_sel = top_eighs([G_sel], params.psi)[0]
    s, Vt = spectrum(eig_sel)
    k = energy_rank(s, params.psi, float(np.trace(G_sel)))
    if needs_full_svd(s, k, cand.size):
        return None
    if k == 0:
        return GroupFit(np.zeros(0, np.int64), np.zeros((0, len(chans))), 0, False)
    p = column_probabilities(np.zeros((0, 0)), s, Vt, k, col_energy=np.diag(G_sel).copy())
    red = []
    signal = 0.0
    for c, tgt in zip(chans, targets, strict=True):  # loop over <= 3 channels
        M = F[c, cand]
        G = M @ M.T
        _, scale = normalised_gram(G)
        tt = float(tgt @ tgt)
        signal += tt
        red.append(reduced_system(G, scale, M @ tgt, tt))
    cols, alpha, capped = search_c(p, k, reduced_trial(red, signal, params.weights), rng, c_max,
                                   params, counts)
    return GroupFit(cand[cols], alpha, k, capped)


def select_groups(F: np.ndarray, Gc: list[np.ndarray], mode: str, params: FitParams
                  ) -> list[tuple[np.ndarray, np.ndarray]]:
    """The selection matrices' Grams and channels: [(G_S (m, m), chans)]. Luminance: S = F lw
    (one GEMM more); per channel: S = F_c, whose Gram is G_c."""
    ch = F.shape[0]
    if mode == "luminance":
        S = np.tensordot(params.luma(ch), F, axes=(0, 0))  # (m, d)
        return [(S @ S.T, np.arange(ch))]
    return [(Gc[c], np.array([c])) for c in range(ch)]


__all__ = ["GramProblem", "GramTexel", "GroupInput", "correlation_from_sums", "fit_many",
           "fit_split", "fit_texel_gram", "select_groups"]
