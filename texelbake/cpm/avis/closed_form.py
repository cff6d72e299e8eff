"""Texels unoccluded over their whole hemisphere and their exact closed-form a_vis."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.spatial import ConvexHull, QhullError, cKDTree

from texelbake.arrays import unique_rows
from texelbake.cpm.avis.cube import check_res, cube_directions
from texelbake.cpm.avis.maps import coerce_samples, default_eps
from texelbake.errors import NumericalError, ShapeError
from texelbake.tol import TOL

# --------------------------------------------------------------------------------------------
# closed form


def unoccluded_texels(positions: np.ndarray, normals: np.ndarray, texel_of_sample: np.ndarray,
                      n_texels: int, mesh_points: np.ndarray, *, eps: float | None = None,
                      chunk: int = 1 << 22) -> np.ndarray:
    """Texels whose every sample is unoccluded in every direction of its hemisphere
    (`unoccluded_samples`; a texel without samples passes: a_vis = 0).

    texel_of_sample : (m,) int in [0, n_texels); the other arguments as `unoccluded_samples`
    returns : (n_texels,) bool
    """
    _, _, _, tex, n_texels = coerce_samples(normals, np.zeros(len(np.asarray(normals))),
                                            texel_of_sample, n_texels, positions)
    ok = unoccluded_samples(positions, normals, mesh_points, eps=eps, chunk=chunk)
    return np.bincount(tex[~ok], minlength=n_texels) == 0


def unoccluded_samples(positions: np.ndarray, normals: np.ndarray, mesh_points: np.ndarray, *,
                       eps: float | None = None, chunk: int = 1 << 22) -> np.ndarray:
    """Samples unoccluded in every direction of their hemisphere.

    What is detected, exactly: sample j passes iff every vertex y of M_org satisfies
    n_j . (y - x_j) <= eps (the mesh lies below the sample's tangent plane, lifted by eps).

    Why this is exact (and complete): the mesh is a union of triangles, each the convex hull of
    its vertices, so the mesh lies in the half-space {y : n_j . (y - x_j) <= eps}. A ray from the
    offset origin o = x_j + eps n_j along any w with n_j . w > 0 has
    n_j . (o + t w - x_j) = eps + t n_j . w > eps for t > 0, so it hits nothing: V(x_j, w) = 1 for
    every w where (n_j . w)^+ > 0, and a_vis(w) = sum_j (n_j . w)^+ dA_j holds for *all* w
    (the rays avis_cube_maps would cast with the same eps all come back unoccluded).
    Conversely, a vertex y above the lifted plane is reached from o by the direction
    (y - o) / |y - o|, which faces n_j: that ray is occluded (by y or something nearer), so a
    failing sample really is occluded in some direction. The max of the linear function
    n_j . y over the mesh is attained on its convex hull, so only hull vertices are tested
    (scipy ConvexHull / Qhull; all vertices when Qhull cannot build a hull, e.g. a flat mesh).

    positions, normals : (m, 3) float64 samples and geometric normals
    mesh_points : (v, 3) float64 vertices of M_org
    eps : default `default_eps(positions)` (the same offset avis_cube_maps uses)
    chunk : bound on the (distinct normals x hull vertices) products held at once
    returns : (m,) bool
    """
    m0 = len(np.asarray(normals))
    pos, nrm, _, _, _ = coerce_samples(normals, np.zeros(m0), np.zeros(m0, np.int64), 1,
                                       positions)
    pts = np.asarray(mesh_points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ShapeError(f"mesh_points must be (v, 3), got {pts.shape}")
    if not np.isfinite(pts).all():
        raise NumericalError("mesh_points contains NaN or Inf")
    eps = default_eps(pos) if eps is None else float(eps)
    m = pos.shape[0]
    if m == 0 or pts.shape[0] == 0:
        return np.ones(m, dtype=bool)
    try:
        hull = ConvexHull(pts)
        cand, facets = pts[hull.vertices], hull.equations  # facets: e . y + off <= 0
    except (QhullError, ValueError):
        cand, facets = np.unique(pts, axis=0), np.zeros((0, 4))
    # The support function h(n) = max_y n . y depends on the normal only, so it is bounded
    # once per distinct normal (samples of one triangle share theirs), then refined only where
    # the bounds cannot decide. All three steps are exact inequalities:
    #   lower: h(n) >= max over a subset of the hull vertices (a vertex above -> sample fails);
    #   upper: with centre c, R = max |y - c| and the hull facet (e, off) nearest to n,
    #          h(n) <= n.c + (-off - e.c) + |n - e| R  (a sample on a hull facet passes);
    #   exact: max over all hull vertices, for the undecided normals only.
    uniq, inv = unique_rows(nrm + 0.0)
    thresh = np.einsum("ji,ji->j", nrm, pos) + eps  # sample passes iff h(n_j) <= thresh_j
    sub = cand[np.linspace(0, cand.shape[0] - 1, min(cand.shape[0], 256)).astype(np.int64)]
    lower = (uniq @ sub.T).max(axis=1)  # (U,)
    centre = cand.mean(axis=0)
    radius = float(np.linalg.norm(cand - centre, axis=1).max())
    upper = uniq @ centre + radius
    if facets.shape[0]:
        _, near = cKDTree(facets[:, :3]).query(uniq)
        e, off = facets[near, :3], facets[near, 3]
        via_facet = (uniq @ centre - off - np.einsum("ui,i->u", e, centre)
                     + np.linalg.norm(uniq - e, axis=1) * radius)
        upper = np.minimum(upper, via_facet)
    ok = thresh >= upper[inv]
    undecided = ~ok & (thresh >= lower[inv])
    need = np.unique(inv[undecided])
    if need.size:
        step = max(1, int(chunk) // max(cand.shape[0], 1))
        exact = np.empty(need.shape[0], dtype=np.float64)
        for s0 in range(0, need.shape[0], step):  # loop over memory-bounded chunks
            exact[s0:s0 + step] = (uniq[need[s0:s0 + step]] @ cand.T).max(axis=1)
        support = np.full(uniq.shape[0], np.inf)
        support[need] = exact
        ok |= undecided & (thresh >= support[inv])
    return ok


@dataclass(frozen=True)
class ClosedForm:
    """a_vis(t, w) = sum_{k in texel t} areas_k (normals_k . w)^+ for closed-form texels
    ((n . w)^+ counts as 0 at or below TOL.grazing_cos, exactly as the ray path does).

    offsets : (n_texels + 1,) int64 CSR over texels (texels not in closed form own no terms)
    normals : (k,) x 3 float64 unit geometric normals, distinct within a texel
    areas : (k,) float64 summed dA_j of the samples with that normal
    """

    offsets: np.ndarray
    normals: np.ndarray
    areas: np.ndarray

    @property
    def n_texels(self) -> int:
        return int(self.offsets.shape[0] - 1)

    def padded(self, max_elems: int = 1 << 23) -> tuple[np.ndarray, np.ndarray] | None:
        """(normals (n_texels, k_max, 3), areas (n_texels, k_max)) zero-padded per texel, or
        None when n_texels * k_max exceeds max_elems (then evaluation uses the CSR pairs).
        Cached: built once per ClosedForm."""
        cache = self.__dict__.get("_padded")
        if cache is not None and cache[0] == max_elems:
            return cache[1]
        counts = np.diff(self.offsets)
        k_max = int(counts.max()) if counts.size else 0
        result: tuple[np.ndarray, np.ndarray] | None = None
        if self.n_texels * max(k_max, 1) <= max_elems:
            nrm = np.zeros((self.n_texels, k_max, 3))
            area = np.zeros((self.n_texels, k_max))
            owner = np.repeat(np.arange(self.n_texels), counts)
            slot = np.arange(owner.shape[0]) - np.repeat(self.offsets[:-1], counts)
            nrm[owner, slot] = self.normals
            area[owner, slot] = self.areas
            result = (nrm, area)
        self.__dict__["_padded"] = (max_elems, result)  # frozen dataclass: bypass setattr
        return result

    def sum_vectors(self) -> np.ndarray:
        """(n_texels, 3) float64 sum_k areas_k normals_k: a_vis(w) = S . w exactly wherever
        every normals_k . w >= 0 (e.g. a flat texel: one term)."""
        owner = np.repeat(np.arange(self.n_texels), np.diff(self.offsets))
        out = np.zeros((self.n_texels, 3), dtype=np.float64)
        np.add.at(out, owner, self.normals * self.areas[:, None])
        return out


def merge_terms(owner: np.ndarray, normals: np.ndarray, areas: np.ndarray,
                 n_texels: int) -> ClosedForm:
    """Merge terms with equal (owner, normal), (n.w)^+ a1 + (n.w)^+ a2 = (n.w)^+ (a1 + a2)."""
    keep = (areas > 0) & np.any(normals != 0, axis=1)
    owner, normals, areas = owner[keep], normals[keep], areas[keep]
    if owner.size == 0:
        return ClosedForm(np.zeros(n_texels + 1, np.int64), np.zeros((0, 3)), np.zeros(0))
    rows = np.column_stack([owner.astype(np.float64), normals + 0.0])  # +0.0: -0.0 -> 0.0
    uniq, inv = unique_rows(rows)
    merged_area = np.bincount(inv, weights=areas, minlength=uniq.shape[0])
    u_owner = uniq[:, 0].astype(np.int64)
    offsets = np.searchsorted(u_owner, np.arange(n_texels + 1)).astype(np.int64)
    return ClosedForm(offsets, uniq[:, 1:].copy(), merged_area)


def closed_form_terms(normals: np.ndarray, areas: np.ndarray, texel_of_sample: np.ndarray,
                      n_texels: int, texel_mask: np.ndarray | None = None) -> ClosedForm:
    """The closed-form terms of the texels in texel_mask (all when None).

    normals : (m, 3) float64 geometric normals; areas : (m,) float64
    texel_of_sample : (m,) int; texel_mask : (n_texels,) bool
    returns : ClosedForm (samples with bit-identical normals in a texel merged into one term)
    """
    nrm, ar, tex, n_texels = coerce_samples(normals, areas, texel_of_sample, n_texels)
    sel = np.ones(tex.shape[0], dtype=bool)
    if texel_mask is not None:
        mask = np.asarray(texel_mask, dtype=bool)
        if mask.shape != (n_texels,):
            raise ShapeError(f"texel_mask must be ({n_texels},), got {mask.shape}")
        sel = mask[tex]
    return merge_terms(tex[sel], nrm[sel], ar[sel], n_texels)


def eval_closed_form(cf: ClosedForm, texels: np.ndarray, dirs_world: np.ndarray, *,
                     dense_limit: int = 1 << 23) -> np.ndarray:
    """Exact a_vis of closed-form texels at arbitrary directions (no rays, no cube map).

    texels : (n,) int; dirs_world : (n, 3) float64 unit
    dense_limit : use the zero-padded (n_texels, k_max) layout when n_texels * k_max is at
        most this (about 4x faster), else the CSR pairs; both give the same sums
    returns : (n,) float64 (0 for texels without terms)
    """
    t = np.asarray(texels, dtype=np.int64).ravel()
    w = np.asarray(dirs_world, dtype=np.float64)
    if w.shape != (t.shape[0], 3):
        raise ShapeError(f"dirs_world must be ({t.shape[0]}, 3), got {w.shape}")
    if t.size and (t.min() < 0 or t.max() >= cf.n_texels):
        raise ShapeError(f"texels must be in [0, {cf.n_texels})")
    if t.size == 0:
        return np.zeros(0, dtype=np.float64)
    padded = cf.padded(dense_limit)
    if padded is not None:
        # dense (n_texels, k_max) layout: one gather and one einsum per chunk of queries
        nrm_p, area_p = padded
        k_max = max(nrm_p.shape[1], 1)
        out = np.empty(t.shape[0], dtype=np.float64)
        step = max(1, (1 << 22) // k_max)
        for q0 in range(0, t.shape[0], step):  # memory-bounded chunks of queries
            tq = t[q0:q0 + step]
            d = np.einsum("qkj,qj->qk", nrm_p[tq], w[q0:q0 + step])  # (q, k_max)
            out[q0:q0 + step] = np.sum(np.where(d > TOL.grazing_cos, d, 0.0) * area_p[tq],
                                       axis=1)
        return out
    start = cf.offsets[t]
    counts = cf.offsets[t + 1] - start  # (n,)
    query = np.repeat(np.arange(t.shape[0]), counts)  # (pairs,)
    first = np.cumsum(counts) - counts
    term = np.arange(query.shape[0]) - np.repeat(first - start, counts)
    dots = np.einsum("ki,ki->k", cf.normals[term], w[query])
    dots = np.where(dots > TOL.grazing_cos, dots, 0.0) * cf.areas[term]
    return np.bincount(query, weights=dots, minlength=t.shape[0])


def closed_form_maps(cf: ClosedForm, res: int, texels: np.ndarray | None = None, *,
                     max_elems: int = 1 << 24) -> np.ndarray:
    """Closed-form a_vis at the cube-map directions (for coarsening into ray-based parents).

    texels : (r,) int (all texels when None)
    returns : (r, 6, res, res) float64
    """
    res = check_res(res)
    t = np.arange(cf.n_texels) if texels is None else np.asarray(texels, dtype=np.int64)
    dirs = cube_directions(res).reshape(-1, 3)
    nd = dirs.shape[0]
    counts = cf.offsets[t + 1] - cf.offsets[t]
    row = np.repeat(np.arange(t.shape[0]), counts)
    first = np.cumsum(counts) - counts
    term = np.arange(row.shape[0]) - np.repeat(first - cf.offsets[t], counts)
    out = np.zeros((t.shape[0], nd), dtype=np.float64)
    step = max(1, int(max_elems) // nd)
    for k0 in range(0, term.shape[0], step):  # memory-bounded chunks of terms
        tk = term[k0:k0 + step]
        proj = cf.normals[tk] @ dirs.T  # (k, nd)
        proj = np.where(proj > TOL.grazing_cos, proj, 0.0) * cf.areas[tk, None]
        owner = sp.csr_matrix((np.ones(tk.shape[0]), (row[k0:k0 + step], np.arange(tk.shape[0]))),
                              shape=(t.shape[0], tk.shape[0]))
        out += owner @ proj
    return out.reshape(t.shape[0], 6, res, res)
