"""Lobes widened by the normal variance a filtered normal map removed: Toksvig's
factor (Toksvig 2005) and the LEAN/LEADR slope statistics (Olano & Baker 2010; Dupuy et al.
2013), applied to the families the bake supports.

What each BRDF family maps to (σ² the Toksvig variance, Σ the meso-scale slope covariance,
x̄ the mean slope, per axis the Beckmann/GGX slope variance of roughness α is α²/2):

| family (`Material.model`) | toksvig                                    | leadr                                          |
|---------------------------|--------------------------------------------|------------------------------------------------|
| lambert                   | albedo/π at n̄/|n̄| (no lobe to widen)      | albedo/π, cosine n̄·ωi (= E[n·ωi])            |
| phong (modified Phong, s) | s' = s / (1 + s σ²) (Toksvig: s f_t)       | s' = 2/α'² − 2, α'² = 2/(s+2) + tr Σ, at n_μ   |
| preview (UsdPreviewSurface| roughness' = (α² + 2σ²)^¼                  | GGX slope distribution, LEADR's two moments:   |
|   GGX + Schlick)          |                                            | sheared to x̄, covariance A = α² I + 2Σ        |
|                           |                                            | (`preview_leadr`), Smith masking along the     |
|                           |                                            | projected roughness                           |
| cellular, merl            | the material at n̄/|n̄| (tabulated or      | the material at n_μ (same)                     |
|                           | procedural lobes: no roughness to widen)   |                                                |

LEADR's paper builds a Beckmann lobe from the moments (the slope distribution
P22 a Gaussian of mean x̄ and covariance Σ + α²/2 I, Smith's Λ of that Gaussian along the
projected direction, with the mean slope shifting cot θ). No material of this project has a
Beckmann lobe: keeping each family's own distribution makes every mode reduce exactly to the
material when Σ = 0 and x̄ = 0 (a flat plane: `toksvig` = `leadr` = `normalmap`, a tested hard
case), where swapping GGX for Beckmann would change the material itself. For UsdPreviewSurface
the GGX slope distribution (an elliptical Student-t, Walter et al. 2007 Eq. 33 in slope space)
takes the same two moments: the mean shifts it, the covariance adds in the variance-matched
convention A = α² I + 2Σ (Beckmann variance α²/2 per axis, the usual GGX ↔ Beckmann mapping).
Masking keeps the material's Schlick–Smith form G1 = z/(z(1 − k) + k), with k = α_o / 2,
α_o² = uᵀ A u the roughness projected on the direction's azimuth u (LEADR, after Smith: Λ
depends only on the slope distribution projected on the azimuth), and z the cosine to the
mean-slope normal (the sheared distribution's mean facet, LEADR's cot θ − x̄_u in Λ).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import replace
from typing import Any

import numpy as np

from texelbake import model
from texelbake.brdf.analytic import preview_surface_params, schlick_weight
from texelbake.brdf.common import INV_PI, PREVIEW_MIN_ROUGHNESS, as_dirs, valid_pairs
from texelbake.tol import TOL


def widen_material(material: model.Material, var_axis: np.ndarray) -> model.Material:
    """The material with its lobe widened by an isotropic slope variance per axis `var_axis`
    (n,) (the table above: Toksvig passes σ², LEADR's isotropic families tr Σ / 2); the
    widened inputs become per-row arrays (n,), so evaluate it on exactly n rows.
    Phong: s' = 2/α'² − 2 with α'² = 2/(s+2) + 2 var (equal to Toksvig's s f_t when
    var = σ² up to the Phong ↔ Beckmann mapping; exact at var = 0); preview: roughness' =
    (α² + 2 var)^¼ clipped to [0.001, 1]. Other families unchanged."""
    p = dict(material.params)
    if material.model == "phong":
        p["exponent"] = float(p.get("exponent", 32.0))
        return replace(material, params=widen_inputs("phong", p, var_axis))
    if material.model == "preview" and "roughness" not in material.textures:
        p["roughness"] = float(p.get("roughness", model.PREVIEW_DEFAULTS["roughness"]))
        return replace(material, params=widen_inputs("preview", p, var_axis))
    return material


def widen_inputs(kind: str, inputs: Mapping[str, Any], var_axis: np.ndarray) -> dict[str, Any]:
    """`widen_material`'s widening on a material's resolved inputs (`brdf.evaluate.
    material_inputs`: constants, or per-row arrays where a texture gave them), so that a
    roughness or exponent texture is widened too: `kind` the model ("phong", "preview"; any
    other is returned as is), var_axis (n,) the rows' variance per axis; the widened input
    comes back per row (n,). Equal to `widen_material` where the input is a constant."""
    v = np.maximum(np.nan_to_num(np.asarray(var_axis, dtype=np.float64), nan=0.0), 0.0)
    out = dict(inputs)
    if kind == "phong":
        s = np.asarray(inputs["exponent"], dtype=np.float64)
        a2 = 2.0 / (s + 2.0) + 2.0 * v
        out["exponent"] = np.where(v > 0, np.maximum(2.0 / a2 - 2.0, 0.0), s)
    elif kind == "preview":
        r = np.maximum(np.asarray(inputs.get("roughness", model.PREVIEW_DEFAULTS["roughness"]),
                                  dtype=np.float64), PREVIEW_MIN_ROUGHNESS)
        out["roughness"] = np.where(v > 0, np.clip(r ** 4 + 2.0 * v, 0.0, 1.0) ** 0.25, r)
    return out


def toksvig_phong_exponent(s: float | np.ndarray, nbar_length: np.ndarray) -> np.ndarray:
    """Toksvig's exponent s' = f_t s, f_t = |n̄| / (|n̄| + s (1 − |n̄|)) (Toksvig 2005,
    §"Eliminating Aliasing of Specular Highlights");
    (n,) float64, 0 <= s' <= s, |n̄| clipped to [0, 1]."""
    ln = np.clip(np.nan_to_num(np.asarray(nbar_length, dtype=np.float64), nan=0.0), 0.0, 1.0)
    s = np.asarray(s, dtype=np.float64)
    den = ln + s * (1.0 - ln)
    return np.divide(ln * s, den, out=np.zeros_like(ln * s), where=den > 0)


def _sheared_ggx(h: np.ndarray, mean: np.ndarray, a_inv: np.ndarray, sqrt_det: np.ndarray
                 ) -> np.ndarray:
    """D(h) = P22(m_h − x̄) / h_z⁴ with the elliptical GGX slope density
    P22(d) = 1 / (π √det A (1 + dᵀA⁻¹d)²) (isotropic A = α² I: Walter et al. 2007 Eq. 33).
    h : (n, 3) unit, h_z > 0; mean : (n, 2); a_inv : (n, 2, 2); sqrt_det : (n,)"""
    hz = np.maximum(h[:, 2], 1e-12)
    d = -h[:, :2] / hz[:, None] - mean  # (n, 2) slope of h minus the mean slope
    q = np.einsum("ni,nij,nj->n", d, a_inv, d)
    return 1.0 / (np.pi * sqrt_det * (1.0 + q) ** 2 * hz ** 4)


def _projected_k(w: np.ndarray, a: np.ndarray) -> np.ndarray:
    """k = α_o / 2, α_o² = uᵀ A u with u the azimuth of w (tr A / 2 at the pole); (n,)."""
    r = np.hypot(w[:, 0], w[:, 1])
    ux = np.divide(w[:, 0], r, out=np.zeros_like(r), where=r > 0)
    uy = np.divide(w[:, 1], r, out=np.zeros_like(r), where=r > 0)
    proj = a[:, 0, 0] * ux * ux + 2.0 * a[:, 0, 1] * ux * uy + a[:, 1, 1] * uy * uy
    a2 = np.where(r > 0, proj, 0.5 * (a[:, 0, 0] + a[:, 1, 1]))
    return 0.5 * np.sqrt(np.maximum(a2, 0.0))


def preview_leadr(params: Mapping[str, Any], wi: Any, wo: Any, mean_slope: np.ndarray,
                  cov: np.ndarray, *, eps: float = TOL.grazing_cos
                  ) -> tuple[np.ndarray, np.ndarray]:
    """UsdPreviewSurface (`analytic.preview_surface`) with its GGX lobes built from LEADR's
    slope statistics (module docstring), in the macro-surface (M1 tangent) frame.

    params : UsdPreviewSurface inputs (rows or constants); wi, wo : (n, 3) local to the macro
        frame; mean_slope : (n, 2) x̄; cov : (n, 2, 2) PSD meso-scale slope covariance Σ
    returns : (specular (n, 3) — F D G / (4 zi zo) (+ clearcoat), to be weighted by the macro
        cosine zi; diffuse (n, 3) — d/π (1 − F), to be weighted by the cosine to the
        mean-slope normal n_μ), both 0 where wi or wo is below the macro horizon or n_μ's.
    With x̄ = 0 and Σ = 0 the sum spec·zi + diffuse·zi is `preview_surface`·zi exactly.
    """
    wi, wo = as_dirs(wi, wo)
    n = wi.shape[0]
    p = preview_surface_params(params, n)
    mean = np.asarray(mean_slope, dtype=np.float64).reshape(n, 2)
    sig = np.asarray(cov, dtype=np.float64).reshape(n, 2, 2)
    n_mu = np.column_stack([-mean, np.ones(n)])
    n_mu /= np.linalg.norm(n_mu, axis=1, keepdims=True)
    zi_mu = np.einsum("ij,ij->i", wi, n_mu)
    zo_mu = np.einsum("ij,ij->i", wo, n_mu)
    ok = valid_pairs(wi, wo, eps) & (zi_mu > eps) & (zo_mu > eps)
    spec = np.zeros((n, 3))
    diffuse = np.zeros((n, 3))
    if not ok.any():
        return spec, diffuse
    idx = np.flatnonzero(ok)
    wi, wo, mean, sig = wi[idx], wo[idx], mean[idx], sig[idx]
    zi, zo, zi_m, zo_m = wi[:, 2], wo[:, 2], zi_mu[idx], zo_mu[idx]
    h = wi + wo
    h /= np.linalg.norm(h, axis=1, keepdims=True)
    cos_d = np.clip(np.einsum("ij,ij->i", wi, h), 0.0, 1.0)
    fres = schlick_weight(cos_d)
    row = {k: (v[idx] if v.shape[0] == n else v) for k, v in p.items()}
    d = row["diffuseColor"]
    m = row["metallic"][:, None]
    spec_wf = row["useSpecularWorkflow"][:, None] != 0.0
    r = (1.0 - row["ior"]) / (1.0 + row["ior"])
    r2 = (r * r)[:, None]
    f0 = np.where(spec_wf, row["specularColor"], r2 * (1.0 - m) + d * m)
    f90 = np.where(spec_wf, 1.0, (1.0 - m) + d * m)
    dcol = np.where(spec_wf, d, d * (1.0 - m))
    fr = f0 + (f90 - f0) * fres[:, None]

    def lobe(alpha: np.ndarray) -> np.ndarray:
        a = sig * 2.0
        a[:, 0, 0] += alpha * alpha
        a[:, 1, 1] += alpha * alpha
        det = a[:, 0, 0] * a[:, 1, 1] - a[:, 0, 1] * a[:, 1, 0]
        inv = np.empty_like(a)
        inv[:, 0, 0], inv[:, 1, 1] = a[:, 1, 1] / det, a[:, 0, 0] / det
        inv[:, 0, 1] = inv[:, 1, 0] = -a[:, 0, 1] / det
        dd = _sheared_ggx(h, mean, inv, np.sqrt(det))
        ki, ko = _projected_k(wi, a), _projected_k(wo, a)
        g = (zi_m / (zi_m * (1.0 - ki) + ki)) * (zo_m / (zo_m * (1.0 - ko) + ko))
        return dd * g / (4.0 * zi * zo)

    alpha = np.broadcast_to(row["alpha"], (idx.size,))
    spec[idx] = fr * lobe(alpha)[:, None]
    cc = np.broadcast_to(row["clearcoat"], (idx.size,))
    if np.any(cc > 0.0):
        fc = (r2[:, 0] + (1.0 - r2[:, 0]) * fres) * cc
        spec[idx] += (fc * lobe(np.broadcast_to(row["alpha_c"], (idx.size,))))[:, None]
    diffuse[idx] = dcol * INV_PI * (1.0 - fr)
    return spec, diffuse
