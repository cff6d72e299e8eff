"""The cellular (Worley, cloisonné-like) multi-material shader."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from texelbake.brdf.analytic import ggx_conductor, lambert
from texelbake.brdf.common import CELLULAR_DEFAULTS, CHUNK, as_color, as_dirs, as_scalar, as_uv
from texelbake.errors import SettingsError, ShapeError
from texelbake.tol import TOL

_M1 = np.uint64(0x9E3779B97F4A7C15)
_M2 = np.uint64(0xC2B2AE3D27D4EB4F)
_M3 = np.uint64(0x165667B19E3779F9)
_S1 = np.uint64(0xBF58476D1CE4E5B9)
_S2 = np.uint64(0x94D049BB133111EB)


def _hash_u64(ix: np.ndarray, iy: np.ndarray, seed: np.ndarray, salt: int) -> np.ndarray:
    """Deterministic 64-bit hash per integer cell (splitmix64 finaliser over the cell
    coordinates, the seed and a salt). int64 arrays of broadcastable shapes -> uint64."""
    x = np.atleast_1d(np.asarray(ix, dtype=np.int64)).view(np.uint64) * _M1
    x ^= np.atleast_1d(np.asarray(iy, dtype=np.int64)).view(np.uint64) * _M2
    sd = np.atleast_1d(np.asarray(seed, dtype=np.int64)).view(np.uint64)
    x ^= (sd + np.uint64(salt)) * _M3
    x ^= x >> np.uint64(30)
    x *= _S1
    x ^= x >> np.uint64(27)
    x *= _S2
    x ^= x >> np.uint64(31)
    return x


def _hash_cells(ix: np.ndarray, iy: np.ndarray, seed: np.ndarray, salt: int) -> np.ndarray:
    """Uniform [0, 1) float64 per integer cell (top 53 bits of ``_hash_u64``)."""
    return (_hash_u64(ix, iy, seed, salt) >> np.uint64(11)).astype(np.float64) * 2.0**-53


def _feature_offsets(ix: np.ndarray, iy: np.ndarray, seed: np.ndarray) -> tuple[np.ndarray, ...]:
    """The Worley feature point of each cell relative to its corner: (u, v) in [0, 1)^2, the
    high and low 32 bits of one hash (one hash per cell instead of two). float64 arrays."""
    h = _hash_u64(ix, iy, seed, 0)
    u = (h >> np.uint64(32)).astype(np.float64) * 2.0**-32
    v = (h & np.uint64(0xFFFFFFFF)).astype(np.float64) * 2.0**-32
    return u, v


def _feature_points(ix: np.ndarray, iy: np.ndarray, seed: np.ndarray) -> tuple[np.ndarray, ...]:
    """Absolute feature points (ix + u, iy + v) of cells, float64 arrays."""
    u, v = _feature_offsets(ix, iy, seed)
    return u + ix, v + iy


_NEIGHBOURS = np.array([(dx, dy) for dy in (-1, 0, 1) for dx in (-1, 0, 1)], dtype=np.int64)


def worley(points: Any, seed: Any = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Worley (1996) cellular noise with one feature point per unit cell.

    Each integer cell (i, j) holds the feature point (i, j) + (u, v), (u, v) from a seeded hash;
    each query checks its own and the 8 neighbouring cells (a loop over the 9 offsets, each
    vectorized over all queries, keeping running nearest / second-nearest distances).
    3 x 3 cells give F1 exactly and F2 in all but rare configurations (a feature point two cells
    away can be nearer than the 3 x 3 second-nearest) — the usual Worley trade-off.

    points : (n, 2) float64 (uv * cellScale); seed : () or (n,) int
    returns : f1 (n,) float64, f2 (n,) float64 (nearest and second-nearest feature distances),
        cell (n, 2) int64 (the cell of the nearest feature point). Non-finite points get
        f1 = f2 = NaN and cell (0, 0).
    """
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 2:
        raise ShapeError(f"points must be (n, 2), got {pts.shape}")
    n = pts.shape[0]
    seed_a = np.asarray(seed, dtype=np.int64)
    if seed_a.ndim > 1 or (seed_a.ndim == 1 and seed_a.shape[0] not in (1, n)):
        raise ShapeError(f"seed must be () or ({n},), got {seed_a.shape}")
    f1 = np.empty(n)
    f2 = np.empty(n)
    cell = np.empty((n, 2), dtype=np.int64)
    finite: np.ndarray = np.all(np.isfinite(pts), axis=1)
    for lo in range(0, n, CHUNK):
        hi = min(lo + CHUNK, n)
        p = np.where(finite[lo:hi, None], pts[lo:hi], 0.0)
        base = np.floor(p).astype(np.int64)  # (b, 2)
        frac = p - base  # (b, 2) position inside the own cell
        sd = seed_a.reshape(1) if seed_a.size == 1 else seed_a[lo:hi]  # (b|1,)
        d1 = np.full(hi - lo, np.inf)  # running nearest / second-nearest squared distances
        d2 = np.full(hi - lo, np.inf)
        arg = np.zeros(hi - lo, dtype=np.int64)
        for k, (ox, oy) in enumerate(_NEIGHBOURS):  # the 3 x 3 cells, vectorized over b
            fx, fy = _feature_offsets(base[:, 0] + ox, base[:, 1] + oy, sd)
            fx += ox - frac[:, 0]  # feature - query, relative to the own cell: no large
            fy += oy - frac[:, 1]  # coordinates, so no cancellation far from the origin
            dk = fx * fx
            dk += fy * fy
            nearer = dk < d1
            np.minimum(d2, np.where(nearer, d1, dk), out=d2)
            np.copyto(d1, dk, where=nearer)
            np.copyto(arg, k, where=nearer)
        f1[lo:hi] = np.sqrt(d1)
        f2[lo:hi] = np.sqrt(d2)
        cell[lo:hi] = base + _NEIGHBOURS[arg]
    f1[~finite] = np.nan
    f2[~finite] = np.nan
    cell[~finite] = 0
    return f1, f2, cell


def cellular_params(params: Mapping[str, Any], n: int) -> dict[str, np.ndarray]:
    unknown = set(params) - set(CELLULAR_DEFAULTS)
    if unknown:
        raise SettingsError(
            f"unknown cellular inputs {sorted(unknown)}; expected {sorted(CELLULAR_DEFAULTS)}"
        )
    get = {**CELLULAR_DEFAULTS, **params}
    p = {k: as_color(get[k], n, k) for k in ("borderColor", "cellColorA", "cellColorB")}
    for k in ("cellScale", "borderWidth", "borderRoughness"):
        p[k] = as_scalar(get[k], n, k)
    seed = np.asarray(get["seed"])
    if not np.issubdtype(seed.dtype, np.integer) and not np.all(seed == np.round(seed)):
        raise SettingsError(f"cellular seed must be an integer, got {get['seed']!r}")
    p["seed"] = as_scalar(seed, n, "seed").astype(np.int64)
    if np.any(p["cellScale"] <= 0):
        raise SettingsError(f"cellScale must be > 0, got min {p['cellScale'].min()}")
    return p




def _cells(p: Mapping[str, np.ndarray], uv: np.ndarray) -> tuple[np.ndarray, ...]:
    seed = p["seed"] if p["seed"].shape[0] > 1 else p["seed"][0]
    return worley(uv * p["cellScale"][:, None], seed)


def cellular_mask(params: Mapping[str, Any], uv: Any) -> np.ndarray:
    """(n,) bool: True on cell borders, F2 - F1 < borderWidth (distances in cell units).

    params : cellular inputs (``CELLULAR_DEFAULTS``); uv : (n, 2) float64
    """
    uv = as_uv(uv)
    p = cellular_params(params, uv.shape[0])
    f1, f2, _ = _cells(p, uv)
    return (f2 - f1) < p["borderWidth"]


def cellular_cell_id(params: Mapping[str, Any], uv: Any) -> np.ndarray:
    """(n,) int64 id of the cell (nearest feature point) under each uv: the cell's integer
    coordinates (i, j) packed as (i mod 2^32) * 2^32 + (j mod 2^32)."""
    uv = as_uv(uv)
    p = cellular_params(params, uv.shape[0])
    _, _, cell = _cells(p, uv)
    return _pack_cell(cell)


def _pack_cell(cell: np.ndarray) -> np.ndarray:
    u = cell.astype(np.int64).view(np.uint64) & np.uint64(0xFFFFFFFF)
    return ((u[:, 0] << np.uint64(32)) | u[:, 1]).view(np.int64)


def _cell_color(p: Mapping[str, np.ndarray], cell: np.ndarray) -> np.ndarray:
    seed = np.broadcast_to(p["seed"], cell.shape[:1])
    t = _hash_cells(cell[:, 0], cell[:, 1], seed, 2)[:, None]
    return p["cellColorA"] + t * (p["cellColorB"] - p["cellColorA"])


def cellular_color(params: Mapping[str, Any], uv: Any) -> np.ndarray:
    """(n, 3) float64 Lambertian albedo of the cell under each uv: cellColorA + t (cellColorB -
    cellColorA) with t in [0, 1) a seeded hash of the cell, so neighbouring cells differ."""
    uv = as_uv(uv)
    p = cellular_params(params, uv.shape[0])
    _, _, cell = _cells(p, uv)
    return _cell_color(p, cell)


def cellular_split(
    p: Mapping[str, np.ndarray], uv: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-uv part of the cellular shader: border (m,) bool, cell colour (m, 3), finite (m,)."""
    f1, f2, cell = _cells(p, uv)
    finite = ~np.isnan(f1)
    return (f2 - f1) < p["borderWidth"], _cell_color(p, cell), finite


def cellular_shade(
    border: np.ndarray,
    color: np.ndarray,
    finite: np.ndarray,
    border_color: np.ndarray,
    border_roughness: np.ndarray,
    wi: np.ndarray,
    wo: np.ndarray,
    eps: float,
) -> np.ndarray:
    """Per-row shading: border (n,) bool, color (n, 3), finite (n,), border_color (1|n, 3),
    border_roughness (1|n,), wi/wo (n, 3) -> (n, 3)."""
    out = lambert(color, wi, wo, eps=eps)
    out[~finite] = 0.0  # non-finite uv: no defined cell, no reflectance
    if np.any(border):
        sel = np.flatnonzero(border)
        bc = border_color if border_color.shape[0] == 1 else border_color[sel]
        br = border_roughness if border_roughness.shape[0] == 1 else border_roughness[sel]
        out[sel] = ggx_conductor(bc, br, wi[sel], wo[sel], eps=eps)
    return out


def cellular(
    params: Mapping[str, Any], uv: Any, wi: Any, wo: Any, *, eps: float = TOL.grazing_cos
) -> np.ndarray:
    """The cloisonne-like procedural shader of seed 000, Sec. 5 (Fig. 7): a cellular texture
    (Worley 1996) over uv * cellScale; inside a cell a Lambertian BRDF with the cell's colour
    (:func:`cellular_color`); on the borders (:func:`cellular_mask`) a sharp metallic GGX lobe
    (:func:`ggx_conductor` with F0 = borderColor, roughness = borderRoughness) standing in for the
    seed's measured gold-metallic-paint BRDF.

    params : cellular inputs; uv : (n, 2) float64; wi, wo : (n, 3) float64
    returns : (n, 3) float64 (0 where uv is not finite)
    """
    wi, wo = as_dirs(wi, wo)
    uv = as_uv(uv)
    n = wi.shape[0]
    if uv.shape[0] != n:
        raise ShapeError(f"uv must be ({n}, 2) to match wi, got {uv.shape}")
    p = cellular_params(params, n)
    border, color, finite = cellular_split(p, uv)
    return cellular_shade(
        border, color, finite, p["borderColor"], p["borderRoughness"], wi, wo, eps
    )
