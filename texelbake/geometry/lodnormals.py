"""Shading normals for a LOD's face corners (what a DCC shades a LOD with): the LOD's own
smooth surface at its scale, split at creases, with M_org's flat facets kept sharp; M_org's
finer detail belongs to the fallback's normal map (`texelbake.stages.filtered`)."""

from __future__ import annotations

import math

import numpy as np

from texelbake.errors import SettingsError
from texelbake.geometry.mesh import face_normals
from texelbake.geometry.raycast import RayCaster

#: a LOD edge whose faces' normals are more than this apart is a crease of the LOD's smooth
#: normals (`smooth_corner_normals`): the corners on either side do not share a normal
CREASE_DEG = 60.0
#: corner pairs held at once while the corners of each vertex are averaged (memory bound)
PAIR_CHUNK = 4_000_000
#: a LOD corner looks M_org's normal up this far into its own face (fraction of the way to
#: the face's centroid): the side of a sharp edge the face is on, not the edge itself
CORNER_INSET = 0.1
#: M_org's normal at a corner within FACET_DEG[0] of the LOD face's normal (and nearer it than
#: the LOD's smooth normal there): M_org is that facet there (flat-shaded, as the LOD), and
#: the corner keeps the face's normal; beyond FACET_DEG[1] the corner takes the LOD's smooth
#: normal; between, a blend
FACET_DEG = (2.0, 5.0)


def lod_corner_normals(vertices: np.ndarray, faces: np.ndarray,
                       org_faces_normals: np.ndarray, caster: RayCaster, *,
                       crease_deg: float = CREASE_DEG) -> np.ndarray:
    """Shading normals for a LOD's face corners (what a DCC shades a LOD with): the LOD's own
    surface at its scale, M_org's detail left to the normal map. A corner where M_org is
    flat-shaded like the LOD face (M_org's normal there, `org_corner_normals`, within
    FACET_DEG of the face's) keeps the face's normal: sharp facets stay sharp (the
    cylinder's ridges, the bolt's bumps on its LOD1) whatever their angle. Elsewhere the
    corner takes the LOD's smooth normal (`smooth_corner_normals`, split at `crease_deg`):
    smooth surfaces stay smooth (the Teapot), and M_org's bumps, which the LOD does not
    have, do not tilt it (a viewer would interpolate them across the face, where the
    texel-rate normal map cannot undo them between texel centres).

    vertices (n, 3), faces (f, 3); org_faces_normals : (F, 3, 3) M_org's unit corner normals
    (`AssetModel.corner_normals`); caster : closest points on M_org;
    returns (f, 3, 3) float64 unit normals
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    if not len(f):
        return np.zeros((0, 3, 3))
    smooth = smooth_corner_normals(v, f, crease_deg=crease_deg).reshape(-1, 3)
    org = org_corner_normals(v, f, org_faces_normals, caster).reshape(-1, 3)
    face = np.repeat(face_normals(v, f), 3, axis=0)
    lo, hi = (math.cos(math.radians(d)) for d in FACET_DEG)
    cos_face = np.einsum("md,md->m", org, face)
    w = np.clip((cos_face - hi) / (lo - hi), 0.0, 1.0)  # (3f,)
    w[cos_face < np.einsum("md,md->m", org, smooth)] = 0.0  # M_org nearer the smooth normal
    w = w[:, None]
    n = w * face + (1.0 - w) * smooth
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    n = np.divide(n, norm, out=smooth.copy(), where=norm > 0.5)
    return n.reshape(-1, 3, 3)


def org_corner_normals(vertices: np.ndarray, faces: np.ndarray,
                       org_faces_normals: np.ndarray, caster: RayCaster) -> np.ndarray:
    """M_org's shading normals at a LOD's face corners: each corner, moved CORNER_INSET of the
    way towards its face's centroid (the side of a sharp edge the face is on), takes M_org's
    interpolated corner normal at the closest point (`caster` over M_org). A normal facing
    away from the LOD face (a thin part's other side) or not finite takes the LOD face's
    normal.

    vertices (n, 3), faces (f, 3); org_faces_normals : (F, 3, 3) M_org's unit corner normals
    (`AssetModel.corner_normals`); returns (f, 3, 3) float64 unit normals
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    if not len(f):
        return np.zeros((0, 3, 3))
    tri = v[f]  # (f, 3, 3)
    fn = face_normals(v, f)
    q = tri + CORNER_INSET * (tri.mean(axis=1, keepdims=True) - tri)
    _, prim, b2 = caster.closest_points(q.reshape(-1, 3))
    bary = np.column_stack([1.0 - b2[:, 0] - b2[:, 1], b2])
    n = np.einsum("mk,mkd->md", bary, np.asarray(org_faces_normals, dtype=np.float64)[prim])
    n = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    face = np.repeat(fn, 3, axis=0)
    bad = ~np.isfinite(n).all(axis=1) | (np.einsum("md,md->m", n, face) <= 0.0)
    n[bad] = face[bad]
    return n.reshape(-1, 3, 3)


def smooth_corner_normals(vertices: np.ndarray, faces: np.ndarray, *,
                          crease_deg: float = CREASE_DEG) -> np.ndarray:
    """The smooth normals of a mesh's face corners, split at its creases: a corner's normal
    is the corner-angle weighted mean of the normals of the faces around its vertex
    (vertices at one position are one) that lie within `crease_deg` of the corner's own
    face's normal.

    vertices (n, 3), faces (f, 3); returns (f, 3, 3) float64 unit normals, each within
    `crease_deg` of its face's normal (a degenerate face's corners: the mean of its
    neighbours', or +z when it has none)
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    if not len(f):
        return np.zeros((0, 3, 3))
    if not 0.0 < float(crease_deg) < 180.0:
        raise SettingsError(f"crease_deg must be in (0, 180), got {crease_deg}")
    tri = v[f]  # (f, 3, 3)
    fn = face_normals(v, f)
    degenerate = np.all(fn == 0.0, axis=1)  # (f,) zero rows of `face_normals`
    to_next, to_prev = np.roll(tri, -1, axis=1) - tri, np.roll(tri, 1, axis=1) - tri
    angle = np.arctan2(np.linalg.norm(np.cross(to_next, to_prev), axis=2),
                       np.einsum("fkd,fkd->fk", to_next, to_prev)).ravel()  # (3f,)
    _, weld_id = np.unique(v, axis=0, return_inverse=True)
    corner_vertex = weld_id.reshape(-1)[f].ravel()  # (3f,)
    corner_face = np.repeat(np.arange(len(f)), 3)
    # the corners of each vertex, contiguous: every ordered pair within a group
    order = np.argsort(corner_vertex, kind="stable")
    count = np.bincount(corner_vertex)  # corners per vertex
    size = count[corner_vertex[order]]  # (3f,) the group's size at each sorted position
    first = (np.cumsum(count) - count)[corner_vertex[order]]  # (3f,) the group's start
    cos_crease = math.cos(math.radians(float(crease_deg)))
    acc = np.zeros((3 * len(f), 3))
    start = 0
    while start < len(order):  # chunks of corners whose pairs fit in PAIR_CHUNK
        cum = np.cumsum(size[start:])
        stop = start + max(1, int(np.searchsorted(cum, PAIR_CHUNK, side="right")))
        rep = size[start:stop]
        i = np.repeat(np.arange(start, stop), rep)  # (p,) sorted positions
        j = first[i] + (np.arange(len(i)) - np.repeat(np.cumsum(rep) - rep, rep))
        ci, cj = order[i], order[j]  # corners
        fi, fj = corner_face[ci], corner_face[cj]
        keep = (np.einsum("pd,pd->p", fn[fi], fn[fj]) >= cos_crease) | degenerate[fi]
        w = angle[cj[keep]][:, None] * fn[fj[keep]]  # (p', 3)
        for d in range(3):
            acc[:, d] += np.bincount(ci[keep], weights=w[:, d], minlength=3 * len(f))
        start = stop
    norm = np.linalg.norm(acc, axis=1, keepdims=True)
    face = np.repeat(fn, 3, axis=0)
    out = np.divide(acc, norm, out=face.copy(), where=norm > 0)
    bad = ~(np.linalg.norm(out, axis=1) > 0.5)
    out[bad] = [0.0, 0.0, 1.0]
    return out.reshape(-1, 3, 3)
