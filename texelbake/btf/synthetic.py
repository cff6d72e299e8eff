"""A deterministic synthetic BTF that behaves like a measured one (for tests and benchmarks).

A periodic height field of round bumps (jittered grid, cos^2 profiles) on a striped ground,
two materials (glossy bumps, near-matte ground), rendered analytically per (light, view) pair:

* normals from the height field's gradient;
* light shadowing by marching the height field towards the light (soft horizon test);
* parallax: a rectified BTF image shows, at texel p, the surface point q with
  q + h(q) tan(theta_o) u_o = p (two fixed-point steps), so images shift with the view as
  real BTF images do;
* masking approximated by the same horizon test towards the viewer (darkening);
* radiance = visibility * (ambient + (n.l)+ (albedo + ks (n.h)^alpha)), scaled so the 99.9th
  percentile is 1, clipped to [0, 1] and (by default) quantised to 8 bits like a photograph.

Pairs are light-major (row = l * n_v + v), texelbake's product-grid convention. Default
directions: the Bonn UBO2003 sampling (81 x 81). Loops run over directions (81), never texels.
"""

from __future__ import annotations

import numpy as np

from texelbake.btf.lut import bonn_directions
from texelbake.errors import SettingsError


def _bilinear(field: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Periodic bilinear sample. field : (s, s, ...) ; q : (..., 2) in texel units (x, y)."""
    s = field.shape[0]
    x, y = q[..., 0] - 0.5, q[..., 1] - 0.5
    x0, y0 = np.floor(x), np.floor(y)
    fx, fy = x - x0, y - y0
    x0 = x0.astype(np.int64) % s
    y0 = y0.astype(np.int64) % s
    x1, y1 = (x0 + 1) % s, (y0 + 1) % s
    extra = (None,) * (field.ndim - 2)
    fx = fx[(..., *extra)]
    fy = fy[(..., *extra)]
    return ((field[y0, x0] * (1 - fx) + field[y0, x1] * fx) * (1 - fy)
            + (field[y1, x0] * (1 - fx) + field[y1, x1] * fx) * fy)


def _surface(size: int, rng: np.random.Generator):
    c = (np.arange(size) + 0.5) / size
    xx, yy = np.meshgrid(c, c)  # (s, s), row = y
    height = np.zeros((size, size))
    mask = np.zeros((size, size))
    grid = 5
    for row in range(grid):  # 25 bumps: a handful, each vectorized over all texels
        for col in range(grid):
            cx = (col + 0.5 + rng.uniform(-0.25, 0.25)) / grid
            cy = (row + 0.5 + rng.uniform(-0.25, 0.25)) / grid
            r = rng.uniform(0.06, 0.095)
            a = rng.uniform(0.035, 0.07)
            dx = (xx - cx + 0.5) % 1.0 - 0.5
            dy = (yy - cy + 0.5) % 1.0 - 0.5
            dist = np.sqrt(dx * dx + dy * dy)
            inside = dist < r
            bump = np.where(inside, a * np.cos(0.5 * np.pi * dist / r) ** 2, 0.0)
            height = np.maximum(height, bump)
            mask = np.maximum(mask, np.clip((r - dist) / (0.15 * r), 0.0, 1.0))
    height += 0.003 * np.sin(2 * np.pi * 3 * xx) * np.sin(2 * np.pi * 2 * yy)
    stripes = 0.8 + 0.2 * np.sin(2 * np.pi * 8 * (xx + 0.3 * yy))
    mottle = 1.0 + 0.12 * np.sin(2 * np.pi * (2 * xx + 1 * yy) + rng.uniform(0, 6.28))
    albedo_a = np.array([0.60, 0.30, 0.15]) * mottle[..., None]
    albedo_b = np.array([0.20, 0.28, 0.40]) * stripes[..., None]
    albedo = mask[..., None] * albedo_a + (1 - mask[..., None]) * albedo_b  # (s, s, 3)
    spec_k = 0.35 * mask + 0.05 * (1 - mask)
    spec_alpha = 30.0 * mask + 6.0 * (1 - mask)
    # normals from central differences (periodic), height in tile units, texel = 1 / size
    gx = (np.roll(height, -1, axis=1) - np.roll(height, 1, axis=1)) * size / 2
    gy = (np.roll(height, -1, axis=0) - np.roll(height, 1, axis=0)) * size / 2
    normal = np.stack([-gx, -gy, np.ones_like(gx)], axis=-1)
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    return height, albedo, spec_k, spec_alpha, normal


def _visibility(height: np.ndarray, dirs: np.ndarray, steps: int = 14, soft: float = 0.008):
    """(n, s, s) soft horizon visibility of every texel towards each direction."""
    size = height.shape[0]
    c = np.arange(size) + 0.5
    xx, yy = np.meshgrid(c, c)
    out = np.ones((dirs.shape[0], size, size))
    for i, w in enumerate(dirs):  # one pass per direction, vectorized over texels and steps
        sin_t = np.hypot(w[0], w[1])
        if sin_t < 1e-9 or w[2] <= 0:
            out[i] = 1.0 if w[2] > 0 else 0.0
            continue
        u = w[:2] / sin_t
        s = np.arange(1, steps + 1, dtype=np.float64)  # texels along the ray
        qx = xx[None] + s[:, None, None] * u[0]
        qy = yy[None] + s[:, None, None] * u[1]
        h = _bilinear(height, np.stack([qx, qy], axis=-1))  # (steps, s, s)
        rise = s[:, None, None] / size * (w[2] / sin_t)
        occl = np.max(h - height[None] - rise, axis=0)
        out[i] = np.clip(1.0 - occl / soft, 0.0, 1.0)
    return out


def synthetic_btf(
    size: int = 64,
    light_dirs: np.ndarray | None = None,
    view_dirs: np.ndarray | None = None,
    *,
    seed: int = 0,
    quantize: bool = True,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Render the synthetic BTF.

    size : texels per side; light_dirs, view_dirs : (n_l, 3), (n_v, 3) unit (default Bonn 81)
    returns : (btf (n_l * n_v, size, size, 3) float32 in [0, 1], dirs_i, dirs_o (d, 3) float64)
    """
    if int(size) < 1:
        raise SettingsError(f"size must be >= 1, got {size}")
    size = int(size)
    lights = bonn_directions() if light_dirs is None else np.asarray(light_dirs, np.float64)
    views = bonn_directions() if view_dirs is None else np.asarray(view_dirs, np.float64)
    rng = np.random.default_rng(seed)
    height, albedo, ks, alpha, normal = _surface(size, rng)
    vis_l = _visibility(height, lights)  # (n_l, s, s)
    vis_v = _visibility(height, views)  # (n_v, s, s)
    fields = np.concatenate(
        [albedo, ks[..., None], alpha[..., None], normal, np.moveaxis(vis_l, 0, -1)], axis=-1
    )  # (s, s, 3 + 1 + 1 + 3 + n_l)
    n_l, n_v = lights.shape[0], views.shape[0]
    btf = np.empty((n_l * n_v, size, size, 3), np.float32)
    c = np.arange(size) + 0.5
    xx, yy = np.meshgrid(c, c)
    p = np.stack([xx, yy], axis=-1)  # (s, s, 2) texel units
    for v, wo in enumerate(views):  # one image block per view, vectorized over lights/texels
        tan_t = np.hypot(wo[0], wo[1]) / max(wo[2], 1e-3)
        shift = wo[:2] / max(np.hypot(wo[0], wo[1]), 1e-12) * tan_t * size  # texels per unit h
        q = p - height[..., None] * shift
        q = p - _bilinear(height, q)[..., None] * shift
        f = _bilinear(fields, q)  # (s, s, k)
        alb, k_s, a_s = f[..., 0:3], f[..., 3], f[..., 4]
        nrm = f[..., 5:8] / np.linalg.norm(f[..., 5:8], axis=-1, keepdims=True)
        v_l = np.moveaxis(f[..., 8:], -1, 0)  # (n_l, s, s)
        mask_v = 0.6 + 0.4 * _bilinear(vis_v[v][..., None], q)[..., 0]
        half = lights + wo[None]
        half /= np.linalg.norm(half, axis=1, keepdims=True)
        n_dot_l = np.clip(np.einsum("lk,yxk->lyx", lights, nrm), 0.0, None)
        n_dot_h = np.clip(np.einsum("lk,yxk->lyx", half, nrm), 0.0, None)
        spec = k_s[None] * n_dot_h ** a_s[None]  # (n_l, s, s)
        rad = v_l[..., None] * n_dot_l[..., None] * (alb[None] + spec[..., None])
        rad += 0.03 * alb[None]
        rad *= mask_v[None, ..., None]
        below = (lights[:, 2] <= 0)[:, None, None, None] | (wo[2] <= 0)
        btf[v::n_v] = np.where(below, 0.0, rad)
    sample = btf.reshape(-1)[:: 97]
    scale = 1.0 / max(float(np.quantile(sample, 0.999)), 1e-12)
    btf *= np.float32(scale)
    np.clip(btf, 0.0, 1.0, out=btf)
    if quantize:
        np.multiply(btf, 255.0, out=btf)
        np.round(btf, out=btf)
        btf /= np.float32(255.0)
    dirs_i = np.repeat(lights, n_v, axis=0)
    dirs_o = np.tile(views, (n_l, 1))
    return btf, dirs_i, dirs_o
