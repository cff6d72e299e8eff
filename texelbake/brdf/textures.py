"""Texture look-ups (bilinear, wrap modes) of `texelbake.model.Texture` at uv."""

from __future__ import annotations

from typing import Any

import numpy as np

from texelbake import model
from texelbake.brdf.common import as_uv
from texelbake.errors import SettingsError, ShapeError

_WRAP_MODES = ("repeat", "clamp", "mirror", "black")


def _wrap(i: np.ndarray, size: int, mode: str) -> tuple[np.ndarray, np.ndarray | None]:
    """Texel indices -> (in-range indices, valid mask or None)."""
    if mode == "repeat":
        return np.mod(i, size), None
    if mode == "clamp":
        return np.clip(i, 0, size - 1), None
    if mode == "mirror":
        j = np.mod(i, 2 * size)
        return np.where(j >= size, 2 * size - 1 - j, j), None
    # black: texels outside the image are 0 (blend with black within half a texel of the edge)
    valid = (i >= 0) & (i < size)
    return np.clip(i, 0, size - 1), valid


def sample_texture(tex: model.Texture, uv: Any) -> np.ndarray:
    """Bilinearly filtered texture lookup, UsdUVTexture semantics.

    Texel (row r, column c) of ``tex.pixels`` (row 0 = top) has its centre at
    s = (c + 0.5) / w, t = 1 - (r + 0.5) / h, so uv (0, 0) is the bottom-left corner of the image
    (USD convention). Wrap modes per axis: repeat, clamp, mirror (mirrored repeat), black (0
    outside [0, 1]), after ``tex.st_transform`` (a UsdTransform2d on st). Output = scale * texel
    + bias per channel (UsdUVTexture ``scale``,
    ``bias``, first c of the 4 components).

    tex : model.Texture with pixels (h, w, c); uv : (n, 2) float64
    returns : (n, c) float64
    """
    uv = as_uv(uv)
    a, b, c, d, e, f = (float(x) for x in tex.st_transform)
    if (a, b, c, d, e, f) != (1.0, 0.0, 0.0, 0.0, 1.0, 0.0):  # a UsdTransform2d
        uv = np.stack([a * uv[:, 0] + b * uv[:, 1] + c, d * uv[:, 0] + e * uv[:, 1] + f], 1)
    pix = np.asarray(tex.pixels)
    if pix.ndim == 2:
        pix = pix[:, :, None]
    if pix.ndim != 3 or pix.shape[0] == 0 or pix.shape[1] == 0 or pix.shape[2] == 0:
        raise ShapeError(f"texture {tex.path!r}: pixels must be (h, w, c), got {pix.shape}")
    for axis, mode in (("wrapS", tex.wrap_s), ("wrapT", tex.wrap_t)):
        if mode not in _WRAP_MODES:
            raise SettingsError(
                f"texture {tex.path!r}: {axis} {mode!r} not one of {list(_WRAP_MODES)}"
            )
    h, w, c = pix.shape
    if c > 4:
        raise ShapeError(f"texture {tex.path!r}: at most 4 channels, got {c}")
    n = uv.shape[0]
    if n == 0:
        return np.zeros((0, c))
    x = uv[:, 0] * w - 0.5
    y = (1.0 - uv[:, 1]) * h - 0.5
    x0f = np.floor(x)
    y0f = np.floor(y)
    fx = (x - x0f)[:, None]
    fy = (y - y0f)[:, None]
    x0 = x0f.astype(np.int64)
    y0 = y0f.astype(np.int64)
    cols = [_wrap(x0, w, tex.wrap_s), _wrap(x0 + 1, w, tex.wrap_s)]
    rows = [_wrap(y0, h, tex.wrap_t), _wrap(y0 + 1, h, tex.wrap_t)]
    out = np.zeros((n, c))
    for (r, rv), wy in ((rows[0], 1.0 - fy), (rows[1], fy)):
        for (col, cv), wx in ((cols[0], 1.0 - fx), (cols[1], fx)):
            v = pix[r, col].astype(np.float64)  # (n, c)
            wgt = wy * wx
            if rv is not None:
                wgt = wgt * rv[:, None]
            if cv is not None:
                wgt = wgt * cv[:, None]
            out += v * wgt
    scale = np.resize(np.asarray(tex.scale, dtype=np.float64), 4)[:c]
    bias = np.resize(np.asarray(tex.bias, dtype=np.float64), 4)[:c]
    out *= scale
    out += bias
    return out
