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
  the reduced system `fit._Fitter._reduce` forms from F itself (same algebra, the products
  M^T t replaced by G 1);
- the SNR signal of Eq. 7 is sum_c 1^T G_c 1.

The Grams (one GEMM per matrix) and the eigendecompositions (`texelbake.cpm.gram_linalg`:
torch.linalg.eigh over stacks of equal-size matrices, or LAPACK's top eigenpairs of a wide one;
a texel's result never depends on which texels share its batch) are computed by the caller; here, per texel, only the m-sized work remains: probabilities, the
bisection on c with its trials (NNLS on r x c systems, r <= m), and the reported in-sample SNR,
recomputed in d space from F with the stored float32 weights as `fit_texel` does.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from texelbake.cpm.column_sampling import (
    column_probabilities,
    energy_rank,
    fit_weights,
    sample_columns,
)
from texelbake.cpm.columns import Columns, SelectionRows
from texelbake.cpm.fit import (
    LUMA_709,
    TexelFit,
    _empty_fit,
    _storable_weights,
    all_points_fit,
    needs_all_points,
)
from texelbake.cpm.gram_linalg import (
    batched_eigh,
    needs_full_svd,
    normalised_gram,
    reduced_system,
    spectrum,
    top_eighs,
)
from texelbake.cpm.identical import identical_columns, unmerge
from texelbake.cpm.matrix import points_sum, snr_db
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


@dataclass
class GroupInput:
    """One selection group of a texel: its selection Gram's eigh and the channels it fits."""

    sel_eig: tuple[np.ndarray, np.ndarray]
    sel_diag: np.ndarray  # (m,) exact column energies of S
    sel_total: float  # ||S||_F^2
    chans: np.ndarray  # channel indices fitted by this group


#: counts of the trial work done by `_bisect` in this process (probes of c, NNLS draws solved,
#: draws not solved because a probe stopped at the target); read by benchmarks/cpm_cpu.py
COUNTS = {"probes": 0, "draws": 0, "merged_texels": 0, "merged_columns": 0}


def _bisect(
    p: np.ndarray, k: int, red: list[tuple], signal: float, *, eps_db: float, c_max: int,
    n_trials: int, weights: str, rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray, bool]:
    """`fit._Fitter._select_direct`'s bisection on [k, c_max] with n_trials draws per probe, in
    the reduced space. returns (columns, alpha (c, ch_g), capped)."""
    cache: dict[int, tuple[np.ndarray, np.ndarray, float]] = {}

    def best_of_trials(c: int) -> tuple[np.ndarray, np.ndarray, float]:
        if c not in cache:
            COUNTS["probes"] += 1
            best: tuple[np.ndarray, np.ndarray, float] | None = None
            seen: set[bytes] = set()
            for _ in range(n_trials):  # loop over a handful of randomized trials
                local = sample_columns(p, c, rng)
                key = local.tobytes()
                if key in seen:
                    continue
                seen.add(key)
                COUNTS["draws"] += 1
                alpha = np.zeros((local.size, len(red)))
                noise = 0.0
                for g, (A, t, rest) in enumerate(red):  # loop over <= 3 channels
                    C = A[:, local]
                    alpha[:, g] = fit_weights(C, t, weights)  # type: ignore[arg-type]
                    r = C @ alpha[:, g] - t
                    noise += float(r @ r) + rest
                snr = math.inf if noise <= 0.0 else (
                    -math.inf if signal <= 0.0 else 10.0 * math.log10(signal / noise))
                if best is None or snr > best[2]:
                    best = (local, alpha, snr)
            assert best is not None
            cache[c] = best
        return cache[c]

    def passes(c: int) -> bool:
        return best_of_trials(c)[2] >= eps_db

    capped = c_max < k
    lo, hi = (c_max, c_max) if capped else (k, c_max)
    while lo < hi:  # seed 000 §4.1: bisection with the median as the probe
        mid = (lo + hi) // 2
        if passes(mid):
            hi = mid
        else:
            lo = mid + 1
    cols, alpha, _ = best_of_trials(lo)
    return cols, alpha, capped


def fit_texel_gram(
    F: np.ndarray,
    valid: np.ndarray,
    Gc: list[np.ndarray],
    groups: list[GroupInput],
    *,
    mode: str,
    corr: float,
    psi: float,
    eps_db: float,
    c_max: int,
    n_trials: int,
    weights: str,
    seed: int,
    targets: np.ndarray | None = None,
) -> tuple[TexelFit | None, str]:
    """One texel's fit from its Grams; returns (TexelFit, ""), or
    (None, "full_svd") when the Gram route cannot resolve span(V_k) (`top_singular` redoes a
    full SVD then; the caller fits that texel with `fit.fit_texel`).

    F : (ch, m, d) float64, F = diag(1/a_vis) R transposed per channel (invalid rows zero);
    valid : (d,) bool rows with a_vis above the floor; Gc : ch Grams F_c F_c^T (m, m);
    groups : the selection groups (one in luminance mode, one per channel otherwise);
    targets : (ch, d) what the points fit, Eq. 7's row sums of a texel whose candidates F holds
    as merged columns (`identical`); default F's own row sums F 1.
    Caller handles m = 0, no valid row, all-zero R and non-finite input (`fit_texel`'s cases).
    """
    ch, m, _ = F.shape
    rng = np.random.default_rng(seed)
    # per channel F_c^T target and ||target||^2 (the signal of Eq. 7's SNR): of the given
    # targets, or of F's own row sums (then reduced_system forms G 1 itself)
    fits_of: list[tuple[np.ndarray | None, float | None]]
    if targets is None:
        fits_of = [(None, None)] * ch
        signals = [float(Gc[c].sum()) for c in range(ch)]
    else:
        signals = [float(targets[c] @ targets[c]) for c in range(ch)]
        fits_of = [(F[c] @ targets[c], signals[c]) for c in range(ch)]
    reds, scales = [], []
    for c in range(ch):  # loop over <= 3 channels
        Gn_scale = np.sqrt(np.maximum(np.diag(Gc[c]), 0.0))
        scales.append(np.where(Gn_scale > 0, Gn_scale, 1.0))
        reds.append(reduced_system(Gc[c], scales[c], *fits_of[c]))
    specs = []
    for gi in groups:  # loop over <= ch groups
        s, Vt = spectrum(gi.sel_eig)
        k = energy_rank(s, psi, gi.sel_total)
        if needs_full_svd(s, k, m):
            return None, "full_svd"
        specs.append((s, Vt, k))
    fits = []
    for gi, (s, Vt, k) in zip(groups, specs, strict=True):  # loop over <= ch groups
        chans = gi.chans
        if k == 0:
            fits.append((np.zeros(0, np.int64), np.zeros((0, len(chans))), 0, False))
            continue
        p = column_probabilities(np.zeros((0, 0)), s, Vt, k, col_energy=gi.sel_diag)
        signal = float(sum(signals[c] for c in chans))
        cols, alpha, capped = _bisect(
            p, k, [reds[c] for c in chans], signal, eps_db=eps_db, c_max=c_max,
            n_trials=n_trials, weights=weights, rng=rng,
        )
        fits.append((cols, alpha, k, capped))
    return _merge(F, valid, fits, groups, mode=mode, corr=corr, eps_db=eps_db,
                  c_max=c_max, ref=None if targets is None else targets.T), ""


def _merge(F, valid, fits, groups, *, mode, corr, eps_db, c_max, ref=None) -> TexelFit:
    """`fit_texel`'s merge: union of the groups' columns, float32 weights, points with a zero
    weight everywhere dropped, the in-sample SNR of Eq. 7 recomputed in d space (against
    ref (d, ch), default F's row sums)."""
    ch = F.shape[0]
    columns = np.unique(np.concatenate([f[0] for f in fits])).astype(np.int64)
    w64 = np.zeros((columns.size, ch), dtype=np.float64)
    for (cols, alpha, _, _), gi in zip(fits, groups, strict=True):  # loop over <= ch groups
        pos = np.searchsorted(columns, cols)
        w64[np.ix_(pos, gi.chans)] = alpha
    w32 = _storable_weights(w64)
    live = np.any(w32 != 0.0, axis=1)
    columns, w32 = columns[live], w32[live]
    w = w32.astype(np.float64)
    approx = points_sum(F, columns, w)  # (d, ch)
    if ref is None:
        ref = F.sum(axis=1).T  # (d, ch): Eq. 7, 1/a_vis folded into F
    snr = snr_db(ref, approx, valid)
    capped = any(f[3] for f in fits)
    reasons = []
    if capped:
        reasons.append(f"c_max={c_max} < k: c capped")
    if snr < eps_db:
        reasons.append(f"eps {eps_db} dB not reached (SNR {snr:.2f} dB)")
    return TexelFit(
        columns=columns, weights=w32, k=max(f[2] for f in fits), c=int(columns.size),
        snr_db_insample=snr, colour_mode=mode, valid=True, reason="; ".join(reasons),
        channel_correlation=corr,
        k_channels=np.array([f[2] for f in fits], dtype=np.int64),
        c_channels=np.array([int(np.count_nonzero(np.any(f[1] != 0.0, axis=1))) for f in fits],
                            dtype=np.int64),
        c_capped=capped, eps_reached=bool(snr >= eps_db),
    )


def fit_many(
    Fs: list[np.ndarray | Columns],
    valids: list[np.ndarray],
    corrs: list[float],
    seeds: list[int],
    *,
    psi: float,
    eps_db: float,
    c_max: int,
    n_trials: int,
    weights: str,
    colour: str,
    decorrelation_threshold: float,
    n_batch: int | None = None,
    small: str = "fit",
    identical: str = "keep",
) -> list[tuple[TexelFit | None, str]]:
    """Fits of many texels: Grams per texel, every eigendecomposition in `batched_eigh`, then
    `fit_texel_gram` per texel. With small="all" a texel of m <= c_max candidates whose fit is
    not exact on the grid keeps them all (`fit.needs_all_points`, skip "all").
    identical="merge": a texel's candidates with identical columns are fitted as one column
    (`texelbake.cpm.identical`: the seed's fit in distribution, Grams of u^2 d for u distinct
    columns, no point stored twice; under small="all" a texel of m <= c_max candidates is not
    merged, one of more whose u distinct columns are <= c_max keeps them all); "keep": as the
    seed. A texel the Gram route cannot resolve ("full_svd") is fitted by the caller over all
    its candidates.
    Fs[t] : (ch, m, d) F = diag(1/a_vis) R per channel (contiguous blocks), or `Columns`
    (m > n_batch only); valids[t] : (d,)
    bool; corrs[t] : `channel_correlation` of R; seeds[t] : rng seed.
    Texels must have m >= 1, d >= 2 min(m, n_batch), a valid row and a nonzero R
    (`fit_texel`'s cases); texels wider than n_batch columns go through `fit_split`."""
    plans: list[tuple | None] = []
    mats: list[np.ndarray] = []
    for F, corr, seed in zip(Fs, corrs, seeds, strict=True):  # loop over texels: Grams (GEMMs)
        ch = F.shape[0]
        if n_batch is not None and F.shape[1] > n_batch:
            plans.append(None)
            continue
        if isinstance(F, Columns):
            raise ValueError(f"Columns are for texels wider than n_batch ({n_batch}), "
                             f"got {F.shape[1]} columns")
        mode = "per_channel" if (ch > 1 and corr < decorrelation_threshold) else "luminance"
        if colour != "auto":
            mode = colour
        if ch == 1:
            mode = "luminance"
        targets = merge = None
        if identical == "merge" and not needs_all_points(small, F.shape[1], c_max, -math.inf):
            # (a texel that keeps every candidate when its fit is not exact is not merged:
            # identical on the grid is not identical between its directions)
            merge = identical_columns(F, seed)
            if merge is not None:
                COUNTS["merged_texels"] += 1
                COUNTS["merged_columns"] += F.shape[1] - merge.rep.size
                targets = F.sum(axis=1)  # (ch, d): Eq. 7 over every candidate
                F = merge.columns(F)  # a copy, dropped after the Grams (memory)
        Gc = [F[c] @ F[c].T for c in range(ch)]
        groups = select_groups(F, Gc, mode)
        plans.append((mode, Gc, groups, len(mats), targets, merge))
        mats += [g for g, _ in groups]
    eigs = top_eighs(mats, psi)
    out: list[tuple[TexelFit | None, str]] = []
    for F, valid, corr, seed, plan in zip(
        Fs, valids, corrs, seeds, plans, strict=True
    ):  # loop over texels: the m-sized work
        targets = merge = None
        if plan is None:
            got = fit_split(
                F, valid, corr, seed, n_batch=int(n_batch or 0), psi=psi, eps_db=eps_db,
                c_max=c_max, n_trials=n_trials, weights=weights, colour=colour,
                decorrelation_threshold=decorrelation_threshold)
        else:
            assert not isinstance(F, Columns)  # narrowed in the first loop
            mode, Gc, groups, first, targets, merge = plan
            F_sel = F if merge is None else merge.columns(F)
            ginp = [GroupInput(eigs[first + j], np.diag(g).copy(), float(np.trace(g)), chans)
                    for j, (g, chans) in enumerate(groups)]
            got = fit_texel_gram(
                F_sel, valid, Gc, ginp, mode=mode, corr=corr,
                psi=psi, eps_db=eps_db, c_max=c_max, n_trials=n_trials, weights=weights,
                seed=seed, targets=targets,
            )
        fit = got[0]
        m_fit = F.shape[1] if merge is None else merge.rep.size  # columns the fit saw
        if fit is not None and needs_all_points(small, m_fit, c_max, fit.snr_db_insample):
            ref = (F.sum(axis=1) if targets is None else targets).T  # (d, ch): Eq. 7, 1/a_vis in F
            if merge is not None:  # every group at its size: the sum of its members
                assert not isinstance(F, Columns)  # what a merge implies
                cols, size = merge.groups()
                approx = points_sum(F, cols, size)
                fit = all_points_fit(ref, approx, valid, F.shape[1], corr, eps_db, fit.k,
                                     columns=cols, weights=size)
                got = (dataclasses.replace(fit, merged=merge.merged), "all")
            else:
                approx = (ref if isinstance(F, Columns) else  # every column at weight 1: the sum
                          points_sum(F, None, np.ones(F.shape[1])))
                got = (all_points_fit(ref, approx, valid, F.shape[1], corr, eps_db, fit.k), "all")
        elif fit is not None and merge is not None:  # merged columns -> the texel's candidates
            assert not isinstance(F, Columns) and targets is not None  # what a merge implies
            got = (unmerge(fit, merge, F, targets, valid, eps_db), got[1])
        out.append(got)
    return out


def fit_split(
    F: np.ndarray | Columns, valid: np.ndarray, corr: float, seed: int, *, n_batch: int, psi: float,
    eps_db: float, c_max: int, n_trials: int, weights: str, colour: str,
    decorrelation_threshold: float,
) -> tuple[TexelFit | None, str]:
    """A texel wider than n_batch columns: `fit._Fitter.select`'s batches (contiguous batches
    of n_batch columns fitted on their partial sums with c_max capped at n_batch // 2, the union
    of their points fitted against the full sum), every step from Grams of <= n_batch columns:
    Gram work m n_batch d instead of m^2 d. Same draws as `fit_texel` with the same n_batch.
    F : the texel's F, held or as `Columns` (read a block of <= n_batch columns at a time:
    the memory of a step is n_batch d, whatever m).
    Returns (None, "full_svd") when a step needs the full SVD (see `fit_texel_gram`)."""
    if not isinstance(F, Columns):
        F = Columns.of_array(F, n_batch)
    ch, m, _ = F.shape
    mode = "per_channel" if (ch > 1 and corr < decorrelation_threshold) else "luminance"
    if colour != "auto":
        mode = colour
    if ch == 1:
        mode = "luminance"
    rng = np.random.default_rng(seed)
    sel_rows: list[tuple[SelectionRows, np.ndarray]]
    if mode == "luminance":
        lw = LUMA_709 if ch == 3 else np.full(ch, 1.0 / ch)
        sel_rows = [(SelectionRows(F, lw), np.arange(ch))]
    else:
        sel_rows = [(SelectionRows(F, None, c), np.array([c])) for c in range(ch)]
    kw = {"psi": psi, "eps_db": eps_db, "n_trials": n_trials, "weights": weights, "rng": rng}
    fits = []
    for S, chans in sel_rows:  # loop over <= ch groups
        def select(cand: np.ndarray, cm: int, S=S, chans=chans) -> tuple | None:
            total = F.sum_over(cand)  # (ch, d)
            targets = [total[c] for c in chans]  # (d,) per channel
            if cand.size > n_batch:
                c_batch = min(c_max, n_batch // 2)
                pools = []
                for b0 in range(0, cand.size, n_batch):  # loop over column batches
                    got = select(cand[b0:b0 + n_batch], c_batch)
                    if got is None:
                        return None
                    pools.append(got[0])
                pool = np.unique(np.concatenate(pools)).astype(np.int64)
                if pool.size > n_batch:
                    got = select(pool, c_batch)
                    if got is None:
                        return None
                    pool = got[0]
                cand = pool
            return _select_direct(F, S, chans, cand, targets, c_max=cm, **kw)
        got = select(np.arange(m, dtype=np.int64), c_max)
        if got is None:
            return None, "full_svd"
        fits.append(got)
    groups = [GroupInput((np.zeros(0), np.zeros((0, 0))), np.zeros(0), 0.0, chans)
              for _, chans in sel_rows]
    return _merge(F, valid, fits, groups, mode=mode, corr=corr, eps_db=eps_db,
                  c_max=c_max), "split"


def _select_direct(F, S, chans, cand, targets, *, c_max, psi, eps_db, n_trials, weights, rng):
    """`fit._Fitter._select_direct` on columns cand against the given targets, from Grams."""
    Sc = S[cand]
    G_sel = Sc @ Sc.T
    eig_sel = top_eighs([G_sel], psi)[0]
    s, Vt = spectrum(eig_sel)
    k = energy_rank(s, psi, float(np.trace(G_sel)))
    if needs_full_svd(s, k, cand.size):
        return None
    if k == 0:
        return (np.zeros(0, np.int64), np.zeros((0, len(chans))), 0, False)
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
    cols, alpha, capped = _bisect(p, k, red, signal, eps_db=eps_db, c_max=c_max,
                                  n_trials=n_trials, weights=weights, rng=rng)
    return (cand[cols], alpha, k, capped)


def select_groups(
    F: np.ndarray, Gc: list[np.ndarray], mode: str
) -> list[tuple[np.ndarray, np.ndarray]]:
    """The selection matrices' Grams and channels: [(G_S (m, m), chans)]. Luminance: S = F lw
    (one GEMM more); per channel: S = F_c, whose Gram is G_c."""
    ch = F.shape[0]
    if mode == "luminance":
        lw = LUMA_709 if ch == 3 else np.full(ch, 1.0 / ch)
        S = np.tensordot(lw, F, axes=(0, 0))  # (m, d)
        return [(S @ S.T, np.arange(ch))]
    return [(Gc[c], np.array([c])) for c in range(ch)]


__all__ = [
    "GroupInput", "batched_eigh", "correlation_from_sums", "top_eighs", "fit_many", "fit_texel_gram",
    "needs_full_svd",
    "normalised_gram", "select_groups", "spectrum", "_empty_fit",
]
