"""A finest texel's dense samples merged into a few weighted candidates before its fit
(BakeSettings.level0_candidates = "clustered"): the candidates follow the texel's detail, not
its sample count.

Seed 000 §3.3 offers every dense sample of a finest texel as a candidate column of R. Over a
texel of a large atlas the samples of a curved surface differ only in their normals, by a few
degrees, and their columns are nearly collinear: the fit's cost (R at m x d entries, the Gram
at m^2 d) pays for 100-200 candidates where a few carry the texel. Here the samples are
grouped by material and by their shading and geometric normals on a grid of step
`CLUSTER_SLOPE` in the slopes (x/z, y/z) of the texel's frame; each group is one candidate:
its sample whose shading normal is nearest the group's area-weighted mean (lowest id on a tie),
with the group's area as its weight and the group's slope variance about that mean as its
lobe's widening (`texelbake.cpm.lobe`: the group's sum of lobes is, to second order in the slopes,
the point's lobe convolved with their distribution, as LEAN/LEADR filter a normal map; the
first-order term cancels about the mean). The fit's target, the sum of every candidate's
column, is then the sum of the groups' widened lobes: the error of merging is of higher order
in the group's slope spread (at most `CLUSTER_SLOPE` / 2 per axis). A coarse level's
candidates are its children's points the same way (BakeSettings.hierarchy = "children").

What a group cannot carry stays apart: a sample whose normal is more than `STEEP_COS` from
the texel's frame (a fold, a silhouette) is a candidate of its own, each material has its own
groups, and within a material each sample's own response (its BRDF on `RESPONSE_PAIRS`, local
directions of its own frame, on a log grid of `RESPONSE_STEP`: a texture, a cellular pattern)
its own cells. Visibility: a texel the geometry bounds as open (`classify.open_texels`) needs
no key; in another, the samples whose visibility patterns the classes found with their own
rays on every training direction (`classify.TexelClasses.pattern`) are grouped by pattern too
(not the probe's: a pattern on a quarter of the directions merges samples that differ on the
rest), and the others (a texel sent to the fit before any ray, for its facets or inputs)
by their part of a `POSITION_CELLS` x `POSITION_CELLS` grid over the texel's extent, where
shadows change. The held-out pairs, summed over every dense sample,
measure what the groups lose. A texel whose groups are each one sample is fitted on its
samples as the seed's (`level_by_need.fit_level_by_need`).
"""

from __future__ import annotations

import numpy as np

from texelbake import brdf as brdf_mod
from texelbake.cpm.classify import open_texels
from texelbake.cpm.dense import LevelPass
from texelbake.cpm.level import PointSet, segment_sum
from texelbake.cpm.lobe import slope_variance

#: step of the grid in the slopes (tan of the angle from the texel's frame normal, per axis)
#: on which a texel's samples are grouped: 0.05 is 2.9 degrees at the frame normal
CLUSTER_SLOPE = 0.05

#: local (w_i, w_o) pairs on which a sample's response keys its group: normal incidence, a
#: mirror pair at 45 degrees (a specular lobe's peak) and a skew pair at 60 degrees
_S45, _S60 = np.sqrt(0.5), np.sqrt(0.75)
RESPONSE_PAIRS = np.array([
    [[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]],
    [[_S45, 0.0, _S45], [-_S45, 0.0, _S45]],
    [[_S60, 0.0, 0.5], [0.0, _S60, 0.5]],
])
#: relative step of the log grid of responses within which samples share a group (2 %: the
#: group's point stands for its members to within that, ~34 dB)
RESPONSE_STEP = 0.02
#: responses below this (a black channel) share the grid's lowest cell
RESPONSE_FLOOR = 1e-6

#: decimals of the cosine to a group's mean normal below which its samples tie for its point
TIE_DIGITS = 12

#: cells per side of the position grid on which a texel that may be shadowed, and whose
#: samples cast no ray in the classes, is grouped too
POSITION_CELLS = 4

#: cosine to the texel's frame normal at or below which a sample is a candidate of its own
#: (76 degrees: a slope of 4, where the grid's cells shrink to under a degree anyway)
STEEP_COS = 0.25


def cluster_candidates(lp: LevelPass, texels: np.ndarray, dense: np.ndarray, dseg: np.ndarray,
                       pattern: np.ndarray | None = None) -> PointSet:
    """The candidates of `texels` (flat ids at lp.level) from their dense samples (`dense`
    (n,) int64 grouped by texel, `dseg` (n,) their texel positions, ascending): one per group
    of one material and shading and geometric normals in one cell of the slope grid and,
    where the texel may be shadowed, one visibility pattern (`pattern` (n,), the classes'
    groups by the samples' own rays, -1 where none was cast) or else one part of its extent
    (module docstring); grouped by texel, by sample id within a texel. Weights are the
    groups' areas (3 channels), `var` their slope variances about their mean normals."""
    geo = lp.src.geo
    if dense.size == 0:
        return PointSet(np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0, np.int64),
                        np.zeros(0))
    nrm = geo["sample_nrm"][dense]
    area = geo["sample_area"][dense]
    keys = [c for cols in group_keys(lp, texels, dense, dseg, pattern).values() for c in cols]
    _, grp = np.unique(np.stack(keys, axis=1), axis=0, return_inverse=True)
    grp = grp.ravel()
    n_g = int(grp.max()) + 1
    tot = np.bincount(grp, weights=area, minlength=n_g)
    by_grp = np.argsort(grp, kind="stable")
    mean = segment_sum(nrm[by_grp] * area[by_grp][:, None], grp[by_grp], n_g, 0)
    mean /= np.maximum(np.linalg.norm(mean, axis=1), 1e-300)[:, None]
    # each group's point: nearest its mean normal, lowest sample id on a tie (cosines equal to
    # TIE_DIGITS decimals: two samples are equally near their bisector, up to rounding)
    cos_mean_exact = np.einsum("ij,ij->i", nrm, mean[grp])
    cos_mean = np.round(cos_mean_exact, TIE_DIGITS)
    order = np.lexsort((dense, -cos_mean, grp))
    first = order[np.r_[True, grp[order][1:] != grp[order][:-1]]]  # one row per group
    rep = np.empty(n_g, np.int64)
    rep[grp[first]] = first
    # the spread about the group's mean normal: the point's offset from the mean is a shift
    # of the lobe, not a spread, and is left out of the widening
    var = np.bincount(grp, weights=area * slope_variance(cos_mean_exact), minlength=n_g)
    var = np.divide(var, tot, out=np.zeros(n_g), where=tot > 0)
    out = np.lexsort((dense[rep], dseg[rep]))
    rep = rep[out]
    return PointSet(dense[rep], np.repeat(tot[out][:, None], 3, axis=1),
                    texels[dseg[rep]], var[out])


def group_keys(lp: LevelPass, texels: np.ndarray, dense: np.ndarray, dseg: np.ndarray,
               pattern: np.ndarray | None = None) -> dict[str, list[np.ndarray]]:
    """The keys whose equal values make a group of `cluster_candidates`, by name (each a list
    of (n,) int64 columns, empty where it does not apply): the texel, the material, the
    shading and geometric normals' slope cells, the visibility pattern (`pattern`), the
    position cells of a texel not bounded open where no ray was cast, the response cells and
    a steep sample's own row (module docstring)."""
    geo = lp.src.geo
    fr = lp.frames[texels[dseg]]  # (n, 3, 3) rows t, b, n
    keys: dict[str, list[np.ndarray]] = {
        "texel": [dseg.astype(np.int64)],
        "material": [np.asarray(geo["sample_mat"][dense], np.int64)], "normals": []}
    steep = np.zeros(dense.size, bool)
    for n in (geo["sample_nrm"][dense], geo["sample_gnrm"][dense]):  # shading, geometric
        loc = np.einsum("nij,nj->ni", fr, n)
        steep |= loc[:, 2] <= STEEP_COS
        z = np.maximum(loc[:, 2], STEEP_COS)
        keys["normals"] += [np.floor(loc[:, 0] / z / CLUSTER_SLOPE).astype(np.int64),
                            np.floor(loc[:, 1] / z / CLUSTER_SLOPE).astype(np.int64)]
    # a texel the geometry does not bound as open: its samples also grouped by the
    # visibility pattern the classes found with their rays, and where they cast none by
    # position, on a POSITION_CELLS^2 grid of its frame over its extent
    n_t = int(dseg.max()) + 1
    cast = np.zeros(dense.size, bool) if pattern is None else pattern >= 0
    keys["pattern"] = [] if pattern is None else [pattern]
    shut = ~open_texels(lp, dense, dseg, np.arange(dense.size), n_t)[dseg] & ~cast
    keys["position"] = []
    if POSITION_CELLS > 1 and shut.any():
        pos = geo["sample_pos"][dense]
        area = geo["sample_area"][dense]
        a_t = segment_sum(area, dseg, n_t, 0)
        cen = segment_sum(pos * area[:, None], dseg, n_t, 0) / np.maximum(a_t, 1e-300)[:, None]
        cell = np.sqrt(np.maximum(a_t, 1e-300)) / POSITION_CELLS
        uv = np.einsum("nij,nj->ni", fr[:, :2], pos - cen[dseg]) / cell[dseg][:, None]
        q = np.floor(uv).astype(np.int64)
        keys["position"] = [np.where(shut, q[:, 0], 0), np.where(shut, q[:, 1], 0)]
    keys["response"] = list(_response_keys(lp, dense).T)
    # a steep sample is its own group: its row number as one more key (-1 for the others)
    keys["steep"] = [np.where(steep, np.arange(dense.size), -1)]
    return keys


def _response_keys(lp: LevelPass, dense: np.ndarray) -> np.ndarray:
    """(n, 3 len(RESPONSE_PAIRS)) int64 each sample's BRDF on `RESPONSE_PAIRS` (local
    directions of its own frame: what its inputs make of it whatever its normal), per channel
    on a log grid of relative step RESPONSE_STEP: samples of one material whose textured or
    patterned inputs differ land in different cells."""
    geo = lp.src.geo
    k = len(RESPONSE_PAIRS)
    wi = np.repeat(RESPONSE_PAIRS[:, 0][None], dense.size, axis=0).reshape(-1, 3)
    wo = np.repeat(RESPONSE_PAIRS[:, 1][None], dense.size, axis=0).reshape(-1, 3)
    idx = np.repeat(np.arange(dense.size), k)
    f = brdf_mod.evaluate_by_face(lp.src.materials, geo["sample_mat"][dense][idx], wi, wo,
                                  geo["sample_uv"][dense], sample_index=idx)  # (n k, 3)
    q = np.floor(np.log(np.maximum(f, RESPONSE_FLOOR)) / np.log1p(RESPONSE_STEP))
    return q.astype(np.int64).reshape(dense.size, 3 * k)


__all__ = ["CLUSTER_SLOPE", "POSITION_CELLS", "RESPONSE_PAIRS", "RESPONSE_STEP", "STEEP_COS",
           "TIE_DIGITS", "cluster_candidates", "group_keys"]
