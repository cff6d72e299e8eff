"""A characteristic point whose lobe carries the normal spread of the surface it stands for
(BakeSettings.point_lobe = "widened").

Seed 000 Eq. 7 replaces a texel's dense samples by a few of them, each evaluated with its own
BRDF at its own normal. Over a curved glossy texel the samples' normals spread along the
curve, and the sum over them is a broad lobe; a few narrow lobes at a few normals reproduce it
on the training grid (the weights are fitted there) but not between the grid's directions,
where the held-out pairs lie. Each point here gets the slope statistics of its cell (the
surface it stands for), as LEAN/LEADR filter a normal map (Olano & Baker 2010; Dupuy et al.
2013): the lobe of a point at normal n_p over samples at normals n_j is, to second order, the
point's own lobe convolved with the distribution of the slopes of n_j in n_p's frame, i.e. its
GGX slope variance per axis raised by their variance (`texelbake.brdf.widened.widen_inputs`:
alpha'^2 = alpha^2 + 2 var for UsdPreviewSurface, the Phong exponent through the
Phong <-> Beckmann mapping; Lambert, cellular and MERL materials are unchanged).

The cell of a point is the candidates of its texel closest to it in shading normal among
those of its material (lowest point on a tie); a candidate of a material no point has adds to
no cell. Its variance per axis is the weighted mean over the cell of the candidate's own
variance plus half its squared slope in the point's frame, tan^2(angle(n_j, n_p)) / 2 (the
slope's variance split over two axes), weights the candidates' mean weight over channels
(their area at level 0, the children's fitted weights above). A candidate at or past 90
degrees from its point adds `VAR_MAX` (the slope is unbounded; the widened roughness is
clipped to 1 anyway). Composed level by level this way, a coarse point's variance is the
parallel-axis sum over its children's cells, up to the tan^2 of composed angles not adding
exactly.

The widened points keep the seed's selection (the points of its fit); their weights are
fitted again by NNLS per channel on the widened columns of the training grid. They replace
the seed's in a texel only where they reproduce it better on the validation pairs
(`level.VALIDATION` x `level.VALIDATION` directions of their own seeds, `wider_wins`): a
widened lobe spreads energy where the surface shadows and masks itself, and there the seed's
points stay. A coarser level's candidates carry their children's chosen variance. A
roughness (or Phong exponent) texture is widened per sample (`widen_inputs` on the resolved
inputs).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping

import numpy as np
from scipy.optimize import nnls

from texelbake.cpm.dense import (
    VAL_KEYS,
    DenseSums,
    LevelPass,
    heldout_snr,
    points_on,
    to_texel,
    validation_sums,
)
from texelbake.cpm.gram.columns import Columns
from texelbake.cpm.level import PointSet
from texelbake.cpm.matrix import points_sum, snr_db
from texelbake.cpm.texel_fit import TexelFit, storable_weights

#: variance per axis of a candidate at or past 90 degrees from its point (widened roughness
#: is 1 well before: alpha'^2 = alpha^2 + 2 var >= 1 from var = 0.5)
VAR_MAX = 1.0

#: 1 - cos below which two unit normals count as one (a few float64 roundings of a dot
#: product of unit vectors)
FLAT_COS = 1e-12


def slope_variance(cos: np.ndarray, own: np.ndarray | float = 0.0) -> np.ndarray:
    """The variance per axis a normal at cosine `cos` (n,) from its point's adds to the
    point's cell, on top of its own `own`: own + tan^2 / 2, VAR_MAX at or past 90 degrees and
    at most VAR_MAX (module docstring)."""
    c = np.clip(cos, -1.0, 1.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        slope2 = np.where(c > 0, (1.0 - c * c) / (c * c), np.inf)
    # normals equal up to rounding (a unit vector's dot with itself can be 1 - 1e-16): no
    # slope, so that a flat cell's point keeps its own lobe bit for bit
    slope2[c >= 1.0 - FLAT_COS] = 0.0
    return np.minimum(own + 0.5 * slope2, VAR_MAX)


def cell_variance(nrm: np.ndarray, mat: np.ndarray, weight: np.ndarray,
                  var: np.ndarray | None, points: np.ndarray) -> np.ndarray:
    """The slope variance per axis of each point of one texel (module docstring).

    nrm : (m, 3) unit shading normals of the texel's candidates; mat : (m,) their materials;
    weight : (m, 3) their weights; var : (m,) their own variance per axis, None for 0;
    points : (k,) the candidate rows chosen as points
    returns : (k,) float64 >= 0; a cell of one normal and variance 0 gets exactly 0
    """
    k = len(points)
    if k == 0:
        return np.zeros(0)
    cos = nrm @ nrm[points].T  # (m, k)
    score = np.where(mat[:, None] == mat[points][None, :], cos, -np.inf)
    best = np.argmax(score, axis=1)  # first maximum: lowest point on a tie
    has = np.isfinite(score[np.arange(len(nrm)), best])
    own = np.zeros(len(nrm)) if var is None else np.asarray(var, np.float64)
    contrib = slope_variance(cos[np.arange(len(nrm)), best], own)
    w = np.abs(weight).mean(axis=1) * has
    tot = np.bincount(best, weights=w, minlength=k)
    num = np.bincount(best, weights=w * np.where(has, contrib, 0.0), minlength=k)
    out = np.divide(num, tot, out=np.zeros(k), where=tot > 0)
    return np.maximum(out, 0.0)


def nnls_channels(F: np.ndarray, target: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """Per channel the nonnegative weights (k, ch) of F's columns (ch, k, d) that fit target
    (ch, d) on `rows` in least squares."""
    ch, k = F.shape[:2]
    w = np.zeros((k, ch))
    for c in range(ch):  # loop over colour channels
        w[:, c] = nnls(F[c][:, rows].T, target[c, rows], maxiter=50 * max(k, 1))[0]
    return w


def cell_spread(geo: Mapping[str, np.ndarray], cset: PointSet, fit: TexelFit) -> np.ndarray:
    """(c,) `cell_variance` of a texel fit's points among its candidates `cset` (their own
    cells' variance in `cset.var`)."""
    cols = np.asarray(fit.columns, np.int64)
    return cell_variance(geo["sample_nrm"][cset.sample], geo["sample_mat"][cset.sample],
                         cset.weight, cset.var, cols)


def widen_fit(fit: TexelFit, cset: PointSet, var: np.ndarray, F: np.ndarray | Columns,
              valid: np.ndarray, lp: LevelPass, columns: Callable[[PointSet], np.ndarray]
              ) -> tuple[TexelFit, np.ndarray] | None:
    """The widened alternative of a texel's fit (`cset` its candidates, F (ch, m, d) their
    columns of F = diag(1/a_vis) R, valid (d,) its rows above the a_vis floor): the same
    points, each with its cell's variance `var` (c,) (`cell_spread`), their weights fitted
    again on the widened columns (`columns(points)` builds them, (ch, c, d)) by NNLS per
    channel against the candidates' sum on every valid row of the training grid (points left
    at weight 0 in every channel dropped). Returns (fit, var (c,)), or None where there is
    nothing to widen (each cell's variance its point's own: one normal per cell) or no
    weight is left."""
    cols = np.asarray(fit.columns, np.int64)
    own = np.zeros(cols.size) if cset.var is None else cset.var[cols]
    if not fit.valid or cols.size == 0 or np.array_equal(var, own):
        return None
    F_wide = columns(PointSet(cset.sample[cols], cset.weight[cols], cset.texel[cols], var))
    target = F.sum(axis=1)
    w32 = storable_weights(nnls_channels(F_wide, target, np.flatnonzero(valid)))
    live = np.any(w32 != 0.0, axis=1)
    if not live.any():
        return None
    snr = snr_db(target.T, points_sum(F_wide[:, live], None, w32[live].astype(np.float64)),
                 valid)
    return dataclasses.replace(
        fit, columns=cols[live], weights=w32[live], c=int(live.sum()), snr_db_insample=snr,
        eps_reached=bool(snr >= lp.src.settings.eps_db)), var[live]


def validation_truth(lp: LevelPass, texels: np.ndarray, sums: DenseSums | None,
                     dense: np.ndarray | None, dseg: np.ndarray | None, loc: np.ndarray
                     ) -> tuple[np.ndarray, ...]:
    """`dense.validation_sums` of the texels at positions `loc` of `texels`: from their
    dense samples (`dense`, positions `dseg`), or read from their `sums`."""
    if sums is not None:
        part = sums.rows(loc)
        return part.val_ref, part.val_avis, part.val_area
    assert dense is not None and dseg is not None
    rows = np.isin(dseg, loc)
    return validation_sums(lp, texels[loc], dense[rows], np.searchsorted(loc, dseg[rows]))


def wider_wins(lp: LevelPass, texels: np.ndarray, area: np.ndarray,
               truth: tuple[np.ndarray, ...],
               own: tuple[np.ndarray, ...], wide: list[tuple[TexelFit, np.ndarray, PointSet]]
               ) -> np.ndarray:
    """(t,) bool: the widened points reproduce each of `texels` (area (t,)) better than its own
    points on the validation pairs (`level.VALIDATION`), whose directions neither the fit's
    grid nor the held-out pairs share (the held-out SNR stays an independent measure). A
    widened lobe spreads a point's energy over directions where the surface it stands for
    shadows or masks itself (a bolt's bumps): there the own points win and are kept.

    truth : the texels' `dense.validation_sums` (ref, a_vis, area of the kept samples);
    own : the points as stored (sample ids (p,), texel positions (p,), weights (p, 3), lobe
    variances (p,)); wide : per texel its widened (fit, var (c,), candidates)"""
    val_ref, val_avis, val_area = truth
    ref, avis = to_texel(val_ref, val_avis, area, val_area)
    wide_pts = tuple(np.concatenate(x) for x in zip(*[  # loop over texels: their points
        (cset.sample[fit.columns], np.full(fit.c, t),
         (fit.weights * cset.weight[fit.columns]).astype(np.float32).astype(np.float64),
         var.astype(np.float32).astype(np.float64))
        for t, (fit, var, cset) in enumerate(wide)], strict=True))

    def snr(pts: tuple[np.ndarray, ...]) -> np.ndarray:
        smp, pseg, pw, pvar = pts
        apx = points_on(lp, texels, smp, pseg, pw, pvar, VAL_KEYS)
        return np.array([heldout_snr(ref[t], apx[t], avis[t], area[t])
                         for t in range(len(texels))])  # loop over texels: one SNR each

    # NaN (no kept sample) compares False: the own points stay
    return snr(wide_pts) > snr(own)


__all__ = ["FLAT_COS", "VAR_MAX", "cell_spread", "cell_variance", "nnls_channels",
           "slope_variance", "validation_truth", "widen_fit", "wider_wins"]
