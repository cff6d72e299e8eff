"""UsdPreviewSurface inputs fitted to a texel's filtered appearance (the fitted fallback).

The target of a texel is its filtered reflectance over a fixed set of light directions and
view cells in the tangent frame of the LOD surface (`fit_directions`, `cell_views`: each
sample sees a view drawn in each cell; the fit's basis takes each cell's mean, the diffuse on
a stratified set of views, the lobe by importance sampling, `_specular_cells`), from dense
samples of M_org with shadowing and masking (seed 000, Eq. 7 evaluated on the samples):

    T(l, v) = Σ_s A_s f_s(l, v) V_s(l) (n_s·l)⁺ V_s(v) (n_g,s·v)⁺ / Σ_s A_s V_s(v) (n_g,s·v)⁺

the radiance toward v under unit irradiance from l, averaged over the texel's visible
projected area, as `texelbake.cpm.level.visibility_cos` builds R (shading cosine for the
light, geometric for the view). The fallback shades the LOD surface with its shading normal n
(the texel's mean normal, what the normal map carries) as a viewer and the `preview-surface`
mode do: L(l, v) = f_ps(l, v) (n·l)⁺.

The fit uses the specular workflow (``useSpecularWorkflow = 1``), where the UsdPreviewSurface
BRDF (`brdf.analytic.preview_surface`, the specification's) is, at a fixed roughness,
*linear* in d' = diffuseColor (1 − specularColor) and s = specularColor per channel:

    f = d' (1 − w)/π + s (1 − w) DG + w DG,   w = (1 − v·h)⁵,  DG = D G / (4 (n·l)(n·v))

so per texel the least-squares inputs at its roughness are closed form (a convex 2-variable
QP per channel over d' ≥ 0, s ≥ 0, d' + s ≤ 1, i.e. diffuseColor, specularColor in [0, 1]).
The roughness is not searched: the direction set samples a narrow lobe only at its mirror
pairs, so a search matches the peaks with a wider, brighter lobe (measured on the bolt: the
object 2.9x too bright at LOD1, 12x at LOD2); the texel's slope statistics give the width
(`filtered_maps.fallback_roughness`, the widened roughness) and the fit gives the colours,
which carry the shadowing and masking that the widened lobe lacks. The
objective is the linear radiance residual Σ_(l,v) Σ_rgb (L_fit − T)², equal weight per
(light, view cell) pair (pairs whose view sees nothing of the texel left out): what an
image's PSNR measures. Point views instead of cells made it match a metal's mirror peaks
with the diffuse (the bolt's object 2.9x too bright at LOD1); a relative residual
((L − T)/(T + τ))² with point views left the object 0.16-0.75x as bright as the original. The
residual reported per texel is the fit's RMS over the pairs and channels divided by the
RMS of T (0 is exact; 1 is no better than black). A mix of a metal and a dielectric at one roughness is such a
surface but for the metal's tinted Fresnel edge (F90 = its colour, white in the specular
workflow): both F0s go to specularColor, the dielectric's share to diffuseColor, where the
metallic workflow's one metallic would blend the two colours into both lobes;
a texel no lobe can match (deep grooves whose masking darkens grazing views) gets the
inputs of least residual, and its residual says how far it is.

No iteration, no randomness: the result is a function of the sums, bit for bit.
"""

from __future__ import annotations

import numpy as np

from texelbake.brdf.analytic import preview_surface
from texelbake.brdf.common import PREVIEW_MIN_ROUGHNESS
from texelbake.errors import ShapeError
from texelbake.geometry.basis import tangent_frames
from texelbake.tol import TOL

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


def _specular_cells(normal: np.ndarray, roughness: np.ndarray, params: dict) -> np.ndarray:
    """Each view cell's mean of f_ps (n·l)⁺ (t, k, k) for specular-only inputs `params` (no
    diffuse), by importance sampling the GGX lobe (IS_STRATA² stratified half vectors per
    texel and light, v the reflection of l, pdf D (n·h) / (4 v·h)): the lobe is as narrow as
    the roughness makes it, which a uniform quadrature of a cell misses."""
    dirs = fit_directions()
    t, k = normal.shape[0], dirs.shape[0]
    g = (np.arange(IS_STRATA) + 0.5) / IS_STRATA
    u = np.stack(np.meshgrid(g, g, indexing="ij"), axis=-1).reshape(-1, 2)  # (S, 2)
    ns = u.shape[0]
    fr = tangent_frames(np.asarray(normal, dtype=np.float64))  # rows (t, b, n)
    li = np.einsum("tij,kj->tki", fr, dirs)  # (t, k, 3) lights in n's frame
    alpha = np.clip(roughness, PREVIEW_MIN_ROUGHNESS, 1.0) ** 2  # (t,)
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
    rows = {key: np.repeat(val, k * ns) if np.ndim(val) == 1 and len(val) == t else val
            for key, val in params.items()}
    f = preview_surface(rows, wi, v.reshape(-1, 3))[:, 0].reshape(t, k, ns)
    est = np.where(ok, f * np.maximum(li[:, :, None, 2], 0.0) / np.where(ok, pdf, 1.0), 0.0)
    out = np.zeros((t, k, k))
    ti, ii, si = np.nonzero(ok)
    np.add.at(out, (ti, ii, cell[ti, ii, si]), est[ti, ii, si])
    return out / (ns * cell_solid_angles()[None, None, :])


def _basis(normal: np.ndarray, roughness: np.ndarray
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The specular workflow's terms a, b, c (t, k, k) of L = d' a + s b + c at each texel's
    roughness (t,), each a view cell's mean, radiance per unit irradiance (n·l)⁺ included,
    from `preview_surface` itself: a (the diffuse, smooth: f at (d, s) = (1, 0) minus (0, 0) on
    the stratified `basis_views`), b and c (the lobe: f at (0, 1) minus (0, 0), and (0, 0),
    importance-sampled, `_specular_cells`); a texel's shading normal (t, 3) unit."""
    t, k = normal.shape[0], fit_directions().shape[0]
    wi, wo = _pair_dirs(normal)
    m = wi.shape[0] // (t * k * k)
    cos_l = np.maximum(wi[:, 2], 0.0)
    diffuse = []
    for d in (1.0, 0.0):  # the diffuse part on the stratified views
        p = {"useSpecularWorkflow": 1, "diffuseColor": (d, d, d), "specularColor": (0, 0, 0),
             "roughness": np.repeat(roughness, k * k * m)}
        diffuse.append((preview_surface(p, wi, wo)[:, 0] * cos_l).reshape(t, k, k, m).mean(3))
    lobe = [_specular_cells(normal, roughness, {"useSpecularWorkflow": 1, "diffuseColor": (0, 0, 0),
                                                "specularColor": (s, s, s),
                                                "roughness": roughness}) for s in (1.0, 0.0)]
    return diffuse[0] - diffuse[1], lobe[0] - lobe[1], lobe[1]


def _qp_triangle(gaa, gab, gbb, ra, rb):
    """argmin of x² gaa + 2xy gab + y² gbb − 2(x ra + y rb) over x, y ≥ 0, x + y ≤ 1, for
    (t, 3) arrays (the Gram entries (t, 1) broadcast): the convex minimum lies inside or on
    an edge, so the best of the interior and the three edges' clipped minimisers is it."""
    eps = TOL.brdf_eps
    det = gaa * gbb - gab * gab
    xi = np.where(det > eps, (ra * gbb - rb * gab) / np.maximum(det, eps), -1.0)
    yi = np.where(det > eps, (rb * gaa - ra * gab) / np.maximum(det, eps), -1.0)
    cands = [(xi, yi)]
    cands.append((np.clip(ra / np.maximum(gaa, eps), 0.0, 1.0), np.zeros_like(ra)))
    cands.append((np.zeros_like(rb), np.clip(rb / np.maximum(gbb, eps), 0.0, 1.0)))
    den = gaa - 2.0 * gab + gbb
    ye = np.clip((gaa - gab - ra + rb) / np.maximum(den, eps), 0.0, 1.0)
    cands.append((1.0 - ye, ye))
    best_x, best_y = np.zeros_like(ra), np.zeros_like(ra)
    best = np.zeros_like(ra)  # (0, 0) is feasible with objective 0
    for x, y in cands:  # the four candidates
        ok = (x >= 0.0) & (y >= 0.0) & (x + y <= 1.0 + 1e-12)
        q = x * x * gaa + 2.0 * x * y * gab + y * y * gbb - 2.0 * (x * ra + y * rb)
        take = ok & (q < best)
        best_x, best_y, best = (np.where(take, x, best_x), np.where(take, y, best_y),
                                np.where(take, q, best))
    return best_x, best_y, best


def _fit_at(tgt, valid, normal, roughness):
    """Closed-form (d', s) per channel at each texel's roughness (t,); returns (x, y,
    residual² (t,) summed over pairs and channels)."""
    a, b, c = _basis(normal, roughness)
    w = np.broadcast_to(valid[..., None], tgt.shape).astype(np.float64)  # (t, k, k, 3)
    aw, bw = a[..., None] * w, b[..., None] * w
    r = (tgt - c[..., None]) * w  # (t, k, k, 3)
    gaa = np.einsum("tijc,tijc->tc", aw, aw)
    gab = np.einsum("tijc,tijc->tc", aw, bw)
    gbb = np.einsum("tijc,tijc->tc", bw, bw)
    ra = np.einsum("tijc,tijc->tc", aw, r)
    rb = np.einsum("tijc,tijc->tc", bw, r)
    x, y, q = _qp_triangle(gaa, gab, gbb, ra, rb)
    res2 = np.einsum("tijc,tijc->t", r, r) + q.sum(axis=1)
    return x, y, np.maximum(res2, 0.0)


def fit_preview(target: np.ndarray, valid: np.ndarray, normal: np.ndarray,
                roughness: np.ndarray) -> dict[str, np.ndarray]:
    """The specular-workflow UsdPreviewSurface inputs of least radiance residual (module
    docstring) for each texel, at its given roughness.

    target : (t, k, k, 3) float64 T(light i, view o); valid : (t, k, k) bool pairs that count
    normal : (t, 3) the shading normal in the tangent frame (unit; the normal map's)
    roughness : (t,) the lobe's roughness (the texel's widened one, `filtered_maps.
        fallback_roughness`: a sparse direction set samples a narrow lobe only at its peak,
        so it cannot tell its width; the slope statistics can)
    returns : diffuseColor (t, 3), specularColor (t, 3), roughness (t,), residual (t,) (relative
        RMS), all float64"""
    dirs = fit_directions()
    tgt = np.asarray(target, dtype=np.float64)
    rough = np.clip(np.asarray(roughness, dtype=np.float64), 0.0, 1.0)
    t, k = tgt.shape[0], dirs.shape[0]
    if (tgt.shape != (t, k, k, 3) or valid.shape != (t, k, k) or normal.shape != (t, 3)
            or rough.shape != (t,)):
        raise ShapeError(f"fit_preview: target {tgt.shape}, valid {valid.shape}, normal "
                         f"{normal.shape}, roughness {rough.shape} do not match "
                         f"({t}, {k}, {k}, 3)")
    x, y, res2 = _fit_at(tgt, valid, np.asarray(normal, dtype=np.float64), rough)
    diffuse = np.where(y < 1.0, x / np.maximum(1.0 - y, 1e-12), 0.0)
    norm2 = np.einsum("tijc,tijc->t", tgt * valid[..., None], tgt)
    rel = np.sqrt(res2 / np.maximum(norm2, 1e-300))
    return {"diffuseColor": np.clip(diffuse, 0.0, 1.0), "specularColor": y,
            "roughness": rough, "residual": np.where(norm2 > 0, rel, 0.0)}


def render_fit(params: dict[str, np.ndarray], normal: np.ndarray) -> np.ndarray:
    """L(l, v) (t, k, k, 3) of fitted specular-workflow inputs (`fit_preview`'s keys) on the
    set, each view cell's mean as the fit computes it (`_basis`): what the fit reproduces."""
    a, b, c = _basis(np.asarray(normal, dtype=np.float64), params["roughness"])
    s = params["specularColor"]
    x = params["diffuseColor"] * (1.0 - s)
    return a[..., None] * x[:, None, None] + b[..., None] * s[:, None, None] + c[..., None]


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
