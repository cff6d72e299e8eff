"""Tangent frames and direction changes of basis.

A frame is a (n, 3, 3) float64 array whose rows are (t, b, n): `local = frame @ world`,
`world = frame.transpose @ local`. Local +z is the normal.
"""

from __future__ import annotations

import numpy as np

from texelbake.errors import ShapeError


def _unit(v: np.ndarray, eps: float = 1e-300) -> tuple[np.ndarray, np.ndarray]:
    length = np.linalg.norm(v, axis=-1, keepdims=True)
    valid = length[..., 0] > eps
    return np.divide(v, length, out=np.zeros_like(v), where=length > eps), valid


def tangent_frames(normals: np.ndarray, tangents: np.ndarray | None = None) -> np.ndarray:
    """Orthonormal frames with rows (t, b, n).

    normals : (n, 3) float64, need not be unit
    tangents : (n, 3) float64 or None. Projected onto the plane of the normal; where absent or
        parallel to the normal, a deterministic tangent is built (Duff et al. 2017, "Building an
        orthonormal basis, revisited"), so every frame is defined.
    returns : (n, 3, 3) float64
    """
    normals = np.asarray(normals, dtype=np.float64)
    if normals.ndim != 2 or normals.shape[1] != 3:
        raise ShapeError(f"normals must be (n, 3), got {normals.shape}")
    n, n_ok = _unit(normals)
    n[~n_ok] = (0.0, 0.0, 1.0)
    # Duff et al. branchless basis: always defined.
    sign = np.where(n[:, 2] >= 0.0, 1.0, -1.0)
    a = -1.0 / (sign + n[:, 2])
    b = n[:, 0] * n[:, 1] * a
    t_default = np.stack([1.0 + sign * n[:, 0] ** 2 * a, sign * b, -sign * n[:, 0]], axis=1)
    t = t_default
    if tangents is not None:
        tangents = np.asarray(tangents, dtype=np.float64)
        if tangents.shape != normals.shape:
            raise ShapeError(f"tangents must match normals {normals.shape}, got {tangents.shape}")
        proj = tangents - np.sum(tangents * n, axis=1, keepdims=True) * n
        proj, ok = _unit(proj, eps=1e-12)
        t = np.where(ok[:, None], proj, t_default)
    bt = np.cross(n, t)
    return np.stack([t, bt, n], axis=1)


def to_local(frames: np.ndarray, dirs_world: np.ndarray) -> np.ndarray:
    """(n, 3) world directions -> (n, 3) local, one frame per direction (or one frame (3, 3))."""
    frames = np.asarray(frames, dtype=np.float64)
    dirs_world = np.asarray(dirs_world, dtype=np.float64)
    if frames.ndim == 2:
        return dirs_world @ frames.T
    return np.einsum("nij,nj->ni", frames, dirs_world)


def to_world(frames: np.ndarray, dirs_local: np.ndarray) -> np.ndarray:
    """(n, 3) local directions -> (n, 3) world (inverse of `to_local`)."""
    frames = np.asarray(frames, dtype=np.float64)
    dirs_local = np.asarray(dirs_local, dtype=np.float64)
    if frames.ndim == 2:
        return dirs_local @ frames
    return np.einsum("nji,nj->ni", frames, dirs_local)


def grid_to_world(frames: np.ndarray, dirs_local: np.ndarray) -> np.ndarray:
    """(p, D, 3) world directions of one local direction set dirs_local (D, 3) in each of the
    frames (p, 3, 3) (rows: the frame's axes). A broadcast matmul: the einsum it replaced
    ("dk,pkl->pdl") looped without BLAS and was ~25x slower (the profile, docs/profile.md); equal to it
    up to rounding (FMA)."""
    return np.matmul(dirs_local, frames)


def grid_to_local(frames: np.ndarray, w_world: np.ndarray) -> np.ndarray:
    """(A, p, 3) directions w_world (p, A, 3) in each sample's frame (p, 3, 3) (rows: the
    frame's axes). A batched matmul: the einsum it replaced looped without BLAS and was ~5x
    slower (the profile, docs/profile.md); equal to it up to rounding."""
    ft = np.ascontiguousarray(frames.transpose(0, 2, 1))
    return np.ascontiguousarray(np.matmul(w_world, ft).transpose(1, 0, 2))
