"""Texels stored as a few filtered lobes around their mean normal, no R, Gram or trial
(BakeSettings.lobe_class = "validated"): the "lobe" class between the exact texels and the
seed's fit (`texelbake.cpm.level_by_need` stores them, `skip` LOBE_SKIP).

A texel of one material over a smoothly curved surface is not exact (its samples' normals
differ), yet its Eq. 7 sum, sum_j a_j f_r(n_j; w_i, w_o) V (n_j . w_i)+ V (n_j . w_o)+, is
close to a lobe at its mean normal convolved with the distribution of the samples' slopes, as
LEAN/LEADR filter a normal map (Olano & Baker 2010; Dupuy et al. 2013;
`texelbake.brdf.widened.widen_inputs`: alpha'^2 = alpha^2 + 2 var for GGX, the Phong exponent
through the Phong <-> Beckmann mapping). One sample's lobe stands for that only to first order
in its normal's offset from the mean, which for a narrow lobe is most of the error (measured:
docs/decisions.md, "A curved texel of one material is a few lobes"). So the texel is stored as

- a point per cell: the samples split by the quadrant of their shading normal's and of their
  geometric normal's offset from the texel's area-weighted means, in the mean shading normal's
  tangent plane (up to 16 cells: the view cosine and a_vis read the geometric normal); each
  cell's point its sample nearest both means (lowest id on a tie), its lobe widened by the
  cell's slope variance about it (`texelbake.cpm.lobe.cell_variance`'s rule, areas as
  weights);
- weights by NNLS per channel against the texel's truth on the fit pairs, about
  `FIT_PAIRS` x `FIT_PAIRS` pairs of the training grid;
- kept where, with those weights, it reproduces the truth to at least BakeSettings.eps_db
  (the SNR the seed's fit stops at on its own grid) on the fit pairs and then on the
  validation pairs (`level.LOBE_VALIDATION` x `level.LOBE_VALIDATION`, their own seeds:
  neither the grid's nor the held-out pairs'; only the texels that passed the first are
  validated).

Only a texel of one material, with no cut-out sample and every normal within 90 degrees of
the mean is tried, and only one of one visibility pattern is validated (tested after the fit
pairs, the cheaper test): a point is shaded with its own rays, so a shadow edge across the
texel, which the fit's points carry, is not a lobe. A training direction
"splits" a texel where one of its samples above its horizons is occluded and another is not
(found by the samples' own rays, or bounded from the geometry: none where the whole mesh lies
below every sample's tangent plane, `unoccluded_samples`). The split directions' share of the
texel's light, sum of (n_mean . w)+ over them against over all the grid's light and view
directions, may be at most 10^(-eps_db / 20): a shadow edge there changes no more of the
texel's light, in amplitude, than eps_db allows in all (a grazing edge, on a few directions
near the horizon, is so). Every other texel goes on to the seed's fit; the held-out pairs then
measure each lobe texel as they measure a fitted one.

Only the finest level is tried (`level_by_need`): a coarser classed texel holds 4^level times
the samples, whose truth on the fit pairs costs as much as its fit from its children's points,
and few of them were kept (docs/decisions.md, "A curved texel of one material is a few
lobes").
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from texelbake.cpm.classify import open_texels, seg_all, visibility_patterns
from texelbake.cpm.dense import (
    LevelPass,
    heldout_snr,
    inv_avis,
    points_on,
    to_texel,
    validation_sums,
)
from texelbake.cpm.level import segment_sum, world_dirs
from texelbake.cpm.level_batched import chunk_bounds
from texelbake.cpm.lobe import nnls_channels, slope_variance
from texelbake.tol import TOL

#: the fit pairs, on which the points' weights are solved: about FIT_PAIRS light and view
#: directions of the training grid, every (n // FIT_PAIRS)-th (8 x 8 of 64 x 64)
FIT_PAIRS = 8
FIT_KEYS = ("fit_i", "fit_o")
#: the validation pairs, on which a texel's lobes are kept or not (`level.LOBE_VALIDATION`)
LOBE_KEYS = ("lobe_i", "lobe_o")

#: bytes per (dense sample, training direction) while the lobe class is tested: world
#: directions, cosines and visibility (float64), with the validation pass's own batches
BYTES_PER_LOBE_ENTRY = 8 * 12


@dataclass(frozen=True)
class LobeTexels:
    """The lobe class of a chunk's texels: lobe (t,) bool stored so; offsets (t + 1,) int64,
    points (p,) int64 sample ids, weights (p, 3) float64 and var (p,) float64 the lobes'
    slope variance per axis, CSR over the texels (none for the others); snr_val (t,) the SNR
    that decided: on the validation pairs, or on the fit pairs where it missed eps_db there
    (NaN: not tried)."""

    lobe: np.ndarray
    offsets: np.ndarray
    points: np.ndarray
    weights: np.ndarray
    var: np.ndarray
    snr_val: np.ndarray

    @classmethod
    def none(cls, n_t: int) -> LobeTexels:
        return cls(np.zeros(n_t, bool), np.zeros(n_t + 1, np.int64), np.zeros(0, np.int64),
                   np.zeros((0, 3)), np.zeros(0), np.full(n_t, np.nan))


def _quadrant_points(nrm: np.ndarray, mean: np.ndarray, gnrm: np.ndarray, gmean: np.ndarray,
                     dseg: np.ndarray, dense: np.ndarray,
                     rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The cells of the sample rows `rows` (module docstring: per texel, the quadrant of the
    shading normal `nrm`'s offset from the mean `mean` (t, 3) and of the geometric normal
    `gnrm`'s from `gmean` (t, 3), both in the mean shading normal's tangent plane) and each
    cell's sample nearest both means, lowest id on a tie: (point rows (p,) grouped by texel,
    each row's cell (r,) as a position in the point rows)."""
    # a tangent frame of each texel's mean normal (any one: the quadrants only need to split
    # the plane), per texel, read by its rows
    axis = np.where((np.abs(mean[:, 0]) < 0.6)[:, None], [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    t1 = np.cross(mean, axis)
    # zero only where the mean is (a texel not tried, whose rows are not read)
    t1 /= np.maximum(np.linalg.norm(t1, axis=1), 1e-300)[:, None]
    t2 = np.cross(mean, t1)
    seg = dseg[rows]
    du = np.einsum("ij,ij->i", nrm[rows], t1[seg])
    dv = np.einsum("ij,ij->i", nrm[rows], t2[seg])
    gd = gnrm[rows] - gmean[seg]
    gu = np.einsum("ij,ij->i", gd, t1[seg])
    gv = np.einsum("ij,ij->i", gd, t2[seg])
    key = seg * 16 + (du >= 0) + 2 * (dv >= 0) + 4 * ((gu >= 0) + 2 * (gv >= 0))
    order = np.lexsort((dense[rows], du * du + dv * dv + gu * gu + gv * gv, key))
    head = np.r_[True, key[order][1:] != key[order][:-1]]
    pts = rows[order[head]]
    cell = np.empty(rows.size, np.int64)
    cell[order] = np.cumsum(head) - 1
    return pts, cell


def lobe_texels(lp: LevelPass, texels: np.ndarray, dense: np.ndarray, dseg: np.ndarray,
                tried: np.ndarray) -> LobeTexels:
    """The lobe class (module docstring) of the `tried` (t,) bool texels among `texels` (flat
    ids at lp.level; their dense samples `dense` grouped by texel, positions `dseg`
    ascending)."""
    src, geo = lp.src, lp.src.geo
    n_t = len(texels)
    out = LobeTexels.none(n_t)
    if dense.size == 0 or not tried.any():
        return out
    count = np.bincount(dseg, minlength=n_t)
    area = geo["sample_area"][dense]
    mat = geo["sample_mat"][dense]
    nrm = geo["sample_nrm"][dense]
    first = np.r_[0, np.cumsum(count)][:-1]
    m0 = mat[np.minimum(first, dense.size - 1)]
    # one material and no cut-out sample (no area: its texel is fitted, as in classify)
    cand = tried & (count > 0) & seg_all((mat == m0[dseg]) & (area > 0), dseg, n_t)
    mean = segment_sum(nrm * area[:, None], dseg, n_t, 0)
    length = np.linalg.norm(mean, axis=1)
    # every sample within 90 degrees of the mean normal
    cand &= (length > 0) & seg_all(
        np.einsum("ij,ij->i", nrm, mean[dseg]) > TOL.grazing_cos * length[dseg], dseg, n_t)
    mean = mean / np.where(length > 0, length, 1.0)[:, None]
    if not cand.any():
        return out
    loc = np.flatnonzero(cand)
    pos = np.full(n_t, -1, np.int64)
    pos[loc] = np.arange(loc.size)
    rows = np.flatnonzero(pos[dseg] >= 0)
    gn = geo["sample_gnrm"][dense]
    gmean = segment_sum(gn * area[:, None], dseg, n_t, 0)
    gmean /= np.maximum(np.linalg.norm(gmean, axis=1), 1e-300)[:, None]
    pts, cell = _quadrant_points(nrm, mean, gn, gmean, dseg, dense, rows)
    # each point's lobe variance: its cell's slope variance (`cell_variance`, areas as weights)
    a_r = area[rows]
    contrib = slope_variance(np.einsum("ij,ij->i", nrm[rows], nrm[pts[cell]]))
    var = np.bincount(cell, weights=a_r * contrib, minlength=pts.size) / np.bincount(
        cell, weights=a_r, minlength=pts.size)

    tot = np.bincount(dseg, weights=area, minlength=n_t)[loc]
    sub = dataclasses.replace(lp, dirs=lp.dirs | {
        k: lp.dirs[d][::max(len(lp.dirs[d]) // FIT_PAIRS, 1)]
        for k, d in zip(FIT_KEYS, ("dirs_i", "dirs_o"), strict=True)})
    pseg = pos[dseg[pts]]
    rseg = pos[dseg[rows]]

    def on_pairs(keys: tuple[str, str], on: np.ndarray):
        """The truth of the texels loc[on] on the pairs `keys` (ref, a_vis) and their points'
        unit-weight columns (p_on, a, b, 3)."""
        at = np.cumsum(on) - 1  # loc position -> position among loc[on]
        r, q = rows[on[rseg]], pts[on[pseg]]
        t_ref, t_avis, t_area = validation_sums(sub, texels[loc[on]], dense[r],
                                                at[pos[dseg[r]]], keys)
        cols = points_on(sub, texels[loc][pseg[on[pseg]]], dense[q], np.arange(q.size),
                         np.ones((q.size, 3)), var[on[pseg]], keys)
        return (*to_texel(t_ref, t_avis, tot[on], t_area), cols)

    # the weights, on the filtered reflectance (Eq. 7 over a_vis, as the seed's F = diag(1 /
    # a_vis) R and the held-out SNR read it: each view's rows scaled by 1/a_vis, those under
    # the texel's a_vis floor left out)
    fit_ref, fit_avis, cols = on_pairs(FIT_KEYS, np.ones(loc.size, bool))
    _, inv = inv_avis(fit_avis, tot)  # (t, b)
    bounds = np.r_[0, np.cumsum(np.bincount(pseg, minlength=loc.size))]
    w = np.zeros((pts.size, 3))
    snr = np.full(loc.size, np.nan)
    for t in range(loc.size):  # loop over texels: a few points' NNLS and one SNR each
        a, b = bounds[t], bounds[t + 1]
        F = (cols[a:b] * inv[t][None, None, :, None]).reshape(b - a, -1, 3)
        target = (fit_ref[t] * inv[t][None, :, None]).reshape(-1, 3)
        w[a:b] = nnls_channels(F.transpose(2, 0, 1), target.T, np.arange(target.shape[0]))
        w[a:b] = w[a:b].astype(np.float32)  # as stored and rendered
        snr[t] = heldout_snr(fit_ref[t], np.einsum("pabc,pc->abc", cols[a:b], w[a:b]),
                             fit_avis[t], tot[t])
    # only the texels whose lobes reach eps_db on the pairs they were fitted on are tested for
    # one visibility pattern (their samples' rays on the whole grid), and only those validated
    on = snr >= src.settings.eps_db
    one = np.zeros(n_t, bool)
    one[loc[on]] = True
    on &= _one_pattern(lp, texels, dense, dseg, one, mean)[loc]
    if on.any():
        ref, avis, cols = on_pairs(LOBE_KEYS, on)
        w_on = w[on[pseg]]
        b_on = np.r_[0, np.cumsum(np.bincount(pseg[on[pseg]], minlength=loc.size)[on])]
        for j, i in enumerate(np.flatnonzero(on).tolist()):  # loop over texels: one SNR each
            a, b = b_on[j], b_on[j + 1]
            snr[i] = heldout_snr(ref[j], np.einsum("pabc,pc->abc", cols[a:b], w_on[a:b]),
                                 avis[j], tot[i])
    live = np.any(w > 0, axis=1)
    keep = on & (snr >= src.settings.eps_db) & (np.bincount(pseg, weights=live,
                                                            minlength=loc.size) > 0)
    lobe = np.zeros(n_t, bool)
    lobe[loc[keep]] = True
    sel = keep[pseg] & live
    counts = np.bincount(loc[pseg[sel]], minlength=n_t)
    snr_val = np.full(n_t, np.nan)
    snr_val[loc] = snr
    return LobeTexels(lobe, np.r_[0, np.cumsum(counts)].astype(np.int64), dense[pts[sel]],
                      w[sel], var[sel], snr_val)


def lobes_bounded(lp: LevelPass, texels: np.ndarray, dense: np.ndarray, dseg: np.ndarray,
                  tried: np.ndarray) -> LobeTexels:
    """`lobe_texels` over chunks of texels whose samples' rays on the training directions fit
    the worker's memory budget (a texel's samples are never split), joined as one."""
    n_t = len(texels)
    n_dense = np.bincount(dseg, minlength=n_t)
    starts = np.r_[0, np.cumsum(n_dense)]
    n_dirs = len(lp.dirs["dirs_i"]) + len(lp.dirs["dirs_o"])
    cap = max(lp.budget // (BYTES_PER_LOBE_ENTRY * n_dirs), 1)
    parts = [lobe_texels(lp, texels[a:b], dense[starts[a]:starts[b]],
                         dseg[starts[a]:starts[b]] - a, tried[a:b])
             for a, b in chunk_bounds(n_dense, cap)]  # loop over chunks (memory bound)
    if not parts:
        return lobe_texels(lp, texels, dense, dseg, tried)
    counts = np.concatenate([np.diff(p.offsets) for p in parts])
    return LobeTexels(
        np.concatenate([p.lobe for p in parts]), np.r_[0, np.cumsum(counts)].astype(np.int64),
        *(np.concatenate([getattr(p, f) for p in parts])
          for f in ("points", "weights", "var", "snr_val")))


def _one_pattern(lp: LevelPass, texels: np.ndarray, dense: np.ndarray, dseg: np.ndarray,
                 cand: np.ndarray, mean: np.ndarray) -> np.ndarray:
    """(t,) bool: each `cand` texel has one visibility pattern on the training directions up
    to a share of its light no larger than the amplitude eps_db allows (module docstring):
    bounded from the geometry (`classify.open_texels`: no direction split), else by the
    samples' own rays (`classify.visibility_patterns`). `mean` (t, 3) the texels' mean shading
    normals, whose cosines weigh the split directions."""
    src, dirs = lp.src, lp.dirs
    n_t = len(texels)
    rows = np.flatnonzero(cand[dseg])
    if rows.size == 0:
        return np.zeros(n_t, bool)
    open_t = open_texels(lp, dense, dseg, rows, n_t) & cand
    cast = rows[~open_t[dseg[rows]]]
    if cast.size == 0:
        return open_t
    lit_all, _ = visibility_patterns(lp, texels, dense, dseg, cast)  # light, then view
    smp, tex = dense[cast], texels[dseg[cast]]
    sn, gnc = src.geo["sample_nrm"][smp], src.geo["sample_gnrm"][smp]
    split = np.zeros(n_t)
    total = np.zeros(n_t)
    cast_t = np.unique(dseg[cast])
    n_i = len(dirs["dirs_i"])
    for key, lit in (("dirs_i", lit_all[:, :n_i]), ("dirs_o", lit_all[:, n_i:])):
        w = world_dirs(lp.frames, tex, dirs[key])
        above = (np.einsum("pk,pdk->pd", sn, w) > TOL.grazing_cos) & \
            (np.einsum("pk,pdk->pd", gnc, w) > TOL.grazing_cos)
        # per texel and direction: some sample above its horizons occluded, another not
        n_occ = segment_sum((above & ~lit).astype(np.float64), dseg[cast], n_t, 0)
        n_lit = segment_sum(lit.astype(np.float64), dseg[cast], n_t, 0)
        cos_t = np.maximum(np.einsum("tk,tdk->td", mean[cast_t],
                                     world_dirs(lp.frames, texels[cast_t], dirs[key])), 0.0)
        split[cast_t] += np.sum(cos_t * ((n_occ > 0) & (n_lit > 0))[cast_t], axis=1)
        total[cast_t] += cos_t.sum(axis=1)
    share = np.divide(split, total, out=np.ones(n_t), where=total > 0)
    return open_t | (cand & ~open_t & (share <= 10.0 ** (-src.settings.eps_db / 20.0)))


__all__ = ["BYTES_PER_LOBE_ENTRY", "LobeTexels", "lobe_texels", "lobes_bounded"]
