"""The apparent-reflectance matrix R of a texel, Eq. 7's filtered reflectance and its SNR
(seed 000, §3.2, Eqs. 3, 4, 7, 9) on plain arrays.

Notation (seed 000): a texel p owns m surface samples x_j of M_org with normals n_j and areas
dA_j (its g(p)). On d direction pairs (w_i, w_o) the apparent reflectance (Eq. 4) times the
sample area fills the matrix of Eq. 9,

    R[(i, o), j] = V(x_j, w_i) V(x_j, w_o) f_r(x_j, w_i, w_o) (n_j . w_i)+ (n_j . w_o)+ dA_j,

and the filtered reflectance is Eq. 7, f_bar(w_i, w_o) = (R 1)[(i, o)] / a_vis(w_o) with the visible
projected area a_vis(w_o) = sum_j V(x_j, w_o) (n_j . w_o)+ dA_j (Eq. 3, discretised on the same
samples and the same visibility, so a flat Lambertian texel reproduces its BRDF exactly:
R 1 / a_vis = (rho / pi) cos(theta_i) there, whatever the sample areas).

Rows follow `texelbake.geometry.directions.product_pairs`: row r = i * n_o + o on a product grid of n_i
light and n_o view directions. Arrays carry a trailing colour axis ch (1 or 3).

Limit a_vis -> 0 (grazing or fully masked view directions). In exact arithmetic f_bar stays
bounded there (it is an a_vis-weighted mean of V_i f_r cos_i), but both R 1 and any
approximation C alpha go to zero with a_vis, so their ratio is 0/0 in floating point and the
approximation error is amplified without bound. Such a row also carries no light to the
viewer: the texel's projected visible area is zero. Definition used everywhere in texelbake:
when a_vis(w_o) <= eps (eps = TOL.avis_floor * texel area by default), f_bar := 0 and the row
is *invalid*: excluded from every SNR and from the renderer's sum (its radiance contribution
is a_vis * f_bar <= eps * max(f_r cos_i), i.e. nothing).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np

from texelbake.errors import NumericalError, ShapeError
from texelbake.tol import TOL

BrdfFn = Callable[[np.ndarray, np.ndarray], np.ndarray]

# --------------------------------------------------------------------------- the matrix R


def _clamped_cos(name: str, cos: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    cos = np.asarray(cos, dtype=np.float64)
    if cos.shape != shape:
        raise ShapeError(f"{name} must be {shape}, got {cos.shape}")
    # below TOL.grazing_cos the direction counts as below the horizon (same rule as avis)
    return np.where(cos > TOL.grazing_cos, cos, 0.0)


def _check_vis(name: str, vis: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    vis = np.asarray(vis)
    if vis.shape != shape:
        raise ShapeError(f"{name} must be {shape}, got {vis.shape}")
    return vis.astype(bool)


def _check_area(area: np.ndarray) -> np.ndarray:
    area = np.asarray(area, dtype=np.float64)
    if area.ndim != 1:
        raise ShapeError(f"area must be (m,), got {area.shape}")
    if not np.all(np.isfinite(area)) or np.any(area < 0):
        raise NumericalError("area must be finite and >= 0 (sample areas dA_j)")
    return area


def reflectance_matrix(
    brdf_vals: np.ndarray | BrdfFn,
    vis_i: np.ndarray,
    vis_o: np.ndarray,
    cos_i: np.ndarray,
    cos_o: np.ndarray,
    area: np.ndarray,
    *,
    rows_per_chunk: int = 512,
) -> np.ndarray:
    """The matrix of seed 000 Eq. 9 on a product grid (separable visibility): Eq. 4 x dA.

    R[(i, o), j] = V(x_j, w_i) V(x_j, w_o) f_r(x_j, w_i, w_o) (n_j . w_i)+ (n_j . w_o)+ dA_j,
    row (i, o) = i * n_o + o. Visibility is separable on a product grid, so it costs
    m * (n_i + n_o) rays.

    brdf_vals : (n_i, n_o, m, ch) float, f_r in each sample's shading frame, or a callable
        brdf(row_i (b,) int64, row_o (b,) int64) -> (b, m, ch) float evaluated over chunks of
        rows_per_chunk rows (bounds memory to one chunk of BRDF values)
    vis_i : (m, n_i) bool, V(x_j, w_i); vis_o : (m, n_o) bool, V(x_j, w_o)
    cos_i : (m, n_i) float, n_j . w_i with the sample's shading normal (clamped again here: values
        <= TOL.grazing_cos count as 0); cos_o : (m, n_o) float, n_j . w_o
    area : (m,) float, dA_j >= 0
    returns : (n_i * n_o, m, ch) float64
    """
    area = _check_area(area)
    m = area.shape[0]
    vis_i = np.asarray(vis_i)
    vis_o = np.asarray(vis_o)
    if vis_i.ndim != 2 or vis_o.ndim != 2:
        raise ShapeError(
            f"vis_i, vis_o must be (m, n_i), (m, n_o); got {vis_i.shape}, {vis_o.shape}"
        )
    n_i, n_o = vis_i.shape[1], vis_o.shape[1]
    vis_i = _check_vis("vis_i", vis_i, (m, n_i))
    vis_o = _check_vis("vis_o", vis_o, (m, n_o))
    gi = (vis_i * _clamped_cos("cos_i", cos_i, (m, n_i))).T  # (n_i, m)
    go = (vis_o * _clamped_cos("cos_o", cos_o, (m, n_o)) * area[:, None]).T  # (n_o, m)
    d = n_i * n_o
    if callable(brdf_vals):
        row_i, row_o = np.repeat(np.arange(n_i), n_o), np.tile(np.arange(n_o), n_i)
        chunks = []
        step = max(int(rows_per_chunk), 1)
        for r0 in range(0, d, step):  # loop over row chunks (memory bound), not per row
            ri, ro = row_i[r0 : r0 + step], row_o[r0 : r0 + step]
            f = np.asarray(brdf_vals(ri, ro), dtype=np.float64)
            if f.ndim != 3 or f.shape[:2] != (ri.size, m):
                raise ShapeError(f"brdf callable must return ({ri.size}, {m}, ch), got {f.shape}")
            chunks.append(f * (gi[ri] * go[ro])[:, :, None])
        if not chunks:
            return np.zeros((0, m, 1), dtype=np.float64)
        return np.concatenate(chunks, axis=0)
    f = np.asarray(brdf_vals, dtype=np.float64)
    if f.ndim != 4 or f.shape[:3] != (n_i, n_o, m):
        raise ShapeError(f"brdf_vals must be ({n_i}, {n_o}, {m}, ch), got {f.shape}")
    R = f * (gi[:, None, :] * go[None, :, :])[:, :, :, None]  # (n_i, n_o, m, ch)
    return R.reshape(d, m, f.shape[3])


def reflectance_pairs(
    brdf_vals: np.ndarray,
    vis_i: np.ndarray,
    vis_o: np.ndarray,
    cos_i: np.ndarray,
    cos_o: np.ndarray,
    area: np.ndarray,
) -> np.ndarray:
    """Eq. 9's matrix on d arbitrary (paired, not product) direction pairs, e.g. held-out pairs.

    brdf_vals : (d, m, ch) float; vis_i, vis_o : (m, d) bool; cos_i, cos_o : (m, d) float;
    area : (m,) float
    returns : (d, m, ch) float64, R[r, j] = V_i V_o f_r cos_i+ cos_o+ dA_j for pair r
    """
    area = _check_area(area)
    m = area.shape[0]
    f = np.asarray(brdf_vals, dtype=np.float64)
    if f.ndim != 3 or f.shape[1] != m:
        raise ShapeError(f"brdf_vals must be (d, {m}, ch), got {f.shape}")
    d = f.shape[0]
    g = (
        _check_vis("vis_i", vis_i, (m, d))
        * _check_vis("vis_o", vis_o, (m, d))
        * _clamped_cos("cos_i", cos_i, (m, d))
        * _clamped_cos("cos_o", cos_o, (m, d))
        * area[:, None]
    ).T  # (d, m)
    return f * g[:, :, None]


def avis_on_grid(vis_o: np.ndarray, cos_o: np.ndarray, area: np.ndarray) -> np.ndarray:
    """Visible projected area a_vis(w_o) = sum_j V(x_j, w_o) (n_j . w_o)+ dA_j (seed 000 Eq. 3).

    Same samples, visibility and cosine clamp as `reflectance_matrix`, so Eq. 7 is exact for a
    flat Lambertian texel.

    vis_o : (m, n_o) bool; cos_o : (m, n_o) float; area : (m,) float
    returns : (n_o,) float64 (index a row r of R with row_o = r % n_o)
    """
    area = _check_area(area)
    m = area.shape[0]
    vis_o = np.asarray(vis_o)
    if vis_o.ndim != 2:
        raise ShapeError(f"vis_o must be (m, n_o), got {vis_o.shape}")
    n_o = vis_o.shape[1]
    vis_o = _check_vis("vis_o", vis_o, (m, n_o))
    return np.einsum("jo,j->o", vis_o * _clamped_cos("cos_o", cos_o, (m, n_o)), area)


def avis_floor(texel_area: float) -> float:
    """Absolute a_vis floor eps = TOL.avis_floor * texel_area (texel_area = sum of dA_j)."""
    return TOL.avis_floor * float(texel_area)


def filtered_reflectance(
    R_times_weights: np.ndarray, avis_rows: np.ndarray, eps: float
) -> tuple[np.ndarray, np.ndarray]:
    """Eq. 7: f_bar = (R w) / a_vis row by row, with the defined limit at a_vis -> 0.

    R_times_weights : (d, ch) or (d,) float, R 1 (reference) or C alpha (approximation)
    avis_rows : (d,) float, a_vis(w_o) of each row (avis_on_grid(...)[row_o])
    eps : absolute floor (see `avis_floor`); rows with a_vis <= eps get f_bar = 0, valid False
    returns : (f_bar same shape as R_times_weights, float64; valid (d,) bool)
    """
    rw = np.asarray(R_times_weights, dtype=np.float64)
    avis_rows = np.asarray(avis_rows, dtype=np.float64).ravel()
    if rw.shape[0] != avis_rows.shape[0] or rw.ndim not in (1, 2):
        raise ShapeError(
            f"R_times_weights (d, ch) and avis_rows (d,) disagree: {rw.shape}, {avis_rows.shape}"
        )
    valid = np.isfinite(avis_rows) & (avis_rows > float(eps))
    denom = np.where(valid, avis_rows, 1.0)
    fbar = rw / (denom[:, None] if rw.ndim == 2 else denom)
    fbar[~valid] = 0.0
    return fbar, valid


def snr_db(ref: np.ndarray, approx: np.ndarray, valid: np.ndarray | None = None) -> float:
    """SNR in dB, 10 log10(sum ref^2 / sum (ref - approx)^2), over valid rows and all channels.

    ref, approx : (d, ch) or (d,) float; valid : (d,) bool or None (all rows)
    returns : float. Defined limits: error 0 -> +inf (also when the signal is 0 too, e.g. an
        all-zero target reproduced by alpha = 0, or no valid row); signal 0 with error > 0 ->
        -inf. Both sums are scaled by max |value| first, so no overflow or underflow for
        values spanning 1e-300..1e300.
    """
    ref = np.asarray(ref, dtype=np.float64)
    approx = np.asarray(approx, dtype=np.float64)
    if ref.shape != approx.shape:
        raise ShapeError(
            f"ref and approx must have the same shape, got {ref.shape}, {approx.shape}"
        )
    if valid is not None:
        valid = np.asarray(valid, dtype=bool).ravel()
        if valid.shape[0] != ref.shape[0]:
            raise ShapeError(f"valid must be ({ref.shape[0]},), got {valid.shape}")
        ref, approx = ref[valid], approx[valid]
    if ref.size == 0:
        return math.inf
    scale = float(max(np.max(np.abs(ref)), np.max(np.abs(approx))))
    if not math.isfinite(scale):
        raise NumericalError("snr_db: non-finite reference or approximation")
    if scale == 0.0:
        return math.inf
    r, a = ref / scale, approx / scale
    signal = float(np.sum(r * r))
    noise = float(np.sum((r - a) ** 2))
    if noise == 0.0:
        return math.inf
    if signal == 0.0:
        return -math.inf
    return 10.0 * math.log10(signal / noise)


def points_sum(F: Any, columns: np.ndarray | None, w: np.ndarray) -> np.ndarray:
    """Eq. 8's right side on the grid: sum_k alpha_k f(x_k) per channel.

    F : (ch, m, d) channel-major F (or R), an array or any object indexed as one by
        F[c, columns] (`columns.Columns`); columns : (c,) the points' columns, None for all m;
    w : (c, ch) per-channel weights or (c,) one weight for every channel
    returns : (d, ch) float64
    """
    ch = F.shape[0]
    return np.stack([(w if w.ndim == 1 else w[:, c]) @ (F[c] if columns is None else F[c, columns])
                     for c in range(ch)], axis=1)  # loop over colour channels
