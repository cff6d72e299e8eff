"""Importing a measured BTF: a folder of images, one per (light, view) pair.

Directions come from, in this order:
1. a directions file given explicitly, or `directions.json` / `directions.csv` in the folder:
   JSON: a list (or {"images": [...]}) of {"file", "theta_i", "phi_i", "theta_o", "phi_o"};
   CSV: a header row with those five columns. Angles in degrees, theta from the normal, phi
   from the tangent; `file` relative to the folder;
2. otherwise the Bonn UBO2003 file names, `[NNNNN ]tlTTT plPPP tvTTT pvPPP.jpg` (light theta,
   light phi, view theta, view phi in degrees; spaces or underscores between the fields).

Images are read with OpenImageIO (PNG, JPEG, EXR, anything it reads). Integer images (8/16-bit
PNG, JPEG) are sRGB-encoded and decoded to linear with the IEC 61966-2-1 curve (written out
here: OIIO's built-in sRGB->linear conversion differs from the standard curve by up to 2e-3 on
8-bit input on this machine); float images (EXR) are taken as linear. Grey images are repeated
to RGB; alpha and extra channels are dropped. Every image must have the same size.
"""

from __future__ import annotations

import csv
import json
import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from texelbake.btf.lut import dirs_from_degrees
from texelbake.btf.maps_io import read_float_pixels
from texelbake.errors import AssetError, AssetPathError
from texelbake.io.images import srgb_to_linear

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".exr", ".tif", ".tiff", ".hdr")
DIRECTION_FILES = ("directions.json", "directions.csv")
_NUM = r"(\d+(?:\.\d+)?)"
UBO2003_NAME = re.compile(
    rf"tl{_NUM}[ _-]*pl{_NUM}[ _-]*tv{_NUM}[ _-]*pv{_NUM}", re.IGNORECASE
)
_FIELDS = ("theta_i", "phi_i", "theta_o", "phi_o")


@dataclass(frozen=True, eq=False)
class MeasuredBTF:
    """btf : (d, h, w, 3) float32 linear RGB; dirs_i, dirs_o : (d, 3) float64 unit (texel
    frame); angles : (d, 4) float64 degrees (theta_i, phi_i, theta_o, phi_o); files : d paths."""

    btf: np.ndarray
    dirs_i: np.ndarray
    dirs_o: np.ndarray
    angles: np.ndarray
    files: tuple[str, ...]


def parse_ubo2003_name(name: str) -> tuple[float, float, float, float]:
    """(theta_i, phi_i, theta_o, phi_o) in degrees from a UBO2003 file name.

    e.g. "00042 tl015 pl060 tv030 pv120.jpg" -> (15.0, 60.0, 30.0, 120.0)
    """
    m = UBO2003_NAME.search(Path(name).name)
    if m is None:
        raise AssetError(
            "file name does not follow the UBO2003 pattern 'tlTTT plPPP tvTTT pvPPP' and no "
            "directions.json/.csv was given", path=str(name))
    tl, pl, tv, pv = (float(g) for g in m.groups())
    for label, value, hi in (("tl", tl, 90.0), ("tv", tv, 90.0), ("pl", pl, 360.0),
                             ("pv", pv, 360.0)):
        if not 0.0 <= value <= hi:
            raise AssetError(f"{label}={value:g} outside [0, {hi:g}] degrees", path=str(name))
    return tl, pl, tv, pv


def read_directions_file(path: str | os.PathLike) -> dict[str, tuple[float, float, float, float]]:
    """file name -> (theta_i, phi_i, theta_o, phi_o) degrees, from a JSON or CSV file."""
    path = Path(path)
    if not path.is_file():
        raise AssetPathError("directions file not found", path=str(path))
    rows: list[dict] = []
    if path.suffix.lower() == ".json":
        try:
            data = json.loads(path.read_text())
        except json.JSONDecodeError as exc:
            raise AssetError(f"invalid JSON: {exc}", path=str(path)) from exc
        if isinstance(data, dict):
            data = data.get("images")
        if not isinstance(data, list):
            raise AssetError("expected a list of {file, theta_i, phi_i, theta_o, phi_o} (or "
                             "{'images': [...]})", path=str(path))
        rows = data
    elif path.suffix.lower() == ".csv":
        with path.open(newline="") as fh:
            rows = list(csv.DictReader(fh))
    else:
        raise AssetError(f"directions file must be .json or .csv, got '{path.suffix}'",
                         path=str(path))
    out: dict[str, tuple[float, float, float, float]] = {}
    for i, row in enumerate(rows):
        if not isinstance(row, dict) or "file" not in row:
            raise AssetError(f"entry {i}: expected keys 'file', {', '.join(_FIELDS)}",
                             path=str(path))
        try:
            ang = tuple(float(row[k]) for k in _FIELDS)
        except (KeyError, TypeError, ValueError) as exc:
            raise AssetError(f"entry {i} ({row.get('file')}): bad or missing angle ({exc}); "
                             f"expected numbers {', '.join(_FIELDS)} in degrees",
                             path=str(path)) from exc
        if not (0 <= ang[0] <= 90 and 0 <= ang[2] <= 90):
            raise AssetError(f"entry {i} ({row['file']}): theta outside [0, 90] degrees: {ang}",
                             path=str(path))
        name = str(row["file"])
        if name in out:
            raise AssetError(f"entry {i}: file '{name}' listed twice", path=str(path))
        out[name] = ang  # type: ignore[assignment]
    return out


def read_image_rgb(path: str | os.PathLike, *, srgb: str = "auto") -> np.ndarray:
    """One image as (h, w, 3) float32 linear RGB. srgb : "auto" | "yes" | "no"."""
    px, info = read_float_pixels(Path(path))
    if px.shape[2] >= 3:
        px = px[:, :, :3]
    else:
        px = np.repeat(px[:, :, :1], 3, axis=2)
    decode = srgb == "yes" or (srgb == "auto" and not info.is_float)
    return srgb_to_linear(px) if decode else np.ascontiguousarray(px)


def load_measured_btf(
    folder: str | os.PathLike,
    directions: str | os.PathLike | None = None,
    *,
    srgb: str = "auto",
    crop: tuple[int, int, int, int] | None = None,
) -> MeasuredBTF:
    """Read a folder of BTF images and their directions (see module docstring).

    folder : directory of images; directions : optional JSON/CSV file (default: the folder's
        directions.json/.csv, else UBO2003 names); crop : (y0, x0, h, w) region of each image
    returns : MeasuredBTF with pairs in sorted file-name order
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise AssetPathError("BTF folder not found", path=str(folder))
    if srgb not in ("auto", "yes", "no"):
        raise AssetError(f"srgb must be 'auto', 'yes' or 'no', got {srgb!r}", path=str(folder))
    if directions is None:
        for cand in DIRECTION_FILES:
            if (folder / cand).is_file():
                directions = folder / cand
                break
    if directions is not None:
        table = read_directions_file(directions)
        files = sorted(table)
        for f in files:
            p = (folder / f).resolve()
            if folder.resolve() not in p.parents or not p.is_file():
                raise AssetPathError("image listed in the directions file is missing or outside "
                                     "the BTF folder", path=str(folder / f))
        angles = np.array([table[f] for f in files], dtype=np.float64).reshape(-1, 4)
    else:
        files = sorted(p.name for p in folder.iterdir()
                       if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file())
        if not files:
            raise AssetError("no images (png, jpg, exr, ...) in the BTF folder", path=str(folder))
        angles = np.array([parse_ubo2003_name(f) for f in files], dtype=np.float64)
    if len(files) == 0:
        raise AssetError("the directions file lists no images", path=str(directions))
    images = []
    first_shape = None
    for f in files:  # one read per image file: I/O bound, not a per-pixel loop
        img = read_image_rgb(folder / f, srgb=srgb)
        if crop is not None:
            y0, x0, h, w = (int(v) for v in crop)
            if y0 < 0 or x0 < 0 or y0 + h > img.shape[0] or x0 + w > img.shape[1] or h < 1 or w < 1:
                raise AssetError(f"crop {crop} outside the image of size {img.shape[:2]}",
                                 path=str(folder / f))
            img = img[y0:y0 + h, x0:x0 + w]
        if first_shape is None:
            first_shape = img.shape
        elif img.shape != first_shape:
            raise AssetError(f"image size {img.shape[:2]} differs from the first image's "
                             f"{first_shape[:2]}", path=str(folder / f))
        images.append(img)
    btf = np.stack(images).astype(np.float32, copy=False)
    dirs_i = dirs_from_degrees(angles[:, 0], angles[:, 1])
    dirs_o = dirs_from_degrees(angles[:, 2], angles[:, 3])
    return MeasuredBTF(btf, dirs_i, dirs_o, angles, tuple(str(f) for f in files))
