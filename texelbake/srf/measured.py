"""Import of a measured surface reflectance field: a folder of images, one per (camera,
light), HDR (EXR, float) or LDR (PNG, 8-bit sRGB, decoded to linear), read through
`texelbake.io.images`, and a JSON describing the rig:

    {"cameras": [{"width": 64, "height": 48, "fov_x_deg": 30,          (or "tan_half_x")
                  "world_from_camera": [[...4 x 4, USD column vectors...]]}   (or
                  "position" (3,) + "rotation" (3, 3), columns x, y, z; looks down -z)
                 , ...],
     "lights": [[x, y, z], ...]            directions toward each light (or {"direction": ...})
     "images": [["cam0/l00.exr", ...], ...]  per camera, one path per light, relative to the
                                           JSON's folder
     "irradiance": 1.0,                    optional: the capture lights' irradiance; pixels
                                           are divided by it (reflectance per unit irradiance)
     "masks": ["cam0/mask.png", ...],      optional: per camera, the object's coverage (first
                                           channel, 0..1) for the visual hull (`srf.hull`)
     "bounds": [[x, y, z], [x, y, z]]}     optional: a box around the object (carving region)

Cameras are pinholes with square pixels and the principal point at the image centre (the
renderer's camera model); a rig needing lens distortion must be undistorted first. Every
error names the JSON field or the image file.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from texelbake.errors import AssetError, SettingsError
from texelbake.io.images import read_pixels, srgb_to_linear
from texelbake.srf.rig import camera_from_json
from texelbake.srf.store import SrfStore, SrfWriter


def _light_dirs(raw: object, where: str) -> np.ndarray:
    if not isinstance(raw, list) or not raw:
        raise SettingsError(f"{where}: field 'lights' must be a non-empty list")
    rows = [r.get("direction") if isinstance(r, dict) else r for r in raw]
    try:
        dirs = np.asarray(rows, dtype=np.float64)
    except (TypeError, ValueError):
        raise SettingsError(f"{where}: field 'lights' must hold 3-vectors") from None
    if dirs.ndim != 2 or dirs.shape[1] != 3:
        raise SettingsError(f"{where}: field 'lights' must hold 3-vectors, got {dirs.shape}")
    return dirs


def read_reflectance(path: Path, width: int, height: int, irradiance: float) -> np.ndarray:
    """One image as linear RGB reflectance (h, w, 3) float32; AssetError naming the file."""
    px, info = read_pixels(path)
    if px.shape[:2] != (height, width):
        raise AssetError(f"image is {px.shape[1]} x {px.shape[0]}, the camera says "
                         f"{width} x {height}", path=str(path))
    if px.shape[2] >= 3:
        rgb = px[:, :, :3]
    elif px.shape[2] in (1, 2):  # grey (and grey + alpha)
        rgb = np.repeat(px[:, :, :1], 3, axis=2)
    else:
        raise AssetError(f"image has {px.shape[2]} channels", path=str(path))
    if info.is_8bit:
        rgb = srgb_to_linear(rgb)
    if not np.isfinite(rgb).all():
        raise AssetError("image has NaN or Inf pixels", path=str(path))
    return (rgb / irradiance).astype(np.float32)


def import_measured(rig_json: str | Path, out: str | Path, *, encoding: str = "raw",
                    tile: int = 4, components: int = 6) -> SrfStore:
    """Import the rig described by `rig_json` (module docstring) into the store `out`."""
    rig = Path(rig_json)
    try:
        desc = json.loads(rig.read_text())
    except (OSError, ValueError) as e:
        raise AssetError(f"cannot read the rig description ({e})", path=str(rig)) from None
    where = str(rig)
    if not isinstance(desc, dict):
        raise SettingsError(f"{where}: expected a JSON object")
    cams_raw, images = desc.get("cameras"), desc.get("images")
    if not isinstance(cams_raw, list) or not cams_raw:
        raise SettingsError(f"{where}: field 'cameras' must be a non-empty list")
    cams = [camera_from_json(c, f"{where}: cameras[{i}]") for i, c in enumerate(cams_raw)]
    dirs = _light_dirs(desc.get("lights"), where)
    if not isinstance(images, list) or len(images) != len(cams):
        raise SettingsError(f"{where}: field 'images' must list one row per camera "
                            f"({len(cams)}), got {len(images) if isinstance(images, list) else images!r}")
    irr = float(desc.get("irradiance", 1.0))
    if not irr > 0:
        raise SettingsError(f"{where}: field 'irradiance' must be > 0, got {irr}")
    writer = SrfWriter(out, cams, dirs, encoding=encoding, tile=tile, components=components,
                       source=str(rig))
    for c, row in enumerate(images):  # a loop over the images, each read whole
        if not isinstance(row, list) or len(row) != len(dirs):
            raise SettingsError(f"{where}: images[{c}] must name one image per light "
                                f"({len(dirs)})")
        for j, name in enumerate(row):
            p = rig.parent / str(name)
            if not p.is_file():
                raise AssetError(f"images[{c}][{j}] does not exist", path=str(p))
            writer.write(c, j, read_reflectance(p, cams[c].width, cams[c].height, irr))
    masks = desc.get("masks")
    if masks is not None:
        if not isinstance(masks, list) or len(masks) != len(cams):
            raise SettingsError(f"{where}: field 'masks' must name one image per camera "
                                f"({len(cams)})")
        for c, name in enumerate(masks):
            p = rig.parent / str(name)
            if not p.is_file():
                raise AssetError(f"masks[{c}] does not exist", path=str(p))
            px, info = read_pixels(p)
            if px.shape[:2] != (cams[c].height, cams[c].width):
                raise AssetError(f"mask is {px.shape[1]} x {px.shape[0]}, the camera says "
                                 f"{cams[c].width} x {cams[c].height}", path=str(p))
            writer.write_silhouette(c, np.clip(px[:, :, 0], 0.0, 1.0))
    extra = {}
    if "bounds" in desc:
        b = np.asarray(desc["bounds"], dtype=np.float64)
        if b.shape != (2, 3) or not np.isfinite(b).all() or np.any(b[1] < b[0]):
            raise SettingsError(f"{where}: field 'bounds' must be [[min x, y, z], [max x, y, "
                                f"z]], got {desc['bounds']!r}")
        extra["bounds"] = b.tolist()
    return writer.close(extra)
