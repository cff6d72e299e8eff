"""The fitted UsdPreviewSurface fallback's measure: a texel's filtered reflectance over a
fixed set of light directions and view cells, and the preview surface's over the same.

The target of a texel is its filtered reflectance over a fixed set of light directions and
view cells in the tangent frame of the LOD surface (`fit_directions`, `cell_views`: each
sample sees a view drawn in each cell), from dense samples of M_org with shadowing and masking
(seed 000, Eq. 7 evaluated on the samples):

    T(l, v) = Σ_s A_s f_s(l, v) V_s(l) (n_s·l)⁺ V_s(v) (n_g,s·v)⁺ / Σ_s A_s V_s(v) (n_g,s·v)⁺

the radiance toward v under unit irradiance from l, averaged over the texel's visible
projected area, as `texelbake.cpm.level.visibility_cos` builds R (shading cosine for the
light, geometric for the view). The preview surface on the LOD with shading normal n (the
texel's mean normal) gives L(l, v) = f_ps(l, v) (n·l)⁺, each view cell's mean
(`model_cells`: a diffuse term on a stratified set of views, a lobe by importance sampling
it, so a lobe narrower than the set's spacing counts by its energy).

`texelbake.stages.fallback` fits, with these, a smooth gain on the averaged fallback's
diffuseColor (docs/decisions.md says why not a per-texel fit of every input). No iteration,
no randomness: the results are functions of the sums, bit for bit.
"""

from __future__ import annotations

import numpy as np

from texelbake.brdf.analytic import preview_surface
from texelbake.brdf.common import PREVIEW_MIN_ROUGHNESS
from texelbake.errors import ShapeError
from texelbake.geometry.basis import tangent_frames

#: pairs whose view sees less of the texel than this (projected-area fraction) are left out
VIEW_FLOOR = 1e-6


def fit_directions() -> np.ndarray:
    """The fixed light and view directions of the fit, unit (k, 3) float64 in the tangent
    frame: the normal, four at 35° and four at 65° from it (the rings 45° apart in azimuth,
    each ring holding its own mirror pairs)."""
    out = [np.array([0.0, 0.0, 1.0])]
    for theta, phi0 in ((35.0, 0.0), (65.0, 45.0)):
        t = np.radians(theta)
        for j in range(4):  # four azimuths a ring
            p = np.radians(phi0 + 90.0 * j)
            out.append(np.array([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)]))
    return np.stack(out)


#: the view cells: (θ from, θ to, azimuth half-width) in degrees per ring of `fit_directions`
_CELLS = ((0.0, 20.0, 180.0), (20.0, 50.0, 45.0), (50.0, 80.0, 45.0))
#: stratified views per cell of the basis's diffuse term (4 x 4)
CELL_STRATA = 4
#: importance-sampled half vectors per texel and light of the basis's lobe (16 x 16)
IS_STRATA = 16


def cell_views(u: np.ndarray) -> np.ndarray:
    """Views inside each view cell of the set, uniform in solid angle: u (..., k, 2) in [0, 1)²
    -> (..., k, 3) unit, tangent frame. Cell o is the part of the hemisphere nearest
    `fit_directions()[o]` within its ring (the normal's cap to 20°, the 35° ring's cells
    20°-50°, the 65° ring's 50°-80°, each ±45° in azimuth around its direction): a view is a
    cell's average, so a lobe narrower than the set's spacing counts by its energy, not by
    whether a direction hits its peak."""
    u = np.asarray(u, dtype=np.float64)
    centre = fit_directions()
    k = centre.shape[0]
    ring = np.array([0] + [1] * 4 + [2] * 4)
    lo = np.cos(np.radians([_CELLS[r][0] for r in ring]))
    hi = np.cos(np.radians([_CELLS[r][1] for r in ring]))
    half = np.radians([_CELLS[r][2] for r in ring])
    phi0 = np.arctan2(centre[:, 1], centre[:, 0])
    if u.shape[-2:] != (k, 2):
        raise ShapeError(f"cell_views: u must be (..., {k}, 2), got {u.shape}")
    cos_t = lo + (hi - lo) * u[..., 0]
    phi = phi0 + half * (2.0 * u[..., 1] - 1.0)
    sin_t = np.sqrt(np.maximum(1.0 - cos_t * cos_t, 0.0))
    return np.stack([sin_t * np.cos(phi), sin_t * np.sin(phi), cos_t], axis=-1)


def basis_views() -> np.ndarray:
    """The basis's stratified views (k, CELL_STRATA², 3) of every cell (`cell_views`)."""
    g = (np.arange(CELL_STRATA) + 0.5) / CELL_STRATA
    uu = np.stack(np.meshgrid(g, g, indexing="ij"), axis=-1).reshape(-1, 2)  # (M, 2)
    k = fit_directions().shape[0]
    return cell_views(np.broadcast_to(uu[:, None, :], (uu.shape[0], k, 2))).transpose(1, 0, 2)


def _pair_dirs(normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(wi, wo) (t·k·k·M, 3) in each texel's shading frame: light i of the set, view m of
    cell o, in (t, i, o, m) order."""
    dirs = fit_directions()
    views = basis_views()  # (k, M, 3)
    t, k, m = normal.shape[0], dirs.shape[0], views.shape[1]
    fr = tangent_frames(np.asarray(normal, dtype=np.float64))  # rows (t, b, n) of n's frame
    li = np.einsum("tij,kj->tki", fr, dirs)  # (t, k, 3)
    vo = np.einsum("tij,kmj->tkmi", fr, views)  # (t, k, M, 3)
    wi = np.broadcast_to(li[:, :, None, None, :], (t, k, k, m, 3)).reshape(-1, 3)
    wo = np.broadcast_to(vo[:, None, :, :, :], (t, k, k, m, 3)).reshape(-1, 3)
    return wi, wo


def sample_terms(f: np.ndarray, vis_l: np.ndarray, vis_v: np.ndarray, area: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
    """One chunk of samples' contributions to the target sums.

    f : (m, k, k, 3) float64 BRDF of each sample at (light i, view o); vis_l : (m, k) V (n_s·l)⁺;
    vis_v : (m, k) V (n_g·v)⁺; area : (m,)
    returns : (num (m, k·k·3), den (m, k)) float64, to be summed per texel"""
    f = np.asarray(f, dtype=np.float64)
    m, k = vis_l.shape
    if f.shape != (m, k, k, 3) or vis_v.shape != (m, k) or area.shape != (m,):
        raise ShapeError(f"sample_terms: f {f.shape}, vis_l {vis_l.shape}, vis_v "
                         f"{vis_v.shape}, area {area.shape} do not agree on (m, k)")
    w = area[:, None, None] * vis_l[:, :, None] * vis_v[:, None, :]  # (m, k, k)
    num = (f * w[..., None]).reshape(m, -1)
    return num, area[:, None] * vis_v


def targets(num: np.ndarray, den: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """T (t, k, k, 3) from per-texel sums num (t, k·k·3), den (t, k), and the pairs that
    count (t, k, k) bool (the view sees the texel)."""
    t = num.shape[0]
    seen = den > VIEW_FLOOR * np.maximum(den.max(axis=1, keepdims=True), 1e-300)  # (t, k)
    tgt = num.reshape(t, k, k, 3) / np.where(seen, den, 1.0)[:, None, :, None]
    valid = np.broadcast_to(seen[:, None, :], (t, k, k))
    return np.where(valid[..., None], tgt, 0.0), valid.copy()


def cell_of(v: np.ndarray) -> np.ndarray:
    """The view cell (`cell_views`) of tangent-frame unit directions v (n, 3): (n,) int, -1
    outside every cell (below 10° of elevation)."""
    theta = np.degrees(np.arccos(np.clip(v[:, 2], -1.0, 1.0)))
    phi = np.degrees(np.arctan2(v[:, 1], v[:, 0]))
    j1 = np.mod(np.round(phi / 90.0), 4).astype(np.int64)
    j2 = np.mod(np.round((phi - 45.0) / 90.0), 4).astype(np.int64)
    return np.where(theta < _CELLS[0][1], 0, np.where(
        theta < _CELLS[1][1], 1 + j1, np.where(theta <= _CELLS[2][1], 5 + j2, -1)))


def cell_solid_angles() -> np.ndarray:
    """(k,) the solid angle of each view cell, sr."""
    out = []
    for lo, hi, half in (_CELLS[0],) + (_CELLS[1],) * 4 + (_CELLS[2],) * 4:
        out.append(2.0 * np.radians(half) * (np.cos(np.radians(lo)) - np.cos(np.radians(hi))))
    return np.asarray(out)



def _rows(per_texel: dict, t: int, reps: int) -> dict:
    """Per-texel inputs (t,) or (t, 3) repeated for `reps` consecutive rows each."""
    out = {}
    for key, val in per_texel.items():
        val = np.asarray(val, dtype=np.float64)
        if val.shape[0] != t:
            raise ShapeError(f"per-texel input {key} has {val.shape[0]} rows, expected {t}")
        out[key] = np.repeat(val, reps, axis=0)
    return out


def model_cells(const: dict, per_texel: dict, normal: np.ndarray, lobe: bool) -> np.ndarray:
    """Each (light, view cell) mean of f_ps (n·l)⁺ (t, k, k, 3) of UsdPreviewSurface inputs
    `const` (constants) and `per_texel` ((t,) or (t, 3) arrays) on the shading normals (t, 3):
    lobe False by the stratified views of `basis_views` (a diffuse term: smooth over a cell),
    lobe True by importance sampling the GGX lobe at per_texel["roughness"] (`_lobe_cells`:
    a narrow lobe, which a uniform quadrature of a cell misses)."""
    normal = np.asarray(normal, dtype=np.float64)
    t, k = normal.shape[0], fit_directions().shape[0]
    for key, val in per_texel.items():
        if np.shape(val)[:1] != (t,):
            raise ShapeError(f"model_cells: per-texel input {key} {np.shape(val)} does not "
                             f"have the normals' {t} rows")
    if lobe:
        return _lobe_cells(normal, const, per_texel)
    wi, wo = _pair_dirs(normal)
    m = wi.shape[0] // max(t * k * k, 1)
    f = preview_surface({**const, **_rows(per_texel, t, k * k * m)}, wi, wo)
    return (f * np.maximum(wi[:, 2:3], 0.0)).reshape(t, k, k, m, 3).mean(axis=3)


def _lobe_cells(normal: np.ndarray, const: dict, per_texel: dict) -> np.ndarray:
    """`model_cells` of a lobe: IS_STRATA² stratified GGX half vectors per texel and light at
    per_texel["roughness"], v the reflection of l, pdf D (n·h) / (4 v·h), each estimate added
    to the cell v falls in; (t, k, k, 3)."""
    dirs = fit_directions()
    t, k = normal.shape[0], dirs.shape[0]
    g = (np.arange(IS_STRATA) + 0.5) / IS_STRATA
    u = np.stack(np.meshgrid(g, g, indexing="ij"), axis=-1).reshape(-1, 2)  # (S, 2)
    ns = u.shape[0]
    fr = tangent_frames(normal)  # rows (t, b, n)
    li = np.einsum("tij,kj->tki", fr, dirs)  # (t, k, 3) lights in n's frame
    rough = np.asarray(per_texel["roughness"], dtype=np.float64)
    alpha = np.clip(rough, PREVIEW_MIN_ROUGHNESS, 1.0) ** 2  # (t,)
    a2 = (alpha * alpha)[:, None]
    cos2 = (1.0 - u[None, :, 0]) / (1.0 + (a2 - 1.0) * u[None, :, 0])  # (t, S) GGX cos²θh
    ch = np.sqrt(cos2)
    sh = np.sqrt(np.maximum(1.0 - cos2, 0.0))
    ph = 2.0 * np.pi * u[None, :, 1]
    h = np.stack([sh * np.cos(ph), sh * np.sin(ph), ch], axis=-1)  # (t, S, 3)
    lh = np.einsum("tki,tsi->tks", li, h)  # (t, k, S)
    v = 2.0 * lh[..., None] * h[:, None] - li[:, :, None]  # (t, k, S, 3) reflections
    d = a2[:, :, None] / (np.pi * (cos2[:, None] * (a2[:, :, None] - 1.0) + 1.0) ** 2)
    pdf = d * ch[:, None] / np.maximum(4.0 * lh, 1e-300)  # (t, k, S)
    v_tex = np.einsum("tji,tksj->tksi", fr, v)  # back to the texel frame
    cell = cell_of(v_tex.reshape(-1, 3)).reshape(t, k, ns)
    ok = (lh > 0.0) & (v[..., 2] > 0.0) & (cell >= 0)
    wi = np.broadcast_to(li[:, :, None], v.shape).reshape(-1, 3)
    f = preview_surface({**const, **_rows(per_texel, t, k * ns)}, wi, v.reshape(-1, 3))
    f = f.reshape(t, k, ns, 3)
    w = np.where(ok, np.maximum(li[:, :, None, 2], 0.0) / np.where(ok, pdf, 1.0), 0.0)
    out = np.zeros((t, k, k, 3))
    ti, ii, si = np.nonzero(ok)
    np.add.at(out, (ti, ii, cell[ti, ii, si]), f[ti, ii, si] * w[ti, ii, si, None])
    return out / (ns * cell_solid_angles()[None, None, :, None])


def gain_sums(l0: np.ndarray, dl: np.ndarray, tgt: np.ndarray, valid: np.ndarray):
    """Per texel and channel Σ ΔL² and Σ ΔL (T − L0) over the pairs that count: (t, 3) each."""
    w = valid[..., None]
    return (np.einsum("tijc,tijc->tc", dl * w, dl), np.einsum("tijc,tijc->tc", dl * w,
                                                              tgt - l0))


def shrunk_gain(sdd: np.ndarray, sdr: np.ndarray, lam: float) -> np.ndarray:
    """The least-squares gain shrunk toward 1: argmin Σ(L0 + g ΔL − T)² + λ Σ ΔL² (g − 1)²."""
    if not np.isfinite(lam):
        return np.ones_like(sdd)
    ok = sdd > 1e-12 * max(float(sdd.max(initial=0.0)), 1e-300)
    g = np.where(ok, (sdr + lam * sdd) / np.where(ok, (1.0 + lam) * sdd, 1.0), 1.0)
    return np.maximum(g, 0.0)


def gain_residual(l0: np.ndarray, dl: np.ndarray, tgt: np.ndarray, valid: np.ndarray,
                  g: np.ndarray) -> np.ndarray:
    """Per texel the relative residual of the gained model against its targets,
    sqrt(Σ (L0 + g ΔL − T)²) / sqrt(Σ T²) over the pairs that count and the three channels:
    (t,) float64, 0 for a texel the model reproduces, NaN where no pair counts or every
    target is 0 (nothing to reproduce). g : (t, 3)."""
    w = valid[..., None]
    r = (l0 + np.asarray(g)[:, None, None, :] * dl - tgt) * w
    num = np.einsum("tijc,tijc->t", r, r)
    den = np.einsum("tijc,tijc->t", tgt * w, tgt)
    return np.sqrt(np.divide(num, den, out=np.full(den.shape, np.nan), where=den > 0))
