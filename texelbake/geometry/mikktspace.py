"""Tangent frames the way MikkTSpace computes them (Mikkelsen 2008, the tangent space of
Blender, glTF and most bakers), so a normal map baked here decodes in another tool as it was
baked.

Per triangle (MikkTSpace's `InitTriInfo`): with d1 = p1 − p0, d2 = p2 − p0 and the uv edges
t21 = uv1 − uv0, t31 = uv2 − uv0, the signed uv area a = t21 × t31, the triangle is
orientation preserving when a > 0, and its tangent is vOs = t31.y d1 − t21.y d2, unit and
times sign(a) (zero when a or vOs is). Per corner (`EvalTspace`): vOs projected on the plane of
the corner's normal n and made unit, weighted by the corner's angle measured in that plane.
Corners are grouped as MikkTSpace welds and groups them: the same position, normal and uv
(one welded vertex) and the same orientation; each group's tangent is the unit sum of its
corners' weighted tangents, and every corner of the group takes it. Blender's default
angular threshold (180°) merges all of a group's sub-groups, as here. Not modelled: a welded
vertex whose corners form two fans that share no edge (a pinch) is one group here, two in
MikkTSpace; triangles of zero area (MikkTSpace's degenerate prologue) keep their own
zero-weight corners.

A point inside a triangle gets the frame a renderer's normal-map node builds there (Cycles'
`svm_node_normal_map`, Blender's bake `RE_bake_normal_world_to_tangent`): the tangent T and
normal N interpolated barycentrically and not renormalised, B = sign · N × T; a tangent-space
normal (x, y, z) decodes to normalize(x T + y B + z N), and a world normal encodes to
normalize([T B N]⁻¹ n), its exact inverse.
"""

from __future__ import annotations

import numpy as np

from texelbake.errors import ShapeError
from texelbake.geometry.basis import tangent_frames

#: MikkTSpace's `NotZero` (lengths and areas at or below it count as zero)
_NOT_ZERO = 1e-30


def _unit(x: np.ndarray) -> np.ndarray:
    """Rows made unit where their length is not zero (MikkTSpace's `NotZero` guard)."""
    n = np.linalg.norm(x, axis=-1, keepdims=True)
    return np.where(n > _NOT_ZERO, x / np.where(n > _NOT_ZERO, n, 1.0), x)


def mikk_tangents(vertices: np.ndarray, faces: np.ndarray, corner_normals: np.ndarray,
                  corner_uvs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-corner MikkTSpace tangents (module docstring).

    vertices : (n, 3); faces : (f, 3) int; corner_normals : (f, 3, 3); corner_uvs : (f, 3, 2)
    returns : tangent (f, 3, 3) unit (a corner whose group sums to zero gets a deterministic
        tangent of its normal's plane), sign (f,) ±1 the bitangent sign of each triangle"""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    cn = np.asarray(corner_normals, dtype=np.float64)
    uv = np.asarray(corner_uvs, dtype=np.float64)
    nf = f.shape[0]
    if f.ndim != 2 or f.shape[1] != 3 or cn.shape != (nf, 3, 3) or uv.shape != (nf, 3, 2):
        raise ShapeError(f"mikk_tangents: faces {f.shape}, corner_normals {cn.shape}, "
                         f"corner_uvs {uv.shape} do not agree on ({nf}, 3)")
    p = v[f]  # (f, 3, 3)
    d1, d2 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    t21, t31 = uv[:, 1] - uv[:, 0], uv[:, 2] - uv[:, 0]
    area = t21[:, 0] * t31[:, 1] - t21[:, 1] * t31[:, 0]
    orient = area > 0.0
    sign = np.where(orient, 1.0, -1.0)
    vos = t31[:, 1:2] * d1 - t21[:, 1:2] * d2
    len_os = np.linalg.norm(vos, axis=1, keepdims=True)
    live = (np.abs(area) > _NOT_ZERO)[:, None] & (len_os > _NOT_ZERO)
    vos = np.where(live, sign[:, None] * vos / np.where(live, len_os, 1.0), vos)
    n = _unit(cn)  # (f, 3, 3) per corner
    t = vos[:, None, :] - np.einsum("fcj,fj->fc", n, vos)[..., None] * n
    t = _unit(t)
    # the corner's angle in the plane of its normal
    e1 = p[:, [2, 0, 1]] - p  # previous corner minus this one
    e2 = p[:, [1, 2, 0]] - p  # next corner minus this one
    e1 = _unit(e1 - np.einsum("fcj,fcj->fc", n, e1)[..., None] * n)
    e2 = _unit(e2 - np.einsum("fcj,fcj->fc", n, e2)[..., None] * n)
    angle = np.arccos(np.clip(np.einsum("fcj,fcj->fc", e1, e2), -1.0, 1.0))
    # groups: one welded vertex (position, normal, uv: exact values) and one orientation
    # welded on float32 values, as the host (Blender, a USD file) holds them
    key = np.concatenate([p, cn, uv, np.broadcast_to(sign[:, None, None], (nf, 3, 1))],
                         axis=2).reshape(nf * 3, -1).astype(np.float32) + np.float32(0.0)
    _, group = np.unique(np.ascontiguousarray(key).view(
        np.dtype((np.void, key.dtype.itemsize * key.shape[1]))).ravel(), return_inverse=True)
    acc = np.zeros((int(group.max(initial=-1)) + 1, 3))
    np.add.at(acc, group, (angle[..., None] * t).reshape(-1, 3))
    out = acc[group]
    length = np.linalg.norm(out, axis=1)
    ok = length > _NOT_ZERO
    out = np.where(ok[:, None], out / np.where(ok, length, 1.0)[:, None], 0.0)
    if not ok.all():  # a group with no usable tangent: any in its normal's plane
        bad = np.flatnonzero(~ok)
        out[bad] = tangent_frames(n.reshape(-1, 3)[bad])[:, 0]
    return out.reshape(nf, 3, 3), sign


def frames_at(tangent: np.ndarray, sign: np.ndarray, corner_normals: np.ndarray,
              face: np.ndarray, bary: np.ndarray) -> np.ndarray:
    """The normal-map frame at points of triangles `face` (m,) with barycentrics bary (m, 3):
    (m, 3, 3) columns T, B, N (interpolated, not renormalised; B = sign · N × T)."""
    tn = np.einsum("mk,mkj->mj", bary, tangent[face])
    nn = np.einsum("mk,mkj->mj", bary, np.asarray(corner_normals, np.float64)[face])
    b = sign[face][:, None] * np.cross(nn, tn)
    return np.stack([tn, b, nn], axis=2)


def encode(frames: np.ndarray, world: np.ndarray) -> np.ndarray:
    """Unit tangent-space normals (m, 3) of world normals (m, 3) in `frames_at`'s frames:
    the exact inverse of `decode` (a degenerate frame gives (0, 0, 1))."""
    det = np.linalg.det(frames)
    ok = np.abs(det) > _NOT_ZERO
    safe = np.where(ok[:, None, None], frames, np.eye(3))
    x = np.linalg.solve(safe, np.asarray(world, np.float64)[..., None])[..., 0]
    x = np.where(ok[:, None], x, [0.0, 0.0, 1.0])
    return x / np.maximum(np.linalg.norm(x, axis=1, keepdims=True), 1e-300)


def decode(frames: np.ndarray, local: np.ndarray) -> np.ndarray:
    """World unit normals normalize(x T + y B + z N) (m, 3) of tangent-space normals (m, 3)."""
    w = np.einsum("mij,mj->mi", frames, np.asarray(local, np.float64))
    return w / np.maximum(np.linalg.norm(w, axis=1, keepdims=True), 1e-300)
