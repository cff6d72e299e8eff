"""Pinhole cameras and stratified eye rays (wavefront: all rays of a pass at once).

A camera looks down its local -Z with +Y up (USD). The horizontal field of view comes from the
USD camera's horizontal aperture and focal length; the vertical one follows the image aspect
(square pixels), as USD's "conform horizontal" does.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from texelbake.errors import SettingsError, ShapeError
from texelbake.model import Camera


@dataclass(frozen=True, eq=False)
class PinholeCamera:
    """position : (3,) float64; rotation : (3, 3) float64 world_from_camera (columns x, y, z of
    the camera in world space); tan_half_x : tan of half the horizontal field of view;
    width, height : pixels."""

    position: np.ndarray
    rotation: np.ndarray
    tan_half_x: float
    width: int
    height: int

    @property
    def tan_half_y(self) -> float:
        return self.tan_half_x * self.height / self.width

    @property
    def forward(self) -> np.ndarray:
        """(3,) unit viewing direction (camera -Z) in world space."""
        return -self.rotation[:, 2]

    @property
    def pixel_angle(self) -> float:
        """Angular size of one pixel at the image centre (radians, small-angle)."""
        return 2.0 * self.tan_half_x / self.width


def _check_size(width: int, height: int) -> tuple[int, int]:
    w, h = int(width), int(height)
    if w < 1 or h < 1:
        raise SettingsError(f"field 'width'/'height': must be >= 1, got {w} x {h}")
    return w, h


def from_usd(camera: Camera, width: int, height: int) -> PinholeCamera:
    """The asset's camera (texelbake.model.Camera) at this image size."""
    w, h = _check_size(width, height)
    m = np.asarray(camera.world_from_camera, dtype=np.float64)
    if m.shape != (4, 4):
        raise ShapeError(f"world_from_camera must be (4, 4), got {m.shape}")
    rot = m[:3, :3]
    # strip scale so directions stay unit
    rot = rot / np.linalg.norm(rot, axis=0, keepdims=True)
    if camera.focal_length <= 0 or camera.horizontal_aperture <= 0:
        raise SettingsError(
            f"camera {camera.path}: focal length and aperture must be > 0, got "
            f"{camera.focal_length}, {camera.horizontal_aperture}")
    tan_x = 0.5 * camera.horizontal_aperture / camera.focal_length
    return PinholeCamera(m[:3, 3].copy(), rot, float(tan_x), w, h)


def look_at(eye: object, target: object, width: int, height: int, *, fov_deg: float = 27.0,
            up: object = (0.0, 1.0, 0.0)) -> PinholeCamera:
    """A camera at `eye` looking at `target` with horizontal field of view `fov_deg`."""
    w, h = _check_size(width, height)
    eye = np.asarray(eye, dtype=np.float64)
    z = eye - np.asarray(target, dtype=np.float64)
    if np.linalg.norm(z) == 0:
        raise SettingsError("field 'camera': eye and target coincide")
    z /= np.linalg.norm(z)
    up = np.asarray(up, dtype=np.float64)
    if abs(float(np.dot(up, z))) > 0.999:
        up = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 0.0, 1.0])
    x = np.cross(up, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return PinholeCamera(eye.copy(), np.stack([x, y, z], axis=1),
                         math.tan(math.radians(fov_deg) / 2.0), w, h)


def auto_frame(bounds: object, width: int, height: int, *, distance: float = 1.1,
               view_from: object = (0.3, 0.4, 1.0), fov_deg: float = 27.0) -> PinholeCamera:
    """Frame a bounding box: look at its centre from direction `view_from`, at `distance`
    times the distance at which the bounding sphere just fills the narrower field of view."""
    b = np.asarray(bounds, dtype=np.float64)
    if b.shape != (2, 3):
        raise ShapeError(f"bounds must be (2, 3), got {b.shape}")
    if distance <= 0:
        raise SettingsError(f"field 'distance': must be > 0, got {distance}")
    centre = b.mean(axis=0)
    radius = max(0.5 * float(np.linalg.norm(b[1] - b[0])), 1e-12)
    d = np.asarray(view_from, dtype=np.float64)
    d = d / np.linalg.norm(d)
    tan_x = math.tan(math.radians(fov_deg) / 2.0)
    tan_min = min(tan_x, tan_x * height / width)
    dist = distance * radius / math.sin(math.atan(tan_min))
    return look_at(centre + dist * d, centre, width, height, fov_deg=fov_deg)


def strata(spp: int) -> tuple[int, int]:
    """(nx, ny) with nx * ny == spp and nx the largest divisor of spp not above sqrt(spp)."""
    spp = int(spp)
    if spp < 1:
        raise SettingsError(f"field 'spp': must be >= 1, got {spp}")
    nx = max(d for d in range(1, math.isqrt(spp) + 1) if spp % d == 0)
    return nx, spp // nx


def sample_offsets(spp: int, n_pixels: int, seed: int, start: int = 0,
                   stop: int | None = None, pixels: np.ndarray | None = None) -> np.ndarray:
    """Stratified jittered sub-pixel positions of samples start..stop-1 of every pixel, or of
    the row-major `pixels` (p,) only (ascending): (stop - start, n_pixels or p, 2) float64 in
    [0, 1).

    Sample s of every pixel lies in stratum s of an nx x ny grid (`strata`), jittered
    independently per pixel by a generator seeded with (seed, start), so a pass of samples
    can be generated on its own (memory stays bounded at 1024 samples per pixel). The jitter
    of `pixels` is the whole frame's at those pixels, bit for bit, whichever way it is drawn.
    """
    nx, ny = strata(spp)
    stop = spp if stop is None else int(stop)
    if not 0 <= start < stop <= spp:
        raise SettingsError(f"sample range [{start}, {stop}) outside [0, {spp})")
    bits = np.random.PCG64([int(seed), int(start)])  # numpy's default_rng, its PCG64 at hand
    rng = np.random.Generator(bits)
    s = np.arange(start, stop)
    cell = np.stack([s % nx, s // nx], axis=1).astype(np.float64)  # (k, 2)
    if pixels is None:
        jitter = rng.random((stop - start, n_pixels, 2))
    else:
        pixels = np.asarray(pixels, np.int64)
        if pixels.ndim != 1 or np.any(np.diff(pixels) <= 0) or (
                pixels.size and not 0 <= pixels[0] <= pixels[-1] < n_pixels):
            raise ShapeError(f"pixels must be ascending ids in [0, {n_pixels})")
        jitter = _span_jitter(rng, bits, stop - start, n_pixels, pixels)
    return (cell[:, None, :] + jitter) / np.array([nx, ny], dtype=np.float64)


def _span_jitter(rng: np.random.Generator, bits: np.random.PCG64, k: int, n_pixels: int,
                 pixels: np.ndarray) -> np.ndarray:
    """`rng.random((k, n_pixels, 2))[:, pixels]` drawing, for each sample, only the span from
    the first of `pixels` to the last (`box_pixels`' rectangle: its rows and what lies between
    them), PCG64's `advance` stepping over the values before and after it (one 64-bit draw
    per float64). numpy's generators give a stream in order only: a frame of an object a few
    dozen pixels wide drew its whole 512² jitter before (docs/decisions.md, "Eye rays are
    traced only where the object can be")."""
    out = np.empty((k, pixels.size, 2))
    if pixels.size == 0:
        return out
    lo, hi = int(pixels[0]), int(pixels[-1]) + 1
    at = 0  # values drawn so far
    for s in range(k):  # a loop over the pass's samples: one span each
        first = (s * n_pixels + lo) * 2
        bits.advance(first - at)
        out[s] = rng.random((hi - lo, 2))[pixels - lo]
        at = first + 2 * (hi - lo)
    return out


def eye_rays(cam: PinholeCamera, offsets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Eye rays through the given sub-pixel positions of every pixel.

    offsets : (k, h * w, 2) float64 positions in [0, 1)² per pixel (row-major pixels)
    returns : (origins (k * h * w, 3), dirs (k * h * w, 3) unit) float64, ordered
        [sample][pixel] so that a (k, h * w) reshape sums samples per pixel
    """
    w, h = cam.width, cam.height
    off = np.asarray(offsets, dtype=np.float64)
    if off.ndim != 3 or off.shape[1:] != (h * w, 2):
        raise ShapeError(f"offsets must be (k, {h * w}, 2), got {off.shape}")
    pix = np.broadcast_to(np.arange(h * w), off.shape[:2])
    return eye_rays_at(cam, pix.reshape(-1), off.reshape(-1, 2))


def eye_rays_at(cam: PinholeCamera, pixels: np.ndarray, offsets: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray]:
    """Eye rays through sub-pixel positions of given pixels.

    pixels : (n,) int row-major pixel indices; offsets : (n, 2) float64 positions in [0, 1)²
    returns : (origins (n, 3), dirs (n, 3) unit) float64
    """
    w = cam.width
    off = np.asarray(offsets, dtype=np.float64)
    rows, cols = np.divmod(np.asarray(pixels, dtype=np.int64), w)
    if off.shape != (rows.size, 2):
        raise ShapeError(f"offsets must be ({rows.size}, 2), got {off.shape}")
    x = (2.0 * (cols + off[:, 0]) / w - 1.0) * cam.tan_half_x
    y = (1.0 - 2.0 * (rows + off[:, 1]) / cam.height) * cam.tan_half_y
    d_cam = np.stack([x, y, -np.ones_like(x)], axis=-1)
    d = d_cam @ cam.rotation.T
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return np.broadcast_to(cam.position, d.shape).copy(), d


def box_pixels(cam: PinholeCamera, box: np.ndarray) -> np.ndarray | None:
    """(p,) int64 row-major ids, ascending, of the pixels of the screen rectangle that holds the
    projection of the axis-aligned box (2, 3) [lo, hi] (its eight corners' bounds, one pixel
    of margin): no eye ray through another pixel meets the box. None when a corner is not in
    front of the camera (the projection is unbounded: every pixel)."""
    lo, hi = np.asarray(box, np.float64)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                        for z in (lo[2], hi[2])])
    p = (corners - cam.position) @ cam.rotation  # camera frame: x right, y up, -z forward
    depth = -p[:, 2]
    if np.any(depth <= 1e-12):
        return None
    col = (p[:, 0] / (depth * cam.tan_half_x) + 1.0) * 0.5 * cam.width
    row = (1.0 - p[:, 1] / (depth * cam.tan_half_y)) * 0.5 * cam.height
    c0, c1 = max(int(np.floor(col.min())) - 1, 0), min(int(np.ceil(col.max())) + 1, cam.width)
    r0, r1 = max(int(np.floor(row.min())) - 1, 0), min(int(np.ceil(row.max())) + 1, cam.height)
    if c0 >= c1 or r0 >= r1:
        return np.zeros(0, np.int64)
    return (np.arange(r0, r1)[:, None] * cam.width + np.arange(c0, c1)[None, :]).reshape(-1)


def dolly(cam: PinholeCamera, centre: object, distance: float) -> PinholeCamera:
    """The same camera moved along its viewing axis so that `centre`'s depth along the axis
    becomes `distance` (orientation and field of view kept: the same view from farther)."""
    c = np.asarray(centre, dtype=np.float64)
    depth = float(np.dot(c - cam.position, cam.forward))
    pos = cam.position - cam.forward * (float(distance) - depth)
    return PinholeCamera(pos, cam.rotation.copy(), cam.tan_half_x, cam.width, cam.height)
