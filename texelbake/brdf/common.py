"""Shared by the BRDF modules: constants, the defaults of texelbake's shader ids, and the
coercion of direction and parameter arrays (conventions in `texelbake.brdf`)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from texelbake.errors import ShapeError

INV_PI = 1.0 / np.pi

#: rows per block in the chunked kernels (temporaries of a block stay in L2 cache)
CHUNK = 1 << 15

#: UsdPreviewSurface: the Hydra Storm reference shader clamps roughness to at least 0.001
#: (previewSurface.glslfx, ``evaluateLight``), so alpha = roughness**2 >= 1e-6.
PREVIEW_MIN_ROUGHNESS = 1e-3

#: defaults of texelbake's own shader ids (the UsdPreviewSurface ones are model.PREVIEW_DEFAULTS)
LAMBERT_DEFAULTS: Mapping[str, Any] = {"diffuseColor": (0.18, 0.18, 0.18)}

PHONG_DEFAULTS: Mapping[str, Any] = {
    "diffuseColor": (0.18, 0.18, 0.18),
    "specularColor": (0.0, 0.0, 0.0),
    "exponent": 32.0,
}
CELLULAR_DEFAULTS: Mapping[str, Any] = {
    "cellScale": 8.0,
    "seed": 0,
    "borderWidth": 0.08,
    "borderColor": (1.0, 0.78, 0.34),  # a gold F0
    "borderRoughness": 0.25,
    "cellColorA": (0.70, 0.08, 0.06),
    "cellColorB": (0.05, 0.20, 0.65),
}
MERL_DEFAULTS: Mapping[str, Any] = {"scale": 1.0}


def as_dirs(wi: Any, wo: Any) -> tuple[np.ndarray, np.ndarray]:
    wi = np.asarray(wi, dtype=np.float64)
    wo = np.asarray(wo, dtype=np.float64)
    if wi.ndim != 2 or wi.shape[1] != 3:
        raise ShapeError(f"wi must be (n, 3) float64, got shape {wi.shape}")
    if wo.shape != wi.shape:
        raise ShapeError(f"wo must match wi {wi.shape}, got shape {wo.shape}")
    return wi, wo


def as_color(x: Any, n: int, name: str) -> np.ndarray:
    """(1, 3) or (n, 3) float64 from a scalar, (3,), (1, 3) or (n, 3) input."""
    a = np.asarray(x, dtype=np.float64)
    if a.ndim == 0:
        a = np.full((1, 3), float(a))
    elif a.ndim == 1 and a.shape[0] == 3:
        a = a[None, :]
    elif a.ndim == 1 and a.shape[0] == n:  # a grey value per element
        a = np.repeat(a[:, None], 3, axis=1)
    if a.ndim != 2 or a.shape[1] != 3 or a.shape[0] not in (1, n):
        raise ShapeError(f"colour input {name!r} must be (3,), (1, 3) or ({n}, 3), got {a.shape}")
    return a


def as_scalar(x: Any, n: int, name: str) -> np.ndarray:
    """(1,) or (n,) float64 from a scalar, (1,) or (n,) input."""
    a = np.asarray(x, dtype=np.float64)
    if a.ndim == 0:
        a = a[None]
    if a.ndim == 2 and a.shape[1] == 1:
        a = a[:, 0]
    if a.ndim != 1 or a.shape[0] not in (1, n):
        raise ShapeError(f"scalar input {name!r} must be (), (1,) or ({n},), got {a.shape}")
    return a


def row_block(a: np.ndarray, lo: int, hi: int) -> np.ndarray:
    return a if a.shape[0] == 1 else a[lo:hi]


def valid_pairs(wi: np.ndarray, wo: np.ndarray, eps: float) -> np.ndarray:
    """(n,) bool: both directions above the horizon and finite."""
    ok = (wi[:, 2] > eps) & (wo[:, 2] > eps)
    s = wi[:, 0] + wi[:, 1]  # column sums: ~5x faster than .sum(axis=1) on (n, 3)
    s += wi[:, 2]
    s += wo[:, 0]
    s += wo[:, 1]
    s += wo[:, 2]
    ok &= np.isfinite(s)
    return ok


def as_uv(uv: Any) -> np.ndarray:
    a = np.asarray(uv, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 2:
        raise ShapeError(f"uv must be (n, 2) float64, got shape {a.shape}")
    return a
