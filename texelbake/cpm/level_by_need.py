"""One CPM level with its texels classed by need first (`texelbake.cpm.classify`): the exact
texels stored as one point each and the grouped ones as a point per group, measured on the
held-out pairs, and only the others given to the seed's fit (`level_batched` or
`level_per_texel`, as BakeSettings.fit_method chooses).

The level's arrays are those of the fit, for every texel, in texel order, plus `classed`
(1,) int64 = 1 (summed over a level's tiles: that the level was classed). A stored `skip` of
`EXACT_SKIP` marks an exact texel, `GROUPED_SKIP` a texel stored as a point per group of one
facet, material and visibility pattern. No seconds are stored: artifacts are byte-identical
from run to run (`benchmarks/texel_classes.py` times the classes)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from schemas.settings import BakeSettings
from texelbake.cpm.classify import (
    CHECK_LIGHTS,
    CHECK_VIEWS,
    REASONS,
    TexelClasses,
    classify_texels,
)
from texelbake.cpm.cluster import cluster_candidates
from texelbake.cpm.dense import LevelPass, dense_of, heldout_from_samples, heldout_snr
from texelbake.cpm.level import (
    LEVEL_TOTALS,
    POINT_KEYS,
    FitInputs,
    PointSet,
    carries_lobe_var,
    clusters_level0,
    sort_by_texel,
)
from texelbake.cpm.level_batched import chunk_bounds
from texelbake.cpm.lobe_class import LobeTexels, lobes_bounded

#: the `skip` codes of an exact texel, a grouped one and a lobe one (after
#: level_batched.SKIP_CODES' 0-3)
EXACT_SKIP = 4
GROUPED_SKIP = 5
LOBE_SKIP = 6

#: bytes per (sample, direction or check pair) while texels are classed: world directions,
#: visibility and cosines, the BRDF and its copies (float64)
BYTES_PER_CLASS_ENTRY = 8 * 12

FitFn = Callable[[np.ndarray, PointSet], dict[str, np.ndarray]]


def fit_level_by_need(src: FitInputs, level: int, texels: np.ndarray, candidates: PointSet,
                      fit: FitFn) -> dict[str, np.ndarray]:
    """The level's arrays for `texels` (flat ids at `level`, ascending): exact texels as one
    point and grouped ones as a point per group (`classify_texels`), the rest by
    `fit(texels, candidates)` (the seed's fit of those
    texels among their candidates)."""
    texels = np.asarray(texels, np.int64)
    lp = LevelPass.of(src, level)
    dense, dseg = dense_of(lp, texels)
    cls = classes_bounded(lp, texels, dense, dseg)
    stored = cls.exact | cls.grouped
    parts = [_stored_arrays(lp, texels, dense, dseg, cls)]
    tried = lobe_tried(src.settings, level, cls)
    if tried is not None:
        lob = lobes_bounded(lp, texels, dense, dseg, tried)
        parts.append(_lobe_arrays(lp, texels, dense, dseg, lob))
        stored = stored | lob.lobe
    rest = texels[~stored]
    if rest.size and level == 0 and clusters_level0(src.settings):
        groups, seg = fitted_groups(lp, texels, dense, dseg, cls, np.flatnonzero(~stored))
        # a texel whose every group is one sample is fitted on its samples as the seed's (a
        # texel of at most c_max of them keeps them all, exact); the others on their groups
        single = np.bincount(np.searchsorted(rest, groups.texel), minlength=rest.size) == \
            np.bincount(seg, minlength=rest.size)
        if single.any():
            keep = np.isin(candidates.texel, rest[single])
            parts.append(fit(rest[single], candidates.take(np.flatnonzero(keep))))
        if not single.all():
            keep = np.isin(groups.texel, rest[~single])
            parts.append(fit(rest[~single], groups.take(np.flatnonzero(keep))))
    elif rest.size:
        keep = np.isin(candidates.texel, rest)
        parts.append(fit(rest, candidates.take(np.flatnonzero(keep))))
    out = merge_levels(parts)
    out["classed"] = np.ones(1, np.int64)
    return out


def lobe_tried(settings: BakeSettings, level: int, cls: TexelClasses) -> np.ndarray | None:
    """(t,) bool the texels of a chunk classed `cls` that the lobe class tries
    (`texelbake.cpm.lobe_class`: BakeSettings.lobe_class on, the finest level only): neither
    exact nor grouped, holding samples, none cut; None where it tries none."""
    if settings.lobe_class == "off" or level != 0:
        return None
    return (~(cls.exact | cls.grouped) & (cls.reason != REASONS["empty"])
            & (cls.reason != REASONS["cut"]))


def fitted_groups(lp: LevelPass, texels: np.ndarray, dense: np.ndarray, dseg: np.ndarray,
                  cls: TexelClasses, on: np.ndarray) -> tuple[PointSet, np.ndarray]:
    """The candidates of the texels at positions `on` (ascending) as groups of their dense
    samples (`texelbake.cpm.cluster`, by the classes' patterns), and each of those samples'
    texel position among `on`."""
    rows, seg = texel_rows(dseg, on, len(texels))
    return cluster_candidates(lp, texels[on], dense[rows], seg, cls.pattern[rows]), seg


def texel_rows(dseg: np.ndarray, on: np.ndarray, n_t: int) -> tuple[np.ndarray, np.ndarray]:
    """The dense rows (of texel positions `dseg`, n_t texels) of the texels at positions `on`
    (ascending), and each row's texel position among `on`."""
    at = np.full(n_t, -1, np.int64)
    at[on] = np.arange(on.size)
    rows = np.flatnonzero(at[dseg] >= 0)
    return rows, at[dseg[rows]]


def classes_bounded(lp: LevelPass, texels: np.ndarray, dense: np.ndarray, dseg: np.ndarray
                    ) -> TexelClasses:
    """`classify_texels` over chunks of texels whose samples' temporaries fit the worker's
    memory budget (a texel's samples are never split), joined as one."""
    n_t = len(texels)
    n_dense = np.bincount(dseg, minlength=n_t)
    starts = np.r_[0, np.cumsum(n_dense)]
    n_dirs = len(lp.dirs["dirs_i"]) + len(lp.dirs["dirs_o"])
    cap = max(lp.budget // (BYTES_PER_CLASS_ENTRY * (n_dirs + 3 * CHECK_LIGHTS * CHECK_VIEWS)),
              1)
    parts = [classify_texels(lp, texels[a:b], dense[starts[a]:starts[b]],
                             dseg[starts[a]:starts[b]] - a)
             for a, b in chunk_bounds(n_dense, cap)]  # loop over chunks (memory bound)
    if not parts:
        return classify_texels(lp, texels, dense, dseg)
    def cat(name: str) -> np.ndarray:
        return np.concatenate([getattr(c, name) for c in parts])

    counts = np.concatenate([np.diff(c.offsets) for c in parts])
    return TexelClasses(
        exact=cat("exact"), grouped=cat("grouped"),
        offsets=np.r_[0, np.cumsum(counts)].astype(np.int64), points=cat("points"),
        weights=cat("weights"), reason=cat("reason"), rays=sum(c.rays for c in parts),
        pattern=cat("pattern"))


def _heldout_of(lp: LevelPass, texels: np.ndarray, dense: np.ndarray, dseg: np.ndarray,
                ex: np.ndarray, points: np.ndarray, counts: np.ndarray, w32: np.ndarray,
                var32: np.ndarray | None, unmeasured: float) -> np.ndarray:
    """(e,) the held-out SNR of the texels at positions `ex` of `texels`, stored without a
    fit as `points` (p,) with `counts` (e,) per texel, their stored (float32: what the renderer
    reads) weights (p, 3) and lobe variances (p,) or None, against brute-force Eq. 7 over each
    texel's dense samples; `unmeasured` where the level has no held-out pairs."""
    n_e = ex.size
    if not (n_e and len(lp.dirs["held_i"])):
        return np.full(n_e, unmeasured)
    rows, sub_seg = texel_rows(dseg, ex, len(texels))
    sub_dense = dense[rows]
    ref, apx, avis_h = heldout_from_samples(
        lp, texels[ex], sub_dense, sub_seg, points, np.repeat(np.arange(n_e), counts),
        w32.astype(np.float64), None if var32 is None else var32.astype(np.float64))
    area = np.bincount(sub_seg, weights=lp.src.geo["sample_area"][sub_dense], minlength=n_e)
    return np.array([heldout_snr(ref[t], apx[t], avis_h[t], area[t])
                     for t in range(n_e)])  # loop over texels: one SNR each


def _stored_arrays(lp: LevelPass, texels: np.ndarray, dense: np.ndarray, dseg: np.ndarray,
                   cls: TexelClasses) -> dict[str, np.ndarray]:
    """The fit's arrays for the exact and grouped texels (`cls`): their points, and their
    held-out SNR (`_heldout_of`)."""
    ex = np.flatnonzero(cls.exact | cls.grouped)
    counts = np.diff(cls.offsets)[ex]
    w32 = cls.weights.astype(np.float32)
    # exact on the grid by construction: +inf where no held-out pair measures it
    snr = _heldout_of(lp, texels, dense, dseg, ex, cls.points, counts, w32, None, np.inf)
    # exact on the grid by construction (a point per group of one facet, one pattern and f_r
    # proportional on the check pairs); the held-out pairs are the measurement
    return _point_arrays(lp, texels[ex], counts, cls.points, w32, None,
                         np.full(ex.size, np.inf), snr,
                         np.where(cls.grouped[ex], GROUPED_SKIP, EXACT_SKIP))


def _lobe_arrays(lp: LevelPass, texels: np.ndarray, dense: np.ndarray, dseg: np.ndarray,
                 lob: LobeTexels) -> dict[str, np.ndarray]:
    """The fit's arrays for the lobe texels (`lob`, `texelbake.cpm.lobe_class`): their points
    with their lobe variances, and their held-out SNR (`_heldout_of`)."""
    ex = np.flatnonzero(lob.lobe)
    counts = np.diff(lob.offsets)[ex]
    w32 = lob.weights.astype(np.float32)
    var32 = lob.var.astype(np.float32)
    snr = _heldout_of(lp, texels, dense, dseg, ex, lob.points, counts, w32, var32, np.nan)
    # weights fitted on the fit pairs, kept on the validation pairs: the SNR that decided
    return _point_arrays(lp, texels[ex], counts, lob.points, w32, var32, lob.snr_val[ex], snr,
                         np.full(ex.size, LOBE_SKIP))


def _point_arrays(lp: LevelPass, texels: np.ndarray, counts: np.ndarray, points: np.ndarray,
                  w32: np.ndarray, var32: np.ndarray | None, snr_in: np.ndarray,
                  snr_ho: np.ndarray, skip: np.ndarray) -> dict[str, np.ndarray]:
    """The fit's arrays for texels stored without a fit: `texels` (e,) with `counts` (e,)
    points each, `points` (p,) their samples, stored weights (p, 3) and lobe variances (p,)
    (None: each keeps its sample's lobe, 0), and per texel the SNRs and `skip` code; with the
    batched fit's optional arrays, so that every tile's level has the same keys."""
    s = lp.src.settings
    n_e = len(texels)
    extra = {"merged": np.zeros(n_e, np.int32)} \
        if s.identical_columns == "merge" and s.fit_method == "batched" else {}
    if var32 is not None or carries_lobe_var(s):
        extra["point_var"] = np.zeros(len(points), np.float32) if var32 is None else var32
    return extra | {
        "texel": texels, "offsets": np.r_[0, np.cumsum(counts)].astype(np.int64),
        "point_sample": points.astype(np.int64), "point_weight": w32,
        "k": counts.astype(np.int32), "c": counts.astype(np.int32),
        "snr_in": snr_in.astype(np.float32), "snr_ho": snr_ho.astype(np.float32),
        "mode": np.zeros(n_e, np.int8), "valid": np.ones(n_e, bool),
        "skip": skip.astype(np.int8),
    }


def merge_levels(parts: list[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """Disjoint texel sets' arrays of one level as one, sorted by texel (CSR offsets
    re-based); a per-texel array one part lacks (the per-texel loop's `skip`, `merged`) is
    zero there (a stored texel's `point_var`: its one facet's lobe is the sample's own),
    per-level totals (`LEVEL_TOTALS`) are summed."""
    n = [len(p["texel"]) for p in parts]
    keys = sorted({k for p in parts for k in p} - {"offsets", *LEVEL_TOTALS})
    out: dict[str, np.ndarray] = {}
    for k in keys:
        like = next(p[k] for p in parts if k in p)
        out[k] = np.concatenate([
            p[k] if k in p else np.zeros((m if k not in POINT_KEYS
                                          else int(p["offsets"][-1]),) + like.shape[1:],
                                         like.dtype)
            for p, m in zip(parts, n, strict=True)])
    base = np.cumsum([0] + [int(p["offsets"][-1]) for p in parts])
    out["offsets"] = np.concatenate([[0]] + [p["offsets"][1:] + b
                                             for p, b in zip(parts, base, strict=False)])
    for k in LEVEL_TOTALS:
        if any(k in p for p in parts):
            out[k] = np.sum([p[k] for p in parts if k in p], axis=0)
    return sort_by_texel(out)


__all__ = ["EXACT_SKIP", "GROUPED_SKIP", "LOBE_SKIP", "classes_bounded", "fit_level_by_need",
           "fitted_groups", "lobe_tried", "merge_levels", "texel_rows"]
