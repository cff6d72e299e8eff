"""Analytic BRDFs: Lambert, modified Phong, UsdPreviewSurface (GGX + Schlick), a GGX conductor."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from texelbake import model
from texelbake.brdf.common import (
    CHUNK,
    INV_PI,
    PREVIEW_MIN_ROUGHNESS,
    as_color,
    as_dirs,
    as_scalar,
    row_block,
    valid_pairs,
)
from texelbake.errors import SettingsError
from texelbake.tol import TOL


def lambert(albedo: Any, wi: Any, wo: Any, *, eps: float = TOL.grazing_cos) -> np.ndarray:
    """Lambertian BRDF f_r = albedo / pi.

    albedo : (3,) or (n, 3) float64 (diffuse reflectance rho, directional albedo = rho)
    wi, wo : (n, 3) float64 unit vectors, local frame
    returns : (n, 3) float64, 1/sr
    """
    wi, wo = as_dirs(wi, wo)
    n = wi.shape[0]
    rho = as_color(albedo, n, "albedo")
    ok = valid_pairs(wi, wo, eps)
    return np.where(ok[:, None], rho * INV_PI, 0.0)


def phong(
    kd: Any, ks: Any, exponent: Any, wi: Any, wo: Any, *, eps: float = TOL.grazing_cos
) -> np.ndarray:
    """Energy-normalised modified Phong (Lafortune & Willems 1994, "Using the modified Phong
    reflectance model for physically based rendering", Sec. 3):

        f_r = kd / pi + ks (e + 2) / (2 pi) max(0, cos a)^e,   cos a = r(wi) . wo,

    r(wi) = (-wi.x, -wi.y, wi.z) the mirror direction of wi about the normal. cos a is
    symmetric in (wi, wo), so the model is reciprocal; with kd + ks <= 1 its directional albedo
    is <= 1 (the lobe integrates to at most 1 at normal incidence). Not the same function as the
    shading-model fit of seed 001, Eq. 5 (ka + kd (N.L) + ks (N.H)^alpha, a cosine-weighted
    Blinn-Phong), which the BTF stage owns.

    kd, ks : (3,) or (n, 3) float64; exponent : () or (n,) float64 >= 0
    wi, wo : (n, 3) float64; returns : (n, 3) float64
    """
    wi, wo = as_dirs(wi, wo)
    n = wi.shape[0]
    kd_ = as_color(kd, n, "kd")
    ks_ = as_color(ks, n, "ks")
    e = as_scalar(exponent, n, "exponent")
    if np.any(e < 0):
        raise SettingsError(f"phong exponent must be >= 0, got min {e.min()}")
    ok = valid_pairs(wi, wo, eps)
    # cos a, symmetric term by term: wi.z*wo.z - wi.x*wo.x - wi.y*wo.y
    cos_a = wi[:, 2] * wo[:, 2]
    cos_a -= wi[:, 0] * wo[:, 0]
    cos_a -= wi[:, 1] * wo[:, 1]
    np.maximum(cos_a, 0.0, out=cos_a)
    lobe = np.power(cos_a, e)  # (n,)
    lobe *= (e + 2.0) * (0.5 * INV_PI)
    out = ks_ * lobe[:, None]
    out += kd_ * INV_PI
    out[~ok] = 0.0
    return out


def _half_terms(wi: np.ndarray, wo: np.ndarray) -> tuple[np.ndarray, ...]:
    """Half-vector terms without forming h, exactly symmetric in (wi, wo).

    returns zi, zo (clipped >= 0), nh2 = (n.h)^2, cos_d = wi.h = wo.h, each (n,) float64.
    |wi + wo|^2 = 2 (1 + wi.wo), so n.h = (zi + zo) / sqrt(2 (1 + c)), wo.h = sqrt((1 + c) / 2).
    """
    zi = np.maximum(wi[:, 2], 0.0)
    zo = np.maximum(wo[:, 2], 0.0)
    c = wi[:, 0] * wo[:, 0]
    c += wi[:, 1] * wo[:, 1]
    c += wi[:, 2] * wo[:, 2]
    c += 1.0  # 1 + wi.wo  (= |wi + wo|^2 / 2)
    np.maximum(c, TOL.brdf_eps, out=c)
    nh2 = zi + zo
    nh2 *= nh2
    nh2 /= 2.0 * c
    np.minimum(nh2, 1.0, out=nh2)
    c *= 0.5
    cos_d = np.sqrt(c, out=c)
    np.minimum(cos_d, 1.0, out=cos_d)
    return zi, zo, nh2, cos_d


def _ggx_dv(nh2: np.ndarray, zi: np.ndarray, zo: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """D(h) * G(wi, wo) / (4 (n.wi) (n.wo)) for GGX with separable Schlick-GGX G.

    D = a^2 / (pi ((n.h)^2 (a^2 - 1) + 1)^2)                  (Walter et al. 2007, Eq. 33)
    G = G1(wi) G1(wo), G1(w) = n.w / ((n.w)(1 - k) + k), k = a/2
        (Schlick's approximation of Smith, with Karis' k = alpha/2, as in the Hydra Storm
        UsdPreviewSurface shader, previewSurface.glslfx ``Geometric``)
    so G / (4 zi zo) = 1 / (4 (zi (1 - k) + k) (zo (1 - k) + k)), which has no 0/0 at grazing.
    All (n,) or (1,) float64; returns (n,) float64.
    """
    a2 = alpha * alpha
    d = nh2 * (a2 - 1.0)
    d += 1.0
    d *= d
    d *= np.pi
    k = 0.5 * alpha
    gi = zi * (1.0 - k)
    gi += k
    go = zo * (1.0 - k)
    go += k
    gi *= go
    gi *= 4.0
    d *= gi
    return a2 / d


def schlick_weight(cos_d: np.ndarray) -> np.ndarray:
    """(1 - cos_d)^5, (n,) float64 (Schlick 1994)."""
    w = 1.0 - cos_d
    np.maximum(w, 0.0, out=w)
    w2 = w * w
    w2 *= w2
    w *= w2
    return w


def _preview_block(
    wi: np.ndarray, wo: np.ndarray, p: Mapping[str, np.ndarray]
) -> np.ndarray:
    zi, zo, nh2, cos_d = _half_terms(wi, wo)
    fres = schlick_weight(cos_d)  # (b,)
    diffuse = p["diffuseColor"]
    m = p["metallic"][:, None]
    spec_wf = p["useSpecularWorkflow"][:, None] != 0.0
    r = (1.0 - p["ior"]) / (1.0 + p["ior"])
    r2 = (r * r)[:, None]
    f0 = np.where(spec_wf, p["specularColor"], r2 * (1.0 - m) + diffuse * m)
    f90 = np.where(spec_wf, 1.0, (1.0 - m) + diffuse * m)
    dcol = np.where(spec_wf, diffuse, diffuse * (1.0 - m))
    fr = f0 + (f90 - f0) * fres[:, None]  # (b, 3) Schlick F
    dv = _ggx_dv(nh2, zi, zo, p["alpha"])  # (b,)
    out = fr * dv[:, None]
    out += dcol * INV_PI * (1.0 - fr)
    cc = p["clearcoat"]
    if np.any(cc > 0.0):
        r2c = r2[:, 0]
        fc = r2c + (1.0 - r2c) * fres
        fc *= cc
        fc *= _ggx_dv(nh2, zi, zo, p["alpha_c"])
        out += fc[:, None]
    return out


def preview_surface(
    params: Mapping[str, Any], wi: Any, wo: Any, *, eps: float = TOL.grazing_cos
) -> np.ndarray:
    """UsdPreviewSurface BRDF (direct lighting part), per the published spec
    (openusd.org, "UsdPreviewSurface Specification", input docs of ``metallic``,
    ``specularColor``, ``roughness``, ``clearcoat``, ``ior``) and its reference implementation,
    the Hydra Storm shader ``previewSurface.glslfx`` (``evaluateLight``). Exactly:

        alpha = max(roughness, 0.001)^2                          (Storm clamps roughness)
        w     = (1 - wo.h)^5,  h = (wi + wo)/|wi + wo|             (Schlick; wo.h = wi.h)
        R     = ((1 - ior) / (1 + ior))^2
        specular workflow (useSpecularWorkflow != 0):
            F0 = specularColor, F90 = 1, d = diffuseColor
        metallic workflow (spec: "If metallic is 1, F0 and F90 are the albedo; if 0, F0 = R and
        F90 is white; in between we interpolate"):
            F0 = (1 - m) R + m diffuseColor, F90 = (1 - m) + m diffuseColor,
            d = (1 - m) diffuseColor
        F     = F0 + (F90 - F0) w
        f_r   = d / pi * (1 - F)                         (Storm: "glazing angles have less diffuse")
              + F D G / (4 (n.wi)(n.wo))                 (GGX D, Schlick-GGX G with k = alpha/2:
                                                          see ``_ggx_dv``)
              + clearcoat * Fc Dc Gc / (4 (n.wi)(n.wo))   (white lobe, Fc = R + (1 - R) w,
                                                          alpha_c = max(clearcoatRoughness,
                                                          0.001)^2, added as in Storm)

    Deviations from Storm, on purpose: Storm's metallic F0 is R * mix(1, diffuseColor, m), which
    at m = 1 gives R * albedo, contradicting the spec text; we follow the spec (as MaterialX
    PR #1187 and RenderMan's UsdPreviewSurfaceParameters.osl do). Storm's EPSILON = 0.001 in
    D's numerator and in the 4 (n.l)(n.v) denominator, and its PI = 3.1415, are GPU guards, not
    part of the model, and are left out. Not BRDF terms, hence not evaluated here: emissive,
    opacity, occlusion (an AO factor; texelbake computes visibility itself), displacement, and
    the ``normal`` input (the caller's shading frame).

    Energy: the model as specified is not strictly energy conserving. The diffuse weight
    (1 - F(wo.h)) does not remove the energy the specular lobe takes at grazing view angles:
    measured by Monte Carlo (4e5 samples), diffuseColor = 1, roughness 0.3, ior 1.5 has
    directional albedo 1.16 +- 0.01 at 80 deg and 1.26 +- 0.03 at 89 deg; diffuseColor = 0.8
    stays <= 1 up to 80 deg. The clearcoat lobe is added without attenuating the base (as in
    Storm), adding up to ~clearcoat * Fc more at grazing angles. We keep the spec's numbers
    (the baked result must match what USD renderers show) and test albedo <= 1 for realistic
    albedos (diffuseColor <= 0.8, metals, the specular workflow).

    params : dict with any of the UsdPreviewSurface inputs (missing ones take
        ``model.PREVIEW_DEFAULTS``): colours (3,) or (n, 3); scalars () or (n,)
    wi, wo : (n, 3) float64; returns : (n, 3) float64

    Speed (2 shared cores, 2**21 pairs): 0.20 s in numpy (blocks of ``CHUNK`` rows), against
    1.17 s for the same formulas in torch CPU on whole arrays, so numpy is used.
    """
    wi, wo = as_dirs(wi, wo)
    n = wi.shape[0]
    p = preview_surface_params(params, n)
    ok = valid_pairs(wi, wo, eps)
    out = np.empty((n, 3), dtype=np.float64)
    for lo in range(0, n, CHUNK):
        hi = min(lo + CHUNK, n)
        pb = {k: row_block(v, lo, hi) for k, v in p.items()}
        out[lo:hi] = _preview_block(wi[lo:hi], wo[lo:hi], pb)
    out[~ok] = 0.0
    return out


def preview_surface_params(params: Mapping[str, Any], n: int) -> dict[str, np.ndarray]:
    unknown = set(params) - set(model.PREVIEW_DEFAULTS)
    if unknown:
        raise SettingsError(
            f"unknown UsdPreviewSurface inputs {sorted(unknown)}; expected a subset of "
            f"{sorted(model.PREVIEW_DEFAULTS)}"
        )
    get = {**model.PREVIEW_DEFAULTS, **params}
    p: dict[str, np.ndarray] = {}
    for name in ("diffuseColor", "specularColor"):
        p[name] = as_color(get[name], n, name)
    for name in ("metallic", "roughness", "clearcoat", "clearcoatRoughness", "ior",
                 "useSpecularWorkflow"):
        p[name] = as_scalar(get[name], n, name)
    p["metallic"] = np.clip(p["metallic"], 0.0, 1.0)
    p["clearcoat"] = np.clip(p["clearcoat"], 0.0, 1.0)
    p["alpha"] = np.clip(p.pop("roughness"), PREVIEW_MIN_ROUGHNESS, 1.0) ** 2
    p["alpha_c"] = np.clip(p.pop("clearcoatRoughness"), PREVIEW_MIN_ROUGHNESS, 1.0) ** 2
    return p


def ggx_conductor(
    f0: Any, roughness: Any, wi: Any, wo: Any, *, eps: float = TOL.grazing_cos
) -> np.ndarray:
    """A metallic GGX lobe with no diffuse: f_r = F D G / (4 (n.wi)(n.wo)), Schlick F from F0 to
    white, the same D and G as :func:`preview_surface` (equal to it with metallic = 1,
    diffuseColor = f0, clearcoat = 0). Used for the cellular shader's borders.

    f0 : (3,) or (n, 3) float64; roughness : () or (n,) float64 (alpha = roughness^2, clamped
    as in :func:`preview_surface`); wi, wo : (n, 3) float64; returns : (n, 3) float64
    """
    wi, wo = as_dirs(wi, wo)
    n = wi.shape[0]
    f0_ = as_color(f0, n, "f0")
    alpha = np.clip(as_scalar(roughness, n, "roughness"), PREVIEW_MIN_ROUGHNESS, 1.0) ** 2
    ok = valid_pairs(wi, wo, eps)
    out = np.empty((n, 3), dtype=np.float64)
    for lo in range(0, n, CHUNK):
        hi = min(lo + CHUNK, n)
        zi, zo, nh2, cos_d = _half_terms(wi[lo:hi], wo[lo:hi])
        w = schlick_weight(cos_d)[:, None]
        f0b = row_block(f0_, lo, hi)
        fr = f0b + (1.0 - f0b) * w
        fr *= _ggx_dv(nh2, zi, zo, row_block(alpha, lo, hi))[:, None]
        out[lo:hi] = fr
    out[~ok] = 0.0
    return out
