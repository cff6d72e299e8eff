"""The sum correction of a level's compressed a_vis: per cube direction, the power (bounded
texels) or scale that restores the level's total after truncation."""

from __future__ import annotations

import numpy as np

from texelbake.errors import ShapeError

#: bisection steps of the bounded texels' correction (c in [-8, 16]: 24 / 2^30 = 2.2e-8)
_GAMMA_STEPS = 30


_LOG_GAMMA_MAX = 8.0


_SCALE_SPAN = 8.0  # c in (8, 16]: the power at 8 times the scale (16 - c) / 8


def sum_correction(exact: np.ndarray, approx: np.ndarray, weight: np.ndarray,
                   bounded: bool) -> np.ndarray:
    """Per-direction correction that restores a level's total a_vis after compression.

    Truncating every texel's Haar table drops similar coefficients in similar texels (a
    height field's texels all mask alike), so their errors add up instead of cancelling:
    measured, the total over a level's texels was off by 5-10 % where each texel was off by
    2-5 % (benchmarks/avis_methods.py). One scalar per cube pixel puts the group's missing
    total back:

    * bounded texels (the table holds F = a_vis / U in [0, 1]): one parameter c per pixel,
      solved by bisection so that sum_t U_t F'_t = sum_t U_t F_t, of a family decreasing in c:
      for c in [-8, 8] the power F' = F~^exp(c), which keeps 0 at 0 (a fully masked direction
      stays masked), 1 at 1 and F in [0, 1] and spans every total between the fully visible
      texels' U and all non-zero texels' U; for c in (8, 16] the power at 8 times the scale
      (16 - c) / 8, which takes the total on down to 0. The scale is for a pixel where the
      reconstruction calls texels fully visible that are not (a periodic field's alike coarse
      texels at grazing pixels: measured, the V-grooves' level 2 at res 32 was 11 % over its
      total there, 1.1 % off the identity between pixels). A target above the range gets
      c = -8.
    * direct texels (the table holds a_vis itself, W = 1): a~ (1 + m) with
      m = sum_t (a_t - a~_t) / sum_t a~_t, clipped to [-1, 1] (0 stays 0).

    Either way the group's total is exact at every cube pixel, so the identity
    sum_texels a_vis = A cos(theta) of a height field survives compression up to the bilinear
    look-up's own interpolation error.

    exact, approx : (n, 6, res, res) X and its reconstruction (F~ clipped to [0, 1], a~ >= 0)
    weight : (n, 6, res, res) U (bounded) or ones; bounded : which rule
    returns : (6, res, res) float32: g (bounded) or m (direct), stored as float16
    """
    x = np.asarray(exact, np.float64)
    a = np.asarray(approx, np.float64)
    u = np.asarray(weight, np.float64)
    if not (x.shape == a.shape == u.shape) or x.ndim != 4 or x.shape[1] != 6:
        raise ShapeError(f"exact, approx, weight must share a (n, 6, res, res) shape, got "
                         f"{x.shape}, {a.shape}, {u.shape}")
    target = np.sum(u * x, axis=0)  # (6, res, res)
    if not bounded:
        have = np.sum(u * a, axis=0)
        m = np.divide(target - have, have, out=np.zeros_like(have), where=have > 0)
        return np.clip(m, -1.0, 1.0).astype(np.float32)
    # the total decreases in c: bisection on [-8, 16], vectorized over pixels; `apply_correction`
    # with log F~ taken once
    logf = np.log(np.where(a > 0, a, 1.0))  # (n, 6, res, res); F~ = 0 terms masked below
    pos = a > 0
    lo = np.full(target.shape, -_LOG_GAMMA_MAX)
    hi = np.full(target.shape, _LOG_GAMMA_MAX + _SCALE_SPAN)
    for _ in range(_GAMMA_STEPS):  # a loop over bisection steps, each over all pixels
        mid = 0.5 * (lo + hi)
        g, scale = _power_and_scale(mid)
        total = np.sum(u * (np.where(pos, np.exp(np.exp(g[None]) * logf), 0.0) * scale[None]),
                       axis=0)
        too_big = total > target
        lo = np.where(too_big, mid, lo)
        hi = np.where(too_big, hi, mid)
    return (0.5 * (lo + hi)).astype(np.float32)


def _power_and_scale(c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The bounded correction's parameter c as (the power's log-exponent, the scale)."""
    return (np.minimum(c, _LOG_GAMMA_MAX),
            np.clip((_LOG_GAMMA_MAX + _SCALE_SPAN - c) / _SCALE_SPAN, 0.0, 1.0))


def apply_correction(values: np.ndarray, c: np.ndarray, bounded: bool) -> np.ndarray:
    """`sum_correction`'s rule at cube pixels: the corrected F from F~ in [0, 1] and g
    (bounded), or the corrected a_vis from a~ >= 0 and m (direct)."""
    v = np.asarray(values, np.float64)
    c = np.asarray(c, np.float64)
    if bounded:
        g, scale = _power_and_scale(c)
        return np.where(v > 0, np.exp(np.exp(g) * np.log(np.where(v > 0, v, 1.0))), 0.0) * scale
    return v * (1.0 + c)
