"""Which samples cast a_vis rays: a bounded, stratified share of each facet of a texel.

a_vis(p, w) = sum_j V(x_j, w) (n_j . w)^+ dA_j (Eq. 3) over a texel's samples. Within one
M_org triangle of one texel every sample has the same normal n, so the triangle's share is
n_k-term A_k (n . w)^+ times the area-weighted mean of V over the triangle's samples. That mean
is an integral over a piece of one plane: it needs as many rays as V varies over the piece,
not as many as the dense count. `facet_subsample` keeps, in every (texel, triangle) group of
samples that cast rays, at most `per_facet` of them, chosen at evenly spaced, centred ranks in
sample order (the sampler's order within a triangle is stratified along one barycentric coordinate:
`texelbake.geometry.sampling`), and gives them the group's whole area. The estimate is exact
wherever V is one pattern over the group (a facet seen whole, or shadowed whole), and a
stratified estimate of the mean otherwise. A texel over many small triangles keeps every
sample; a texel inside one large facet casts `per_facet` samples' rays instead of all.

The areas of the texel (its closed-form terms, the unoccluded bound, the a_vis -> 0 floor) are
not changed: only the weights with which rays are counted.
"""

from __future__ import annotations

import numpy as np

from texelbake.errors import SettingsError, ShapeError


def facet_subsample(texel_of_sample: np.ndarray, face_of_sample: np.ndarray,
                    areas: np.ndarray, per_facet: int,
                    cast: np.ndarray | None = None) -> np.ndarray:
    """The areas with which a_vis rays are counted (module docstring).

    texel_of_sample : (m,) int64 texel of each sample; face_of_sample : (m,) int64 its M_org
        triangle; areas : (m,) float64 dA_j
    per_facet : most samples per (texel, triangle) that keep a nonzero weight; 0 keeps every
        sample (the seed's dense a_vis: `areas` returned unchanged)
    cast : (m,) bool, the samples that would cast rays (default: all); the others keep their
        own area (e.g. free samples, counted without rays)
    returns : (m,) float64; in each group of cast samples with area > 0, `per_facet` of them
        (all when fewer) carry the group's summed area in proportion to their own, the rest 0
    """
    tex = np.asarray(texel_of_sample, np.int64)
    face = np.asarray(face_of_sample, np.int64)
    ar = np.asarray(areas, np.float64)
    m = ar.shape[0]
    if tex.shape != (m,) or face.shape != (m,):
        raise ShapeError(f"texel_of_sample and face_of_sample must be ({m},), got "
                         f"{tex.shape} and {face.shape}")
    if int(per_facet) < 0:
        raise SettingsError(f"per_facet must be >= 0 (0: every sample), got {per_facet}")
    out = ar.copy()
    if per_facet == 0 or m == 0:
        return out
    sel = ar > 0
    if cast is not None:
        cast = np.asarray(cast, bool)
        if cast.shape != (m,):
            raise ShapeError(f"cast must be ({m},), got {cast.shape}")
        sel &= cast
    idx = np.flatnonzero(sel)  # ascending sample ids
    if idx.size == 0:
        return out
    # groups (texel, triangle), ids ascending inside each (a stable sort of ascending ids)
    order = np.lexsort((face[idx], tex[idx]))
    js = idx[order]
    key_t, key_f = tex[js], face[js]
    head = np.r_[True, (key_t[1:] != key_t[:-1]) | (key_f[1:] != key_f[:-1])]
    group = np.cumsum(head) - 1  # (k,) group of each sorted sample
    starts = np.flatnonzero(head)
    size = np.diff(np.r_[starts, js.size])  # (g,)
    rank = np.arange(js.size) - starts[group]
    k = np.minimum(size, int(per_facet))[group]
    n_g = size[group]
    # evenly spaced, centred ranks floor((i + 1/2) n / k), i = 0..k-1: rank r is one of them
    # when an integer i lies in [r k / n - 1/2, (r + 1) k / n - 1/2), i.e. when
    # ceil((2 (r + 1) k - n) / 2n) > ceil((2 r k - n) / 2n)
    chosen = (-((n_g - 2 * (rank + 1) * k) // (2 * n_g))) > (-((n_g - 2 * rank * k) // (2 * n_g)))
    g_area = np.bincount(group, weights=ar[js], minlength=starts.size)
    c_area = np.bincount(group, weights=np.where(chosen, ar[js], 0.0), minlength=starts.size)
    scale = g_area / np.where(c_area > 0, c_area, 1.0)
    out[js] = np.where(chosen, ar[js] * scale[group], 0.0)
    return out


__all__ = ["facet_subsample"]
