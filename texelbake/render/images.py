"""Image files: linear float EXR and sRGB PNG through OpenImageIO, written atomically."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np

from texelbake.errors import ShapeError


def linear_to_srgb(x: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1 encoding of linear values in [0, 1] (clipped). (..., c) float64."""
    x = np.clip(np.asarray(x, dtype=np.float64), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1.0 / 2.4) - 0.055)


def _write(path: Path, pixels: np.ndarray, fmt: str) -> Path:
    import OpenImageIO as oiio

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    h, w, c = pixels.shape
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.stem}.", suffix=path.suffix)
    os.close(fd)
    try:
        out = oiio.ImageOutput.create(tmp)
        if out is None or not out.open(tmp, oiio.ImageSpec(w, h, c, fmt)):
            raise OSError(f"cannot write {path}: {oiio.geterror()}")
        ok = out.write_image(np.ascontiguousarray(pixels))
        out.close()
        if not ok:
            raise OSError(f"cannot write {path}: {out.geterror()}")
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return path


def _check(image: object) -> np.ndarray:
    img = np.asarray(image, dtype=np.float64)
    if img.ndim == 2:
        img = img[..., None]
    if img.ndim != 3 or img.shape[2] not in (1, 3, 4) or img.size == 0:
        raise ShapeError(f"image must be (h, w), (h, w, 1|3|4), got {img.shape}")
    return img


def write_exr(path: str | Path, image: object) -> Path:
    """Linear float32 EXR (channels R, G, B). image : (h, w, 3) float."""
    return _write(Path(path), _check(image).astype(np.float32), "float")


def write_png(path: str | Path, image: object, *, srgb: bool = True,
              exposure: float = 1.0) -> Path:
    """8-bit PNG; linear values times `exposure`, clipped to [0, 1], sRGB-encoded when `srgb`.

    image : (h, w, 3) float
    """
    x = _check(image) * float(exposure)
    x = linear_to_srgb(x) if srgb else np.clip(x, 0.0, 1.0)
    return _write(Path(path), np.round(x * 255.0).astype(np.uint8), "uint8")


def read_image(path: str | Path) -> np.ndarray:
    """(h, w, c) float32 pixels of an image file (no colour conversion)."""
    import OpenImageIO as oiio

    buf = oiio.ImageBuf(str(path))
    if buf.has_error:
        raise OSError(f"cannot read {path}: {buf.geterror()}")
    return np.asarray(buf.get_pixels(oiio.FLOAT), dtype=np.float32)
