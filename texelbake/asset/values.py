"""Small helpers of ingest: USD values to Python/numpy, warnings, the sRGB decode, the
warning class of recoverable asset problems."""

from __future__ import annotations

import warnings
from typing import Any

import numpy as np

from texelbake.errors import AssetWarning


def first_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split())
    return text[:300]


def warn(warns: list[str], message: str) -> None:
    warns.append(message)
    warnings.warn(message, AssetWarning, stacklevel=3)


def usd_matrix(gf_matrix: Any) -> np.ndarray:
    """Gf.Matrix4d -> (4, 4) float64, USD row-vector convention."""
    return np.array(gf_matrix, dtype=np.float64).reshape(4, 4)


def _to_python(value: Any) -> Any:
    """A USD attribute value -> float / int / str / bool / (k,) float64 array."""
    from pxr import Sdf

    if value is None:
        return None
    if isinstance(value, Sdf.AssetPath):
        return value.resolvedPath or value.path
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return float(value)
    if isinstance(value, str):
        return str(value)
    try:
        arr = np.array(value, dtype=np.float64)
    except (TypeError, ValueError):
        return str(value)
    return arr


def coerce_like(value: Any, default: Any) -> Any:
    """Shape an authored value like its default (colours as (3,) float64 arrays)."""
    value = _to_python(value)
    if isinstance(default, tuple):
        arr = np.asarray(value, dtype=np.float64).reshape(-1)
        if arr.shape[0] == 1:
            arr = np.repeat(arr, len(default))
        return arr
    if isinstance(default, bool):
        return bool(value)
    if isinstance(default, int) and not isinstance(value, str):
        return int(np.asarray(value).reshape(-1)[0])
    if isinstance(default, float) and not isinstance(value, str):
        return float(np.asarray(value).reshape(-1)[0])
    return value


def default_param(default: Any) -> Any:
    return np.asarray(default, dtype=np.float64) if isinstance(default, tuple) else default


