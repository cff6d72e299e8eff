"""One CPM level as the payload's dense per-texel arrays (CSR points, weights, statistics,
the compressed a_vis table) and its report entry (percentiles, a_vis compression error)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from texelbake.cpm import avis as avis_mod
from texelbake.cpm.avis.compress import LevelChunks, chunks_of, compress_chunks
from texelbake.cpm.avis.table import avis_table_arrays
from texelbake.cpm.level_by_need import EXACT_SKIP, GROUPED_SKIP, LOBE_SKIP

#: an SNR of +inf (an exact reproduction) enters the report's percentiles as this many dB:
#: float64 round-off alone stays below ~313 dB, so no measured value reaches it
SNR_EXACT_DB = 320.0


def percentiles(x: np.ndarray, posinf: float | None = None) -> dict[str, float]:
    """n, mean, p5, p50, p95, min, max over the finite values of x; with `posinf`, +inf
    values count as that value instead of being left out (an exact texel's SNR)."""
    x = np.asarray(x, dtype=np.float64)
    if posinf is not None:
        x = np.where(np.isposinf(x), posinf, x)
    x = x[np.isfinite(x)]
    if x.size == 0:
        return {"n": 0}
    return {"n": int(x.size), "mean": float(x.mean()), "p5": float(np.percentile(x, 5)),
            "p50": float(np.median(x)), "p95": float(np.percentile(x, 95)),
            "min": float(x.min()), "max": float(x.max())}


#: two-sided confidence of the held-out SNR's quantile intervals in the report
HELDOUT_CONFIDENCE = 0.95


def quantile_ci(x: np.ndarray, q: float, population: int, *,
                confidence: float = HELDOUT_CONFIDENCE) -> tuple[float, float]:
    """Distribution-free interval for the population's q-quantile from a sample x (n,) of it:
    the order statistics x_(r) and x_(s) with r, s the binomial (n, q) quantiles at
    (1 -+ confidence) / 2 (coverage >= confidence for i.i.d. draws of any continuous
    distribution; sampling without replacement from a finite population only concentrates
    the count below the quantile, so it stays conservative). No resampling: the bootstrap's
    interval of a low quantile from a few hundred values is too narrow (it never sees values
    below the sample's minimum). -inf / +inf where the sample is too small to bound that side;
    (v, v) when the sample is the whole population (nothing is estimated).

    x : (n,) float64 finite; population : size of what was sampled (>= n)
    returns : (low, high) float
    """
    from scipy.stats import binom

    x = np.sort(np.asarray(x, np.float64))
    n = x.size
    if n == 0:
        return (float("nan"), float("nan"))
    if n >= population:
        v = float(np.percentile(x, 100 * q))
        return (v, v)
    a = (1.0 - confidence) / 2
    r = int(binom.ppf(a, n, q))  # x_(r), 1-based: F(r - 1) < a
    s = int(binom.ppf(1.0 - a, n, q)) + 1  # x_(s): F(s - 1) >= 1 - a
    low = float(x[r - 1]) if r >= 1 else -np.inf
    high = float(x[s - 1]) if s <= n else np.inf
    return (low, high)


def heldout_stats(snr: np.ndarray, population: int) -> dict:
    """The report's held-out SNR of one level: `percentiles` over the measured texels (the
    seeded sample, `cpm.truth_sample.measured_texels`; NaN entries are the others) and the
    intervals of the median and the 5th percentile (`quantile_ci`)."""
    x = np.asarray(snr, np.float64)
    x = np.where(np.isposinf(x), SNR_EXACT_DB, x)
    out: dict = dict(percentiles(x, SNR_EXACT_DB))
    fin = x[np.isfinite(x)]
    out["population"] = int(population)
    if fin.size:
        out["confidence"] = HELDOUT_CONFIDENCE
        out["p50_ci"] = list(quantile_ci(fin, 0.5, population))
        out["p5_ci"] = list(quantile_ci(fin, 0.05, population))
    return out


#: a texel's compressed a_vis table may differ from its uncompressed maps by this relative L2
#: (over its six faces) before the bake report flags it (the per-texel bound)
AVIS_TEXEL_TOLERANCE = 0.02


def _skips(data: Mapping[str, np.ndarray], valid: np.ndarray) -> dict:
    """Texels the batched fit did not fit by draws and trials, with their held-out SNR:
    "per_texel" (fitted by `fit.fit_texel`), "all_points" (every candidate kept,
    `BakeSettings.small_texels`). Empty for the per-texel path, which records no skip."""
    if "skip" not in data:
        return {}
    skip = data["skip"][valid]
    ho = data["snr_ho"][valid]
    return {name: {"texels": int(np.sum(skip == code)),
                   "snr_heldout_db": percentiles(ho[skip == code], SNR_EXACT_DB)}
            for code, name in ((2, "per_texel"), (3, "all_points"))}


def _classes(data: Mapping[str, np.ndarray], valid: np.ndarray) -> dict:
    """The level's texels by class (`texelbake.cpm.level_by_need`): "exact" (one point, no
    fit), "grouped" (a point per group of one facet, material and visibility pattern, no fit),
    "lobe" (a few widened lobes, no fit: BakeSettings.lobe_class; where the level holds
    such texels) and "points" (the seed's fit), each with its texels, its mean stored points and
    its held-out SNR. Empty when the bake classed no texel (texel_classes="points", or a level
    coarser than classed_levels)."""
    if "classed" not in data:
        return {}
    skip = data["skip"][valid]
    exact, grouped, lobe = skip == EXACT_SKIP, skip == GROUPED_SKIP, skip == LOBE_SKIP
    ho = data["snr_ho"][valid]
    c = data["c"][valid]
    names = (("exact", exact), ("grouped", grouped)) + \
        ((("lobe", lobe),) if lobe.any() else ()) + \
        (("points", ~exact & ~grouped & ~lobe),)
    return {name: {"texels": int(np.sum(sel)),
                   "points_mean": float(c[sel].mean()) if sel.any() else 0.0,
                   "snr_heldout_db": percentiles(ho[sel], SNR_EXACT_DB)}
            for name, sel in names}


def fitted_shares(levels: Sequence[Mapping[str, np.ndarray]]) -> list[float] | None:
    """Per classed level from the finest (its arrays carry "classed"), the share of its valid
    texels the classes left to the fit (neither exact nor grouped): what the cost model's fit
    terms are priced on (`texelbake.estimate.costmodel.atlas_trade`). None when no level was
    classed."""
    out = []
    for data in levels:  # a loop over the few classed levels
        if "classed" not in data:
            break
        skip = np.asarray(data["skip"])[np.asarray(data["valid"], bool)]
        out.append(float(np.mean((skip != EXACT_SKIP) & (skip != GROUPED_SKIP)
                                 & (skip != LOBE_SKIP)))
                   if skip.size else 1.0)
    return out or None


def _merged(data: Mapping[str, np.ndarray], valid: np.ndarray) -> dict:
    """identical_columns="merge": the texels that merged identical candidates, the candidates
    fitted as copies of others (columns the Grams and eigendecompositions did not hold) and
    those texels' held-out SNR. Empty when the bake did not merge."""
    if "merged" not in data:
        return {}
    merged = data["merged"][valid]
    return {"texels": int(np.sum(merged > 0)), "candidates": int(merged.sum()),
            "snr_heldout_db": percentiles(data["snr_ho"][valid][merged > 0], SNR_EXACT_DB)}


def assemble_level(geo: Mapping[str, np.ndarray], atlas_resolution: int, avis_keep_fraction: float,
                   level: int, data: dict[str, np.ndarray],
                   avis_level: avis_mod.AvisLevel | LevelChunks, avis_selection: str = "texel",
                   ) -> tuple[dict[str, np.ndarray], dict]:
    """One CPM level as dense per-texel payload arrays, and its report entry.

    geo : the geometry stage's arrays; data : the level's fit (`texelbake.cpm.level`, sorted
    by texel); avis_level : its a_vis maps (`texelbake.cpm.avis.levels`), in memory or read a
    chunk at a time (`cpm.avis.compress.LevelChunks`: the export's, memory bounded).
    """
    n_l = atlas_resolution >> level
    n_tex = n_l * n_l
    counts = np.zeros(n_tex, np.int64)
    counts[data["texel"]] = np.diff(data["offsets"])
    # data is sorted by texel id, so its points are already in dense-CSR order
    pts = data["point_sample"]

    def dense(name: str, fill, dtype) -> np.ndarray:
        out = np.full(n_tex, fill, dtype=dtype)
        out[data["texel"]] = data[name]
        return out

    frames = geo[f"frames_L{level}"]
    src = avis_level if isinstance(avis_level, LevelChunks) else chunks_of(avis_level)
    table, errs = compress_chunks(src, frames, avis_keep_fraction, selection=avis_selection,
                                  errors=True)
    assert errs is not None  # asked for
    arrays = {
        "texel_offsets": np.concatenate([[0], np.cumsum(counts)]).astype(np.int64),
        "point_sample": pts.astype(np.int64),
        "point_position": geo["sample_pos"][pts].astype(np.float32),
        "point_normal": geo["sample_nrm"][pts].astype(np.float32),
        "point_geom_normal": geo["sample_gnrm"][pts].astype(np.float32),
        "point_material": geo["sample_mat"][pts].astype(np.int32),
        "point_uv": geo["sample_uv"][pts].astype(np.float32),
        "point_weight": data["point_weight"].astype(np.float32),
        "texel_k": dense("k", 0, np.int32),
        "texel_c": dense("c", 0, np.int32),
        "texel_snr_insample": dense("snr_in", np.nan, np.float32),
        "texel_snr_heldout": dense("snr_ho", np.nan, np.float32),
        "texel_valid": dense("valid", False, bool),
        "texel_mode": dense("mode", 0, np.uint8),
        "frames": frames.astype(np.float64),
    }
    if "point_var" in data:  # widened lobes (BakeSettings.point_lobe): their slope variance
        arrays["point_var"] = data["point_var"].astype(np.float32)
    arrays.update(avis_table_arrays(table))
    # a_vis compression error against the uncompressed maps, relative L2 over the ray-based
    # texels' cube pixels, of a_vis as the renderer reads it (U times the corrected fraction
    # for bounded texels): the whole level and per texel against AVIS_TEXEL_TOLERANCE (the
    # texels the report flags); computed chunk by chunk (`compress_chunks(errors=True)`)
    err, per_texel = errs.rel_error, errs.per_texel
    valid = data["valid"]
    report = {
        "level": level,
        "resolution": n_l,
        "texels": n_tex,
        "texels_with_samples": int(len(data["texel"]) - np.sum(np.isnan(data["snr_in"]))),
        "texels_valid": int(valid.sum()),
        "k": percentiles(data["k"][valid]),
        "c": percentiles(data["c"][valid]),
        "snr_insample_db": percentiles(data["snr_in"][valid], SNR_EXACT_DB),
        "snr_heldout_db": heldout_stats(data["snr_ho"][valid], int(valid.sum())),
        "per_channel_texels": int(np.sum(data["mode"][valid] == 1)),
        "skips": _skips(data, valid),
        # texels classed by need: exact ones stored as one point, the rest fitted
        "classes": _classes(data, valid),
        # identical_columns="merge": texels with identical candidates, and the candidates
        # fitted as copies of others (columns the Grams and eigendecompositions did not hold)
        "merged": _merged(data, valid),
        "points": int(len(pts)),
        "rays": int(data["rays"].sum()) if "rays" in data else 0,
        "bytes": int(sum(a.nbytes for a in arrays.values())),
        "avis": {
            "closed_form_texels": int(src.level.closed.sum()),
            "ray_texels": int(len(src.ray_texels)),
            "kept_fraction": float(table.haar.kept_fraction),
            "rel_error": err,
            "texel_rel_error": percentiles(per_texel),
            "tolerance": AVIS_TEXEL_TOLERANCE,
            "texels_above_tolerance": int(np.sum(per_texel > AVIS_TEXEL_TOLERANCE)),
        },
    }
    return arrays, report
