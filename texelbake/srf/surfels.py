"""The impostor of a surface reflectance field as surfels (seed 002 §5.1, Table 1): points of
the impostor mesh — the baked enclosing LOD mesh M_i, or any mesh enclosing the object —
each carrying its rest position p0, the rest tangent frame R0 as a Rodrigues vector r0
(Eq. 5) and a tangential system (u0, v0) spanning an elliptical footprint (Fig. 9), all
from `texelbake.deform.impostor` (one parameterization for meshes and surfels).

Sampling: the mesh is split 1 → 4 (edge midpoints) until no edge is longer than `spacing`;
the vertices are the surfels. Footprint: a point of a triangle is no farther from any of its
corners than the triangle's longest edge at that corner, and its offset along a unit
tangent t is bounded by the incident edges' |e·t| (convexity). So either the disc of radius
max |e| or the ellipse with semi-axes √2 max |e·u0|, √2 max |e·v0| covers every incident
triangle (as seen in the tangent plane); each surfel keeps whichever has the smaller area
(the ellipse on anisotropic meshes). The footprint vectors are u = s_u u0, v = s_v v0.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from texelbake.deform.impostor import impostor_params, vertex_normals
from texelbake.errors import SettingsError, ShapeError

#: impostor meshes are split until their edges are at most this fraction of the bounding-box
#: diagonal (about a capture pixel at 48² of an object filling the frame)
DEFAULT_SPACING = 1.0 / 40.0
#: at most this many 1 → 4 splits (16 k triangles per input triangle)
MAX_SPLITS = 7


@dataclass
class Surfels:
    """Rest surfels (all float64): p0 (n, 3), r0 (n, 3) Rodrigues, u0, v0 (n, 3) unit rest
    tangents (R0 = (u0, v0, u0 × v0)), su, sv (n,) footprint semi-axes along u0, v0, and the
    impostor mesh (vertices (v, 3), faces (f, 3)) they sample (for visibility)."""

    p0: np.ndarray
    r0: np.ndarray
    u0: np.ndarray
    v0: np.ndarray
    su: np.ndarray
    sv: np.ndarray
    mesh_vertices: np.ndarray
    mesh_faces: np.ndarray

    def __len__(self) -> int:
        return int(self.p0.shape[0])

    @property
    def u(self) -> np.ndarray:
        """(n, 3) footprint vector s_u u0 (Table 1's (u, v) at rest)."""
        return self.su[:, None] * self.u0

    @property
    def v(self) -> np.ndarray:
        return self.sv[:, None] * self.v0

    @property
    def normal(self) -> np.ndarray:
        return np.cross(self.u0, self.v0)


def _edges(faces: np.ndarray) -> np.ndarray:
    return np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]),
                   axis=1)


def split(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One 1 → 4 midpoint split of every triangle (shared edges share their midpoint)."""
    uniq, inv = np.unique(_edges(faces), axis=0, return_inverse=True)
    mid = vertices[uniq].mean(axis=1)
    m = inv.reshape(3, -1) + len(vertices)  # midpoints of edges 01, 12, 20
    a, b, c = faces.T
    f = np.concatenate([np.stack([a, m[0], m[2]], 1), np.stack([b, m[1], m[0]], 1),
                        np.stack([c, m[2], m[1]], 1), np.stack([m[0], m[1], m[2]], 1)])
    return np.concatenate([vertices, mid]), f


def surfels_from_mesh(vertices: object, faces: object, spacing: float | None = None
                      ) -> Surfels:
    """Surfels of an impostor mesh (module docstring).

    vertices (v, 3) float64, faces (f, 3) int64; spacing : absolute maximum edge length
    (default DEFAULT_SPACING of the bounding-box diagonal)"""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
        raise ShapeError(f"impostor mesh: vertices (v, 3) and faces (f >= 1, 3) expected, got "
                         f"{v.shape}, {f.shape}")
    if not np.isfinite(v).all():
        raise ShapeError("impostor mesh: vertices contain NaN or Inf")
    if f.min() < 0 or f.max() >= len(v):
        raise ShapeError(f"impostor mesh: face indices outside [0, {len(v)})")
    used = np.unique(f)  # drop vertices no face uses
    remap = np.full(len(v), -1, np.int64)
    remap[used] = np.arange(used.size)
    v, f = v[used], remap[f]
    diag = float(np.linalg.norm(v.max(axis=0) - v.min(axis=0)))
    h = DEFAULT_SPACING * diag if spacing is None else float(spacing)
    if not h > 0:
        raise SettingsError(f"field 'spacing': must be > 0, got {spacing}")
    for _ in range(MAX_SPLITS):  # a loop over refinement levels
        e = _edges(f)
        if np.linalg.norm(v[e[:, 0]] - v[e[:, 1]], axis=1).max() <= h:
            break
        v, f = split(v, f)
    prm = impostor_params(v, f)
    # footprint: per vertex, the incident edges' longest length and tangential extents
    e = np.unique(_edges(f), axis=0)
    vec = v[e[:, 1]] - v[e[:, 0]]
    ends = np.concatenate([e[:, 0], e[:, 1]])
    vv = np.concatenate([vec, vec])
    r = np.zeros(len(v))
    eu, ev = np.zeros(len(v)), np.zeros(len(v))
    np.maximum.at(r, ends, np.linalg.norm(vv, axis=1))
    np.maximum.at(eu, ends, np.abs(np.einsum("ij,ij->i", vv, prm.u0[ends])))
    np.maximum.at(ev, ends, np.abs(np.einsum("ij,ij->i", vv, prm.v0[ends])))
    su, sv = np.sqrt(2.0) * eu, np.sqrt(2.0) * ev
    disc = (r * r <= 2.0 * su * sv) | (su <= 0) | (sv <= 0)  # area π r² vs π su sv
    su, sv = np.where(disc, r, su), np.where(disc, r, sv)
    return Surfels(prm.p0, prm.r0, prm.u0, prm.v0, su, sv, v, f)


def surfels_from_baked(scene: object, lod: int = 1, spacing: float | None = None) -> Surfels:
    """Surfels of the baked enclosing LOD mesh M_lod (1 = M1, the finest) of a
    `render.scene.RenderScene`."""
    meshes = scene.baked.meshes  # type: ignore[attr-defined]
    if not 1 <= int(lod) <= len(meshes):
        raise SettingsError(f"field 'lod': the bake has M1..M{len(meshes)}, got {lod}")
    m = meshes[int(lod) - 1]
    return surfels_from_mesh(m.vertices, m.faces, spacing)


def mesh_normals(s: Surfels) -> np.ndarray:
    """Area-weighted vertex normals of the impostor mesh (v, 3) (visibility offsets)."""
    return vertex_normals(s.mesh_vertices, s.mesh_faces)
