"""Catmull–Clark subdivision surfaces as sparse linear operators: a USD mesh with
`subdivisionScheme = catmullClark` is baked from its refined, limit-projected mesh.

Hand-written because no library does what USD's scheme needs from Python: OpenSubdiv has no
wheel on PyPI, and pymeshlab's Catmull–Clark filter refines the *triangulated* cage (a quad's
two triangles become six quads: another surface), carries no face-varying UVs and has no
limit-position rule.

Every step is linear in the cage's points, so it is built once as a sparse matrix: refined
points = `vertex_matrix @ cage points`, and the same matrix refines time samples or any
vertex primvar. Face-varying values (UVs) are refined bilinearly (`fv_matrix`), which is
UsdGeom's `faceVaryingLinearInterpolation = "all"`; the smooth rules of the other modes move
interior UVs by a fraction of a cage face's UV extent and are not modelled.

Rules (Catmull & Clark 1978; boundaries as in OpenSubdiv's `edgeOnly`/`edgeAndCorner`):
face point = mean of the face's vertices; interior edge point = mean of its two ends and the
two adjacent face points; boundary (or non-manifold) edge point = the edge's midpoint;
interior vertex of valence n: (Q + S_e / n + (n − 2) v) / n with Q the mean of its faces'
points and S_e the sum of its edge neighbours; boundary vertex (v_a + 6 v + v_b) / 8 from its
two boundary neighbours; a corner (a boundary vertex of one face, under `edgeAndCorner`) and
a non-manifold vertex stay. Limit positions of a quad mesh (Halstead, Kass & DeRose 1993):
interior (n² v + 4 Σ e_j + Σ d_j) / (n (n + 5)), e_j edge and d_j diagonal neighbours;
boundary (v_a + 4 v + v_b) / 6; corners stay.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from texelbake.errors import ShapeError

#: refinement levels: one level with limit positions puts every vertex on the limit surface
#: and the faces between within a quarter of LOD1's default error bound of it on the Teapot
#: (0.099 % of the diagonal against 1/256; level 2: 0.025 % for 4x the triangles and no gain in
#: Blender's render, docs/decisions.md)
SUBDIVISION_LEVELS = 1
#: a coarse cage gets further levels (up to MAX_SUBDIVISION_LEVELS) until it has this many
#: quads: one level of a 6-quad cube is a 24-quad polyhedron whose outline missed Blender's
#: render (IoU 0.92); the error of a level falls with the faces' size, 4x per level
MIN_REFINED_QUADS = 4096
MAX_SUBDIVISION_LEVELS = 5
#: a cage refined past this many quads gets one level fewer (a level multiplies by 4)
MAX_REFINED_QUADS = 1_000_000

BOUNDARY_RULES = ("edgeAndCorner", "edgeOnly", "none")


@dataclass(frozen=True, eq=False)
class Refinement:
    """A polygon cage refined to quads.

    counts : (F',) int64 faceVertexCounts (all 4 after one level)
    indices : (C',) int64 faceVertexIndices into the refined points
    face_parent : (F',) int64 the cage polygon each refined face lies in
    vertex_matrix : (n', n) sparse float64: refined points = vertex_matrix @ cage points
    fv_matrix : (C', C) sparse float64: refined face-varying values from the cage's
    levels : refinement levels applied
    cage_faces : polygons of the cage
    """

    counts: np.ndarray
    indices: np.ndarray
    face_parent: np.ndarray
    vertex_matrix: sp.csr_matrix
    fv_matrix: sp.csr_matrix
    levels: int
    cage_faces: int

    @property
    def num_points(self) -> int:
        return int(self.vertex_matrix.shape[0])


def _check(counts: object, indices: object, n_points: int) -> tuple[np.ndarray, np.ndarray]:
    c = np.asarray(counts, dtype=np.int64)
    i = np.asarray(indices, dtype=np.int64)
    if c.ndim != 1 or i.ndim != 1 or int(c.sum()) != i.shape[0]:
        raise ShapeError(f"counts must sum to the number of indices, got {int(c.sum())} and "
                         f"{i.shape[0]}")
    if (c < 3).any():
        raise ShapeError("every polygon needs at least 3 vertices")
    if i.size and (i.min() < 0 or i.max() >= n_points):
        raise ShapeError(f"indices out of [0, {n_points})")
    return c, i


def _corners(counts: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per corner: its face (C,), the next corner and the previous corner of its face, and
    each face's first corner (F,)."""
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
    face = np.repeat(np.arange(counts.shape[0], dtype=np.int64), counts)
    local = np.arange(face.shape[0], dtype=np.int64) - starts[face]
    k = counts[face]
    nxt = starts[face] + (local + 1) % k
    prv = starts[face] + (local - 1) % k
    return face, nxt, prv, starts


def _edges(indices: np.ndarray, nxt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Undirected edges (E, 2) int64 (sorted ends, sorted rows) and each corner's edge to its
    next corner (C,)."""
    a, b = indices, indices[nxt]
    pairs = np.stack([np.minimum(a, b), np.maximum(a, b)], axis=1)
    edges, corner_edge = np.unique(pairs, axis=0, return_inverse=True)
    return edges, corner_edge.reshape(-1)


def _csr(rows: np.ndarray, cols: np.ndarray, vals: np.ndarray, shape: tuple[int, int]):
    return sp.csr_matrix((vals, (rows, cols)), shape=shape)  # duplicates are summed


def _boundary_vertices(n: int, edges: np.ndarray, edge_faces: np.ndarray,
                       vertex_faces: np.ndarray, rule: str):
    """Per vertex: boundary (on exactly two boundary edges), fixed (a corner under
    edgeAndCorner, or on a non-manifold edge / more than two boundary edges)."""
    on_bd = edge_faces == 1
    bd_count = np.bincount(edges[on_bd].ravel(), minlength=n)
    nonmanifold = np.bincount(edges[edge_faces > 2].ravel(), minlength=n) > 0
    fixed = nonmanifold | (bd_count > 2) | (bd_count == 1)
    if rule == "edgeAndCorner":
        fixed |= (bd_count == 2) & (vertex_faces == 1)
    boundary = (bd_count == 2) & ~fixed
    return boundary, fixed, on_bd


def _step(counts: np.ndarray, indices: np.ndarray, n: int, rule: str):
    """One Catmull–Clark level: (counts', indices', face_parent, S (n', n), Sfv (C', C))."""
    nf, nc = counts.shape[0], indices.shape[0]
    face, nxt, prv, starts = _corners(counts)
    edges, ce = _edges(indices, nxt)  # (E, 2), (C,)
    ne = edges.shape[0]
    edge_faces = np.bincount(ce, minlength=ne)  # (E,)
    vertex_faces = np.bincount(indices, minlength=n)  # (n,)
    boundary, fixed, on_bd = _boundary_vertices(n, edges, edge_faces, vertex_faces, rule)

    # face points (F, n): the mean of the face's corners
    fmat = _csr(face, indices, 1.0 / counts[face], (nf, n))
    # edge points (E, n): interior (v0 + v1 + f_a + f_b) / 4, else the midpoint
    interior_e = edge_faces == 2
    w_end = np.where(interior_e, 0.25, 0.5)
    e_ends = _csr(np.repeat(np.arange(ne), 2), edges.ravel(), np.repeat(w_end, 2), (ne, n))
    corner_in = interior_e[ce]
    e_faces = _csr(ce[corner_in], face[corner_in], np.full(int(corner_in.sum()), 0.25),
                   (ne, nf))
    emat = e_ends + e_faces @ fmat
    # vertex points (n, n)
    valence = np.bincount(edges.ravel(), minlength=n).astype(np.float64)  # incident edges
    inner = ~(boundary | fixed)
    safe_val = np.maximum(valence, 1.0)
    # Q / n: the faces' points, each weighted 1 / (faces * n)
    w_q = 1.0 / (np.maximum(vertex_faces, 1) * safe_val)
    q_part = _csr(indices, face, w_q[indices], (n, nf)) @ fmat
    # S_e / n^2 over interior vertices; boundary neighbours 1/8 along boundary edges
    ea, eb = edges[:, 0], edges[:, 1]
    w_a = np.where(inner[ea], 1.0 / safe_val[ea] ** 2, np.where(boundary[ea] & on_bd, 0.125, 0))
    w_b = np.where(inner[eb], 1.0 / safe_val[eb] ** 2, np.where(boundary[eb] & on_bd, 0.125, 0))
    nbr = _csr(np.concatenate([ea, eb]), np.concatenate([eb, ea]),
               np.concatenate([w_a, w_b]), (n, n))
    self_w = np.where(inner, (safe_val - 2.0) / safe_val, np.where(boundary, 0.75, 1.0))
    vmat = nbr + sp.diags(self_w) + sp.diags(inner.astype(np.float64)) @ q_part
    smat = sp.vstack([vmat, fmat, emat]).tocsr()  # points: [vertices, faces, edges]

    # children: one quad per corner (v_c, e_c, f, e_prev)
    new_idx = np.stack([indices, n + nf + ce, np.full(nc, n) + face, n + nf + ce[prv]], axis=1)
    # face-varying: corner value, edge midpoint, face mean, previous edge midpoint
    rows = np.arange(nc, dtype=np.int64) * 4
    own = np.arange(nc, dtype=np.int64)
    half = np.full(nc, 0.5)
    # the face mean: each of the k corners of the face adds 1/k to the child's centre corner
    k_c = counts[face]  # (C,)
    child_of = np.repeat(own, k_c)  # (sum k^2,)
    first = np.concatenate([[0], np.cumsum(k_c)[:-1]])
    mate = starts[face][child_of] + np.arange(child_of.shape[0]) - first[child_of]
    fvmat = _csr(np.concatenate([rows, rows + 1, rows + 1, rows[child_of] + 2, rows + 3,
                                 rows + 3]),
                 np.concatenate([own, own, nxt, mate, prv, own]),
                 np.concatenate([np.ones(nc), half, half, 1.0 / k_c[child_of], half, half]),
                 (4 * nc, nc))
    return (np.full(nc, 4, dtype=np.int64), new_idx.reshape(-1), face, smat, fvmat)


def _limit(counts: np.ndarray, indices: np.ndarray, n: int, rule: str) -> sp.csr_matrix:
    """(n, n) limit positions of an all-quad mesh's vertices."""
    face, nxt, prv, starts = _corners(counts)
    edges, ce = _edges(indices, nxt)
    edge_faces = np.bincount(ce, minlength=edges.shape[0])
    vertex_faces = np.bincount(indices, minlength=n)
    boundary, fixed, on_bd = _boundary_vertices(n, edges, edge_faces, vertex_faces, rule)
    inner = ~(boundary | fixed)
    val = np.maximum(np.bincount(edges.ravel(), minlength=n).astype(np.float64), 1.0)
    denom = val * (val + 5.0)
    ea, eb = edges[:, 0], edges[:, 1]
    w_a = np.where(inner[ea], 4.0 / denom[ea], np.where(boundary[ea] & on_bd, 1.0 / 6.0, 0.0))
    w_b = np.where(inner[eb], 4.0 / denom[eb], np.where(boundary[eb] & on_bd, 1.0 / 6.0, 0.0))
    nbr = _csr(np.concatenate([ea, eb]), np.concatenate([eb, ea]),
               np.concatenate([w_a, w_b]), (n, n))
    diag_v = indices[starts[face] + (np.arange(indices.shape[0]) - starts[face] + 2) % 4]
    w_d = np.where(inner[indices], 1.0 / denom[indices], 0.0)
    dmat = _csr(indices, diag_v, w_d, (n, n))
    self_w = np.where(inner, val * val / denom, np.where(boundary, 4.0 / 6.0, 1.0))
    return (nbr + dmat + sp.diags(self_w)).tocsr()


def catmull_clark(counts: object, indices: object, n_points: int,
                  levels: int = SUBDIVISION_LEVELS, *,
                  boundary: str = "edgeAndCorner", limit: bool = True) -> Refinement:
    """Refine a polygon cage `levels` times (Catmull–Clark), then move the points to their
    limit positions (`limit`).

    counts : (F,) int64 faceVertexCounts (each >= 3); indices : (C,) int64 faceVertexIndices;
    n_points : cage points; boundary : UsdGeom `interpolateBoundary` ("none" is refined as
    "edgeOnly": the faces it would leave unrendered are kept)
    """
    c, i = _check(counts, indices, int(n_points))
    if boundary not in BOUNDARY_RULES:
        raise ShapeError(f"boundary must be one of {BOUNDARY_RULES}, got {boundary!r}")
    if int(levels) < 1:
        raise ShapeError(f"levels must be >= 1, got {levels}")
    rule = "edgeOnly" if boundary == "none" else boundary
    n = int(n_points)
    smat: sp.csr_matrix = sp.identity(n, format="csr")
    fvmat: sp.csr_matrix = sp.identity(i.shape[0], format="csr")
    n_cage = c.shape[0]
    parent = np.arange(n_cage, dtype=np.int64)
    for _ in range(int(levels)):  # a loop over the few levels, each whole-array
        c, i, face, s, fv = _step(c, i, n, rule)
        parent = parent[face]
        smat, fvmat, n = (s @ smat).tocsr(), (fv @ fvmat).tocsr(), s.shape[0]
    if limit:
        smat = (_limit(c, i, n, rule) @ smat).tocsr()
    return Refinement(c, i, parent, smat, fvmat, int(levels), int(n_cage))


def refinement_levels(counts: np.ndarray, levels: int = SUBDIVISION_LEVELS, *,
                      min_quads: int = MIN_REFINED_QUADS, max_quads: int = MAX_REFINED_QUADS,
                      max_levels: int = MAX_SUBDIVISION_LEVELS) -> int:
    """The levels a cage is refined by: `levels`, raised (up to `max_levels`) while the refined
    mesh has fewer than `min_quads` quads, lowered (not below 1) while it exceeds `max_quads`.
    The first level makes one quad per corner, each further one four per quad."""
    corners = int(np.asarray(counts).sum())
    k = int(levels)
    while k < max_levels and corners * 4 ** (k - 1) < min_quads \
            and corners * 4 ** k <= max_quads:
        k += 1
    while k > 1 and corners * 4 ** (k - 1) > max_quads:
        k -= 1
    return k
