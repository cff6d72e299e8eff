"""UsdPreviewSurface inputs fitted to a texel's filtered appearance (the fitted fallback).

The target of a texel is its filtered reflectance over a fixed set of light and view
directions in the tangent frame of the LOD surface (`fit_directions`), from dense samples of
M_org with shadowing and masking (seed 000, Eq. 7 evaluated on the samples):

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
objective is the relative radiance residual Σ_(l,v) Σ_rgb ((L_fit − T) / (T + τ))², τ the
texel's mean T over the set per channel (`relative_weights`), equal weight per direction pair
(pairs whose view sees nothing of the texel left out): a linear residual is all mirror peaks
(on the bolt a peak is 10⁵ times the off-peak radiance) and leaves the diffuse free to take
anything, so the fit made a metal's diffuseColor 1 (object 4.7x too bright at LOD1). It stays
a weighted linear least squares (the weights are the target's), so still closed form. The
residual reported per texel is that objective's RMS over the pairs and channels (0 is exact,
1 is an error the size of the target). A mix of a metal and a dielectric at one roughness is such a
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


def _basis(normal: np.ndarray, dirs: np.ndarray, roughness: np.ndarray
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The specular workflow's terms a, b, c (t, k, k) of L = d' a + s b + c at each texel's
    roughness (t,),
    radiance per unit irradiance (n·l)⁺ included, from `preview_surface` itself (f at
    (d, s) = (1, 0), (0, 1), (0, 0)): a texel's shading normal (t, 3) unit, dirs (k, 3)."""
    t, k = normal.shape[0], dirs.shape[0]
    fr = tangent_frames(normal)  # (t, 3, 3) rows (t, b, n): the BRDF in n's frame
    loc = np.einsum("tij,kj->tki", fr, dirs)  # (t, k, 3)
    wi = np.broadcast_to(loc[:, :, None, :], (t, k, k, 3)).reshape(-1, 3)
    wo = np.broadcast_to(loc[:, None, :, :], (t, k, k, 3)).reshape(-1, 3)
    cos_l = np.broadcast_to(np.maximum(loc[:, :, None, 2], 0.0), (t, k, k)).reshape(-1)
    out = []
    for d, s in ((1.0, 0.0), (0.0, 1.0), (0.0, 0.0)):  # three evaluations of the spec's BRDF
        p = {"useSpecularWorkflow": 1, "diffuseColor": (d, d, d), "specularColor": (s, s, s),
             "roughness": np.repeat(roughness, k * k)}
        out.append(preview_surface(p, wi, wo)[:, 0] * cos_l)
    a, b, c = out[0] - out[2], out[1] - out[2], out[2]
    return a.reshape(t, k, k), b.reshape(t, k, k), c.reshape(t, k, k)


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


def relative_weights(tgt: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """The objective's weights 1 / (T + τ) (t, k, k, 3), τ the texel's mean T over its valid
    pairs per channel (a floor, relative to the texel's own level), 0 on invalid pairs."""
    wv = valid.astype(np.float64)[..., None]
    n = np.maximum(wv.sum(axis=(1, 2)), 1.0)  # (t, 1)
    tau = (tgt * wv).sum(axis=(1, 2)) / n  # (t, 3)
    tau = np.maximum(tau, 1e-12)[:, None, None, :]
    return wv / (np.maximum(tgt, 0.0) + tau)


def _fit_at(tgt, valid, normal, dirs, roughness):
    """Closed-form (d', s) per channel at each texel's roughness (t,); returns (x, y,
    weighted residual² (t,) summed over pairs and channels)."""
    a, b, c = _basis(normal, dirs, roughness)
    w = relative_weights(tgt, valid)  # (t, k, k, 3)
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
                roughness: np.ndarray, dirs: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """The specular-workflow UsdPreviewSurface inputs of least radiance residual (module
    docstring) for each texel, at its given roughness.

    target : (t, k, k, 3) float64 T(light i, view o); valid : (t, k, k) bool pairs that count
    normal : (t, 3) the shading normal in the tangent frame (unit; the normal map's)
    roughness : (t,) the lobe's roughness (the texel's widened one, `filtered_maps.
        fallback_roughness`: a sparse direction set samples a narrow lobe only at its peak,
        so it cannot tell its width; the slope statistics can)
    dirs : (k, 3) the directions of the set (`fit_directions()` when None)
    returns : diffuseColor (t, 3), specularColor (t, 3), roughness (t,), residual (t,) (relative
        RMS), all float64"""
    dirs = fit_directions() if dirs is None else np.asarray(dirs, dtype=np.float64)
    tgt = np.asarray(target, dtype=np.float64)
    rough = np.clip(np.asarray(roughness, dtype=np.float64), 0.0, 1.0)
    t, k = tgt.shape[0], dirs.shape[0]
    if (tgt.shape != (t, k, k, 3) or valid.shape != (t, k, k) or normal.shape != (t, 3)
            or rough.shape != (t,)):
        raise ShapeError(f"fit_preview: target {tgt.shape}, valid {valid.shape}, normal "
                         f"{normal.shape}, roughness {rough.shape} do not match "
                         f"({t}, {k}, {k}, 3)")
    x, y, res2 = _fit_at(tgt, valid, np.asarray(normal, dtype=np.float64), dirs, rough)
    diffuse = np.where(y < 1.0, x / np.maximum(1.0 - y, 1e-12), 0.0)
    count = 3.0 * valid.sum(axis=(1, 2))
    rel = np.sqrt(res2 / np.maximum(count, 1.0))
    return {"diffuseColor": np.clip(diffuse, 0.0, 1.0), "specularColor": y,
            "roughness": rough, "residual": np.where(count > 0, rel, 0.0)}


def render_fit(params: dict[str, np.ndarray], normal: np.ndarray,
               dirs: np.ndarray | None = None) -> np.ndarray:
    """L(l, v) (t, k, k, 3) of fitted specular-workflow inputs (`fit_preview`'s keys) on the
    set, from `preview_surface` per texel: what the fit reproduces."""
    dirs = fit_directions() if dirs is None else np.asarray(dirs, dtype=np.float64)
    t, k = normal.shape[0], dirs.shape[0]
    fr = tangent_frames(np.asarray(normal, dtype=np.float64))
    loc = np.einsum("tij,kj->tki", fr, dirs)
    wi = np.broadcast_to(loc[:, :, None, :], (t, k, k, 3)).reshape(-1, 3)
    wo = np.broadcast_to(loc[:, None, :, :], (t, k, k, 3)).reshape(-1, 3)
    rep = np.repeat(np.arange(t), k * k)
    p = {"useSpecularWorkflow": 1, "diffuseColor": params["diffuseColor"][rep],
         "specularColor": params["specularColor"][rep], "roughness": params["roughness"][rep]}
    cos_l = np.maximum(wi[:, 2], 0.0)
    return (preview_surface(p, wi, wo) * cos_l[:, None]).reshape(t, k, k, 3)
