"""Cube maps over world directions (OpenGL convention): directions, solid angles, look-up."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from texelbake.errors import SettingsError, ShapeError

# rows: major axis, U (sc), V (tc) per face, OpenGL cube-map convention
FACE_BASIS = np.array(
    [
        [[1, 0, 0], [0, 0, -1], [0, -1, 0]],   # +X
        [[-1, 0, 0], [0, 0, 1], [0, -1, 0]],   # -X
        [[0, 1, 0], [1, 0, 0], [0, 0, 1]],     # +Y
        [[0, -1, 0], [1, 0, 0], [0, 0, -1]],   # -Y
        [[0, 0, 1], [1, 0, 0], [0, -1, 0]],    # +Z
        [[0, 0, -1], [-1, 0, 0], [0, -1, 0]],  # -Z
    ],
    dtype=np.float64,
)

OccludedFn = Callable[[np.ndarray, np.ndarray], np.ndarray]


# --------------------------------------------------------------------------------------------
# cube map directions


def check_res(res: int) -> int:
    res_i = int(res)
    if res_i != res or res_i < 1:
        raise SettingsError(f"res (cube face side) must be a positive integer, got {res!r}")
    return res_i


def cube_directions(res: int) -> np.ndarray:
    """Unit directions through the centres of the cube-map texels.

    res : texels per face side
    returns : (6, res, res, 3) float64, indexed [face, iv, iu]
    """
    res = check_res(res)
    c = (2.0 * (np.arange(res) + 0.5) / res) - 1.0  # (res,)
    tc, sc = np.meshgrid(c, c, indexing="ij")  # (res, res): rows iv, cols iu
    d = (FACE_BASIS[:, None, None, 0, :] + sc[None, :, :, None] * FACE_BASIS[:, None, None, 1, :]
         + tc[None, :, :, None] * FACE_BASIS[:, None, None, 2, :])  # (6, res, res, 3)
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def cube_solid_angles(res: int) -> np.ndarray:
    """Exact solid angle of every cube-map texel (they sum to 4 pi).

    The solid angle of [0, x] x [0, y] on the face plane at distance 1 is
    atan2(x y, sqrt(x^2 + y^2 + 1)); a texel is the signed combination of its four corners.
    returns : (6, res, res) float64
    """
    res = check_res(res)
    e = np.linspace(-1.0, 1.0, res + 1)
    y, x = np.meshgrid(e, e, indexing="ij")
    area = np.arctan2(x * y, np.sqrt(x * x + y * y + 1.0))  # (res+1, res+1)
    omega = area[1:, 1:] - area[1:, :-1] - area[:-1, 1:] + area[:-1, :-1]
    return np.broadcast_to(np.abs(omega), (6, res, res)).copy()


def dirs_to_cube(dirs: np.ndarray, res: int) -> tuple[np.ndarray, ...]:
    """Cube-map texel of each direction.

    dirs : (n, 3) float, need not be unit; a zero or non-finite direction maps to the centre of
        face 0 (callers flag such directions invalid themselves)
    res : texels per face side
    returns : (face (n,) int64, iu (n,) int64, iv (n,) int64, fu (n,) float64, fv (n,) float64):
        the nearest texel, and continuous coordinates in texel units with texel centres at
        integers (fu = iu exactly at a centre), for bilinear look-ups
    """
    res = check_res(res)
    d = np.asarray(dirs, dtype=np.float64)
    if d.ndim != 2 or d.shape[1] != 3:
        raise ShapeError(f"dirs must be (n, 3), got {d.shape}")
    d = np.where(np.isfinite(d).all(axis=1, keepdims=True), d, 0.0)
    a = np.abs(d)
    axis = np.argmax(a, axis=1)  # ties -> lowest axis, deterministic
    rows = np.arange(d.shape[0])
    major = a[rows, axis]
    neg = d[rows, axis] < 0
    face = (2 * axis + neg).astype(np.int64)
    basis = FACE_BASIS[face]  # (n, 3, 3)
    ok = major > 0
    sc = np.divide(np.einsum("ni,ni->n", d, basis[:, 1]), major, out=np.zeros_like(major),
                   where=ok)
    tc = np.divide(np.einsum("ni,ni->n", d, basis[:, 2]), major, out=np.zeros_like(major),
                   where=ok)
    fu = (sc + 1.0) * 0.5 * res - 0.5
    fv = (tc + 1.0) * 0.5 * res - 0.5
    iu = np.clip(np.floor(fu + 0.5), 0, res - 1).astype(np.int64)
    iv = np.clip(np.floor(fv + 0.5), 0, res - 1).astype(np.int64)
    return face, iu, iv, fu, fv
