"""Evaluating the Laplacian BTF at arbitrary points and directions (seed 001, §3.4, Eq. 7).

    f(p, wi, wo) = sum_{k = floor(lambda)}^{lambda_max} w_k D_k(p)^T E_k(T_pc) + mu'(wi, wo)
    w_k = clamp(1 - lambda + k, 0, 1)                                          (Eq. 7)

then YCbCr -> RGB. D_k(p) is the level-k PCA weight vector of the texel containing p (nearest
texel, consistent with the pyramid's nearest upsampling: the level-k texel of finest texel
(r, c) is (r >> k, c >> k)); E_k(T_pc) the eigen Laplacian BRDFs at the light-view index found
through the direction tables (nearest) or blended over neighbouring sampled pairs
(interpolated). The top-level mean mu' is evaluated analytically at the query directions
(the point of the seed's Phong fit, its Fig. 4) unless it is tabulated.

This is the function the renderer's `btf` mode calls; every query is independent, vectorized
over n queries (a loop over the L <= ~6 levels only).
"""

from __future__ import annotations

import numpy as np

from texelbake.btf.color import RGB_FROM_YCBCR
from texelbake.btf.compress import BTFMaps, mean_on_pairs
from texelbake.btf.lod import lod_weights
from texelbake.btf.lut import lookup_pairs
from texelbake.btf.phong import above_horizon
from texelbake.errors import NumericalError, ShapeError


def texel_of_uv(texel_uv: np.ndarray, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Finest-level (row, col) of texture coordinates, clamped to the map.

    texel_uv : (n, 2) float64 (u, v) in [0, 1]; row 0 is the top of the map (v = 1), as for
        every texelbake texture (model.Texture); u = 0 is column 0.
    returns : (rows (n,) int64, cols (n,) int64)
    """
    h, w = shape
    uv = np.asarray(texel_uv, dtype=np.float64)
    rows = np.clip(np.floor((1.0 - uv[:, 1]) * h), 0, h - 1).astype(np.int64)
    cols = np.clip(np.floor(uv[:, 0] * w), 0, w - 1).astype(np.int64)
    return rows, cols


def btf_lookup_texels(
    maps: BTFMaps,
    rows: np.ndarray,
    cols: np.ndarray,
    wi_local: np.ndarray,
    wo_local: np.ndarray,
    lod: np.ndarray,
    interpolate: bool = False,
    *,
    ycbcr: bool = False,
) -> np.ndarray:
    """`btf_lookup` on finest-level texel indices.

    rows, cols : (n,) int finest-level texel; wi_local, wo_local : (n, 3) float64 unit, texel
    frame; lod : (n,) float64 lambda (clamped to [0, lambda_max]); ycbcr : return YCbCr
    returns : (n, 3) float64 RGB (or YCbCr), 0 where a direction is at or below the horizon
    """
    wi = np.asarray(wi_local, dtype=np.float64)
    wo = np.asarray(wo_local, dtype=np.float64)
    rows = np.asarray(rows, dtype=np.int64)
    cols = np.asarray(cols, dtype=np.int64)
    n = rows.shape[0]
    lod = np.broadcast_to(np.asarray(lod, dtype=np.float64), (n,))
    if wi.shape != (n, 3) or wo.shape != (n, 3) or cols.shape != (n,):
        raise ShapeError(
            f"expected rows/cols (n,), wi/wo (n, 3) with n={n}; got cols {cols.shape}, "
            f"wi {wi.shape}, wo {wo.shape}"
        )
    if not (np.isfinite(wi).all() and np.isfinite(wo).all() and np.isfinite(lod).all()):
        raise NumericalError("btf_lookup: wi_local, wo_local and lod must be finite")
    h, w = maps.shape
    if n and (rows.min() < 0 or rows.max() >= h or cols.min() < 0 or cols.max() >= w):
        raise ShapeError(f"texel indices outside the {h} x {w} map")
    if n == 0:
        return np.zeros((0, 3))
    pair_cols, pair_w = lookup_pairs(maps.lut, wi, wo, interpolate=interpolate)  # (n, m)
    level_w = lod_weights(lod, maps.top_level)  # (n, L)
    slices = maps.channel_slices()
    out = np.zeros((n, 3))
    for k in range(maps.top_level + 1):
        active = level_w[:, k] > 0.0
        if not active.any():
            continue
        idx = np.nonzero(active)[0]
        d_k = maps.weights[k][rows[idx] >> k, cols[idx] >> k].astype(np.float64)  # (a, C)
        e_k = np.einsum(
            "am,amc->ac", pair_w[idx], maps.eigen[k][pair_cols[idx]].astype(np.float64)
        )  # (a, C)
        prod = d_k * e_k
        for c, sl in enumerate(slices):
            out[idx, c] += level_w[idx, k] * prod[:, sl].sum(axis=1)
    out += mean_on_pairs(
        maps.mean_models, maps.mean_params, maps.mean_table, wi, wo, pair_cols, pair_w
    )
    out[~above_horizon(wi, wo)] = 0.0
    return out if ycbcr else out @ RGB_FROM_YCBCR.T


def btf_lookup(
    maps: BTFMaps,
    texel_uv: np.ndarray,
    wi_local: np.ndarray,
    wo_local: np.ndarray,
    lod: np.ndarray,
    interpolate: bool = False,
) -> np.ndarray:
    """Eq. 7 with continuous LOD at n independent queries.

    maps : BTFMaps (built, or read back with `read_btf_maps`)
    texel_uv : (n, 2) float64 (u, v) in [0, 1], row 0 of the map at v = 1 (clamped)
    wi_local, wo_local : (n, 3) float64 unit light / view directions in the texel frame
    lod : (n,) float64 lambda = min(lambda_max, max(log2 footprint, 0)) (see
        `compress.lod_from_distance`); clamped to [0, lambda_max]
    interpolate : False = nearest sampled pair through the tables (the seed); True = blend of
        up to 3 x 3 neighbouring sampled pairs (continuous in the directions)
    returns : (n, 3) float64 linear RGB; 0 where a direction is at or below the horizon
    """
    uv = np.asarray(texel_uv, dtype=np.float64)
    if uv.ndim != 2 or uv.shape[1] != 2:
        raise ShapeError(f"texel_uv must be (n, 2), got {uv.shape}")
    if not np.isfinite(uv).all():
        raise NumericalError("btf_lookup: texel_uv must be finite")
    rows, cols = texel_of_uv(uv, maps.shape)
    return btf_lookup_texels(maps, rows, cols, wi_local, wo_local, lod, interpolate)
