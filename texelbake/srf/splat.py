"""EWA surface splatting of (deformed) surfels (seed 002 §5.1, Figs. 8-9; Zwicker et al.'s
elliptical weighted average), vectorised over all (surfel, pixel) pairs of a frame.

A surfel is a centre c and two tangent vectors (u, v), not necessarily orthonormal, spanning
its elliptical footprint {c + a u + b v : a² + b² ≤ 1}. Per frame:

1. the footprint's screen ellipse: J_s = ∂pixel/∂(a, b) at c (the perspective projection's
   Jacobian times (u, v)); the EWA resampling kernel is the reconstruction Gaussian
   (σ = ½ in footprint units) mapped to the screen, convolved with a pixel prefilter
   (σ_h = ½ pixel): C = σ² J_s J_sᵀ + σ_h² I, weight exp(−½ xᵀ C⁻¹ x) at screen offset x;
2. every pixel of each surfel's bounding box (at most `MAX_RADIUS_PX` from the centre) makes
   a pair; its eye ray through the pixel centre meets the surfel's plane at c + a u + b v
   (exact, not the screen-affine approximation), at depth z;
3. a pair is a fragment where (a, b) lies in the footprint (a² + b² ≤ 1) or within the
   kernel's 2σ (xᵀ C⁻¹ x ≤ 4: the prefilter keeps sub-pixel splats visible); back-facing
   surfels (ray · (u × v) ≥ 0) make none. A kernel-only fragment (outside the footprint)
   is used only in pixels no footprint covers, and its ray-plane hit — which may lie far
   along a grazing plane — enters the z-test at the depth of its point `KERNEL_REACH`
   footprint radii out (so it cannot win with a wrong depth; attributes stay on the ray);
4. visibility is an ε-z-buffer: per pixel the fragments within `DEPTH_TOL` footprint radii
   (of the nearest fragment's surfel) behind the nearest are blended, normalised by their
   summed weights: the deformed point, the rest point (the surfel's rest centre + a u_rest
   + b v_rest, its first-order inverse warp) and the look-up rotation L (blended, then
   projected back onto the rotations by SVD).

With `circular` splats (the comparison of Fig. 8a) the caller passes discs perpendicular to
the deformed normal; they cannot follow an anisotropic stretch and leave holes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from texelbake.errors import ShapeError
from texelbake.trace.camera import PinholeCamera

#: reconstruction kernel's σ in footprint units (the footprint edge is at 2σ)
SIGMA = 0.5
#: pixel prefilter's σ (pixels)
SIGMA_PIXEL = 0.5
#: a splat's screen bounding box is clipped to this radius (pixels): a surfel right at the
#: camera would otherwise cover the frame with pairs
MAX_RADIUS_PX = 48.0
#: a kernel-only fragment is depth-tested at most this many footprint radii out
KERNEL_REACH = 2.0
#: ε-z-buffer tolerance, in footprint radii of the nearest fragment's surfel
DEPTH_TOL = 1.0
#: (surfel, pixel) pairs processed at once (bounds memory: ~300 B per pair, ~80 MB)
PAIR_CHUNK = 1 << 18


@dataclass
class SplatFrame:
    """The splatted G-buffer of a frame (row-major pixels, n = h · w).

    covered : (n,) bool; p_star : (n, 3) deformed surface point; p_rest : (n, 3) rest point;
    lookup : (n, 3, 3) L (identity where not given); weight : (n,) summed kernel weight;
    fragments : fragments blended"""

    covered: np.ndarray
    p_star: np.ndarray
    p_rest: np.ndarray
    lookup: np.ndarray
    weight: np.ndarray
    fragments: int

    def coverage(self, cam: PinholeCamera) -> np.ndarray:
        return self.covered.reshape(cam.height, cam.width).astype(np.float32)


def _vec(x: object, n: int, name: str) -> np.ndarray:
    a = np.asarray(x, dtype=np.float64)
    if a.shape != (n, 3):
        raise ShapeError(f"{name} must be ({n}, 3), got {a.shape}")
    return a


def _screen_jacobian(cam: PinholeCamera, c: np.ndarray, u: np.ndarray, v: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Projected centres (n, 2), depth (n,) and J_s (n, 2, 2) = ∂pixel/∂(a, b)."""
    loc = (c - cam.position) @ cam.rotation
    ul, vl = u @ cam.rotation, v @ cam.rotation
    z = -loc[:, 2]
    safe = np.where(z > 0, z, 1.0)
    fx, fy = 0.5 * cam.width / cam.tan_half_x, 0.5 * cam.height / cam.tan_half_y
    px = np.column_stack([fx * loc[:, 0] / safe + 0.5 * cam.width,
                          0.5 * cam.height - fy * loc[:, 1] / safe])
    # d px / d loc = fx (1/z, 0, x/z²); d py / d loc = -fy (0, 1/z, y/z²)
    dx = fx * np.column_stack([1.0 / safe, np.zeros_like(z), loc[:, 0] / safe ** 2])
    dy = -fy * np.column_stack([np.zeros_like(z), 1.0 / safe, loc[:, 1] / safe ** 2])
    js = np.stack([np.stack([np.einsum("ij,ij->i", dx, ul), np.einsum("ij,ij->i", dx, vl)], 1),
                   np.stack([np.einsum("ij,ij->i", dy, ul), np.einsum("ij,ij->i", dy, vl)], 1)],
                  axis=1)
    return px, z, js


def _nearest_rotation(m: np.ndarray) -> np.ndarray:
    """Closest rotation to each (n, 3, 3) matrix (polar factor by SVD, det +1)."""
    if m.shape[0] == 0:
        return m
    uu, _, vt = np.linalg.svd(m)
    d = np.sign(np.linalg.det(uu @ vt))
    d = np.where(d == 0, 1.0, d)
    uu[:, :, 2] *= d[:, None]
    return uu @ vt


def splat(cam: PinholeCamera, centers: object, u: object, v: object, *,
          rest_centers: object | None = None, rest_u: object | None = None,
          rest_v: object | None = None, lookup: np.ndarray | None = None,
          depth_tol: float = DEPTH_TOL) -> SplatFrame:
    """Splat surfels (module docstring) into the G-buffer of `cam`.

    centers, u, v : (s, 3) float64 deformed centres and footprint vectors; rest_centers,
    rest_u, rest_v : (s, 3) their rest counterparts (default: the deformed ones); lookup :
    (s, 3, 3) per-surfel L or None"""
    c = np.asarray(centers, dtype=np.float64)
    if c.ndim != 2 or c.shape[1] != 3:
        raise ShapeError(f"centers must be (s, 3), got {c.shape}")
    s = c.shape[0]
    u, v = _vec(u, s, "u"), _vec(v, s, "v")
    rc = c if rest_centers is None else _vec(rest_centers, s, "rest_centers")
    ru = u if rest_u is None else _vec(rest_u, s, "rest_u")
    rv = v if rest_v is None else _vec(rest_v, s, "rest_v")
    if lookup is not None and np.shape(lookup) != (s, 3, 3):
        raise ShapeError(f"lookup must be ({s}, 3, 3), got {np.shape(lookup)}")
    w, h = cam.width, cam.height
    npix = w * h
    px, z, js = _screen_jacobian(cam, c, u, v)
    nrm = np.cross(u, v)
    facing = np.einsum("ij,ij->i", nrm, c - cam.position) < 0
    cov = SIGMA ** 2 * js @ np.transpose(js, (0, 2, 1)) + SIGMA_PIXEL ** 2 * np.eye(2)
    # support: the 2σ kernel ellipse (extents 2 sqrt(C_ii)) and the footprint's own
    # screen extent (sqrt of J_s J_sᵀ's diagonal), plus a pixel for the perspective error
    ext = np.maximum(2.0 * np.sqrt(np.diagonal(cov, axis1=1, axis2=2)),
                     np.sqrt(np.einsum("nij,nij->ni", js, js))) * 1.25 + 1.0
    ext = np.minimum(ext, MAX_RADIUS_PX)
    live = facing & (z > 0) & np.isfinite(px).all(axis=1)
    x0 = np.clip(np.floor(px[:, 0] - ext[:, 0]), 0, w).astype(np.int64)
    x1 = np.clip(np.floor(px[:, 0] + ext[:, 0]) + 1, 0, w).astype(np.int64)
    y0 = np.clip(np.floor(px[:, 1] - ext[:, 1]), 0, h).astype(np.int64)
    y1 = np.clip(np.floor(px[:, 1] + ext[:, 1]) + 1, 0, h).astype(np.int64)
    nx, ny = np.where(live, x1 - x0, 0), np.where(live, y1 - y0, 0)
    count = np.maximum(nx, 0) * np.maximum(ny, 0)
    cinv = np.linalg.inv(cov)
    gram = np.stack([np.stack([np.einsum("ij,ij->i", u, u), np.einsum("ij,ij->i", u, v)], 1),
                     np.stack([np.einsum("ij,ij->i", u, v), np.einsum("ij,ij->i", v, v)], 1)],
                    axis=1)
    det = gram[:, 0, 0] * gram[:, 1, 1] - gram[:, 0, 1] ** 2
    live_s = np.flatnonzero(count > 0)
    frags: list[tuple[np.ndarray, ...]] = []
    # chunks of surfels of about PAIR_CHUNK pairs each: a loop over chunks, not surfels
    chunk_id = (np.cumsum(count[live_s]) - 1) // PAIR_CHUNK
    cuts = (np.flatnonzero(np.diff(chunk_id)) + 1).tolist()
    for lo, hi in zip([0, *cuts], [*cuts, live_s.size], strict=True):
        sel = live_s[lo:hi]
        if sel.size == 0:
            continue
        reps = count[sel]
        sid = np.repeat(sel, reps)
        k = np.arange(sid.size) - np.repeat(np.cumsum(reps) - reps, reps)
        ix = x0[sid] + k % nx[sid]
        iy = y0[sid] + k // nx[sid]
        d_cam = np.column_stack([(2.0 * (ix + 0.5) / w - 1.0) * cam.tan_half_x,
                                 (1.0 - 2.0 * (iy + 0.5) / h) * cam.tan_half_y,
                                 -np.ones(sid.size)])
        d = d_cam @ cam.rotation.T
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        denom = np.einsum("ij,ij->i", d, nrm[sid])
        t = np.einsum("ij,ij->i", c[sid] - cam.position, nrm[sid]) / np.where(
            denom < 0, denom, -1.0)
        ok = (denom < -1e-12 * np.linalg.norm(nrm[sid], axis=1)) & (t > 0)
        hit = cam.position + t[:, None] * d
        q = hit - c[sid]
        qu, qv = np.einsum("ij,ij->i", q, u[sid]), np.einsum("ij,ij->i", q, v[sid])
        g = gram[sid]
        dt = np.where(det[sid] > 0, det[sid], 1.0)
        a = (g[:, 1, 1] * qu - g[:, 0, 1] * qv) / dt
        b = (g[:, 0, 0] * qv - g[:, 0, 1] * qu) / dt
        xo = np.column_stack([ix + 0.5, iy + 0.5]) - px[sid]
        m2 = np.einsum("ni,nij,nj->n", xo, cinv[sid], xo)
        keep = ok & (det[sid] > 0) & ((a * a + b * b <= 1.0) | (m2 <= 4.0))
        if not keep.any():
            continue
        kk = np.flatnonzero(keep)
        aa, bb, hh = a[kk], b[kk], hit[kk]
        # a fragment kept by the kernel only (outside the footprint): its ray-plane hit can
        # lie far along a grazing plane; its z-test depth is that of the point at
        # KERNEL_REACH footprint radii (the hit itself stays on the pixel's ray)
        r = np.sqrt(aa * aa + bb * bb)
        scale = np.minimum(1.0, KERNEL_REACH / np.maximum(r, 1e-300))
        s_k = sid[kk]
        near = c[s_k] + (scale * aa)[:, None] * u[s_k] + (scale * bb)[:, None] * v[s_k]
        depth = (near - cam.position) @ cam.forward
        frags.append((iy[kk] * w + ix[kk], depth, s_k, aa, bb, hh, np.exp(-0.5 * m2[kk]),
                      r <= 1.0))
    covered = np.zeros(npix, bool)
    p_star, p_rest = np.zeros((npix, 3)), np.zeros((npix, 3))
    lk = np.broadcast_to(np.eye(3), (npix, 3, 3)).copy()
    wsum = np.zeros(npix)
    if not frags:
        return SplatFrame(covered, p_star, p_rest, lk, wsum, 0)
    pix, depth, sid, a, b, hit, wt, inside = (np.concatenate(x)
                                              for x in zip(*frags, strict=True))
    # where some footprint covers the pixel centre, the kernel-only fragments are not needed
    # (they fill sub-pixel splats and cracks): drop them there
    has_inside = np.bincount(pix, inside, npix) > 0
    use = inside | ~has_inside[pix]
    pix, depth, sid, a, b, hit, wt = (x[use] for x in (pix, depth, sid, a, b, hit, wt))
    # ε-z-buffer: nearest depth per pixel, and the tolerance of that fragment's surfel
    order = np.lexsort((depth, pix))
    first = order[np.flatnonzero(np.r_[True, pix[order][1:] != pix[order][:-1]])]
    zmin = np.full(npix, np.inf)
    tol = np.zeros(npix)
    zmin[pix[first]] = depth[first]
    radius = np.maximum(np.linalg.norm(u, axis=1), np.linalg.norm(v, axis=1))
    tol[pix[first]] = depth_tol * radius[sid[first]]
    front = depth <= zmin[pix] + tol[pix]
    pix, sid, a, b, hit, wt = pix[front], sid[front], a[front], b[front], hit[front], wt[front]
    wsum = np.asarray(np.bincount(pix, wt, npix), dtype=np.float64)
    covered = wsum > 0
    inv = np.divide(1.0, wsum, out=np.zeros(npix), where=covered)
    rest = rc[sid] + a[:, None] * ru[sid] + b[:, None] * rv[sid]
    for ch in range(3):
        p_star[:, ch] = np.bincount(pix, wt * hit[:, ch], npix) * inv
        p_rest[:, ch] = np.bincount(pix, wt * rest[:, ch], npix) * inv
    if lookup is not None:
        lf = np.asarray(lookup, dtype=np.float64)[sid].reshape(-1, 9)
        acc = np.stack([np.bincount(pix, wt * lf[:, j], npix) for j in range(9)], axis=1)
        cv = np.flatnonzero(covered)
        lk[cv] = _nearest_rotation((acc[cv] * inv[cv, None]).reshape(-1, 3, 3))
    return SplatFrame(covered, p_star, p_rest, lk, wsum, int(pix.size))
