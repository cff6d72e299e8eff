"""Shading operations (seed 002 §5.3, Table 2): every reflectance-field look-up of a frame as
one record — REF(S) the shading point it adds to, (i_c, i_l) the reflectance image,
(x_c, y_c) the look-up position on the camera's image plane, (ω_r, ω_g, ω_b) the colour
weights — held as arrays (one row per operation), and the orders they can run in.

Operations are generated point-major (for each shading point: each scene light, each of its
k cameras, each of its k capture lights): the order a shader evaluating one point after the
other would touch the images in, the seed's "naive" order. `sorted_order` groups them by
image (camera, then light) and, inside an image, by row then column: each image is then
needed for one contiguous run, so a cache of a few images reads each image once.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from texelbake.errors import ShapeError


@dataclass
class ShadingOps:
    """Table 2 as arrays: target (n,) int64 shading point, camera (n,) int64, light (n,)
    int64, x, y (n,) float64 pixel coordinates, weight (n, 3) float64 RGB."""

    target: np.ndarray
    camera: np.ndarray
    light: np.ndarray
    x: np.ndarray
    y: np.ndarray
    weight: np.ndarray

    def __len__(self) -> int:
        return int(self.target.shape[0])


def build_ops(cam_idx: np.ndarray, cam_w: np.ndarray, cam_xy: np.ndarray,
              light_idx: np.ndarray, light_w: np.ndarray, radiance: np.ndarray
              ) -> ShadingOps:
    """The operations of p shading points lit by s scene lights.

    cam_idx, cam_w : (p, kc) ULR cameras and weights; cam_xy : (p, kc, 2) look-up positions;
    light_idx, light_w : (s, p, kl) ULR capture lights per scene light; radiance : (s, p, 3)
    the scene light's irradiance at the point (E · A(d), Eq. 11). Operations of zero weight
    are dropped. Point-major order (module docstring)."""
    ci, cw, cxy = (np.asarray(cam_idx, np.int64), np.asarray(cam_w, np.float64),
                   np.asarray(cam_xy, np.float64))
    li, lw, rad = (np.asarray(light_idx, np.int64), np.asarray(light_w, np.float64),
                   np.asarray(radiance, np.float64))
    p, kc = ci.shape
    if cw.shape != (p, kc) or cxy.shape != (p, kc, 2):
        raise ShapeError(f"camera weights {cw.shape} and positions {cxy.shape} must be "
                         f"({p}, {kc}) and ({p}, {kc}, 2)")
    if li.ndim != 3 or li.shape[1] != p or lw.shape != li.shape or rad.shape != li.shape[:2] + (3,):
        raise ShapeError(f"light indices {li.shape}, weights {lw.shape} and radiance "
                         f"{rad.shape} must be (s, {p}, kl), (s, {p}, kl), (s, {p}, 3)")
    s, _, kl = li.shape
    shape = (p, s, kc, kl)
    target = np.broadcast_to(np.arange(p)[:, None, None, None], shape)
    camera = np.broadcast_to(ci[:, None, :, None], shape)
    light = np.broadcast_to(li.transpose(1, 0, 2)[:, :, None, :], shape)
    x = np.broadcast_to(cxy[:, None, :, None, 0], shape)
    y = np.broadcast_to(cxy[:, None, :, None, 1], shape)
    scalar = cw[:, None, :, None] * lw.transpose(1, 0, 2)[:, :, None, :]  # (p, s, kc, kl)
    weight = scalar[..., None] * rad.transpose(1, 0, 2)[:, :, None, None, :]
    keep = (scalar > 0) & (weight.max(axis=-1) > 0)
    return ShadingOps(target[keep], camera[keep], light[keep], x[keep], y[keep],
                      weight[keep])


def naive_order(ops: ShadingOps) -> np.ndarray:
    """Generation (point-major) order. (n,) int64"""
    return np.arange(len(ops), dtype=np.int64)


def sorted_order(ops: ShadingOps) -> np.ndarray:
    """Cache-coherent order: by camera, light, row, column (stable). (n,) int64"""
    return np.lexsort((ops.x, ops.y, ops.light, ops.camera)).astype(np.int64)
