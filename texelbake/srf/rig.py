"""The capture rig of a surface reflectance field: cameras on a sphere looking at the
object's centre and directional lights on a sphere (seed 002 §3: ~200-400 viewpoints × ~40-60
lights), and the cameras' JSON form (intrinsics and extrinsics) shared by the store and the
import of measured fields.

Directions are a Fibonacci (golden-angle) spiral on the unit sphere: every prefix-free count
is spread evenly (no pole clustering as with latitude-longitude grids), deterministic, and
vectorised.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from texelbake.errors import SettingsError, ShapeError
from texelbake.trace import camera as cam_mod
from texelbake.trace.camera import PinholeCamera

#: the seed's Table of models: the mug is 216 viewpoints x 44 lights
DEFAULT_CAMERAS = 216
DEFAULT_LIGHTS = 44
#: capture image size: reduced from the seed's 1360 x 1032 (a CI-sized default)
DEFAULT_SIZE = 48
#: eye rays per capture pixel: the generated scenes' sub-pixel ridges alias into speckle at
#: 2-4 (the seed's photographs have no such noise; 16 removes it visibly on the cylinder)
DEFAULT_SPP = 16


def sphere_directions(n: int, *, offset: float = 0.5) -> np.ndarray:
    """n unit vectors on a golden-angle spiral over the whole sphere. (n, 3) float64"""
    n = int(n)
    if n < 1:
        raise SettingsError(f"field 'count': at least one direction, got {n}")
    k = np.arange(n, dtype=np.float64)
    z = 1.0 - 2.0 * (k + offset) / n
    r = np.sqrt(np.maximum(1.0 - z * z, 0.0))
    phi = k * math.pi * (3.0 - math.sqrt(5.0))
    return np.column_stack([r * np.cos(phi), r * np.sin(phi), z])


def sphere_cameras(bounds: object, n: int, size: int, *, fov_deg: float = 30.0,
                   distance: float = 1.1) -> list[PinholeCamera]:
    """n square cameras of `size` pixels on a sphere around the box `bounds` (2, 3), each
    framing its bounding sphere (`camera.auto_frame`). The directions are offset by a quarter
    step from the lights' so no camera sits exactly on a light."""
    b = np.asarray(bounds, dtype=np.float64)
    if b.shape != (2, 3):
        raise ShapeError(f"bounds must be (2, 3), got {b.shape}")
    return [cam_mod.auto_frame(b, size, size, distance=distance, view_from=d, fov_deg=fov_deg)
            for d in sphere_directions(n, offset=0.25)]  # a loop over the few cameras


def camera_to_json(cam: PinholeCamera) -> dict[str, Any]:
    """Intrinsics (width, height, tan_half_x) and extrinsics (position, world_from_camera
    rotation, columns x, y, z of the camera; it looks down -z, +y up)."""
    return {"width": int(cam.width), "height": int(cam.height),
            "tan_half_x": float(cam.tan_half_x),
            "position": [float(x) for x in cam.position],
            "rotation": [[float(x) for x in row] for row in cam.rotation]}


def camera_from_json(d: dict[str, Any], where: str) -> PinholeCamera:
    """Inverse of `camera_to_json`; also accepts `fov_x_deg` for `tan_half_x` and a 4 x 4
    `world_from_camera` (USD, column vectors) for position and rotation. SettingsError naming
    `where` and the field on anything missing or malformed."""
    try:
        w, h = int(d["width"]), int(d["height"])
        if "tan_half_x" in d:
            tan_x = float(d["tan_half_x"])
        else:
            tan_x = math.tan(math.radians(float(d["fov_x_deg"])) / 2.0)
        if "world_from_camera" in d:
            m = np.asarray(d["world_from_camera"], dtype=np.float64)
            if m.shape != (4, 4):
                raise SettingsError(f"{where}: field 'world_from_camera' must be 4 x 4, got "
                                    f"{m.shape}")
            pos, rot = m[:3, 3].copy(), m[:3, :3].copy()
        else:
            pos = np.asarray(d["position"], dtype=np.float64)
            rot = np.asarray(d["rotation"], dtype=np.float64)
    except KeyError as e:
        raise SettingsError(f"{where}: missing field {e.args[0]!r}") from None
    except (TypeError, ValueError) as e:
        raise SettingsError(f"{where}: malformed camera ({e})") from None
    if pos.shape != (3,) or rot.shape != (3, 3) or not (np.isfinite(pos).all()
                                                       and np.isfinite(rot).all()):
        raise SettingsError(f"{where}: 'position' (3,) and 'rotation' (3, 3) must be finite, "
                            f"got {pos.shape}, {rot.shape}")
    if not (w >= 1 and h >= 1 and math.isfinite(tan_x) and tan_x > 0):
        raise SettingsError(f"{where}: width, height >= 1 and a field of view in (0, 180) "
                            f"expected, got {w} x {h}, tan_half_x={tan_x}")
    ln = np.linalg.norm(rot, axis=0)
    if np.any(ln < 1e-12):
        raise SettingsError(f"{where}: 'rotation' has a zero column")
    rot = rot / ln
    if not np.allclose(rot.T @ rot, np.eye(3), atol=1e-4):
        raise SettingsError(f"{where}: 'rotation' is not a rotation (columns not orthogonal)")
    return PinholeCamera(pos, rot, tan_x, w, h)


def project(cam: PinholeCamera, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Continuous pixel coordinates (x right, y down; pixel (i, j) covers [i, i+1) x [j, j+1))
    of world points, and whether each lies in front of the camera.

    points : (n, 3) float64 → (xy (n, 2) float64, in_front (n,) bool)"""
    p = np.asarray(points, dtype=np.float64)
    local = (p - cam.position) @ cam.rotation  # camera coordinates (x, y, z), looks down -z
    depth = -local[:, 2]
    front = depth > 0
    safe = np.where(front, depth, 1.0)
    x = (local[:, 0] / safe / cam.tan_half_x + 1.0) * 0.5 * cam.width
    y = (1.0 - local[:, 1] / safe / cam.tan_half_y) * 0.5 * cam.height
    return np.column_stack([x, y]), front
