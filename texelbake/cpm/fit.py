"""Characteristic points of one texel (seed 000, §3.3 and §4.1): rank k, DMM06 column sampling,
weights, the bisection on c (Table 2), on the matrix R of `texelbake.cpm.matrix`."""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from typing import Any, Literal

import numpy as np

from texelbake.cpm.column_sampling import (
    column_probabilities,
    fit_weights,
    sample_columns,
    top_singular,
)
from texelbake.cpm.matrix import avis_floor, filtered_reflectance, snr_db
from texelbake.errors import NumericalError, SettingsError, ShapeError
from texelbake.tol import TOL

#: Rec. 709 / sRGB luminance weights, used to select points on one matrix for correlated colour
LUMA_709 = np.array([0.2126, 0.7152, 0.0722], dtype=np.float64)


# --------------------------------------------------------------------------- the fit


@dataclass
class TexelFit:
    """Characteristic points of one texel: f_bar ~ (sum_k weights[k] R[:, columns[k]]) / a_vis.

    columns : (c,) int64, sorted unique sample indices into the texel's m samples; only points
        with a nonzero weight in some channel are kept (NNLS leaves many drawn points at 0)
    weights : (c, ch) float32, alpha per point and channel (>= 0). In per-channel mode a point
        selected for one channel has zero weight in the others, so the renderer's sum is the
        same in both modes.
    k : int, psi-energy rank of the selection matrix (max over channels in per-channel mode; of
        the final candidate pool when batched)
    c : int, number of points (= columns.size)
    snr_db_insample : float, SNR of Eq. 7 on the sampled pairs with the float32 weights
    snr_db_heldout : float, NaN until measured (`evaluate_fit`)
    colour_mode : "luminance" | "per_channel"
    channel_correlation : float, min pairwise Pearson correlation of the channels of R (1.0 for
        a single channel or constant channels)
    k_channels, c_channels : (g,) int64, k and number of points with nonzero weight per selection
        group (one group in luminance mode, one per channel otherwise)
    c_capped : bool, c_max < k so c was capped at c_max
    merged : int, candidates fitted as a copy of another (identical columns of F,
        `texelbake.cpm.identical`): m minus the distinct columns; 0 when not merged
    eps_reached : bool, snr_db_insample >= eps_db
    valid : bool, False when the texel cannot be fitted (no samples, no valid row)
    reason : str, "" or a short description of what was special
    """

    columns: np.ndarray
    weights: np.ndarray
    k: int
    c: int
    snr_db_insample: float
    colour_mode: str
    valid: bool
    reason: str = ""
    snr_db_heldout: float = math.nan
    channel_correlation: float = 1.0
    k_channels: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    c_channels: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    c_capped: bool = False
    eps_reached: bool = False
    merged: int = 0

    def to_dict(self) -> dict[str, Any]:
        """Arrays stay numpy arrays (np.savez-able), scalars become Python scalars."""
        out: dict[str, Any] = {}
        for f in fields(self):
            v = getattr(self, f.name)
            out[f.name] = np.array(v, copy=True) if isinstance(v, np.ndarray) else v
        return out

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> TexelFit:
        """Inverse of to_dict; also accepts the 0-d arrays np.load returns for scalars."""
        kwargs: dict[str, Any] = {}
        types = {
            "columns": np.int64,
            "weights": np.float32,
            "k_channels": np.int64,
            "c_channels": np.int64,
        }
        for f in fields(cls):
            if f.name not in data:
                continue
            v = data[f.name]
            if f.name in types:
                kwargs[f.name] = np.asarray(v, dtype=types[f.name])
            elif f.name in ("k", "c"):
                kwargs[f.name] = int(v)
            elif f.name in ("valid", "c_capped", "eps_reached"):
                kwargs[f.name] = bool(v)
            elif f.name in ("colour_mode", "reason"):
                kwargs[f.name] = str(v)
            else:
                kwargs[f.name] = float(v)
        return cls(**kwargs)


def _empty_fit(m_ch: int, reason: str, valid: bool, snr: float, corr: float = 1.0) -> TexelFit:
    return TexelFit(
        columns=np.zeros(0, dtype=np.int64),
        weights=np.zeros((0, m_ch), dtype=np.float32),
        k=0,
        c=0,
        snr_db_insample=snr,
        colour_mode="luminance",
        valid=valid,
        reason=reason,
        channel_correlation=corr,
        eps_reached=valid and snr == math.inf,
    )


def needs_all_points(small: str, m: int, c_max: int, snr_insample: float) -> bool:
    """small="all": a texel of m <= c_max candidates whose fit is not exact on the grid
    (in-sample SNR under TOL.exact_fit_db: a rank-1 texel's one point is exact everywhere and
    stays one point) keeps every candidate instead (`all_points_fit`)."""
    return small == "all" and m <= c_max and not snr_insample >= TOL.exact_fit_db


def all_points_fit(F_sum: np.ndarray, approx: np.ndarray, valid: np.ndarray, m: int,
                   corr: float, eps_db: float, k: int, columns: np.ndarray | None = None,
                   weights: np.ndarray | None = None) -> TexelFit:
    """A texel that keeps every one of its m candidates with weight 1 (`small="all"`): its
    points are its candidates, so Eq. 7 is reproduced exactly at *every* direction pair, not
    only on the fitted grid (seed 000 §4.1 selects c < m by bisection even when m <= c_max,
    trading accuracy off the grid for storage that c_max already bounds). F_sum, approx :
    (d, ch) Eq. 7 of all candidates and of the stored weights (the same sum up to round-off);
    valid : (d,) rows above the floor; k : the psi-rank the fit found (reported as it is).
    columns, weights : (u,) the kept candidates (sorted) and their weights, when the m
    candidates are kept as u groups of identical ones (`texelbake.cpm.identical`: each group's
    member at the group's size); default every candidate at weight 1."""
    snr = snr_db(F_sum, approx, valid)
    ch = F_sum.shape[1]
    reason = f"all {m} candidates kept (m <= c_max)"
    if columns is None or weights is None:
        columns, weights = np.arange(m, dtype=np.int64), np.ones(m)
    else:
        reason = f"all {columns.size} distinct candidates of {m} kept (u <= c_max)"
    c = int(columns.size)
    return TexelFit(
        columns=columns, weights=np.repeat(np.asarray(weights, np.float32)[:, None], ch, 1),
        k=int(k), c=c, snr_db_insample=snr, colour_mode="luminance", valid=True,
        reason=reason, channel_correlation=corr,
        k_channels=np.array([k], np.int64), c_channels=np.array([c], np.int64),
        c_capped=False, eps_reached=bool(snr >= eps_db),
    )


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


@dataclass
class _GroupFit:
    cols: np.ndarray  # (c,) int64 into the texel's columns
    alpha: np.ndarray  # (c, ch_g) float64
    k: int
    snr: float
    capped: bool


class _Fitter:
    """One selection group: selection matrix S (d, m) and the channels it fits."""

    def __init__(
        self,
        R: np.ndarray,
        S: np.ndarray,
        chans: np.ndarray,
        avis_rows: np.ndarray,
        eps_avis: float,
        *,
        psi: float,
        eps_db: float,
        c_max: int,
        n_trials: int,
        weights: Literal["nnls", "clamp"],
        n_batch: int,
        rng: np.random.Generator,
        rows: Literal["eq7", "seed"],
    ):
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
        self.psi, self.eps_db, self.c_max = psi, eps_db, c_max
        self.n_trials, self.weights, self.n_batch, self.rng = n_trials, weights, n_batch, rng

    def _trial(self, cols: np.ndarray, target: np.ndarray, fbar_ref) -> tuple[np.ndarray, float]:
        n_g = len(self.chans)
        alpha = np.zeros((cols.size, n_g))  # (c, ch_g)
        approx = np.zeros((self.Rc.shape[1], n_g))  # (d, ch_g)
        for g in range(n_g):  # loop over <= 3 channels
            C = self.Rc[g][:, cols]  # (d, c)
            alpha[:, g] = fit_weights(C, target[:, g], self.weights)
            approx[:, g] = C @ alpha[:, g]
        fbar_apx = approx * self.eval_scale[:, None]
        return alpha, snr_db(fbar_ref, fbar_apx, self.valid)

    def _reduce(self, cand: np.ndarray, target: np.ndarray) -> list[tuple] | None:
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

    def _trial_reduced(self, local: np.ndarray, red: list[tuple], signal: float
                       ) -> tuple[np.ndarray, float]:
        """`_trial` in the reduced space (local: indices into cand). The SNR is for ranking
        draws and the bisection; the kept fit's SNR is recomputed in full (`_trial`)."""
        alpha = np.zeros((local.size, len(red)))
        noise = 0.0
        for g, (A, t, rest) in enumerate(red):  # loop over <= 3 channels
            C = A[:, local]
            alpha[:, g] = fit_weights(C, t, self.weights)
            r = C @ alpha[:, g] - t
            noise += float(r @ r) + rest
        if noise <= 0.0:
            return alpha, math.inf
        if signal <= 0.0:
            return alpha, -math.inf
        return alpha, 10.0 * math.log10(signal / noise)

    def select(self, cand: np.ndarray, c_max: int | None = None) -> _GroupFit:
        """Select among candidate columns cand (m',) for the target sum over cand.

        Batching (n_batch bounds the columns in one SVD): if m' > n_batch, cand is split into
        contiguous batches of n_batch (sample order, i.e. spatially coherent in g(p)); each
        batch is fitted on its own partial sum (same psi and eps, c_max capped at n_batch // 2);
        the union of the batch selections is the new candidate pool (reduced again the same way
        while it exceeds n_batch), which is fitted against the full sum over cand with c_max.
        A pool is at most ceil(m'/n_batch) * n_batch/2 <= m'/2 + n_batch/2 < m' columns, so
        the recursion terminates.
        """
        c_max = self.c_max if c_max is None else c_max
        target = self.Rc[:, :, cand].sum(axis=2).T  # (d, ch_g)
        if cand.size > self.n_batch:
            c_batch = min(self.c_max, self.n_batch // 2)
            pools = [
                self.select(cand[b0 : b0 + self.n_batch], c_batch).cols
                for b0 in range(0, cand.size, self.n_batch)  # loop over batches
            ]
            pool = np.unique(np.concatenate(pools)).astype(np.int64)
            if pool.size > self.n_batch:
                pool = self.select(pool, c_batch).cols
            return self._select_direct(pool, target, c_max)
        return self._select_direct(cand, target, c_max)

    def _select_direct(self, cand: np.ndarray, target: np.ndarray, c_max: int) -> _GroupFit:
        fbar_ref = target * self.eval_scale[:, None]  # (d, ch_g), Eq. 7
        S = self.S[:, cand]  # (d, m')
        col_energy = np.einsum("dm,dm->m", S, S)
        U, s, Vt, k = top_singular(S, self.psi, compute_u=False)  # Table 2 needs no U
        if k == 0:  # nothing to select: zero matrix; alpha = 0 reproduces it
            empty = np.zeros(0, dtype=np.int64)
            _, snr = self._trial(empty, target, fbar_ref)
            return _GroupFit(empty, np.zeros((0, len(self.chans))), 0, snr, False)
        p = column_probabilities(U, s, Vt, k, col_energy=col_energy)
        cache: dict[int, tuple[np.ndarray, np.ndarray, float]] = {}
        red = self._reduce(cand, target)
        signal = float(np.sum(fbar_ref[self.valid] ** 2))

        def best_of_trials(c: int) -> tuple[np.ndarray, np.ndarray, float]:
            if c not in cache:
                best: tuple[np.ndarray, np.ndarray, float] | None = None
                seen: set[bytes] = set()
                for _ in range(self.n_trials):  # loop over a handful of randomized trials
                    local = sample_columns(p, c, self.rng)
                    key = local.tobytes()
                    if key in seen:  # same draw again: same fit, skip the solve
                        continue
                    seen.add(key)
                    cols = cand[local]
                    if red is None:
                        alpha, snr = self._trial(cols, target, fbar_ref)
                    else:
                        alpha, snr = self._trial_reduced(local, red, signal)
                    if best is None or snr > best[2]:
                        best = (cols, alpha, snr)
                assert best is not None  # n_trials >= 1 is checked in fit_texel
                cache[c] = best
            return cache[c]

        capped = c_max < k
        lo, hi = (c_max, c_max) if capped else (k, c_max)
        # seed 000 §4.1: bisection on [k, c_max] with the median as the probe
        while lo < hi:
            mid = (lo + hi) // 2
            if best_of_trials(mid)[2] >= self.eps_db:
                hi = mid
            else:
                lo = mid + 1
        cols, alpha, snr = best_of_trials(lo)
        if red is not None:  # the reported SNR in full precision, on the kept weights
            n_g = len(self.chans)
            approx = np.stack([self.Rc[g][:, cols] @ alpha[:, g] for g in range(n_g)], axis=1)
            snr = snr_db(fbar_ref, approx * self.eval_scale[:, None], self.valid)
        return _GroupFit(cols, alpha, k, snr, capped)


def _storable_weights(w64: np.ndarray) -> np.ndarray:
    """float32 weights; a weight that is not finite or would overflow float32 becomes 0.

    NNLS gives a column whose values are vanishingly small (a point seen at grazing angles,
    or a child's point carrying a tiny area at a coarse level) a weight of 1/its scale; past
    float32's range that is inf, and inf x 0 = NaN poisons the next level's R (seen on the
    small bolt at 32²). Such a point represents nothing; dropping it keeps the texel finite,
    and the fit's SNR, recomputed from the stored weights, reports what was lost."""
    w = np.asarray(w64, dtype=np.float64)
    ok = np.isfinite(w) & (np.abs(w) <= 1e-3 * float(np.finfo(np.float32).max))
    return np.where(ok, w, 0.0).astype(np.float32)


def fit_texel(
    R: np.ndarray,
    avis_rows: np.ndarray,
    *,
    psi: float = 0.97,
    eps_db: float = 30.0,
    c_max: int = 64,
    n_trials: int = 8,
    weights: Literal["nnls", "clamp"] = "nnls",
    colour: Literal["auto", "luminance", "per_channel"] = "auto",
    decorrelation_threshold: float = 0.5,
    seed: int = 0,
    n_batch: int = 2048,
    texel_area: float | None = None,
    rows: Literal["eq7", "seed"] = "eq7",
    small: Literal["fit", "all"] = "fit",
) -> TexelFit:
    """Characteristic points and weights of one texel (seed 000 §3.3, §4.1; DMM06 Table 2).

    R : (d, m, ch) float64, Eq. 9's matrix (see `reflectance_matrix`); ch = 1 or 3 (any ch works;
        luminance weights are Rec. 709 for ch = 3 and equal otherwise)
    avis_rows : (d,) float64, a_vis(w_o) per row
    psi : energy fraction for k (seed: 0.97); eps_db : target SNR of Eq. 7 in dB (seed: 30)
    c_max : max number of draws c; n_trials : randomized trials per c, the best (by the Eq. 7 SNR,
        1/a_vis included) is kept; weights : "nnls" (DESIGN.md default) or "clamp" (the seed)
    colour : "luminance" selects on sum_ch w_ch R[..., ch] and fits alpha per channel;
        "per_channel" selects per channel; "auto" = per_channel when the min pairwise channel
        correlation (`channel_correlation`) is below decorrelation_threshold. Measured (random
        two-material texels, m = 120, c_max 64): at correlation -0.17 per-channel reaches 31 dB
        with 86 points where luminance stalls at 19 dB; at 0.76 and 0.93 both give the same SNR
        but per-channel needs 75-86 points against 44-46, hence the default 0.5
    seed : rng seed (trials); equal inputs and seed give byte-identical output
    n_batch : max columns in one SVD (see _Fitter.select for the scheme), >= 2
    texel_area : scale of the a_vis floor (eps = TOL.avis_floor * texel_area); default: the
        largest a_vis over the rows (~ the texel area for directions near its normal)
    rows : "eq7" (default) selects columns and fits alpha on F = diag(1/a_vis) R, whose row sums
        are Eq. 7 itself, so the NNLS objective is exactly the error the SNR measures (the
        "new matrix formulation which also includes the 1/a_vis term" the seed's §3.2 leaves to
        future work); "seed" selects and fits on R as the seed does. Rows with a_vis <= eps
        get zero weight under "eq7". Measured in benchmarks/column_sampling.py.
    small : "fit" (the seed: bisection on c even when m <= c_max) or "all": a texel with
        m <= c_max whose fit is not exact on the grid keeps all its candidates with weight 1
        (`needs_all_points`, `all_points_fit`; BakeSettings.small_texels)
    returns : TexelFit

    c search (seed §4.1): bisection on [k, c_max]; for a probe c, n_trials draws of c columns
    from the Table 2 probabilities, alpha fitted per channel, best SNR kept; the interval keeps
    the half that contains the smallest c reaching eps_db. If c_max < k, c = c_max (c_capped).
    Defined special cases: m = 0 -> c = 0, valid False; all-zero R -> c = 0, SNR +inf, valid
    True; no row with a_vis > eps -> c = 0, valid False; non-finite R or a_vis -> NumericalError.
    """
    R = np.asarray(R, dtype=np.float64)
    avis_rows = np.asarray(avis_rows, dtype=np.float64).ravel()
    if R.ndim != 3:
        raise ShapeError(f"R must be (d, m, ch), got shape {R.shape}")
    d, m, ch = R.shape
    if avis_rows.shape != (d,):
        raise ShapeError(f"avis_rows must be ({d},) to match R {R.shape}, got {avis_rows.shape}")
    if not 0.0 < psi <= 1.0:
        raise SettingsError(f"psi must be in (0, 1], got {psi}")
    if c_max < 1 or n_trials < 1:
        raise SettingsError(
            f"c_max and n_trials must be >= 1, got c_max={c_max}, n_trials={n_trials}"
        )
    if n_batch < 2:
        raise SettingsError(f"n_batch must be >= 2, got {n_batch}")
    if colour not in ("auto", "luminance", "per_channel"):
        raise SettingsError(f"colour must be 'auto', 'luminance' or 'per_channel', got {colour!r}")
    if weights not in ("nnls", "clamp"):
        raise SettingsError(f"weights must be 'nnls' or 'clamp', got {weights!r}")
    if rows not in ("eq7", "seed"):
        raise SettingsError(f"rows must be 'eq7' or 'seed', got {rows!r}")
    if ch < 1:
        raise ShapeError(f"R needs at least one channel, got {R.shape}")
    if not np.all(np.isfinite(R)):
        raise NumericalError(f"R has {int(np.count_nonzero(~np.isfinite(R)))} non-finite entries")
    if not np.all(np.isfinite(avis_rows)):
        raise NumericalError("avis_rows has non-finite entries")
    if m == 0 or d == 0:
        return _empty_fit(ch, "empty texel (m = 0 samples or d = 0 rows)", False, math.nan)

    if texel_area is None:
        texel_area = float(avis_rows.max()) if avis_rows.size else 0.0
    eps_avis = avis_floor(texel_area)
    fbar_ref, valid = filtered_reflectance(R.sum(axis=1), avis_rows, eps_avis)
    if not np.any(valid):
        return _empty_fit(
            ch, "no row with a_vis above the floor (fully masked texel)", False, math.nan
        )
    if float(np.vdot(R, R)) <= TOL.energy_floor:
        return _empty_fit(ch, "all-zero R: nothing reflects, c = 0", True, math.inf)

    corr = channel_correlation(R)
    mode = colour
    if colour == "auto":
        mode = "per_channel" if (ch > 1 and corr < decorrelation_threshold) else "luminance"
    if ch == 1:
        mode = "luminance"
    if small not in ("fit", "all"):
        raise SettingsError(f"small must be 'fit' or 'all', got {small!r}")

    rng = np.random.default_rng(seed)
    cand = np.arange(m, dtype=np.int64)
    if mode == "luminance":
        lw = LUMA_709 if ch == 3 else np.full(ch, 1.0 / ch)
        S = np.einsum("dmc,c->dm", R, lw)  # (d, m)
        groups = [(S, np.arange(ch))]
    else:
        groups = [(R[:, :, g], np.array([g])) for g in range(ch)]
    fits = [
        _Fitter(
            R,
            S,
            chans,
            avis_rows,
            eps_avis,
            psi=psi,
            eps_db=eps_db,
            c_max=int(c_max),
            n_trials=int(n_trials),
            weights=weights,
            n_batch=int(n_batch),
            rng=rng,
            rows=rows,
        ).select(cand)
        for S, chans in groups
    ]

    # merge groups: union of columns, weights (c, ch) with zeros where a group does not fit
    columns = np.unique(np.concatenate([gf.cols for gf in fits])).astype(np.int64)
    w64 = np.zeros((columns.size, ch), dtype=np.float64)
    for gf, (_, chans) in zip(fits, groups, strict=True):  # loop over <= ch groups
        pos = np.searchsorted(columns, gf.cols)
        w64[np.ix_(pos, chans)] = gf.alpha
    w32 = _storable_weights(w64)
    # NNLS solutions are sparse: a drawn point whose weight is 0 in every channel contributes
    # nothing and would only cost render time, so it is not stored
    live = np.any(w32 != 0.0, axis=1)
    columns, w32 = columns[live], w32[live]
    approx = np.einsum("dcx,cx->dx", R[:, columns], w32.astype(np.float64))  # (d, ch)
    fbar_apx, _ = filtered_reflectance(approx, avis_rows, eps_avis)
    snr = snr_db(fbar_ref, fbar_apx, valid)
    if needs_all_points(small, m, c_max, snr):
        approx_all = np.einsum("dcx,cx->dx", R, np.ones((m, ch)))
        return all_points_fit(fbar_ref, filtered_reflectance(approx_all, avis_rows, eps_avis)[0],
                              valid, m, corr, eps_db, max(gf.k for gf in fits))
    capped = any(gf.capped for gf in fits)
    reasons = []
    if capped:
        reasons.append(f"c_max={c_max} < k: c capped")
    if snr < eps_db:
        reasons.append(f"eps {eps_db} dB not reached (SNR {snr:.2f} dB)")
    return TexelFit(
        columns=columns,
        weights=w32,
        k=max(gf.k for gf in fits),
        c=int(columns.size),
        snr_db_insample=snr,
        colour_mode=mode,
        valid=True,
        reason="; ".join(reasons),
        channel_correlation=corr,
        k_channels=np.array([gf.k for gf in fits], dtype=np.int64),
        c_channels=np.array(
            [int(np.count_nonzero(np.any(gf.alpha != 0.0, axis=1))) for gf in fits], dtype=np.int64
        ),
        c_capped=capped,
        eps_reached=bool(snr >= eps_db),
    )


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
