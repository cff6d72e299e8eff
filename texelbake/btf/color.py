"""RGB <-> YCbCr for BTF compression (seed 001, §3.1: "we first convert each BTF image to the
YCbCr color space" to reduce the colour correlation before the per-channel pyramids).

The transform is the full-range ITU-R BT.601 (JPEG/JFIF) matrix *without* the 0.5 chroma
offset: texelbake's BTFs are linear floats, possibly above 1, so Cb and Cr are signed and the
transform is purely linear (an offset would only move the top-level mean, Eq. 6). The inverse
is the numerical inverse of the same matrix, so a round trip is exact to float64 rounding.
Channel axis is the last one.
"""

from __future__ import annotations

import numpy as np

from texelbake.errors import ShapeError

#: rows map (R, G, B) -> (Y, Cb, Cr); BT.601 luma weights, Cb = (B - Y)/1.772, Cr = (R - Y)/1.402
YCBCR_FROM_RGB = np.array(
    [
        [0.299, 0.587, 0.114],
        [-0.299 / 1.772, -0.587 / 1.772, (1.0 - 0.114) / 1.772],
        [(1.0 - 0.299) / 1.402, -0.587 / 1.402, -0.114 / 1.402],
    ],
    dtype=np.float64,
)
RGB_FROM_YCBCR = np.linalg.inv(YCBCR_FROM_RGB)

CHANNELS = ("Y", "Cb", "Cr")


def _check(x: np.ndarray, name: str) -> np.ndarray:
    x = np.asarray(x)
    if x.ndim < 1 or x.shape[-1] != 3:
        raise ShapeError(f"{name} must have a last axis of 3 channels, got shape {x.shape}")
    if not np.issubdtype(x.dtype, np.floating):
        x = x.astype(np.float64)
    return x


def rgb_to_ycbcr(rgb: np.ndarray) -> np.ndarray:
    """rgb : (..., 3) float32|float64 linear RGB -> (..., 3) same dtype (Y, Cb, Cr)."""
    rgb = _check(rgb, "rgb")
    return (rgb @ YCBCR_FROM_RGB.T.astype(rgb.dtype)).astype(rgb.dtype, copy=False)


def ycbcr_to_rgb(ycc: np.ndarray) -> np.ndarray:
    """ycc : (..., 3) float32|float64 (Y, Cb, Cr) -> (..., 3) same dtype linear RGB."""
    ycc = _check(ycc, "ycbcr")
    return (ycc @ RGB_FROM_YCBCR.T.astype(ycc.dtype)).astype(ycc.dtype, copy=False)
