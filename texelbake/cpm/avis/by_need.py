"""Level-0 a_vis whose rays follow the need: a texel's cube cast from a few of its samples,
area-weighted, instead of from every dense sample.

a_vis(w) = sum_j V(x_j, w) (n_j . w)^+ dA_j over the texel's samples is estimated from a
stratified subset S of the samples that cast rays, sample i in S carrying the area of its
stratum (the samples of one stratum, consecutive in a Morton order of the texel): the
weights sum to the texel's area exactly, so an unoccluded texel is exact and the error is
only in where the shadows fall. Samples proven unoccluded (`unoccluded_samples`) cast no
rays in either rebuild; they are kept whole, with their own areas.

How many samples a texel's rays come from (`need_samples`):
* one, when its ray-casting samples share one facet (geometric normals within
  `TOL.exact_normal`) and one visibility pattern on `PATTERN_DIRS` facing directions (the
  samples' own rays): then every sample's term is
  V(w) (n . w)^+ dA_j with the same V and n, and the sum is A (n . w)^+ V(w) from any one of
  them (the a_vis of `texelbake.cpm.classify`'s exact class; material does not enter a_vis,
  and the a_vis stage runs before the cpm stage classes its texels). Exact wherever the
  pattern holds at the fine cube's directions too;
* `strata_for(atlas side)` strata for every other texel (all its samples when it has fewer):
  `K_SAMPLES` up to a 128² atlas, fewer on finer atlases, whose texels vary less across
  their strata.

The maps (`by_need_maps`) are a ratio estimate: the unoccluded projected area
U(w) = sum_j (n_j . w)^+ dA_j is known without rays (the closed-form terms, or every
sample's cosines), so only the visible fraction comes from the strata,
a_vis(w) ~ U(w) * sum_S V (n . w)^+ w_i / sum_S (n . w)^+ w_i. Over one facet the two sums'
cosines cancel and this is the plain area-weighted estimate; over many facets (a bolt's
threads) the strata's normals stand for the texel's only through the fraction (measured:
the bolt's median per-texel error at K = 4 from 25 % to 14 %).

Not the default (`BakeSettings.avis_level0`): a coarse level's fit divides R, from every
dense sample's rays, by its children's a_vis, and an estimate of the shadows that R does not
share costs the coarse levels' held-out tails (docs/decisions.md "Level 0's a_vis").
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from texelbake.cpm.avis.closed_form import ClosedForm, closed_form_maps
from texelbake.cpm.avis.cube import OccludedFn
from texelbake.cpm.avis.maps import avis_cube_maps, never_occluded, pairs_fn
from texelbake.tol import TOL

#: ray-casting samples per texel that is not one facet and one visibility pattern: the
#: smallest K within ~6 % of the dense maps per texel (median) on the cylinder and the bolt at
#: 64²–128², 9–12x fewer rays (`benchmarks/avis_level0.py`, docs/decisions.md "Level 0's a_vis")
K_SAMPLES = 16
#: the atlas side up to which a texel casts from K_SAMPLES strata
K_SIDE = 128
#: the fewest strata on any atlas
K_MIN = 4


def strata_for(atlas_resolution: int) -> int:
    """Strata of a by-need texel at this atlas side: K_SAMPLES up to K_SIDE, then
    ceil(K_SAMPLES sqrt(K_SIDE / side)), at least K_MIN (256²: 12, 512²: 8, 1024²: 6). The
    per-texel error of the maps goes as side^-0.47 at fixed K and K^-0.77 at a fixed side
    (median against the dense maps, the full cylinder and bolt at 128²-512²), so K ~ side^-0.6
    holds the error 128²'s K_SAMPLES gives (docs/decisions.md, "The by-need strata follow
    the atlas side")."""
    side = max(int(atlas_resolution), 1)
    if side <= K_SIDE:
        return K_SAMPLES
    return max(K_MIN, int(np.ceil(K_SAMPLES * np.sqrt(K_SIDE / side) - 1e-9)))


#: world directions that test the visibility pattern (a Fibonacci sphere: even over the
#: sphere down to the horizon, where shadows of rims and ridges fall and a coarse cube's
#: centres are not; measured against 4 x 4 cube faces, docs/decisions.md "Level 0's a_vis")
PATTERN_DIRS = 64


def pattern_directions(n: int = PATTERN_DIRS) -> np.ndarray:
    """(n, 3) float64 unit directions spread evenly over the sphere (Fibonacci lattice)."""
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    r = np.sqrt(1.0 - z * z)
    phi = np.pi * (3.0 - np.sqrt(5.0)) * i
    return np.column_stack([r * np.cos(phi), r * np.sin(phi), z])


@dataclass(frozen=True)
class NeedSamples:
    """The samples a by-need level-0 a_vis is built from.

    rows : (s,) int64 sample ids (into the caller's sample arrays), ascending
    weight : (s,) float64 the area each stands for (per texel, the weights of its rows sum to
        the areas of its live samples)
    one : (n_texels,) bool texels whose ray-casting samples are one facet and one pattern
        (their rays from one sample)
    pattern_rays : int rays cast by the pattern test
    """

    rows: np.ndarray
    weight: np.ndarray
    one: np.ndarray
    pattern_rays: int


def _morton_in_texel(pos: np.ndarray, tex: np.ndarray, n_texels: int) -> np.ndarray:
    """(m,) int64 Morton code of each position in its texel's bounding box (10 bits/axis)."""
    lo = np.full((n_texels, 3), np.inf)
    hi = np.full((n_texels, 3), -np.inf)
    np.minimum.at(lo, tex, pos)
    np.maximum.at(hi, tex, pos)
    span = np.where(hi - lo > 0, hi - lo, 1.0)
    q = np.clip(((pos - lo[tex]) / span[tex] * 1023.0).astype(np.int64), 0, 1023)  # (m, 3)
    code = np.zeros(pos.shape[0], np.int64)
    for b in range(10):  # a loop over bits
        for a in range(3):
            code |= ((q[:, a] >> b) & 1) << (3 * b + a)
    return code


def _pattern_same(pos: np.ndarray, nrm: np.ndarray, ref: np.ndarray, occluded_fn: OccludedFn,
                  eps: float) -> tuple[np.ndarray, int]:
    """(same (c,) bool: sample c is visible on exactly the facing `pattern_directions` its
    texel's reference sample `ref[c]` (a row of the same arrays) is; rays cast)."""
    dirs = pattern_directions()  # (d, 3)
    facing = nrm @ dirs.T > TOL.grazing_cos  # (c, d)
    jj, dd = np.nonzero(facing)
    vis = np.zeros(facing.shape, bool)
    vis[jj, dd] = ~pairs_fn(occluded_fn)(pos + eps * nrm, dirs, jj, dd)
    return np.all(vis == vis[ref], axis=1), int(jj.size)


def need_samples(positions: np.ndarray, normals: np.ndarray, areas: np.ndarray,
                 tex: np.ndarray, n_texels: int, cast: np.ndarray, occluded_fn: OccludedFn,
                 *, eps: float, k: int = K_SAMPLES) -> NeedSamples:
    """Which samples a texel's rays come from, and the area each stands for (module doc).

    positions, normals : (m, 3) float64 samples and unit geometric normals
    areas : (m,) float64; tex : (m,) int64 in [0, n_texels)
    cast : (m,) bool the samples that would cast rays (live, not proven free, texel not in
        closed form); the others are returned as they are when live (area > 0)
    k : strata of a texel that is not one facet and one pattern (>= 1)
    """
    k = max(int(k), 1)
    live = (areas > 0) & np.any(normals != 0, axis=1)
    keep = live & ~cast  # free samples: whole, no rays
    c = np.flatnonzero(cast & live)
    one = np.zeros(n_texels, bool)
    if c.size == 0:
        rows = np.flatnonzero(keep)
        return NeedSamples(rows, areas[rows], one, 0)
    tc = tex[c]
    order = np.lexsort((c, _morton_in_texel(positions[c], tc, n_texels), tc))
    c, tc = c[order], tc[order]  # grouped by texel, Morton order inside
    start = np.r_[True, tc[1:] != tc[:-1]]
    first = np.flatnonzero(start)
    seg = np.cumsum(start) - 1  # (c,) texel position among those with ray samples
    ref = first[seg]  # each sample's reference: its texel's first in Morton order
    n_c = np.diff(np.r_[first, c.size])  # (u,) ray samples per texel
    # one facet: every geometric normal within the tolerance of the reference's
    nrm = normals[c]
    flat = np.einsum("ij,ij->i", nrm, nrm[ref]) >= 1.0 - TOL.exact_normal
    facet = np.bincount(seg[~flat], minlength=first.size) == 0
    # one pattern: the samples' own rays on the coarse cube, for one-facet texels of > 1 sample
    test = facet & (n_c > 1)
    one_u = facet & (n_c == 1)
    rays = 0
    rows_t = np.flatnonzero(test[seg])
    if rows_t.size:
        local_ref = np.searchsorted(rows_t, ref[rows_t])  # reference rows are in rows_t
        same, rays = _pattern_same(positions[c[rows_t]], nrm[rows_t], local_ref, occluded_fn,
                                   eps)
        one_u |= test & (np.bincount(seg[rows_t][~same], minlength=first.size) == 0)
    one[tc[first]] = one_u
    # strata: k_t equal shares of the texel's cumulative area, each sample in the stratum of
    # its area midpoint; the sample nearest the stratum's centre stands for it
    k_t = np.where(one_u, 1, np.minimum(k, n_c))[seg].astype(np.float64)
    a = areas[c]
    cum = np.cumsum(a)
    base = (cum - a)[first][seg]  # area before the texel's first sample
    tot = np.bincount(seg, weights=a)[seg]
    mid = (cum - a - base + 0.5 * a) / tot  # (c,) in (0, 1)
    stratum = np.minimum(np.floor(mid * k_t), k_t - 1)
    dist = np.abs(mid - (stratum + 0.5) / k_t)
    key = seg * (k + 1) + stratum.astype(np.int64)  # (c,) texel-major stratum id
    pick = np.lexsort((np.arange(c.size), dist, key))
    head = pick[np.r_[True, key[pick][1:] != key[pick][:-1]]]  # one row per stratum
    _, inv = np.unique(key, return_inverse=True)  # (c,) stratum of each sample
    w_stratum = np.bincount(inv, weights=a)  # (strata,) ascending key = order of head
    rows = np.r_[np.flatnonzero(keep), c[head]]
    weight = np.r_[areas[keep], w_stratum]  # heads come in ascending key, as w_stratum
    order = np.argsort(rows, kind="stable")
    return NeedSamples(rows[order], weight[order], one, rays)


def by_need_maps(positions: np.ndarray, normals: np.ndarray, areas: np.ndarray,
                 tex: np.ndarray, n_texels: int, res: int, occluded_fn: OccludedFn,
                 closed: np.ndarray, free: np.ndarray | None, cf: ClosedForm,
                 bounded: np.ndarray, *, eps: float, max_rays: int = 1 << 21,
                 k: int = K_SAMPLES) -> np.ndarray:
    """Level-0 a_vis maps by need (module doc): the strata's rays, scaled to the texel's
    unoccluded projected area.

    positions, normals : (m, 3) float64 (unit normals); areas : (m,) float64
    tex : (m,) int64 in [0, n_texels); res : cube face side
    closed : (n_texels,) bool texels in closed form (left at zero, no rays)
    free : (m,) bool samples proven unoccluded, or None
    cf, bounded : the level's closed-form terms and the texels they are complete for
        (`levels._bounded_terms`): U of a bounded texel from its terms, of the others from
        every sample's cosines
    returns : (n_texels, 6, res, res) float64 world-direction maps
    """
    cast = ~closed[tex] if free is None else ~closed[tex] & ~free
    need = need_samples(positions, normals, areas, tex, n_texels, cast, occluded_fn, eps=eps,
                        k=k)
    r = need.rows

    def maps(rows: np.ndarray, weight: np.ndarray, occluded: OccludedFn,
             free_rows: np.ndarray | None = None) -> np.ndarray:
        return avis_cube_maps(positions[rows], normals[rows], weight, tex[rows], n_texels, None,
                              res, occluded, skip_texels=closed, free_samples=free_rows,
                              ray_eps=eps, max_rays=max_rays, dtype=np.float64)

    est = maps(r, need.weight, occluded_fn, None if free is None else free[r])
    u_est = maps(r, need.weight, never_occluded)
    u = np.zeros_like(est)
    ids = np.flatnonzero(~closed & bounded)
    u[ids] = closed_form_maps(cf, res, ids)
    rest = ~closed & ~bounded
    if rest.any():
        js = np.flatnonzero(rest[tex])
        u += maps(js, areas[js], never_occluded)
    ok = u_est > 0
    # where no stratum faces w the fraction is unknown: the plain estimate (0) stays
    return np.where(ok, u * est / np.where(ok, u_est, 1.0), est)


__all__ = ["K_SAMPLES", "PATTERN_DIRS", "NeedSamples", "by_need_maps", "need_samples",
           "pattern_directions", "strata_for"]
