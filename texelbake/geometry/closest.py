"""Closest point on a triangle in float64 (Ericson, Real-Time Collision Detection, §5.1.5).

open3d's RaycastingScene finds the closest *triangle* fast but works in float32; texel
assignment wants float64 barycentrics so that a sample near a texel border lands in the
right texel. No maintained library exposes the vectorized point-triangle projection in
float64 for arrays of (point, triangle) pairs, so it is written here (about 40 lines).
"""

from __future__ import annotations

import numpy as np


def closest_point_on_triangles(
    p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Closest point on triangle (a_i, b_i, c_i) to p_i, for every i.

    p, a, b, c : (n, 3) float64
    returns : (points (n, 3) float64, bary (n, 3) float64 weights of (a, b, c), summing to 1)
    Degenerate triangles are handled by the same Voronoi-region tests (they fall to an
    edge or vertex region), so the result is always finite.
    """
    p = np.asarray(p, dtype=np.float64)
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    c = np.asarray(c, dtype=np.float64)
    n = p.shape[0]
    ab = b - a
    ac = c - a
    ap = p - a
    d1 = np.einsum("ij,ij->i", ab, ap)
    d2 = np.einsum("ij,ij->i", ac, ap)
    bp = p - b
    d3 = np.einsum("ij,ij->i", ab, bp)
    d4 = np.einsum("ij,ij->i", ac, bp)
    cp = p - c
    d5 = np.einsum("ij,ij->i", ab, cp)
    d6 = np.einsum("ij,ij->i", ac, cp)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2

    bary = np.zeros((n, 3), dtype=np.float64)
    done = np.zeros(n, dtype=bool)

    def take(mask: np.ndarray, w: np.ndarray) -> None:
        sel = mask & ~done
        bary[sel] = w[sel]
        done[sel] = True

    def weights(wa: np.ndarray, wb: np.ndarray, wc: np.ndarray) -> np.ndarray:
        return np.stack([wa, wb, wc], axis=1)

    one = np.ones(n)
    zero = np.zeros(n)
    with np.errstate(divide="ignore", invalid="ignore"):
        # vertex regions
        take((d1 <= 0) & (d2 <= 0), weights(one, zero, zero))
        take((d3 >= 0) & (d4 <= d3), weights(zero, one, zero))
        take((d6 >= 0) & (d5 <= d6), weights(zero, zero, one))
        # edge regions
        v_ab = d1 / (d1 - d3)
        take((vc <= 0) & (d1 >= 0) & (d3 <= 0), weights(1 - v_ab, v_ab, zero))
        w_ac = d2 / (d2 - d6)
        take((vb <= 0) & (d2 >= 0) & (d6 <= 0), weights(1 - w_ac, zero, w_ac))
        w_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        take((va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0), weights(zero, 1 - w_bc, w_bc))
        # face region
        denom = va + vb + vc
        inside = np.abs(denom) > 0
        v = np.where(inside, vb / np.where(inside, denom, 1.0), 0.0)
        w = np.where(inside, vc / np.where(inside, denom, 1.0), 0.0)
        take(np.ones(n, dtype=bool), weights(1 - v - w, v, w))
    points = bary[:, :1] * a + bary[:, 1:2] * b + bary[:, 2:] * c
    return points, bary
