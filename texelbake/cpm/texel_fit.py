"""One texel's fit as both fitting paths report it (seed 000 §3.3, §4.1): the fit's parameters
(`FitParams`), a selection group's result (`GroupFit`), the assembly of the groups into the
texel's `TexelFit` (`assemble_fit`), and the texel that keeps every candidate
(`all_points_fit`). The per-texel path (`texelbake.cpm.fit`, on R) and the batched path
(`texelbake.cpm.gram.fit`, on Gram matrices) differ only in how they compute Eq. 7 of a set of
weighted points; everything else about a texel's result is assembled here.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, fields
from typing import Any, Literal

import numpy as np

from texelbake.cpm.matrix import snr_db
from texelbake.errors import SettingsError
from texelbake.tol import TOL

#: Rec. 709 / sRGB luminance weights, used to select points on one matrix for correlated colour
LUMA_709 = np.array([0.2126, 0.7152, 0.0722], dtype=np.float64)


@dataclass(frozen=True)
class FitParams:
    """What the fit of one texel is asked for (the fit group of `BakeSettings`).

    psi : energy fraction for the rank k (seed: 0.97); eps_db : target SNR of Eq. 7 (seed: 30)
    c_max : most points; n_trials : randomized draws per probed c, the best kept
    weights : "nnls" or "clamp" (the seed's C+R1 with negatives set to 0)
    colour : "luminance" selects on sum_ch w_ch R[..., ch] and fits alpha per channel;
        "per_channel" selects per channel; "auto" = per_channel when the min pairwise channel
        correlation is below decorrelation_threshold
    n_batch : most columns in one selection (wider candidate sets go in batches), >= 2
    small : "fit" (the seed's bisection) or "all": a texel of m <= c_max candidates whose fit
        is not exact on the grid keeps every candidate (`needs_all_points`)
    identical : "keep" (the seed) or "merge": identical columns fitted as one
        (`texelbake.cpm.gram.identical`; the batched path only)

    The defaults are a standalone texel's; a bake's come from its settings (`of`)."""

    psi: float = 0.97
    eps_db: float = 30.0
    c_max: int = 64
    n_trials: int = 8
    weights: Literal["nnls", "clamp"] = "nnls"
    colour: Literal["auto", "luminance", "per_channel"] = "auto"
    decorrelation_threshold: float = 0.5
    n_batch: int = 2048
    small: Literal["fit", "all"] = "fit"
    identical: Literal["keep", "merge"] = "keep"

    def __post_init__(self) -> None:
        if not 0.0 < self.psi <= 1.0:
            raise SettingsError(f"psi must be in (0, 1], got {self.psi}")
        if self.c_max < 1 or self.n_trials < 1:
            raise SettingsError(f"c_max and n_trials must be >= 1, got c_max={self.c_max}, "
                                f"n_trials={self.n_trials}")
        if self.n_batch < 2:
            raise SettingsError(f"n_batch must be >= 2, got {self.n_batch}")
        choices = {"colour": ("auto", "luminance", "per_channel"), "weights": ("nnls", "clamp"),
                   "small": ("fit", "all"), "identical": ("keep", "merge")}
        for name, allowed in choices.items():  # four choices
            if getattr(self, name) not in allowed:
                raise SettingsError(f"{name} must be one of {allowed}, got "
                                    f"{getattr(self, name)!r}")

    @classmethod
    def of(cls, settings: Any) -> FitParams:
        """The fit's parameters of a bake (`schemas.settings.BakeSettings`)."""
        s = settings
        return cls(psi=s.psi, eps_db=s.eps_db, c_max=s.c_max, n_trials=s.n_trials,
                   weights=s.weights, colour=s.colour,
                   decorrelation_threshold=s.decorrelation_threshold, n_batch=s.n_batch,
                   small=s.small_texels, identical=s.identical_columns)

    def colour_mode(self, ch: int, corr: float) -> str:
        """"luminance" or "per_channel" for a texel of ch channels whose R has the channel
        correlation corr (`fit.channel_correlation`)."""
        if ch == 1:
            return "luminance"
        if self.colour != "auto":
            return self.colour
        return "per_channel" if corr < self.decorrelation_threshold else "luminance"

    def luma(self, ch: int) -> np.ndarray:
        """(ch,) float64 luminance weights of the selection matrix: Rec. 709 for three
        channels, equal otherwise."""
        return LUMA_709 if ch == 3 else np.full(ch, 1.0 / ch)


@dataclass
class FitCounts:
    """Work done by the fits of one process, for benchmarks: probes of c, NNLS draws solved,
    texels with identical candidates and the candidates merged away (pass one to the fit)."""

    probes: int = 0
    draws: int = 0
    merged_texels: int = 0
    merged_columns: int = 0

    def as_dict(self) -> dict[str, int]:
        return {f.name: int(getattr(self, f.name)) for f in fields(self)}


@dataclass(frozen=True)
class GroupFit:
    """One selection group's points: cols (c,) int64 into the texel's columns, alpha (c, ch_g)
    float64 weights of the group's channels, k the psi-rank, capped when c_max < k."""

    cols: np.ndarray
    alpha: np.ndarray
    k: int
    capped: bool


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
    snr_db_heldout : float, NaN until measured (`fit.evaluate_fit`)
    colour_mode : "luminance" | "per_channel"
    channel_correlation : float, min pairwise Pearson correlation of the channels of R (1.0 for
        a single channel or constant channels)
    k_channels, c_channels : (g,) int64, k and number of points with nonzero weight per selection
        group (one group in luminance mode, one per channel otherwise)
    c_capped : bool, c_max < k so c was capped at c_max
    merged : int, candidates fitted as a copy of another (identical columns of F,
        `texelbake.cpm.gram.identical`): m minus the distinct columns; 0 when not merged
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


def empty_fit(m_ch: int, reason: str, valid: bool, snr: float, corr: float = 1.0) -> TexelFit:
    """A fit of no points: (0,) columns, (0, m_ch) float32 weights."""
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


def storable_weights(w64: np.ndarray) -> np.ndarray:
    """float32 weights (c, ch) of float64 ones; a weight that is not finite or would overflow
    float32 becomes 0.

    NNLS gives a column whose values are vanishingly small (a point seen at grazing angles,
    or a child's point carrying a tiny area at a coarse level) a weight of 1/its scale; past
    float32's range that is inf, and inf x 0 = NaN poisons the next level's R (seen on the
    small bolt at 32²). Such a point represents nothing; dropping it keeps the texel finite,
    and the fit's SNR, recomputed from the stored weights, reports what was lost."""
    w = np.asarray(w64, dtype=np.float64)
    ok = np.isfinite(w) & (np.abs(w) <= 1e-3 * float(np.finfo(np.float32).max))
    return np.where(ok, w, 0.0).astype(np.float32)


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
    candidates are kept as u groups of identical ones (`texelbake.cpm.gram.identical`: each group's
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


def assemble_fit(
    groups: Sequence[GroupFit], chans: Sequence[np.ndarray], ch: int,
    eq7: Callable[[np.ndarray, np.ndarray], np.ndarray], ref: np.ndarray, valid: np.ndarray,
    *, mode: str, corr: float, params: FitParams,
) -> TexelFit:
    """A texel's fit from its selection groups: the union of their columns, float32 weights
    (c, ch) with zeros where a group does not fit a channel, points with a zero weight in every
    channel dropped (NNLS solutions are sparse: such a point would only cost render time), and
    the in-sample SNR of Eq. 7 recomputed from the stored weights.

    groups, chans : each group's `GroupFit` and the channels it fits; ch : channels of R
    eq7 : (columns (c,) int64, weights (c, ch) float64) -> (d, ch) float64, Eq. 7 of those
        weighted points on the grid (the path's own arithmetic)
    ref : (d, ch) float64, Eq. 7 of the texel; valid : (d,) bool rows above the a_vis floor"""
    columns = np.unique(np.concatenate([g.cols for g in groups])).astype(np.int64)
    w64 = np.zeros((columns.size, ch), dtype=np.float64)
    for g, cg in zip(groups, chans, strict=True):  # loop over <= ch groups
        pos = np.searchsorted(columns, g.cols)
        w64[np.ix_(pos, cg)] = g.alpha
    w32 = storable_weights(w64)
    live = np.any(w32 != 0.0, axis=1)
    columns, w32 = columns[live], w32[live]
    snr = snr_db(ref, eq7(columns, w32.astype(np.float64)), valid)
    capped = any(g.capped for g in groups)
    reasons = []
    if capped:
        reasons.append(f"c_max={params.c_max} < k: c capped")
    if snr < params.eps_db:
        reasons.append(f"eps {params.eps_db} dB not reached (SNR {snr:.2f} dB)")
    return TexelFit(
        columns=columns, weights=w32, k=max(g.k for g in groups), c=int(columns.size),
        snr_db_insample=snr, colour_mode=mode, valid=True, reason="; ".join(reasons),
        channel_correlation=corr,
        k_channels=np.array([g.k for g in groups], dtype=np.int64),
        c_channels=np.array([int(np.count_nonzero(np.any(g.alpha != 0.0, axis=1)))
                             for g in groups], dtype=np.int64),
        c_capped=capped, eps_reached=bool(snr >= params.eps_db),
    )


__all__ = ["LUMA_709", "FitCounts", "FitParams", "GroupFit", "TexelFit", "all_points_fit",
           "assemble_fit", "empty_fit", "needs_all_points", "storable_weights"]
