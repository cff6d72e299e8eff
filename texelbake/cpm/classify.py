"""Texels classed by what they need, before any R is built (DESIGN.md, "model only what a
scene needs"): a texel whose dense samples share one facet, one material response up to a
per-channel factor and one visibility pattern is exactly one characteristic point (the
rank-1 case of seed 000 Eq. 7), and one of a few such groups a point per group, so neither
needs R, Gram or trial; every other texel goes to the seed's fit.

Why one point is exact for such a texel: Eq. 7's numerator is
sum_j a_j f_r(x_j, w_i, w_o) V(x_j, w_i) (n_j . w_i)+ V(x_j, w_o) (n_j . w_o)+. With every
n_j equal (one facet: the geometric and the shading normal), V(x_j, .) equal (one visibility
pattern) and f_r(x_j) = s_j * f_r(x_ref) per channel (one material whose varying inputs f_r is
proportional to: a constant material, s_j = 1, or a Lambert albedo texture, s_j = rho_j /
rho_ref), the sum is f_r(x_ref) V (n . w_i)+ V (n . w_o)+ sum_j a_j s_j: one point x_ref
with weight sum_j a_j s_j per channel (the area times the mean of the linear inputs, relative
to the point's own), and a_vis = A (n . w_o)+ V(w_o) in closed form. A non-linear input that
varies (a roughness texture) breaks the proportionality on the check pairs, and the texel is
fitted.

The same sum splits over any partition of a texel's samples into groups that are each one
facet and one material (proportional within the group) and one visibility pattern: every
group's rows of R are equal up to s_j, so one point per group is exact on the training grid
(a ridge's shadow edge across one facet, a fold between two facets, two materials). A texel
of at most BakeSettings.c_max such groups is stored so ("grouped"), each group's point the
sample nearest its centroid with weight sum_{j in g} a_j s_j / s_point (s relative to its
facet's reference; a facet whose reference is black on every check pair, below the
texel's horizon there, is fitted). The held-out pairs, whose directions lie between the
grid's, measure how well a group's point stands for its samples there.

The tests are sampled, never assumed: the BRDF on `CHECK_LIGHTS` x `CHECK_VIEWS` pairs of the
training grid, visibility on every training direction (the texel's own rays) unless the
geometry bounds it (`texelbake.cpm.avis.closed_form.unoccluded_samples`: the whole mesh below
every sample's tangent plane); the held-out pairs, independent of both, then measure each
exact texel (`TOL.exact_fit_db`). A texel with a sample on a cut-out (no area) is fitted.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from texelbake.arrays import unique_rows
from texelbake.cpm.avis.closed_form import unoccluded_samples
from texelbake.cpm.brdf_product import brdf_product
from texelbake.cpm.dense import LevelPass
from texelbake.cpm.level import (
    clusters_level0,
    segment_sum,
    texel_dirs,
    visibility_cos,
    world_dirs,
)
from texelbake.tol import TOL

#: light and view directions of the training grid on whose product the BRDF's
#: proportionality is checked (16 pairs: a varying non-linear input changes f_r's shape over
#: directions, so it shows on generic pairs)
CHECK_LIGHTS = 4
CHECK_VIEWS = 4

#: every this many light and view directions the visibility patterns are probed on first
#: (`_patterns_bounded`): a texel of too many groups there casts none of the others
PROBE_STRIDE = 4

#: why a texel is not exact, as stored in `TexelClasses.reason`
#: ("facets": more facets, each one material, than c_max; "visibility": more groups of a facet
#: and a visibility pattern than c_max; "exact" also for a grouped texel)
REASONS = {"exact": 0, "empty": 1, "facets": 2, "inputs": 4, "visibility": 5, "cut": 6}


@dataclass(frozen=True)
class TexelClasses:
    """The class of each texel of a chunk: exact (t,) bool one point; grouped (t,) bool one
    point per group of one facet, material and visibility pattern; offsets (t + 1,) int64,
    points (p,) int64 and weights (p, 3) float64 the stored points of the exact and grouped
    texels (CSR over the texels, none for the others); reason (t,) int8 (`REASONS`, "exact"
    for both stored classes); rays (int) the visibility rays the test cast; pattern (n,)
    int64 per dense sample its (facet, visibility pattern) group on the directions it was
    cast on (numbered per texel; -1 where no ray was cast), what a fitted texel's candidates
    are grouped by (`texelbake.cpm.cluster`)."""

    exact: np.ndarray
    grouped: np.ndarray
    offsets: np.ndarray
    points: np.ndarray
    weights: np.ndarray
    reason: np.ndarray
    rays: int
    pattern: np.ndarray

    @property
    def point(self) -> np.ndarray:
        """(t,) int64 the exact texel's one sample, -1 for the others."""
        out = np.full(len(self.exact), -1, np.int64)
        out[self.exact] = self.points[self.offsets[:-1][self.exact]]
        return out

    @property
    def weight(self) -> np.ndarray:
        """(t, 3) float64 the exact texel's weight, 0 for the others."""
        out = np.zeros((len(self.exact), 3))
        out[self.exact] = self.weights[self.offsets[:-1][self.exact]]
        return out


def seg_all(ok: np.ndarray, seg: np.ndarray, n_t: int) -> np.ndarray:
    """(n_t,) bool: every row of each segment is ok (an empty segment is True)."""
    return np.bincount(seg[~ok], minlength=n_t) == 0


def open_texels(lp: LevelPass, dense: np.ndarray, dseg: np.ndarray, rows: np.ndarray,
                n_t: int) -> np.ndarray:
    """(n_t,) bool: every sample of the rows `rows` (positions in `dense`, texel positions
    `dseg`) of each texel is unoccluded in its whole hemisphere, bounded from the geometry
    (`unoccluded_samples`: the whole mesh below its tangent plane); True for a texel with no
    such row."""
    src = lp.src
    bound = unoccluded_samples(src.geo["sample_pos"][dense[rows]],
                               src.geo["sample_gnrm"][dense[rows]], src.caster.points,
                               eps=TOL.ray_offset * src.caster.bbox_diag)
    return seg_all(bound, dseg[rows], n_t)


def classify_texels(lp: LevelPass, texels: np.ndarray, dense: np.ndarray, dseg: np.ndarray
                    ) -> TexelClasses:
    """Class the `texels` (flat ids at lp.level) from their dense samples (`dense` (n,) int64
    grouped by texel, `dseg` (n,) their texel positions, ascending), module docstring."""
    src, geo = lp.src, lp.src.geo
    n_t = len(texels)
    reason = np.full(n_t, REASONS["exact"], np.int8)
    count = np.bincount(dseg, minlength=n_t)
    reason[count == 0] = REASONS["empty"]
    if dense.size == 0:
        return TexelClasses(np.zeros(n_t, bool), np.zeros(n_t, bool),
                            np.zeros(n_t + 1, np.int64), np.zeros(0, np.int64),
                            np.zeros((0, 3)), reason, 0, np.zeros(0, np.int64))
    area = geo["sample_area"][dense]
    pos = geo["sample_pos"][dense]
    # a sample on a cut-out (brdf.opacity) carries no area: a texel cut in part or whole is
    # fitted by the seed's path, which weighs by area (its reference sample could be a cut
    # one, and a wholly cut texel holds no surface, which one stored point would paint black)
    reason[(reason == 0) & ~seg_all(area > 0, dseg, n_t)] = REASONS["cut"]
    # the reference sample: the one nearest the texel's area-weighted centroid (lowest id on a
    # tie), where the renderer shades the point
    first, _ = _nearest_centroid(dseg, np.arange(dense.size), pos, area, dense)
    ref_row = np.zeros(n_t, np.int64)
    ref_row[dseg[first]] = first
    # facets: the samples partitioned by material and both normals (within the tolerance of
    # each part's first sample, the texel's reference first); each part's reference is its
    # sample nearest its centroid (the texel's own where the texel is one part)
    c_max = max(src.settings.c_max, 1)
    mat = geo["sample_mat"][dense]
    fac, n_fac = _facet_groups(geo["sample_nrm"][dense], geo["sample_gnrm"][dense], mat, dseg,
                               np.where(reason == 0, ref_row, -1), c_max)
    reason[(reason == 0) & (n_fac > c_max)] = REASONS["facets"]
    live = (reason == 0)[dseg]
    ref = ref_row[dseg]  # (n,) each sample's reference row: its facet's
    multi = live & (n_fac[dseg] > 1)
    if multi.any():
        f_rep, f_of = _nearest_centroid(fac, np.flatnonzero(multi), pos, area, dense)
        ref[multi] = f_rep[f_of]
    # one material response per facet up to a per-channel factor s_j, on the check pairs
    rows = np.flatnonzero(live)
    s_ratio = np.ones((dense.size, 3))
    if rows.size:
        s_rows, ok_f, has = _proportional(lp, texels, dense, dseg, rows, ref)
        s_ratio[rows] = s_rows
        # a facet whose reference is black on every check pair (below the texel's horizon
        # there) gives no factor to scale by: fitted
        bad = ~seg_all(ok_f & has, dseg[rows], n_t)
        reason[(reason == 0) & bad] = REASONS["inputs"]
    # visibility patterns: bounded from the geometry (one), else the texel's own rays
    rays = 0
    group = np.zeros(dense.size, np.int64)  # a sample's pattern, numbered over the chunk
    pattern = np.full(dense.size, -1, np.int64)
    rows = np.flatnonzero((reason == 0)[dseg])
    if rows.size:
        open_t = open_texels(lp, dense, dseg, rows, n_t)
        cast = rows[~open_t[dseg[rows]]]
        group[rows] = fac[rows]  # an open texel: one pattern, a group per facet
        if cast.size:
            # a fitted finest texel's candidates are grouped by its full patterns
            full = lp.level == 0 and clusters_level0(src.settings)
            vis, cast, rays = _patterns_bounded(lp, texels, dense, dseg, cast, fac, c_max,
                                                reason, pattern, full)
            group[cast] = int(fac.max()) + 1 + _pattern_groups(fac[cast], vis)
            pattern[cast] = group[cast]
    live = (reason == 0)[dseg]
    g_ids, g_of = np.unique(group[live], return_inverse=True)
    g_texel = np.zeros(g_ids.size, np.int64)
    g_texel[g_of] = dseg[live]
    n_pat = np.bincount(g_texel, minlength=n_t)
    reason[(reason == 0) & (n_pat > c_max)] = REASONS["visibility"]
    # each sample's weight relative to its facet's reference: a_j s_j per channel
    aw = area[:, None] * s_ratio
    exact = (reason == 0) & (n_pat == 1) & (n_fac == 1)
    point = dense[ref_row[exact]]
    # an exact texel's weight: sum_j a_j s_j per channel (the area when the inputs are constant)
    weight = segment_sum(aw, dseg, n_t, 0)[exact]
    grouped = (reason == 0) & ~exact
    g_pts, g_w, g_t = _group_points(dense, dseg, pos, area, aw, s_ratio, group,
                                    grouped[dseg])
    # a group whose point is black in a channel the group is not cannot carry it: fitted
    bad = np.bincount(g_t, weights=(~np.isfinite(g_w).all(axis=1)).astype(float),
                      minlength=n_t) > 0
    reason[grouped & bad] = REASONS["inputs"]
    grouped &= ~bad
    keep = grouped[g_t]
    t_of = np.r_[np.flatnonzero(exact), g_t[keep]]
    order = np.lexsort((np.r_[point, g_pts[keep]], t_of))
    pts = np.r_[point, g_pts[keep]][order]
    wts = np.concatenate([weight, g_w[keep]])[order]
    offsets = np.r_[0, np.cumsum(np.bincount(t_of, minlength=n_t))].astype(np.int64)
    return TexelClasses(exact, grouped, offsets, pts, wts, reason, rays,
                        _per_texel(pattern, dseg))


def _facet_groups(nrm: np.ndarray, gnrm: np.ndarray, mat: np.ndarray, dseg: np.ndarray,
                  seed: np.ndarray, cap: int) -> tuple[np.ndarray, np.ndarray]:
    """Each texel's samples partitioned into facets: one material, shading and geometric
    normals within TOL.exact_normal of the facet's first sample. `seed` (t,) the first
    sample row of each texel (-1: not partitioned); each next facet starts at the texel's
    lowest unassigned row. Returns (facet (n,) int64, ids round x n_t + texel, -1 where not
    partitioned; count (t,) facets per texel, cap + 1 where there are more than cap)."""
    n_t = len(seed)
    fac = np.full(len(dseg), -1, np.int64)
    count = np.zeros(n_t, np.int64)
    todo = (seed >= 0)[dseg]
    for r in range(cap + 1):  # loop over facets: one per texel and round, vectorized
        on = seed >= 0
        if not on.any():
            break
        count[on] += 1
        rows = np.flatnonzero(todo & on[dseg])
        s = seed[dseg[rows]]
        ok = ((np.einsum("ij,ij->i", nrm[rows], nrm[s]) >= 1.0 - TOL.exact_normal)
              & (np.einsum("ij,ij->i", gnrm[rows], gnrm[s]) >= 1.0 - TOL.exact_normal)
              & (mat[rows] == mat[s])) | (rows == s)
        fac[rows[ok]] = r * n_t + dseg[rows[ok]]
        todo[rows[ok]] = False
        left = np.flatnonzero(todo)
        seed = np.full(n_t, -1, np.int64)
        first = left[np.r_[True, dseg[left][1:] != dseg[left][:-1]]] if left.size else left
        seed[dseg[first]] = first
    count[np.bincount(dseg[todo], minlength=n_t) > 0] = cap + 1
    return fac, count


def _nearest_centroid(group: np.ndarray, rows: np.ndarray, pos: np.ndarray, area: np.ndarray,
                      dense: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For the rows `rows` labelled `group`: (rep (g,) the row of each group's sample nearest
    its area-weighted centroid, lowest id on a tie; g_of (r,) each row's group 0..g-1)."""
    _, g = np.unique(group[rows], return_inverse=True)
    g = g.ravel()
    n_g = int(g.max()) + 1
    a = area[rows]
    tot = np.bincount(g, weights=a, minlength=n_g)
    cen = np.stack([np.bincount(g, weights=pos[rows, k] * a, minlength=n_g)
                    for k in range(3)], axis=1) / np.maximum(tot, 1e-300)[:, None]
    d = pos[rows] - cen[g]
    dist = np.einsum("ij,ij->i", d, d)
    order = np.lexsort((dense[rows], dist, g))
    first = order[np.r_[True, g[order][1:] != g[order][:-1]]]  # one row per group, by g
    return rows[first], g


def _group_points(dense: np.ndarray, dseg: np.ndarray, pos: np.ndarray, area: np.ndarray,
                  aw: np.ndarray, s_ratio: np.ndarray, group: np.ndarray, on: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One point per group (`group`: facet and visibility pattern) of the rows `on`: (sample
    ids (g,), weights (g, 3) sum_{j in g} a_j s_j / s_rep, inf where the point is black in a
    channel the group is not; texel positions (g,)). The point is the group's sample nearest
    its area-weighted centroid (lowest id on a tie), where the renderer shades and traces
    it."""
    rows = np.flatnonzero(on)
    if rows.size == 0:
        return np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0, np.int64)
    rep, g = _nearest_centroid(group, rows, pos, area, dense)
    n_g = rep.size
    w = np.stack([np.bincount(g, weights=aw[rows, k], minlength=n_g) for k in range(3)],
                 axis=1)
    s_rep = s_ratio[rep]
    with np.errstate(divide="ignore", invalid="ignore"):
        w = np.where(w > 0, np.where(s_rep > 0, w / s_rep, np.inf), 0.0)
    return dense[rep], w, dseg[rep]


def _proportional(lp: LevelPass, texels: np.ndarray, dense: np.ndarray, dseg: np.ndarray,
                  rows: np.ndarray, ref: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For the samples `rows` (positions in `dense`): (s (r, 3) the least-squares factor of
    f_r(x_j) against its reference's per channel on the check pairs, ok (r,) every channel
    within TOL.exact_brdf of s_j f_r(x_ref), has (r,) the reference is nonzero on some pair)."""
    src, dirs = lp.src, lp.dirs
    di = dirs["dirs_i"][:CHECK_LIGHTS]
    do = dirs["dirs_o"][:CHECK_VIEWS]
    # every sample of these rows and its reference, evaluated once each
    need = np.unique(np.r_[rows, ref[rows]])
    smp = dense[need]
    tex = texels[dseg[need]]
    wi = world_dirs(lp.frames, tex, di)
    wo = world_dirs(lp.frames, tex, do)
    live = np.ones((len(di), len(do), len(smp)), bool)
    f = brdf_product(src.geo, src.materials, smp, wi, wo, live)  # (3, p, A, B)
    # the pairs below a sample's shading or geometric horizon add nothing to Eq. 7
    sn = src.geo["sample_nrm"][smp]
    gn = src.geo["sample_gnrm"][smp]
    up_i = (np.einsum("pk,pak->pa", sn, wi) > TOL.grazing_cos) & \
        (np.einsum("pk,pak->pa", gn, wi) > TOL.grazing_cos)
    up_o = (np.einsum("pk,pbk->pb", sn, wo) > TOL.grazing_cos) & \
        (np.einsum("pk,pbk->pb", gn, wo) > TOL.grazing_cos)
    f = np.where((up_i[:, :, None] & up_o[:, None, :])[None], f, 0.0)
    f = f.reshape(3, len(smp), -1).transpose(1, 0, 2)  # (p, 3, K)
    at = np.searchsorted(need, rows)
    at_ref = np.searchsorted(need, ref[rows])
    fj, fr = f[at], f[at_ref]  # (r, 3, K)
    rr = np.einsum("rck,rck->rc", fr, fr)
    s = np.einsum("rck,rck->rc", fj, fr) / np.where(rr > 0, rr, 1.0)
    s = np.where(rr > 0, s, 0.0)
    res = np.einsum("rck->rc", (fj - s[..., None] * fr) ** 2)
    scale = np.einsum("rck->r", fj * fj + fr * fr)  # the pair's energy (0: both black)
    ok = np.all(res <= TOL.exact_brdf ** 2 * np.maximum(scale, 1e-300)[:, None], axis=1)
    return s, ok, rr.sum(axis=1) > 0


def visibility_patterns(lp: LevelPass, texels: np.ndarray, dense: np.ndarray,
                        dseg: np.ndarray, rows: np.ndarray, light: np.ndarray | None = None,
                        view: np.ndarray | None = None) -> tuple[np.ndarray, int]:
    """(vis (r, n_i + n_o) bool: sample rows[j] visible on each training direction, light
    then view; rays cast), by the samples' own rays; on the light and view directions of
    the indices `light`, `view` only when given."""
    src, dirs = lp.src, lp.dirs
    smp = dense[rows]
    tex = texels[dseg[rows]]
    d_i = dirs["dirs_i"] if light is None else dirs["dirs_i"][light]
    d_o = dirs["dirs_o"] if view is None else dirs["dirs_o"][view]
    rays0 = src.caster.rays_cast
    vis = np.concatenate([
        visibility_cos(src, smp, texel_dirs(lp.frames, tex, d_i)) > 0,
        visibility_cos(src, smp, texel_dirs(lp.frames, tex, d_o), "geometric") > 0,
    ], axis=1)
    return vis, src.caster.rays_cast - rays0


def _per_texel(ids: np.ndarray, dseg: np.ndarray) -> np.ndarray:
    """`ids` (n,) (-1: none) renumbered 0.. within each texel in their order, so that they
    do not depend on which texels share the chunk."""
    out = np.full(ids.size, -1, np.int64)
    on = ids >= 0
    if not on.any():
        return out
    span = int(ids.max()) + 1
    u, inv = np.unique(dseg[on] * span + ids[on], return_inverse=True)
    tex = u // span
    out[on] = (np.arange(u.size) - np.searchsorted(tex, tex))[inv.ravel()]
    return out


def _pattern_groups(fac: np.ndarray, vis: np.ndarray) -> np.ndarray:
    """(r,) int64 the group 0.. of each row's (facet, visibility pattern) pair, numbered in
    the order of the pairs (the facet's two's-complement bits, then the pattern's bits)."""
    bits = np.packbits(vis, axis=1)
    n, nb = bits.shape
    if n == 0:
        return np.zeros(0, np.int64)
    # one key per row as 64-bit words, the facet first, then the pattern's bytes big-endian
    # and zero-padded: sorting the words sorts the bytes, and a lexsort of a few integer
    # columns (`unique_rows`) is far cheaper than `np.unique(axis=0)` on the bytes
    words = np.zeros((n, 1 + (nb + 7) // 8), np.uint64)
    words[:, 0] = fac.astype(np.int64).view(np.uint64)
    pad = np.zeros((n, 8 * (words.shape[1] - 1)), np.uint8)
    pad[:, :nb] = bits
    words[:, 1:] = pad.view(">u8")
    return unique_rows(words)[1]


def _patterns_bounded(lp: LevelPass, texels: np.ndarray, dense: np.ndarray, dseg: np.ndarray,
                      cast: np.ndarray, fac: np.ndarray, c_max: int, reason: np.ndarray,
                      pattern: np.ndarray, full: bool) -> tuple[np.ndarray, np.ndarray, int]:
    """The visibility patterns of the rows `cast`, a probe first: every PROBE_STRIDE-th light
    and view direction. A texel whose rows form more than c_max (facet, pattern) groups on the
    probe has more on every direction (a pattern's part distinguishes no fewer rows than the
    whole): its reason is set to "visibility" in `reason` and, unless `full` (its patterns
    on every direction wanted: they group its candidates, `texelbake.cpm.cluster`), its rows'
    probe groups are written to `pattern` and it casts no more rays. Returns (vis (r',
    n_i + n_o) in the directions' order, the rows cast on every direction r', rays cast)."""
    n_i, n_o = len(lp.dirs["dirs_i"]), len(lp.dirs["dirs_o"])
    li, vi = np.arange(0, n_i, PROBE_STRIDE), np.arange(0, n_o, PROBE_STRIDE)
    probe, rays = visibility_patterns(lp, texels, dense, dseg, cast, li, vi)
    g = _pattern_groups(fac[cast], probe)
    # groups per texel: the distinct (texel, group) pairs
    n_t = len(reason)
    span = int(g.max()) + 1
    pairs = np.unique(dseg[cast] * span + g)
    over = np.bincount(pairs // span, minlength=n_t) > c_max
    reason[(reason == REASONS["exact"]) & over] = REASONS["visibility"]
    if not full:
        keep = ~over[dseg[cast]]
        pattern[cast[~keep]] = g[~keep]
        cast, probe = cast[keep], probe[keep]
    rest_i = np.setdiff1d(np.arange(n_i), li)
    rest_o = np.setdiff1d(np.arange(n_o), vi)
    vis = np.zeros((cast.size, n_i + n_o), bool)
    vis[:, li], vis[:, n_i + vi] = probe[:, :li.size], probe[:, li.size:]
    if cast.size and (rest_i.size or rest_o.size):
        more, r2 = visibility_patterns(lp, texels, dense, dseg, cast, rest_i, rest_o)
        vis[:, rest_i], vis[:, n_i + rest_o] = more[:, :rest_i.size], more[:, rest_i.size:]
        rays += r2
    return vis, cast, rays


__all__ = ["CHECK_LIGHTS", "CHECK_VIEWS", "REASONS", "TexelClasses", "classify_texels",
           "open_texels", "seg_all", "visibility_patterns"]
