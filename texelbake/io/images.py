"""Image files, one way: every image texelbake reads or writes goes through OpenImageIO here
(EXR, PNG and anything OIIO reads), with the one pair of sRGB transfer functions, written
atomically (`texelbake.io.atomic`) with deterministic headers (OpenEXR's writer stamps the
current time as DateTime unless one is given: a fixed one keeps reruns byte-identical).

sRGB by hand rather than OIIO's colorconvert: the exact IEC 61966-2-1 piecewise formula does
not depend on which OCIO config OIIO finds, and it is two lines.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from texelbake.errors import AssetError, ShapeError
from texelbake.io.atomic import atomic_path

#: the DateTime every EXR we write carries (the format's own field; a fixed value)
EXR_DATETIME = "1970:01:01 00:00:00"


def linear_to_srgb(x: object) -> np.ndarray:
    """IEC 61966-2-1 encoding of linear values, clipped to [0, 1]. (...) float64."""
    x = np.clip(np.asarray(x, dtype=np.float64), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1.0 / 2.4) - 0.055)


def srgb_to_linear(values: object) -> np.ndarray:
    """IEC 61966-2-1 decoding, elementwise, in float32. (...) encoded in [0, 1] -> linear."""
    v = np.asarray(values, dtype=np.float32)
    return np.where(
        v <= np.float32(0.04045),
        v / np.float32(12.92),
        np.power((np.maximum(v, 0.0) + np.float32(0.055)) / np.float32(1.055), np.float32(2.4)),
    ).astype(np.float32)


@dataclass(frozen=True)
class ImageInfo:
    """What a file says about its pixels: channel names, the stored sample type ("uint8",
    "half", "float", ...) and its metadata attributes."""

    channel_names: tuple[str, ...]
    basetype: str
    attributes: dict[str, Any] = field(default_factory=dict)

    @property
    def is_8bit(self) -> bool:
        return self.basetype in ("uint8", "int8")

    @property
    def is_float(self) -> bool:
        return self.basetype in ("half", "float", "double")


def read_pixels(path: str | Path, **context: str) -> tuple[np.ndarray, ImageInfo]:
    """(h, w, c) float32 pixels of the first subimage (no colour conversion) and its
    `ImageInfo`. AssetError naming the file (and `context`, e.g. prim=...) when it cannot be
    opened or decoded."""
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise AssetError(f"cannot open image: {oiio.geterror()}", path=str(path), **context)
    try:
        spec = inp.spec()
        pixels = inp.read_image(0, 0, 0, spec.nchannels, oiio.FLOAT)
        err = inp.geterror()
    finally:
        inp.close()
    if pixels is None:
        raise AssetError(f"cannot decode image: {err}", path=str(path), **context)
    info = ImageInfo(tuple(spec.channelnames), str(spec.format).lower(),
                     {a.name: spec.getattribute(a.name) for a in spec.extra_attribs})
    return (np.asarray(pixels, dtype=np.float32).reshape(spec.height, spec.width,
                                                         spec.nchannels), info)


def write_pixels(path: str | Path, pixels: np.ndarray, fmt: str, *,
                 channel_names: Sequence[str] | None = None,
                 attributes: Mapping[str, Any] | None = None) -> Path:
    """Write (h, w, c) pixels as `fmt` ("uint8", "half", "float") to `path` (format by
    suffix), atomically, EXRs with a fixed DateTime. Returns the path."""
    import OpenImageIO as oiio

    path = Path(path)
    px = np.ascontiguousarray(pixels)
    if px.ndim != 3 or px.size == 0:
        raise ShapeError(f"{path}: pixels must be (h, w, c), got {px.shape}")
    h, w, c = px.shape
    spec = oiio.ImageSpec(w, h, c, fmt)
    if channel_names is not None:
        spec.channelnames = tuple(channel_names)
    for k, v in (attributes or {}).items():
        spec.attribute(k, v)
    if path.suffix.lower() == ".exr":
        spec.attribute("DateTime", EXR_DATETIME)
    with atomic_path(path) as tmp:
        out = oiio.ImageOutput.create(str(tmp))
        if out is None or not out.open(str(tmp), spec):
            raise AssetError(f"cannot write image: {oiio.geterror()}", path=str(path))
        ok = out.write_image(px)
        err = out.geterror()
        out.close()
        if not ok:
            raise AssetError(f"cannot write image: {err}", path=str(path))
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
    return write_pixels(path, _check(image).astype(np.float32), "float")


def to_uint8(image: object, *, srgb: bool = True, exposure: float = 1.0) -> np.ndarray:
    """8-bit pixels of linear values times `exposure`, clipped to [0, 1], sRGB-encoded when
    `srgb`."""
    x = np.asarray(image, dtype=np.float64) * float(exposure)
    x = linear_to_srgb(x) if srgb else np.clip(x, 0.0, 1.0)
    return np.round(x * 255.0).astype(np.uint8)


def write_png(path: str | Path, image: object, *, srgb: bool = True,
              exposure: float = 1.0) -> Path:
    """8-bit PNG of linear values (`to_uint8`); uint8 input is written as it is.

    image : (h, w, 3) float, or uint8 pixels already encoded
    """
    arr = np.asarray(image)
    if arr.dtype == np.uint8:
        return write_pixels(path, arr if arr.ndim == 3 else arr[..., None], "uint8")
    return write_pixels(path, to_uint8(_check(arr), srgb=srgb, exposure=exposure), "uint8")


def write_animation(path: str | Path, frames: Sequence[object], *, fps: float = 8.0,
                    srgb: bool = True, exposure: float = 1.0) -> Path:
    """An animated GIF (looping) of linear frames, each (h, w, 3) float of one size (or uint8
    already encoded), one GIF subimage per frame through OIIO's GIF writer (256 colours per
    frame: a preview, not a measurement). Returns the path."""
    import OpenImageIO as oiio

    path = Path(path)
    if path.suffix.lower() != ".gif":
        raise ShapeError(f"{path}: an animation is written as .gif")
    if not frames or not fps > 0:
        raise ShapeError(f"{path}: need at least one frame and fps > 0, got {len(frames)} "
                         f"frames at {fps} fps")
    px = [np.asarray(f) if np.asarray(f).dtype == np.uint8
          else to_uint8(_check(f), srgb=srgb, exposure=exposure) for f in frames]
    px = [np.ascontiguousarray(p[..., :3] if p.shape[2] >= 3 else np.repeat(p, 3, 2))
          for p in px]
    if len({p.shape for p in px}) != 1:
        raise ShapeError(f"{path}: frames differ in size: {sorted({p.shape for p in px})}")
    h, w, _ = px[0].shape
    specs = []
    for _ in px:
        spec = oiio.ImageSpec(w, h, 3, "uint8")
        spec.attribute("FramesPerSecond", oiio.TypeRational, (int(round(fps * 1000)), 1000))
        spec.attribute("gif:LoopCount", 0)  # loop forever
        specs.append(spec)
    with atomic_path(path) as tmp:
        out = oiio.ImageOutput.create(str(tmp))
        if out is None or not out.open(str(tmp), specs):
            raise AssetError(f"cannot write animation: {oiio.geterror()}", path=str(path))
        ok = True
        for k, p in enumerate(px):  # a loop over frames
            if k:
                ok = ok and out.open(str(tmp), specs[k], "AppendSubimage")
            ok = ok and out.write_image(p)
        err = out.geterror()
        out.close()
        if not ok:
            raise AssetError(f"cannot write animation: {err}", path=str(path))
    return path


def read_image(path: str | Path) -> np.ndarray:
    """(h, w, c) float32 pixels of an image file (no colour conversion)."""
    return read_pixels(path)[0]
