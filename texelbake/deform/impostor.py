"""The local impostor parameterization of seed 002 §4.2 (Table 1), per vertex of a LOD mesh:
p0 (rest position), r0 (the rest tangent frame R0 = (u0, v0, n0) as a Rodrigues vector,
Eq. 5) and the rest tangent vectors u0, v0 (which Ψ carries to u, v: Eq. 6).

Choice of (u0, v0). n0 is the vertex's area-weighted normal. The tangent u0 is one of the
four quarter turns {t, b, −t, −b} of the atlas frame of the vertex's largest incident
triangle (t = dP/du of the atlas, as the CPM texel frames take it: `geometry.texels.
texel_frames`), so the anisotropy axes of the baked texel frames stay the axes of (u0, v0).
Of the four, the one whose R0 has the smallest rotation angle is kept.

Rodrigues near 180°. A rotation whose third column is n0 = −z is a 180° rotation whatever
(u0, v0) are, so no choice of u0 alone keeps every R0 away from the singularity of Eq. 5.
Where n0 points into the lower hemisphere (n0·z < 0), r0 stores instead the rotation
(u0, −v0, −n0) (also proper: two columns negated), whose third column points up. The stored
u0, v0 tell the two apart: `decode_frames` negates the last two columns of R(r0) when its
third column disagrees with u0 × v0. With the quarter-turn choice every stored rotation has an
angle of at most ~100° (`MAX_ANGLE_DEG`, tested on normals over the whole sphere), so
|r0| = tan(θ/2) ≤ 1.2 and float32 storage keeps ~1e-7 of the frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from texelbake.errors import ShapeError
from texelbake.geometry.basis import tangent_frames

#: |w| of the unit quaternion at or below this: the rotation is taken as 180° and has no
#: Rodrigues vector (|r| = |x| / |w| would exceed 1e8; 1 + tan² overflows nothing, but a
#: float32 primvar keeps none of the frame's 7 digits there)
RODRIGUES_MIN_W = 1e-8
#: bound on the rotation angle of every stored R0 (degrees; module docstring)
MAX_ANGLE_DEG = 120.0


@dataclass
class ImpostorParams:
    """Per vertex (all float64): p0 (n, 3) rest position, r0 (n, 3) Rodrigues vector of the
    stored rotation, u0, v0 (n, 3) unit rest tangents (R0 = (u0, v0, u0 × v0))."""

    p0: np.ndarray
    r0: np.ndarray
    u0: np.ndarray
    v0: np.ndarray

    def as_arrays(self) -> dict[str, np.ndarray]:
        return {"p0": self.p0, "r0": self.r0, "u0": self.u0, "v0": self.v0}


def _skew(r: np.ndarray) -> np.ndarray:
    z = np.zeros(r.shape[0])
    return np.stack([np.stack([z, -r[:, 2], r[:, 1]], 1), np.stack([r[:, 2], z, -r[:, 0]], 1),
                     np.stack([-r[:, 1], r[:, 0], z], 1)], axis=1)


def rodrigues_to_matrix(r: np.ndarray) -> np.ndarray:
    """R from r = k tan(θ/2) (Eq. 5): R = I + 2/(1 + r·r) ([r]× + [r]×²), exact for every
    finite r. r : (n, 3) float64 → (n, 3, 3) float64"""
    r = np.asarray(r, dtype=np.float64)
    if r.ndim != 2 or r.shape[1] != 3:
        raise ShapeError(f"r must be (n, 3), got {r.shape}")
    k = _skew(r)
    c = 2.0 / (1.0 + np.einsum("ij,ij->i", r, r))
    return np.eye(3)[None] + c[:, None, None] * (k + k @ k)


def matrix_to_rodrigues(rot: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """r = k tan(θ/2) of rotations (n, 3, 3) through the unit quaternion (w, x) (Shepperd's
    branch on the largest of 4w², 4x², ...): r = x / w.

    returns (r (n, 3) float64, valid (n,) bool — False within ~1e-8 rad of 180°
    (|w| ≤ RODRIGUES_MIN_W), where r is set to 0 and the caller must choose another R)"""
    m = np.asarray(rot, dtype=np.float64)
    if m.ndim != 3 or m.shape[1:] != (3, 3):
        raise ShapeError(f"rot must be (n, 3, 3), got {m.shape}")
    tr = np.trace(m, axis1=1, axis2=2)
    diag = np.diagonal(m, axis1=1, axis2=2)
    # the largest of 4w² = 1 + tr, 4x_i² = 1 + 2 m_ii − tr picks the stable branch
    which = np.argmax(np.column_stack([tr, 2 * diag - tr[:, None]]), axis=1)
    q = np.zeros((m.shape[0], 4))
    s = np.arange(m.shape[0])
    for k in range(4):  # four branches of Shepperd's method, each vectorized
        sel = s[which == k]
        if sel.size == 0:
            continue
        a = m[sel]
        if k == 0:
            w = 0.5 * np.sqrt(np.maximum(1.0 + tr[sel], 0.0))
            f = 0.25 / w
            q[sel] = np.column_stack([w, (a[:, 2, 1] - a[:, 1, 2]) * f,
                                      (a[:, 0, 2] - a[:, 2, 0]) * f,
                                      (a[:, 1, 0] - a[:, 0, 1]) * f])
        else:
            i = k - 1
            j, m_ = (i + 1) % 3, (i + 2) % 3
            x = 0.5 * np.sqrt(np.maximum(1.0 + a[:, i, i] - a[:, j, j] - a[:, m_, m_], 0.0))
            f = 0.25 / x
            qq = np.zeros((sel.size, 4))
            qq[:, 0] = (a[:, m_, j] - a[:, j, m_]) * f
            qq[:, 1 + i] = x
            qq[:, 1 + j] = (a[:, j, i] + a[:, i, j]) * f
            qq[:, 1 + m_] = (a[:, m_, i] + a[:, i, m_]) * f
            q[sel] = qq
    valid = np.abs(q[:, 0]) > RODRIGUES_MIN_W
    r = np.divide(q[:, 1:], q[:, :1], out=np.zeros((m.shape[0], 3)), where=valid[:, None])
    return r, valid


def rotation_angle(rot: np.ndarray) -> np.ndarray:
    """Rotation angle θ ∈ [0, π] of (n, 3, 3) rotations (radians)."""
    tr = np.trace(np.asarray(rot, dtype=np.float64), axis1=1, axis2=2)
    return np.arccos(np.clip(0.5 * (tr - 1.0), -1.0, 1.0))


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals (n, 3) (zero where no incident area)."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    t = v[f]
    fn = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])  # (f, 3), length = 2 area
    acc = np.zeros_like(v)
    for k in range(3):
        np.add.at(acc, f[:, k], fn)
    ln = np.linalg.norm(acc, axis=1, keepdims=True)
    return np.divide(acc, ln, out=np.zeros_like(acc), where=ln > 0)


def _atlas_tangents(v: np.ndarray, f: np.ndarray, cuv: np.ndarray) -> np.ndarray:
    """dP/du of each triangle (f, 3) (zero where the uvs are degenerate)."""
    t = v[f]
    e1, e2 = t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]
    d1, d2 = cuv[:, 1] - cuv[:, 0], cuv[:, 2] - cuv[:, 0]
    det = d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0]
    dpdu = e1 * d2[:, 1:2] - e2 * d1[:, 1:2]
    return np.divide(dpdu, det[:, None], out=np.zeros_like(dpdu), where=det[:, None] != 0)


def impostor_params(vertices: np.ndarray, faces: np.ndarray,
                    corner_uvs: np.ndarray | None = None) -> ImpostorParams:
    """The Table 1 parameterization of every vertex of a mesh (module docstring).

    vertices (n, 3) float64, faces (f, 3) int64, corner_uvs (f, 3, 2) atlas uvs (None: the
    tangent of `frames.tangent_frames`)"""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3:
        raise ShapeError(f"vertices (n, 3) and faces (f, 3) expected, got {v.shape}, {f.shape}")
    n = v.shape[0]
    nrm = vertex_normals(v, f)
    tangent = np.zeros_like(v)
    if corner_uvs is not None and len(f):
        cuv = np.asarray(corner_uvs, dtype=np.float64)
        if cuv.shape != (len(f), 3, 2):
            raise ShapeError(f"corner_uvs must be ({len(f)}, 3, 2), got {cuv.shape}")
        tan_f = _atlas_tangents(v, f, cuv)
        t = v[f]
        area = np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1)
        area = np.where(np.linalg.norm(tan_f, axis=1) > 0, area, -1.0)
        # largest incident triangle per vertex: sort corners by (vertex, area)
        vert = f.reshape(-1)
        ar = np.repeat(area, 3)
        order = np.lexsort((ar, vert))
        last = np.flatnonzero(np.r_[vert[order][1:] != vert[order][:-1], True])
        best = order[last]
        ok = ar[best] > 0
        tangent[vert[best[ok]]] = tan_f[best[ok] // 3]
    base = tangent_frames(np.where(np.linalg.norm(nrm, axis=1)[:, None] > 0, nrm, [0, 0, 1.0]),
                          tangent)  # rows (t, b, n)
    t0, b0 = base[:, 0], base[:, 1]
    best_r = np.zeros((n, 3))
    best_ang = np.full(n, np.inf)
    u_out, v_out = t0.copy(), b0.copy()
    for uu, vv in ((t0, b0), (b0, -t0), (-t0, -b0), (-b0, t0)):  # the four quarter turns
        nn = np.cross(uu, vv)
        flip = nn[:, 2] < 0.0
        s = np.where(flip, -1.0, 1.0)[:, None]
        stored = np.stack([uu, s * vv, s * nn], axis=2)  # columns
        ang = rotation_angle(stored)
        r, ok = matrix_to_rodrigues(stored)
        better = ok & (ang < best_ang)
        best_r[better], best_ang[better] = r[better], ang[better]
        u_out[better], v_out[better] = uu[better], vv[better]
    return ImpostorParams(v.copy(), best_r, u_out, v_out)


def decode_frames(r0: np.ndarray, u0: np.ndarray, v0: np.ndarray) -> np.ndarray:
    """R0 = (u0, v0, n0) as (n, 3, 3) columns from the stored r0, resolving the lower-
    hemisphere flip with u0 × v0 (module docstring)."""
    rot = rodrigues_to_matrix(r0)
    nn = np.cross(np.asarray(u0, np.float64), np.asarray(v0, np.float64))
    flip = np.einsum("ij,ij->i", rot[:, :, 2], nn) < 0.0
    rot[flip, :, 1:] *= -1.0
    return rot
