"""Unstructured-lumigraph interpolation (ULR, Buehler et al. 2001; seed 002 §5.2) over the
capture cameras and over the capture lights, the lights treated as cameras at infinity.

Penalty: the angle between the desired direction at the surface point (toward the viewer,
or toward the light, in the acquisition frame: after the look-up L) and the direction to the
capture camera (or of the capture light) — the angular penalty of Matusik et al. the seed
keeps. The k cameras of smallest penalty are blended with

    w̃_i = (1 − p_i / p_thresh) / p_i,   w_i = w̃_i / Σ_j w̃_j,

p_thresh the (k+1)-th smallest penalty: the weight falls to 0 continuously as a camera
leaves the k nearest, and the 1/p_i factor makes the field epipole-consistent — where a
capture camera's own ray is asked for (p_i → 0) it alone is used, so a capture view
reproduces its image (the issue's acceptance). p_i at or below `EXACT_ANGLE` is that case
(weight exactly 1). With fewer than k + 1 usable cameras p_thresh is π (every usable one
counts); ties at p_thresh (all k weights 0) share equally; a point with no usable camera gets
no weight (`valid` False) and is left black by the caller, never NaN.

Cameras are usable where the point projects inside the image, in front of the camera, and
is visible from it (the ray from the point to the camera's centre misses the impostor).
Lights have no visibility (shadows are in the images; §5.2).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from texelbake.errors import SettingsError, ShapeError
from texelbake.geometry.raycast import RayCaster
from texelbake.trace.camera import PinholeCamera

#: a penalty at or below this (radians) is the capture ray itself: weight 1
EXACT_ANGLE = 1e-9
#: cameras tested for visibility per point beyond the k + 1 ULR needs (occluded ones are
#: replaced by the next candidates)
EXTRA_CANDIDATES = 3
#: (point, camera) pairs evaluated at once (bounds memory: ~200 B per pair)
PAIR_BATCH = 1 << 20


def angles(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle between unit vectors, atan2(|a × b|, a · b) (accurate near 0, unlike arccos).
    a, b : (..., 3) broadcastable → (...) float64 radians"""
    c = np.cross(a, b)
    return np.arctan2(np.linalg.norm(c, axis=-1), np.sum(a * b, axis=-1))


def ulr_weights(penalty: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """ULR blending of m candidates per point (module docstring).

    penalty : (n, m) float64, +inf where a candidate is unusable; k : candidates blended
    returns (index (n, k) int64 into the m candidates, weight (n, k) float64 summing to 1
    where valid, valid (n,) bool)"""
    pen = np.asarray(penalty, dtype=np.float64)
    if pen.ndim != 2:
        raise ShapeError(f"penalty must be (n, m), got {pen.shape}")
    k = int(k)
    if k < 1:
        raise SettingsError(f"field 'k': at least one camera or light is blended, got {k}")
    n, m = pen.shape
    kk = min(k, m)
    order = np.argsort(pen, axis=1, kind="stable")[:, :kk + 1]
    p = np.take_along_axis(pen, order, axis=1)
    thresh = p[:, kk] if m > kk else np.full(n, np.inf)
    thresh = np.where(np.isfinite(thresh), thresh, math.pi)
    pk, idx = p[:, :kk], order[:, :kk]
    usable = np.isfinite(pk)
    with np.errstate(divide="ignore", invalid="ignore"):
        w = np.where(usable, (1.0 - pk / thresh[:, None]) / np.maximum(pk, EXACT_ANGLE), 0.0)
    w = np.maximum(w, 0.0)
    tie = (w.sum(axis=1) <= 0) & usable.any(axis=1)  # every usable one at p_thresh
    w[tie] = usable[tie].astype(np.float64)
    exact = usable[:, 0] & (pk[:, 0] <= EXACT_ANGLE)
    w[exact] = 0.0
    w[exact, 0] = 1.0
    s = w.sum(axis=1)
    valid = s > 0
    w = np.divide(w, s[:, None], out=np.zeros_like(w), where=valid[:, None])
    if kk < k:  # fewer candidates than k: pad with zero weights
        idx = np.pad(idx, ((0, 0), (0, k - kk)))
        w = np.pad(w, ((0, 0), (0, k - kk)))
    return idx.astype(np.int64), w, valid


def _unit(x: np.ndarray) -> np.ndarray:
    ln = np.linalg.norm(x, axis=-1, keepdims=True)
    return np.divide(x, ln, out=np.zeros_like(x), where=ln > 0)


def project_all(cameras: Sequence[PinholeCamera], points: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates of every point in every camera (as `rig.project`).
    returns (xy (n, c, 2) float64, inside (n, c) bool: in front and inside the image)"""
    pos = np.stack([c.position for c in cameras])  # (c, 3)
    rot = np.stack([c.rotation for c in cameras])  # (c, 3, 3)
    tx = np.array([c.tan_half_x for c in cameras])
    ty = np.array([c.tan_half_y for c in cameras])
    w = np.array([c.width for c in cameras], dtype=np.float64)
    h = np.array([c.height for c in cameras], dtype=np.float64)
    local = np.einsum("nci,cij->ncj", points[:, None, :] - pos[None], rot)
    depth = -local[:, :, 2]
    front = depth > 0
    safe = np.where(front, depth, 1.0)
    x = (local[:, :, 0] / safe / tx + 1.0) * 0.5 * w
    y = (1.0 - local[:, :, 1] / safe / ty) * 0.5 * h
    inside = front & (x >= 0) & (x <= w) & (y >= 0) & (y <= h)
    return np.stack([x, y], axis=-1), inside


def camera_weights(cameras: Sequence[PinholeCamera], points: np.ndarray,
                   view_dirs: np.ndarray, k: int, occluder: RayCaster | None,
                   vis_offset: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """`_camera_weights` over batches of points (at most PAIR_BATCH point-camera pairs)."""
    p = np.asarray(points, dtype=np.float64)
    step = max(1, PAIR_BATCH // max(len(cameras), 1))
    if p.ndim != 2 or p.shape[0] <= step:
        return _camera_weights(cameras, p, view_dirs, k, occluder, vis_offset)
    vd = np.asarray(view_dirs, dtype=np.float64)
    parts = [_camera_weights(cameras, p[a:a + step], vd[a:a + step], k, occluder, vis_offset)
             for a in range(0, p.shape[0], step)]  # a loop over batches of points
    return tuple(np.concatenate(x) for x in zip(*parts, strict=True))  # type: ignore[return-value]


def _camera_weights(cameras: Sequence[PinholeCamera], points: np.ndarray,
                    view_dirs: np.ndarray, k: int, occluder: RayCaster | None,
                    vis_offset: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """ULR over capture cameras for points in the acquisition frame.

    points : (n, 3) rest-frame surface points; view_dirs : (n, 3) unit desired directions
    (point → viewer, after L); occluder : the impostor (None: no visibility test);
    vis_offset : visibility rays start this far toward the camera and stop as far short
    returns (camera (n, k) int64, weight (n, k), xy (n, k, 2) pixel coords, valid (n,))"""
    p = np.asarray(points, dtype=np.float64)
    vd = _unit(np.asarray(view_dirs, dtype=np.float64))
    if p.ndim != 2 or p.shape[1] != 3 or vd.shape != p.shape:
        raise ShapeError(f"points and view_dirs must be (n, 3), got {p.shape}, {vd.shape}")
    n = p.shape[0]
    if n == 0:
        return (np.zeros((0, k), np.int64), np.zeros((0, k)), np.zeros((0, k, 2)),
                np.zeros(0, bool))
    pos = np.stack([c.position for c in cameras])
    to_cam = pos[None] - p[:, None, :]  # (n, c, 3)
    pen = angles(vd[:, None, :], _unit(to_cam))
    xy, inside = project_all(cameras, p)
    pen = np.where(inside, pen, np.inf)
    m = pen.shape[1]
    n_cand = min(m, int(k) + 1 + EXTRA_CANDIDATES)
    cand = np.argsort(pen, axis=1, kind="stable")[:, :n_cand]  # (n, q)
    pc = np.take_along_axis(pen, cand, axis=1)
    if occluder is not None:
        live = np.flatnonzero(np.isfinite(pc).reshape(-1))
        if live.size:
            rows = live // n_cand
            d = np.take_along_axis(to_cam, cand[:, :, None], axis=1).reshape(-1, 3)[live]
            dist = np.linalg.norm(d, axis=1)
            dirs = d / dist[:, None]
            occ = occluder.occluded(p[rows] + vis_offset * dirs, dirs,
                                    tmax=np.maximum(dist - 2.0 * vis_offset, 0.0))
            flat = pc.reshape(-1)
            flat[live[occ]] = np.inf
            pc = flat.reshape(pc.shape)
    j, w, valid = ulr_weights(pc, k)
    cam = np.take_along_axis(cand, np.minimum(j, n_cand - 1), axis=1)
    xy_k = np.take_along_axis(xy, cam[:, :, None], axis=1)
    return cam, w, xy_k, valid


def light_weights(light_dirs_rest: np.ndarray, capture_dirs: np.ndarray, k: int
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """ULR over capture lights as cameras at infinity: the penalty is the angle between the
    desired light direction (after L) and each capture light's direction; no visibility.
    light_dirs_rest : (n, 3) unit; capture_dirs : (m, 3) unit
    returns (light (n, k) int64, weight (n, k), valid (n,))"""
    ld = _unit(np.asarray(light_dirs_rest, dtype=np.float64))
    cd = np.asarray(capture_dirs, dtype=np.float64)
    pen = angles(ld[:, None, :], cd[None, :, :])
    return ulr_weights(pen, k)
