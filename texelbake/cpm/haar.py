"""2-D Haar compression of square maps, with point evaluation (seed 000, §3.4).

The seed stores the visible projected area a_vis on a cube map and compresses "each face of the
cube-map using Haar wavelets", keeping 4-6.5 % of the original size, and picks Haar for "rapid
signal reconstruction". This module holds that compression, independent of what the maps mean.

Transform: PyWavelets `wavedec2(x, "haar", mode="periodization")` at full depth
(J = log2(res) levels, so the approximation is a single coefficient). PyWavelets' Haar filters are
orthonormal (1/sqrt 2), so every coefficient c multiplies a basis function of unit L2 norm and
|c| *is* the L2 norm of its contribution: keeping the largest |c| per map is the L2-optimal
choice for the given count (Parseval).

Storage (`HaarCoeffs`): CSR over maps. `indices` are flat positions in the res x res Mallat layout
of `pywt.coeffs_to_array` (approximation at [0, 0]; for a subband of size s the horizontal detail
'da' at rows [s, 2s) x cols [0, s), the vertical detail 'ad' at rows [0, s) x cols [s, 2s), the
diagonal 'dd' at [s, 2s) x [s, 2s)), sorted within each map; exact zeros are not stored.

Point evaluation (`eval_haar_point`) is hand-written because PyWavelets only offers full
inverses: the value at pixel (iv, iu) is the approximation / res plus, for every support size
S = 2, 4, ..., res, the three detail coefficients of the block containing the pixel times
(sign_row, sign_col, sign_row * sign_col) / S, where sign = +1 in the first half of the block and -1
in the second (PyWavelets' Haar detail is (x[2k] - x[2k+1]) / sqrt 2). That is 3J + 1 = O(log res)
look-ups per point, vectorized over all query points; no inverse transform.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pywt

from texelbake.arrays import concat_ranges
from texelbake.errors import NumericalError, SettingsError, ShapeError

_WAVELET = "haar"
_MODE = "periodization"


@dataclass(frozen=True)
class HaarCoeffs:
    """Sparse Haar coefficients of a batch of res x res maps (CSR over maps).

    res : side of every map (a power of two)
    batch_shape : leading shape of the maps that were compressed, e.g. (n_texels, 6)
    offsets : (n_maps + 1,) int64, map i owns entries offsets[i]:offsets[i+1]
    indices : (nnz,) int32, flat index into the res x res Mallat coefficient layout,
        ascending within each map
    values : (nnz,) float32 (or the dtype asked for), the kept coefficients
    """

    res: int
    batch_shape: tuple[int, ...]
    offsets: np.ndarray
    indices: np.ndarray
    values: np.ndarray

    @property
    def n_maps(self) -> int:
        return int(self.offsets.shape[0] - 1)

    @property
    def nnz(self) -> int:
        return int(self.values.shape[0])

    @property
    def kept_fraction(self) -> float:
        """Stored coefficients / dense map entries (the seed's "% of the original space" if an
        index costs no space; with a 16-bit index and a 32-bit value multiply by 1.5)."""
        total = self.n_maps * self.res * self.res
        return float(self.nnz / total) if total else 0.0


def map_range(coeffs: HaarCoeffs, start: int, stop: int, batch_shape: tuple[int, ...]
              ) -> HaarCoeffs:
    """The maps start..stop-1 of `coeffs` (a CSR slice: no copy of the values), shaped
    `batch_shape` (its product: stop - start)."""
    o = coeffs.offsets[start:stop + 1]
    if int(np.prod(batch_shape)) != stop - start or o.shape[0] != stop - start + 1:
        raise ShapeError(f"maps {start}..{stop} of {coeffs.n_maps} as {batch_shape}")
    return HaarCoeffs(coeffs.res, batch_shape, o - o[0], coeffs.indices[o[0]:o[-1]],
                      coeffs.values[o[0]:o[-1]])


def _check_res(res: int, field: str = "res") -> int:
    res_i = int(res)
    if res_i != res or res_i < 1 or (res_i & (res_i - 1)) != 0:
        raise SettingsError(f"{field} must be a positive power of two for a full-depth Haar "
                            f"transform, got {res!r}")
    return res_i


def _mallat_to_list(dense: np.ndarray) -> list:
    """(n, res, res) Mallat layout -> the wavedec2 list [cA, (cH, cV, cD) coarse ... fine]."""
    res = dense.shape[-1]
    out: list = [dense[:, :1, :1]]
    s = 1
    while s < res:
        out.append((dense[:, s:2 * s, :s], dense[:, :s, s:2 * s], dense[:, s:2 * s, s:2 * s]))
        s *= 2
    return out


def compress_haar(face_maps: np.ndarray, keep_fraction: float, *,
                  dtype: type = np.float32) -> HaarCoeffs:
    """Full-depth 2-D Haar transform of every map, keeping its largest coefficients.

    face_maps : (..., res, res) float, res a power of two; every leading index is one map
        (e.g. (n_texels, 6, res, res): one map per cube face per texel)
    keep_fraction : in (0, 1]; each map keeps K = max(1, ceil(keep_fraction * res^2)) coefficients
        of largest magnitude (ties broken by position, so reruns are identical); exact zeros
        among them are dropped
    dtype : storage dtype of the values (float32 by default, DESIGN.md "float32 for storage")
    returns : HaarCoeffs
    """
    maps = np.asarray(face_maps, dtype=np.float64)
    if maps.ndim < 2 or maps.shape[-1] != maps.shape[-2]:
        raise ShapeError(f"face_maps must be (..., res, res), got {maps.shape}")
    res = _check_res(maps.shape[-1], "face_maps.shape[-1]")
    keep = float(keep_fraction)
    if not (0.0 < keep <= 1.0):
        raise SettingsError(f"keep_fraction must be in (0, 1], got {keep_fraction!r}")
    if not np.all(np.isfinite(maps)):
        raise NumericalError("face_maps contains NaN or Inf; Haar compression needs finite maps")
    batch_shape = tuple(int(s) for s in maps.shape[:-2])
    flat_maps = maps.reshape(-1, res, res)  # (n_maps, res, res)
    n_maps = flat_maps.shape[0]
    n_coef = res * res
    if n_maps == 0:
        return HaarCoeffs(res, batch_shape, np.zeros(1, np.int64), np.zeros(0, np.int32),
                          np.zeros(0, dtype))
    levels = int(round(math.log2(res)))
    coeffs = pywt.wavedec2(flat_maps, _WAVELET, mode=_MODE, level=levels, axes=(-2, -1))
    arr, _ = pywt.coeffs_to_array(coeffs, axes=(-2, -1))  # (n_maps, res, res)
    arr = arr.reshape(n_maps, n_coef)
    k = min(n_coef, max(1, math.ceil(keep * n_coef)))
    order = np.argsort(-np.abs(arr), axis=1, kind="stable")[:, :k]  # (n_maps, k)
    order.sort(axis=1)
    vals = np.take_along_axis(arr, order, axis=1)  # (n_maps, k)
    nonzero = vals != 0.0
    counts = nonzero.sum(axis=1)
    offsets = np.zeros(n_maps + 1, dtype=np.int64)
    np.cumsum(counts, out=offsets[1:])
    return HaarCoeffs(res, batch_shape, offsets, order[nonzero].astype(np.int32),
                      vals[nonzero].astype(dtype))


def _dense_coeffs(coeffs: HaarCoeffs) -> np.ndarray:
    """(n_maps, res * res) float64 coefficient arrays with the dropped entries zero."""
    n_coef = coeffs.res * coeffs.res
    dense = np.zeros((coeffs.n_maps, n_coef), dtype=np.float64)
    map_of = np.repeat(np.arange(coeffs.n_maps), np.diff(coeffs.offsets))
    dense[map_of, coeffs.indices] = coeffs.values.astype(np.float64)
    return dense


def decompress_haar(coeffs: HaarCoeffs) -> np.ndarray:
    """Full inverse transform (reference for tests and for re-coarsening; not for rendering).

    returns : (*batch_shape, res, res) float64
    """
    res = coeffs.res
    dense = _dense_coeffs(coeffs).reshape(-1, res, res)
    if dense.shape[0] == 0:
        return np.zeros((*coeffs.batch_shape, res, res), dtype=np.float64)
    if res == 1:
        return dense.reshape(*coeffs.batch_shape, 1, 1)
    rec = pywt.waverec2(_mallat_to_list(dense), _WAVELET, mode=_MODE, axes=(-2, -1))
    return rec.reshape(*coeffs.batch_shape, res, res)


def haar_point_terms(res: int, iu: np.ndarray, iv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The 3J + 1 coefficients whose support contains each pixel, and their basis values.

    res : map side, a power of two
    iu, iv : (n,) int, column and row of the pixel in the map ([row=iv, col=iu])
    returns : (flat_index (n, 3J + 1) int64 into the Mallat layout,
               basis_value (n, 3J + 1) float64)
    """
    res = _check_res(res)
    iu = np.asarray(iu, dtype=np.int64)
    iv = np.asarray(iv, dtype=np.int64)
    levels = int(round(math.log2(res)))
    idx = [np.zeros_like(iu)]
    val = [np.full(iu.shape, 1.0 / res)]
    for j in range(1, levels + 1):  # loop over log2(res) levels, vectorized over points
        size = 1 << j          # support side S
        s = res // size        # subband side
        rr, cc = iv // size, iu // size
        sr = np.where((iv % size) < size // 2, 1.0, -1.0)
        sc = np.where((iu % size) < size // 2, 1.0, -1.0)
        idx += [(s + rr) * res + cc, rr * res + (s + cc), (s + rr) * res + (s + cc)]
        val += [sr / size, sc / size, sr * sc / size]
    return np.stack(idx, axis=-1), np.stack(val, axis=-1)


def eval_haar_point(coeffs: HaarCoeffs, map_index: np.ndarray, iu: np.ndarray,
                    iv: np.ndarray, *, dense_limit: int = 1 << 20) -> np.ndarray:
    """Reconstruct single pixels from the sparse coefficients (no inverse transform).

    coeffs : HaarCoeffs
    map_index : (n,) int, flat index into batch_shape (for (n_texels, 6): texel * 6 + face)
    iu, iv : (n,) int in [0, res), column and row of the pixel
    dense_limit : tables with at most this many dense coefficients (n_maps * res^2) are
        gathered from a dense coefficient array of the whole table; larger ones from the maps
        the pixels read, scattered dense at most this many entries at a time; both give the
        same values
    returns : (n,) float64, equal to decompress_haar(coeffs) at those pixels up to rounding
    """
    map_index = np.asarray(map_index, dtype=np.int64).ravel()
    iu = np.asarray(iu, dtype=np.int64).ravel()
    iv = np.asarray(iv, dtype=np.int64).ravel()
    if not (map_index.shape == iu.shape == iv.shape):
        raise ShapeError(f"map_index, iu, iv must have one shape, got {map_index.shape}, "
                         f"{iu.shape}, {iv.shape}")
    if map_index.size == 0:
        return np.zeros(0, dtype=np.float64)
    res = coeffs.res
    if map_index.min() < 0 or map_index.max() >= coeffs.n_maps:
        raise ShapeError(f"map_index must be in [0, {coeffs.n_maps}), got range "
                         f"[{map_index.min()}, {map_index.max()}]")
    for name, a in (("iu", iu), ("iv", iv)):
        if a.min() < 0 or a.max() >= res:
            raise ShapeError(f"{name} must be in [0, {res}), got [{a.min()}, {a.max()}]")
    n_coef = res * res
    if coeffs.nnz == 0:
        return np.zeros(map_index.shape, dtype=np.float64)
    flat_idx, basis = haar_point_terms(res, iu, iv)  # (n, 3J+1)
    query = map_index[:, None] * n_coef + flat_idx
    if coeffs.n_maps * n_coef <= dense_limit:
        # small tables: gather from the dense coefficient array (same values, ~3x faster)
        vals = _dense_coeffs(coeffs).ravel()[query]
        return np.sum(vals * basis, axis=1)
    vals = _gather_read_maps(coeffs, map_index, flat_idx, dense_limit)
    return np.sum(vals * basis, axis=1)


def _gather_read_maps(coeffs: HaarCoeffs, map_index: np.ndarray, flat_idx: np.ndarray,
                      limit: int) -> np.ndarray:
    """(n, k) float64 the coefficients `flat_idx` (n, k) of the maps `map_index` (n,), 0 where
    not kept: the distinct maps read, in blocks of at most `limit` dense entries, each block's
    CSR entries scattered into a zero (maps, res²) array and gathered from it (a pixel reads a
    few maps of a large table: no search of the whole table's keys)."""
    n_coef = coeffs.res * coeffs.res
    maps, inv = np.unique(map_index, return_inverse=True)
    inv = inv.ravel()
    per = max(limit // n_coef, 1)
    out = np.empty(flat_idx.shape, dtype=np.float64)
    for b0 in range(0, maps.size, per):  # loop over blocks of maps (memory bound)
        block = maps[b0:b0 + per]
        start = coeffs.offsets[block]
        count = coeffs.offsets[block + 1] - start
        row = np.repeat(np.arange(block.size), count)
        src = concat_ranges(start, count)
        dense = np.zeros((block.size, n_coef))
        dense[row, coeffs.indices[src]] = coeffs.values[src]
        q = np.flatnonzero((inv >= b0) & (inv < b0 + block.size))
        out[q] = dense[(inv[q] - b0)[:, None], flat_idx[q]]
    return out


# --------------------------------------------------------------------------------------------
# budgeted selection across maps: one coefficient budget per batch of maps, spent
# where it lowers each group's *relative* error most evenly


def haar_coefficients(face_maps: np.ndarray) -> np.ndarray:
    """Full-depth orthonormal Haar coefficients of every map, Mallat layout.

    face_maps : (..., res, res) float, res a power of two
    returns : (..., res, res) float64 (approximation at [0, 0]; see the module docstring)
    """
    maps = np.asarray(face_maps, dtype=np.float64)
    if maps.ndim < 2 or maps.shape[-1] != maps.shape[-2]:
        raise ShapeError(f"face_maps must be (..., res, res), got {maps.shape}")
    res = _check_res(maps.shape[-1], "face_maps.shape[-1]")
    if not np.all(np.isfinite(maps)):
        raise NumericalError("face_maps contains NaN or Inf; Haar compression needs finite maps")
    flat = maps.reshape(-1, res, res)
    if flat.shape[0] == 0 or res == 1:
        return flat.reshape(maps.shape).copy()
    levels = int(round(math.log2(res)))
    coeffs = pywt.wavedec2(flat, _WAVELET, mode=_MODE, level=levels, axes=(-2, -1))
    arr, _ = pywt.coeffs_to_array(coeffs, axes=(-2, -1))
    return np.asarray(arr, np.float64).reshape(maps.shape)


def haar_support_mean(weight: np.ndarray) -> np.ndarray:
    """Mean of a per-pixel weight over the support of every Haar basis function (Mallat layout).

    A Haar function's square is constant on its support, so for a coefficient c the error of
    dropping it, measured with pixel weights w, is c^2 times this mean (cross terms aside).
    weight : (..., res, res) float; returns (..., res, res) float64
    """
    w = np.asarray(weight, dtype=np.float64)
    res = _check_res(w.shape[-1], "weight.shape[-1]")
    lead = w.shape[:-2]
    out = np.empty_like(w)
    out[..., 0, 0] = w.mean(axis=(-2, -1))
    s = 1
    while s < res:  # loop over log2(res) subbands, each vectorized over every map
        side = res // s  # support side of the subband's functions
        b = w.reshape(*lead, s, side, s, side).mean(axis=(-3, -1))
        out[..., s:2 * s, :s] = b
        out[..., :s, s:2 * s] = b
        out[..., s:2 * s, s:2 * s] = b
        s *= 2
    return out


def budget_mask(importance: np.ndarray, budget: int, *, steps: int = 64) -> np.ndarray:
    """Which coefficients to keep so that every group's relative residual is about equal.

    importance : (g, n) float >= 0, the error each coefficient would add if dropped, divided
        by its group's squared reference norm (a group: one texel's six faces)
    budget : total coefficients to keep (>= g; every group keeps at least its largest one)
    returns : (g, n) bool. Each group keeps its largest-importance coefficients until the sum
        of the dropped ones is at most tau, with one tau for all groups, the smallest whose
        count fits the budget (bisection on log tau). Equal residuals minimise the largest
        per-group error for the count (the per-texel bar is on the worst texel), unlike one
        magnitude threshold for all (which minimises the sum). Ties: lower index first.
    """
    imp = np.asarray(importance, dtype=np.float64)
    if imp.ndim != 2:
        raise ShapeError(f"importance must be (groups, coefficients), got {imp.shape}")
    g, n = imp.shape
    if g == 0 or n == 0:
        return np.zeros(imp.shape, bool)
    order = np.argsort(-imp, axis=1, kind="stable")
    srt = np.take_along_axis(imp, order, axis=1)
    # tail[:, i] = what is dropped when the first i are kept (i = 0..n-1); after all n: 0
    tail = np.cumsum(srt[:, ::-1], axis=1)[:, ::-1]
    nonzero = (srt > 0).sum(axis=1)

    def counts(tau: float) -> np.ndarray:
        return np.clip((tail > tau).sum(axis=1), 1, np.maximum(nonzero, 1))

    hi = float(tail[:, 0].max()) if tail.size else 0.0
    if counts(0.0).sum() <= budget or hi <= 0.0:
        cnt = counts(0.0)
    else:
        lo_l, hi_l = math.log(max(hi, 1e-300) * 1e-30), math.log(hi)
        for _ in range(steps):  # bisection on log tau, each step vectorized over all groups
            mid = 0.5 * (lo_l + hi_l)
            if counts(math.exp(mid)).sum() > budget:
                lo_l = mid
            else:
                hi_l = mid
        cnt = counts(math.exp(hi_l))
    keep_sorted = np.arange(n)[None, :] < cnt[:, None]
    mask = np.zeros((g, n), bool)
    np.put_along_axis(mask, order, keep_sorted, axis=1)
    return mask


def quantize_values(values: np.ndarray, scale: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """float16 storage of coefficients relative to a per-entry scale (float32).

    values : (k,) float; scale : (k,) float > 0 (the group's largest |c|, so |c/scale| <= 1
        and float16's 11-bit mantissa gives 5e-4 relative error per coefficient)
    returns : (q (k,) float16, dequantized (k,) float32 = float32(q) * scale), the second is
        exactly what `dequantize_values` returns from the stored pair
    """
    s = np.asarray(scale, np.float32)
    q = (np.asarray(values, np.float64) / s).astype(np.float16)
    return q, dequantize_values(q, s)


def dequantize_values(q: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """Inverse of `quantize_values` (float32)."""
    return np.asarray(q, np.float16).astype(np.float32) * np.asarray(scale, np.float32)


def coeffs_from_mask(coeffs: np.ndarray, mask: np.ndarray, values: np.ndarray | None = None
                     ) -> HaarCoeffs:
    """HaarCoeffs of the entries of `coeffs` (..., res, res) Mallat layout where `mask` holds;
    `values` (same shape, float32) replaces the stored values (e.g. dequantized ones). Exact
    zeros are not stored."""
    arr = np.asarray(coeffs, np.float64)
    res = _check_res(arr.shape[-1], "coeffs.shape[-1]")
    batch_shape = tuple(int(s) for s in arr.shape[:-2])
    vals_src = arr if values is None else np.asarray(values)
    flat = arr.reshape(-1, res * res)
    keep = np.asarray(mask, bool).reshape(flat.shape) & (flat != 0.0)
    counts = keep.sum(axis=1)
    offsets = np.zeros(flat.shape[0] + 1, dtype=np.int64)
    np.cumsum(counts, out=offsets[1:])
    rows, cols = np.nonzero(keep)  # row-major: ascending indices within each map
    vals = vals_src.reshape(flat.shape)[rows, cols].astype(np.float32)
    return HaarCoeffs(res, batch_shape, offsets, cols.astype(np.int32), vals)
