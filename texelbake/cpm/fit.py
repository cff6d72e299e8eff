"""Characteristic points of one texel on its matrix R (seed 000 §3.3 and §4.1; the per-texel
path): rank k, DMM06 column sampling, weights, the search on c (`texelbake.cpm.search`), on the
matrix R of `texelbake.cpm.matrix`; the result assembled as both paths assemble it
(`texelbake.cpm.texel_fit`)."""

from __future__ import annotations

import math
from typing import Literal

import numpy as np

from texelbake.cpm.column_sampling import column_probabilities, fit_weights, top_singular
from texelbake.cpm.matrix import avis_floor, filtered_reflectance, snr_db
from texelbake.cpm.search import Reduced, Trial, reduced_trial, search_c, select_batched
from texelbake.cpm.texel_fit import (
    LUMA_709,
    FitCounts,
    FitParams,
    GroupFit,
    TexelFit,
    all_points_fit,
    assemble_fit,
    empty_fit,
    needs_all_points,
)
from texelbake.errors import NumericalError, SettingsError, ShapeError
from texelbake.tol import TOL


def channel_correlation(R: np.ndarray) -> float:
    """Min pairwise Pearson correlation between the colour channels of R (d, m, ch), flattened.

    A channel with zero variance correlates with everything (1.0): there is nothing to select
    for it separately. returns 1.0 for ch == 1.
    """
    ch = R.shape[2]
    if ch < 2 or R.shape[0] * R.shape[1] < 2:
        return 1.0
    X = R.reshape(-1, ch)  # (d*m, ch), a view: no copy of a large R
    mu = X.mean(axis=0)
    # one-pass covariance; its cancellation only matters for near-constant channels, and the
    # value feeds a threshold decision, not arithmetic
    cov = X.T @ X - X.shape[0] * np.outer(mu, mu)  # (ch, ch)
    var = np.diag(cov)
    # a variance below the one-pass rounding (TOL.const_channel_var of sum x^2): constant
    ok = var > TOL.const_channel_var * np.einsum("nc,nc->c", X, X)
    sd = np.sqrt(np.where(ok, var, 1.0))
    corr = np.ones((ch, ch))
    both = ok[:, None] & ok[None, :]
    corr[both] = (cov / np.outer(np.where(ok, sd, 1.0), np.where(ok, sd, 1.0)))[both]
    return float(np.clip(corr.min(), -1.0, 1.0))


class _Fitter:
    """One selection group of a texel on R: selection matrix S (d, m) and the channels it fits."""

    def __init__(self, R: np.ndarray, S: np.ndarray, chans: np.ndarray, avis_rows: np.ndarray,
                 eps_avis: float, params: FitParams, rng: np.random.Generator,
                 rows: Literal["eq7", "seed"], counts: FitCounts | None = None):
        self.chans = chans
        valid = np.isfinite(avis_rows) & (avis_rows > eps_avis)
        inv_avis = np.where(valid, 1.0 / np.where(valid, avis_rows, 1.0), 0.0)  # (d,)
        # rows="eq7": select and fit on F = diag(1/a_vis) R, the matrix whose row sums are
        # Eq. 7 itself (invalid rows zero); rows="seed": on R as the seed (§3.2 notes the
        # mismatch). f_bar = (R_fit alpha) * eval_scale in both cases.
        fit_scale = inv_avis if rows == "eq7" else np.ones_like(inv_avis)
        self.eval_scale = np.ones_like(inv_avis) * valid if rows == "eq7" else inv_avis
        self.S = S * fit_scale[:, None]  # (d, m)
        # (ch_g, d, m) contiguous per channel: column gathers and mat-vecs go through BLAS
        self.Rc = np.ascontiguousarray(np.moveaxis(R[:, :, chans], 2, 0) * fit_scale[None, :, None])
        self.valid = valid
        self.rows = rows
        self.params, self.rng, self.counts = params, rng, counts

    def _trial(self, cols: np.ndarray, target: np.ndarray, fbar_ref) -> tuple[np.ndarray, float]:
        """A draw's weights (c, ch_g) fitted on R's columns and its SNR of Eq. 7 in full."""
        n_g = len(self.chans)
        alpha = np.zeros((cols.size, n_g))  # (c, ch_g)
        approx = np.zeros((self.Rc.shape[1], n_g))  # (d, ch_g)
        for g in range(n_g):  # loop over <= 3 channels
            C = self.Rc[g][:, cols]  # (d, c)
            alpha[:, g] = fit_weights(C, target[:, g], self.params.weights)
            approx[:, g] = C @ alpha[:, g]
        fbar_apx = approx * self.eval_scale[:, None]
        return alpha, snr_db(fbar_ref, fbar_apx, self.valid)

    def _reduce(self, cand: np.ndarray, target: np.ndarray) -> list[Reduced] | None:
        """Per channel (A (r, m'), t (r,), rest): ||Rc[g][:, cand] a - target_g||^2 =
        ||A a - t||^2 + rest for every a (to ~sqrt(eps) ||M||), with r <= m' rows instead of d.
        Only for rows="eq7", where the Eq. 7 error *is* this residual (eval_scale is the 0/1
        valid mask and invalid rows are zero in Rc).

        From the Gram matrix of the unit-scaled columns, G = Mn^T Mn = V diag(lam) V^T (one BLAS
        syrk, d m'^2 flops, then an m' x m' eigh): A = diag(sqrt(lam)) V^T diag(norms),
        t = diag(1/sqrt(lam)) V^T Mn^T target over the resolved eigenvalues (lam > m' eps
        lam_max; the rest carry no energy of M). Rank-revealing, so duplicate, collinear and
        zero columns (frequent: one material's facets are rank 1) need no special case.
        Measured, one thread, 4096 x 200: Gram 4.5 ms against 34 ms for a thin QR without
        forming Q. The trials rank draws on this; the kept fit's SNR is recomputed in full."""
        d, m = self.Rc.shape[1], cand.size
        if self.rows != "eq7" or m >= d // 2:
            return None
        out = []
        for g in range(len(self.chans)):  # loop over <= 3 channels
            M = self.Rc[g][:, cand]  # (d, m')
            t = target[:, g]
            norms = np.linalg.norm(M, axis=0)
            scale = np.where(norms > 0, norms, 1.0)
            Mn = M / scale  # unit columns; zero columns stay zero
            lam, V = np.linalg.eigh(Mn.T @ Mn)  # ascending
            keep = lam > max(float(lam[-1]), 0.0) * m * np.finfo(np.float64).eps
            sq = np.sqrt(lam[keep])
            Vk = V[:, keep]  # (m', r)
            A = (sq[:, None] * Vk.T) * scale[None, :]  # (r, m'): A^T A = M^T M
            tq = (Vk.T @ (Mn.T @ t)) / sq  # (r,)
            out.append((A, tq, max(float(t @ t - tq @ tq), 0.0)))
        return out

    def select(self, cand: np.ndarray) -> GroupFit:
        """Points among candidate columns cand (m',) for the sum over cand, in batches of
        n_batch columns when wider (`search.select_batched`)."""
        got = select_batched(cand, self.params.c_max, self.params, self._select_direct)
        assert got is not None  # the direct selection on R always answers
        return got

    def _select_direct(self, cand: np.ndarray, whole: np.ndarray, c_max: int) -> GroupFit:
        """Points among cand for Eq. 7 summed over `whole` (cand itself, or the candidates a
        batched pool came from)."""
        target = self.Rc[:, :, whole].sum(axis=2).T  # (d, ch_g)
        fbar_ref = target * self.eval_scale[:, None]  # (d, ch_g), Eq. 7
        S = self.S[:, cand]  # (d, m')
        col_energy = np.einsum("dm,dm->m", S, S)
        U, s, Vt, k = top_singular(S, self.params.psi, compute_u=False)  # Table 2 needs no U
        if k == 0:  # nothing to select: zero matrix; alpha = 0 reproduces it
            return GroupFit(np.zeros(0, dtype=np.int64), np.zeros((0, len(self.chans))), 0,
                            False)
        p = column_probabilities(U, s, Vt, k, col_energy=col_energy)
        red = self._reduce(cand, target)
        trial: Trial
        if red is None:
            def full_trial(local: np.ndarray) -> tuple[np.ndarray, float]:
                return self._trial(cand[local], target, fbar_ref)
            trial = full_trial
        else:
            signal = float(np.sum(fbar_ref[self.valid] ** 2))
            trial = reduced_trial(red, signal, self.params.weights)
        local, alpha, capped = search_c(p, k, trial, self.rng, c_max, self.params, self.counts)
        return GroupFit(cand[local], alpha, k, capped)


def fit_texel(
    R: np.ndarray,
    avis_rows: np.ndarray,
    params: FitParams | None = None,
    *,
    seed: int = 0,
    texel_area: float | None = None,
    rows: Literal["eq7", "seed"] = "eq7",
    counts: FitCounts | None = None,
) -> TexelFit:
    """Characteristic points and weights of one texel (seed 000 §3.3, §4.1; DMM06 Table 2).

    R : (d, m, ch) float64, Eq. 9's matrix (see `reflectance_matrix`); ch = 1 or 3 (any ch works;
        luminance weights are Rec. 709 for ch = 3 and equal otherwise)
    avis_rows : (d,) float64, a_vis(w_o) per row
    params : `FitParams` (default: its standalone defaults). colour="auto", measured (random
        two-material texels, m = 120, c_max 64): at correlation -0.17 per-channel reaches 31 dB
        with 86 points where luminance stalls at 19 dB; at 0.76 and 0.93 both give the same SNR
        but per-channel needs 75-86 points against 44-46, hence the standalone threshold 0.5
    seed : rng seed (trials); equal inputs and seed give byte-identical output
    texel_area : scale of the a_vis floor (eps = TOL.avis_floor * texel_area); default: the
        largest a_vis over the rows (~ the texel area for directions near its normal)
    rows : "eq7" (default) selects columns and fits alpha on F = diag(1/a_vis) R, whose row sums
        are Eq. 7 itself, so the NNLS objective is exactly the error the SNR measures (the
        "new matrix formulation which also includes the 1/a_vis term" the seed's §3.2 leaves to
        future work); "seed" selects and fits on R as the seed does. Rows with a_vis <= eps
        get zero weight under "eq7". Measured in benchmarks/column_sampling.py.
    counts : `FitCounts` to add the search's work to
    returns : TexelFit

    The search on c is `search.search_c`; with params.small="all" a texel of m <= c_max whose
    fit is not exact on the grid keeps all its candidates with weight 1 (`all_points_fit`).
    Defined special cases: m = 0 -> c = 0, valid False; all-zero R -> c = 0, SNR +inf, valid
    True; no row with a_vis > eps -> c = 0, valid False; non-finite R or a_vis -> NumericalError.
    """
    params = FitParams() if params is None else params
    R = np.asarray(R, dtype=np.float64)
    avis_rows = np.asarray(avis_rows, dtype=np.float64).ravel()
    if R.ndim != 3:
        raise ShapeError(f"R must be (d, m, ch), got shape {R.shape}")
    d, m, ch = R.shape
    if avis_rows.shape != (d,):
        raise ShapeError(f"avis_rows must be ({d},) to match R {R.shape}, got {avis_rows.shape}")
    if rows not in ("eq7", "seed"):
        raise SettingsError(f"rows must be 'eq7' or 'seed', got {rows!r}")
    if ch < 1:
        raise ShapeError(f"R needs at least one channel, got {R.shape}")
    if not np.all(np.isfinite(R)):
        raise NumericalError(f"R has {int(np.count_nonzero(~np.isfinite(R)))} non-finite entries")
    if not np.all(np.isfinite(avis_rows)):
        raise NumericalError("avis_rows has non-finite entries")
    if m == 0 or d == 0:
        return empty_fit(ch, "empty texel (m = 0 samples or d = 0 rows)", False, math.nan)

    if texel_area is None:
        texel_area = float(avis_rows.max()) if avis_rows.size else 0.0
    eps_avis = avis_floor(texel_area)
    fbar_ref, valid = filtered_reflectance(R.sum(axis=1), avis_rows, eps_avis)
    if not np.any(valid):
        return empty_fit(
            ch, "no row with a_vis above the floor (fully masked texel)", False, math.nan
        )
    if float(np.vdot(R, R)) <= TOL.energy_floor:
        return empty_fit(ch, "all-zero R: nothing reflects, c = 0", True, math.inf)

    corr = channel_correlation(R)
    mode = params.colour_mode(ch, corr)
    rng = np.random.default_rng(seed)
    cand = np.arange(m, dtype=np.int64)
    if mode == "luminance":
        S = np.einsum("dmc,c->dm", R, params.luma(ch))  # (d, m)
        groups = [(S, np.arange(ch))]
    else:
        groups = [(R[:, :, g], np.array([g])) for g in range(ch)]
    fits = [_Fitter(R, S, chans, avis_rows, eps_avis, params, rng, rows, counts).select(cand)
            for S, chans in groups]

    def eq7(columns: np.ndarray, w: np.ndarray) -> np.ndarray:  # (d, ch) of weighted points
        approx = np.einsum("dcx,cx->dx", R[:, columns], w)
        return filtered_reflectance(approx, avis_rows, eps_avis)[0]

    fit = assemble_fit(fits, [chans for _, chans in groups], ch, eq7, fbar_ref, valid,
                       mode=mode, corr=corr, params=params)
    if needs_all_points(params.small, m, params.c_max, fit.snr_db_insample):
        approx_all = np.einsum("dcx,cx->dx", R, np.ones((m, ch)))
        return all_points_fit(fbar_ref, filtered_reflectance(approx_all, avis_rows, eps_avis)[0],
                              valid, m, corr, params.eps_db, fit.k)
    return fit


def reconstruct(
    fit: TexelFit, R_rows: np.ndarray, avis_rows: np.ndarray, eps: float
) -> tuple[np.ndarray, np.ndarray]:
    """Eq. 7 from the characteristic points on any rows (e.g. held-out pairs), seed Eq. 8.

    R_rows : (d', m, ch) float64 (only the fit's columns are read; the full matrix is accepted
        so the reference R_rows 1 can be formed from the same array)
    avis_rows : (d',) float64; eps : absolute a_vis floor
    returns : (f_bar_approx (d', ch) float64, valid (d',) bool)
    """
    R_rows = np.asarray(R_rows, dtype=np.float64)
    if R_rows.ndim != 3 or R_rows.shape[2] != fit.weights.shape[1]:
        raise ShapeError(f"R_rows must be (d', m, {fit.weights.shape[1]}), got {R_rows.shape}")
    w = np.asarray(fit.weights, dtype=np.float64)
    approx = np.einsum("dcx,cx->dx", R_rows[:, fit.columns], w)  # (d', ch)
    return filtered_reflectance(approx, avis_rows, eps)


def evaluate_fit(fit: TexelFit, R_rows: np.ndarray, avis_rows: np.ndarray, eps: float) -> float:
    """SNR (dB) of the fit against the full Eq. 7 on the given rows (held-out generalization).

    R_rows : (d', m, ch) float64, all m columns; avis_rows : (d',) float64; eps : a_vis floor
    returns : float (see snr_db for the limits)
    """
    R_rows = np.asarray(R_rows, dtype=np.float64)
    fbar_ref, valid = filtered_reflectance(R_rows.sum(axis=1), avis_rows, eps)
    fbar_apx, _ = reconstruct(fit, R_rows, avis_rows, eps)
    return snr_db(fbar_ref, fbar_apx, valid)


__all__ = ["LUMA_709", "FitParams", "TexelFit", "channel_correlation", "evaluate_fit",
           "fit_texel", "reconstruct"]
