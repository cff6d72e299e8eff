"""BRDF models, vectorized over flat arrays of direction pairs.

Every BRDF here evaluates f_r(x, wi, wo), the SV-BRDF of seed 000, Eq. 1, from which the
apparent reflectance f = V(wi) V(wo) f_r (n.wi)(n.wo) (seed 000, Eq. 4) and the matrix
R[(wi, wo), j] = f(x_j, wi, wo) dA_j (seed 000, Eqs. 7 and 9) are built; the BTF stage filters
the same quantity (seed 001, Eq. 1).

Conventions (shared by every function of this module):

- Directions are unit vectors in the *local shading frame* (z = shading normal):
  ``wi : (n, 3) float64`` toward the light, ``wo : (n, 3) float64`` toward the viewer. They are
  not renormalised (the caller owns that; renormalising would cost a pass over the data).
- The result is ``f_r : (n, 3) float64``, RGB, in 1/sr, *without* the cosine factor.
- Below the horizon (``wi.z <= TOL.grazing_cos`` or ``wo.z <= TOL.grazing_cos``) and for
  non-finite directions the BRDF is exactly 0.
- Per-element parameters are "broadcastable to (n,)": scalars are ``()``, ``(1,)`` or
  ``(n,)``; colours are ``(3,)``, ``(1, 3)`` or ``(n, 3)``.

Models (``Material.model`` -> function): ``lambert`` -> :func:`lambert`, ``phong`` ->
:func:`phong`, ``preview`` -> :func:`preview_surface`, ``merl`` -> :func:`merl_lookup` on a table
from :func:`read_merl`, ``cellular`` -> :func:`cellular`. :func:`evaluate` dispatches on a
:class:`texelbake.model.Material`, resolving textured inputs with :func:`sample_texture`.

Speed: the large kernels run over blocks of ``_CHUNK`` rows so that their temporaries stay in
cache and memory stays bounded for 1e7+ rows. torch (CPU) was measured against numpy for the
UsdPreviewSurface kernel (numbers in :func:`preview_surface`) and was ~6x slower on this 2-core
machine, so numpy is used.

Written by hand because no maintained Python library evaluates these BRDFs vectorized over
numpy arrays with the UsdPreviewSurface semantics (the reference implementations are GLSL/OSL
shaders); the MERL reader follows the layout of MERL's own ``BRDFRead.cpp``.
"""

from __future__ import annotations

import functools
import os
import tempfile
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

from texelbake import model
from texelbake.errors import AssetError, SettingsError, ShapeError
from texelbake.tol import TOL

INV_PI = 1.0 / np.pi

#: rows per block in the chunked kernels (temporaries of a block stay in L2 cache)
_CHUNK = 1 << 15

#: UsdPreviewSurface: the Hydra Storm reference shader clamps roughness to at least 0.001
#: (previewSurface.glslfx, ``evaluateLight``), so alpha = roughness**2 >= 1e-6.
PREVIEW_MIN_ROUGHNESS = 1e-3

#: defaults of texelbake's own shader ids (the UsdPreviewSurface ones are model.PREVIEW_DEFAULTS)
LAMBERT_DEFAULTS: Mapping[str, Any] = {"diffuseColor": (0.18, 0.18, 0.18)}
PHONG_DEFAULTS: Mapping[str, Any] = {
    "diffuseColor": (0.18, 0.18, 0.18),
    "specularColor": (0.0, 0.0, 0.0),
    "exponent": 32.0,
}
CELLULAR_DEFAULTS: Mapping[str, Any] = {
    "cellScale": 8.0,
    "seed": 0,
    "borderWidth": 0.08,
    "borderColor": (1.0, 0.78, 0.34),  # a gold F0
    "borderRoughness": 0.25,
    "cellColorA": (0.70, 0.08, 0.06),
    "cellColorB": (0.05, 0.20, 0.65),
}
MERL_DEFAULTS: Mapping[str, Any] = {"scale": 1.0}

#: MERL binary format: resolution (theta_half, theta_diff, phi_diff) and channel scales
#: (BRDFRead.cpp: RED_SCALE = 1/1500, GREEN_SCALE = 1.15/1500, BLUE_SCALE = 1.66/1500)
MERL_SHAPE = (90, 90, 180)
MERL_SCALE = np.array([1.0 / 1500.0, 1.15 / 1500.0, 1.66 / 1500.0])

_WRAP_MODES = ("repeat", "clamp", "mirror", "black")


# --------------------------------------------------------------------------------------------
# input coercion
# --------------------------------------------------------------------------------------------


def _dirs(wi: Any, wo: Any) -> tuple[np.ndarray, np.ndarray]:
    wi = np.asarray(wi, dtype=np.float64)
    wo = np.asarray(wo, dtype=np.float64)
    if wi.ndim != 2 or wi.shape[1] != 3:
        raise ShapeError(f"wi must be (n, 3) float64, got shape {wi.shape}")
    if wo.shape != wi.shape:
        raise ShapeError(f"wo must match wi {wi.shape}, got shape {wo.shape}")
    return wi, wo


def _color(x: Any, n: int, name: str) -> np.ndarray:
    """(1, 3) or (n, 3) float64 from a scalar, (3,), (1, 3) or (n, 3) input."""
    a = np.asarray(x, dtype=np.float64)
    if a.ndim == 0:
        a = np.full((1, 3), float(a))
    elif a.ndim == 1 and a.shape[0] == 3:
        a = a[None, :]
    elif a.ndim == 1 and a.shape[0] == n:  # a grey value per element
        a = np.repeat(a[:, None], 3, axis=1)
    if a.ndim != 2 or a.shape[1] != 3 or a.shape[0] not in (1, n):
        raise ShapeError(f"colour input {name!r} must be (3,), (1, 3) or ({n}, 3), got {a.shape}")
    return a


def _scalar(x: Any, n: int, name: str) -> np.ndarray:
    """(1,) or (n,) float64 from a scalar, (1,) or (n,) input."""
    a = np.asarray(x, dtype=np.float64)
    if a.ndim == 0:
        a = a[None]
    if a.ndim == 2 and a.shape[1] == 1:
        a = a[:, 0]
    if a.ndim != 1 or a.shape[0] not in (1, n):
        raise ShapeError(f"scalar input {name!r} must be (), (1,) or ({n},), got {a.shape}")
    return a


def _rows(a: np.ndarray, lo: int, hi: int) -> np.ndarray:
    return a if a.shape[0] == 1 else a[lo:hi]


def _valid(wi: np.ndarray, wo: np.ndarray, eps: float) -> np.ndarray:
    """(n,) bool: both directions above the horizon and finite."""
    ok = (wi[:, 2] > eps) & (wo[:, 2] > eps)
    s = wi[:, 0] + wi[:, 1]  # column sums: ~5x faster than .sum(axis=1) on (n, 3)
    s += wi[:, 2]
    s += wo[:, 0]
    s += wo[:, 1]
    s += wo[:, 2]
    ok &= np.isfinite(s)
    return ok


# --------------------------------------------------------------------------------------------
# analytic BRDFs
# --------------------------------------------------------------------------------------------


def lambert(albedo: Any, wi: Any, wo: Any, *, eps: float = TOL.grazing_cos) -> np.ndarray:
    """Lambertian BRDF f_r = albedo / pi.

    albedo : (3,) or (n, 3) float64 (diffuse reflectance rho, directional albedo = rho)
    wi, wo : (n, 3) float64 unit vectors, local frame
    returns : (n, 3) float64, 1/sr
    """
    wi, wo = _dirs(wi, wo)
    n = wi.shape[0]
    rho = _color(albedo, n, "albedo")
    ok = _valid(wi, wo, eps)
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
    wi, wo = _dirs(wi, wo)
    n = wi.shape[0]
    kd_ = _color(kd, n, "kd")
    ks_ = _color(ks, n, "ks")
    e = _scalar(exponent, n, "exponent")
    if np.any(e < 0):
        raise SettingsError(f"phong exponent must be >= 0, got min {e.min()}")
    ok = _valid(wi, wo, eps)
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


def _schlick_weight(cos_d: np.ndarray) -> np.ndarray:
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
    fres = _schlick_weight(cos_d)  # (b,)
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

    Speed (2 shared cores, 2**21 pairs): 0.20 s in numpy (blocks of ``_CHUNK`` rows), against
    1.17 s for the same formulas in torch CPU on whole arrays, so numpy is used.
    """
    wi, wo = _dirs(wi, wo)
    n = wi.shape[0]
    p = _preview_params(params, n)
    ok = _valid(wi, wo, eps)
    out = np.empty((n, 3), dtype=np.float64)
    for lo in range(0, n, _CHUNK):
        hi = min(lo + _CHUNK, n)
        pb = {k: _rows(v, lo, hi) for k, v in p.items()}
        out[lo:hi] = _preview_block(wi[lo:hi], wo[lo:hi], pb)
    out[~ok] = 0.0
    return out


def _preview_params(params: Mapping[str, Any], n: int) -> dict[str, np.ndarray]:
    unknown = set(params) - set(model.PREVIEW_DEFAULTS)
    if unknown:
        raise SettingsError(
            f"unknown UsdPreviewSurface inputs {sorted(unknown)}; expected a subset of "
            f"{sorted(model.PREVIEW_DEFAULTS)}"
        )
    get = {**model.PREVIEW_DEFAULTS, **params}
    p: dict[str, np.ndarray] = {}
    for name in ("diffuseColor", "specularColor"):
        p[name] = _color(get[name], n, name)
    for name in ("metallic", "roughness", "clearcoat", "clearcoatRoughness", "ior",
                 "useSpecularWorkflow"):
        p[name] = _scalar(get[name], n, name)
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
    wi, wo = _dirs(wi, wo)
    n = wi.shape[0]
    f0_ = _color(f0, n, "f0")
    alpha = np.clip(_scalar(roughness, n, "roughness"), PREVIEW_MIN_ROUGHNESS, 1.0) ** 2
    ok = _valid(wi, wo, eps)
    out = np.empty((n, 3), dtype=np.float64)
    for lo in range(0, n, _CHUNK):
        hi = min(lo + _CHUNK, n)
        zi, zo, nh2, cos_d = _half_terms(wi[lo:hi], wo[lo:hi])
        w = _schlick_weight(cos_d)[:, None]
        f0b = _rows(f0_, lo, hi)
        fr = f0b + (1.0 - f0b) * w
        fr *= _ggx_dv(nh2, zi, zo, _rows(alpha, lo, hi))[:, None]
        out[lo:hi] = fr
    out[~ok] = 0.0
    return out


# --------------------------------------------------------------------------------------------
# directional albedo (Monte Carlo, cosine-weighted)
# --------------------------------------------------------------------------------------------


def cosine_hemisphere(u: np.ndarray) -> np.ndarray:
    """Map (m, 2) points of [0, 1)^2 to (m, 3) cosine-distributed unit vectors (pdf = z / pi)."""
    u = np.asarray(u, dtype=np.float64)
    if u.ndim != 2 or u.shape[1] != 2:
        raise ShapeError(f"u must be (m, 2), got {u.shape}")
    r = np.sqrt(u[:, 0])
    phi = 2.0 * np.pi * u[:, 1]
    z = np.sqrt(np.maximum(1.0 - u[:, 0], 0.0))
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def directional_albedo(
    brdf: Callable[[np.ndarray, np.ndarray], np.ndarray],
    wo: Any,
    *,
    n_samples: int = 200_000,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """Directional albedo rho(wo) = integral f_r(wi, wo) (n.wi) dwi by cosine-weighted Monte
    Carlo (estimator pi * f_r), independently for each view direction.

    brdf : callable (m, 3), (m, 3) -> (m, 3) float64
    wo : (k, 3) float64 unit view directions (local frame)
    returns : (mean (k, 3) float64, standard error (k, 3) float64)
    """
    wo = np.asarray(wo, dtype=np.float64).reshape(-1, 3)
    k = wo.shape[0]
    if k == 0:
        return np.zeros((0, 3)), np.zeros((0, 3))
    rng = np.random.default_rng(seed)
    mean = np.empty((k, 3))
    err = np.empty((k, 3))
    for i in range(k):  # a handful of view directions
        wi = cosine_hemisphere(rng.random((n_samples, 2)))
        est = np.pi * np.asarray(brdf(wi, np.broadcast_to(wo[i], wi.shape)), dtype=np.float64)
        mean[i] = est.mean(axis=0)
        err[i] = est.std(axis=0, ddof=1) / np.sqrt(n_samples)
    return mean, err


# --------------------------------------------------------------------------------------------
# MERL measured BRDFs
# --------------------------------------------------------------------------------------------


def write_merl(path: str | os.PathLike[str], table: Any) -> None:
    """Write a BRDF table in the MERL binary format (Matusik et al. 2003, ``BRDFRead.cpp``):
    three little-endian int32 dims (n_theta_half, n_theta_diff, n_phi_diff), then
    3 * prod(dims) little-endian float64, channel-major (R, G, B), each channel C-ordered as
    [theta_half][theta_diff][phi_diff], divided by the channel scale (1, 1.15, 1.66) / 1500.
    Negative values mark invalid entries. Written atomically (temp file + rename).

    table : (3, n_th, n_td, n_pd) float64
    """
    tab = np.asarray(table, dtype=np.float64)
    if tab.ndim != 4 or tab.shape[0] != 3:
        raise ShapeError(f"MERL table must be (3, n_th, n_td, n_pd), got {tab.shape}")
    dims = np.asarray(tab.shape[1:], dtype="<i4")
    data = np.ascontiguousarray(tab / MERL_SCALE[:, None, None, None], dtype="<f8")
    path = os.fspath(path)
    folder = os.path.dirname(os.path.abspath(path))
    fd, tmp = tempfile.mkstemp(dir=folder, prefix=".merl-", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(dims.tobytes())
            f.write(data.tobytes())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def read_merl(path: str | os.PathLike[str]) -> np.ndarray:
    """Read a MERL binary BRDF (layout in :func:`write_merl`).

    returns : (3, n_th, n_td, n_pd) float64 reflectance in 1/sr, channel scales applied,
        invalid (negative) entries set to 0. Standard files are (3, 90, 90, 180).
    raises AssetError (naming the file) when it is missing, truncated or has bad dims.
    """
    path = os.fspath(path)
    try:
        raw = np.fromfile(path, dtype=np.uint8)
    except OSError as exc:
        raise AssetError(f"cannot read MERL BRDF: {exc.strerror}", path=path) from exc
    if raw.size < 12:
        raise AssetError(f"MERL file too short: {raw.size} bytes, expected >= 12", path=path)
    dims = raw[:12].view("<i4").astype(np.int64)
    if np.any(dims <= 0) or np.any(dims > 4096):
        raise AssetError(f"MERL dims must be positive, got {dims.tolist()}", path=path)
    count = 3 * int(np.prod(dims))
    expected = 12 + 8 * count
    if raw.size != expected:
        raise AssetError(
            f"MERL file size {raw.size} bytes does not match dims {dims.tolist()} "
            f"(expected {expected})",
            path=path,
        )
    data = raw[12:].view("<f8").astype(np.float64).reshape(3, *dims.tolist())
    data *= MERL_SCALE[:, None, None, None]
    data[~(data >= 0.0)] = 0.0  # negative = invalid; NaN also dropped
    return data


@functools.lru_cache(maxsize=4)
def _read_merl_cached(path: str, mtime_ns: int, size: int) -> np.ndarray:
    table = read_merl(path)
    table.flags.writeable = False
    return table


def _merl_table_from_file(path: str) -> np.ndarray:
    try:
        st = os.stat(path)
    except OSError as exc:
        raise AssetError(f"MERL BRDF file not found: {exc.strerror}", path=path) from exc
    return _read_merl_cached(os.path.abspath(path), st.st_mtime_ns, st.st_size)


def _merl_angles(wi: np.ndarray, wo: np.ndarray) -> tuple[np.ndarray, ...]:
    """(theta_half, theta_diff, phi_diff in [0, pi)), each (n,) float64 (Rusinkiewicz 1998
    half/difference angles, as ``std_coords_to_half_diff_coords`` in ``BRDFRead.cpp``)."""
    h = wi + wo
    h /= np.maximum(np.linalg.norm(h, axis=1, keepdims=True), TOL.brdf_eps)
    # cos/sin of theta_half and phi_half straight from h (no trig round trip)
    ct = np.clip(h[:, 2], -1.0, 1.0)
    th = np.arccos(ct)
    st = np.hypot(h[:, 0], h[:, 1])
    pole = st <= TOL.brdf_eps  # h = n: phi_half undefined, take 0 (as atan2(0, 0) in MERL)
    inv = 1.0 / np.where(pole, 1.0, st)
    cp = np.where(pole, 1.0, h[:, 0] * inv)
    sp = np.where(pole, 0.0, h[:, 1] * inv)
    # rotate wi by -phi_half about the normal, then by -theta_half about the binormal
    x = cp * wi[:, 0] + sp * wi[:, 1]
    y = cp * wi[:, 1] - sp * wi[:, 0]
    z = wi[:, 2]
    dx = x * ct - z * st
    dz = x * st + z * ct
    td = np.arccos(np.clip(dz, -1.0, 1.0))
    pd = np.mod(np.arctan2(y, dx), np.pi)  # reciprocity: phi_diff and phi_diff + pi coincide
    return th, td, pd


def merl_lookup(
    table: Any, wi: Any, wo: Any, *, interpolate: bool = False, eps: float = TOL.grazing_cos
) -> np.ndarray:
    """Evaluate a tabulated BRDF in MERL layout.

    Bins as in MERL's ``BRDFRead.cpp``: theta_half index = floor(sqrt(theta_half / (pi/2)) n_th)
    (the non-linear mapping that puts more bins near the specular peak), theta_diff index =
    floor(theta_diff / (pi/2) n_td), phi_diff index = floor((phi_diff mod pi) / pi n_pd) (the
    table stores phi_diff in [0, pi) only, using reciprocity f(phi_d) = f(phi_d + pi)).
    ``interpolate=False`` returns the containing bin (the reference reader); ``True``
    interpolates trilinearly between bin centres in those index coordinates (clamped in the
    two theta axes, periodic in phi_diff).

    table : (3, n_th, n_td, n_pd) float64 (from :func:`read_merl` / :func:`tabulate_merl`)
    wi, wo : (n, 3) float64; returns : (n, 3) float64
    """
    tab = np.asarray(table, dtype=np.float64)
    if tab.ndim != 4 or tab.shape[0] != 3:
        raise ShapeError(f"MERL table must be (3, n_th, n_td, n_pd), got {tab.shape}")
    wi, wo = _dirs(wi, wo)
    n = wi.shape[0]
    n_th, n_td, n_pd = tab.shape[1:]
    flat = tab.reshape(3, -1)
    ok = _valid(wi, wo, eps)
    out = np.zeros((n, 3), dtype=np.float64)
    up_z = np.array([0.0, 0.0, 1.0])
    for lo in range(0, n, _CHUNK):
        hi = min(lo + _CHUNK, n)
        okb = ok[lo:hi, None]  # invalid rows (zeroed below) get a harmless stand-in direction
        th, td, pd = _merl_angles(np.where(okb, wi[lo:hi], up_z), np.where(okb, wo[lo:hi], up_z))
        uh = np.sqrt(th * (2.0 / np.pi)) * n_th
        ud = td * (2.0 / np.pi) * n_td
        up = pd * (1.0 / np.pi) * n_pd
        if not interpolate:
            ih = np.clip(uh.astype(np.int64), 0, n_th - 1)
            i_d = np.clip(ud.astype(np.int64), 0, n_td - 1)
            ip = np.clip(up.astype(np.int64), 0, n_pd - 1)
            idx = (ih * n_td + i_d) * n_pd + ip
            for ch in range(3):  # np.take per channel: ~10x faster than flat[:, idx]
                out[lo:hi, ch] = np.take(flat[ch], idx)
            continue
        xh = np.clip(uh - 0.5, 0.0, n_th - 1.0)
        xd = np.clip(ud - 0.5, 0.0, n_td - 1.0)
        xp = np.mod(up - 0.5, n_pd)
        h0 = np.minimum(xh.astype(np.int64), n_th - 2) if n_th > 1 else np.zeros(hi - lo, int)
        d0 = np.minimum(xd.astype(np.int64), n_td - 2) if n_td > 1 else np.zeros(hi - lo, int)
        p0 = np.minimum(xp.astype(np.int64), n_pd - 1)
        fh, fd, fp = xh - h0, xd - d0, xp - p0
        h1 = np.minimum(h0 + 1, n_th - 1)
        d1 = np.minimum(d0 + 1, n_td - 1)
        p1 = (p0 + 1) % n_pd
        acc = np.zeros((hi - lo, 3))
        for ih, wh in ((h0, 1.0 - fh), (h1, fh)):  # 8 corners
            for i_d, wd in ((d0, 1.0 - fd), (d1, fd)):
                for ip, wp in ((p0, 1.0 - fp), (p1, fp)):
                    idx = (ih * n_td + i_d) * n_pd + ip
                    wgt = wh * wd * wp
                    for ch in range(3):
                        acc[:, ch] += np.take(flat[ch], idx) * wgt
        out[lo:hi] = acc
    out[~ok] = 0.0
    return out


def merl_bin_directions(shape: tuple[int, int, int] = MERL_SHAPE) -> tuple[np.ndarray, np.ndarray]:
    """The (wi, wo) pair at the centre of every MERL bin, with phi_half = 0.

    Bin centres: theta_half = ((i + 0.5) / n_th)^2 pi/2 (inverse of the sqrt mapping),
    theta_diff = (j + 0.5) / n_td pi/2, phi_diff = (k + 0.5) / n_pd pi. wi is the difference
    vector rotated back by theta_half about the binormal; wo is wi mirrored about h.
    returns : wi, wo each (n_th * n_td * n_pd, 3) float64, in the table's C order. Pairs with a
        direction below the horizon are included (a BRDF returns 0 there).
    """
    n_th, n_td, n_pd = (int(s) for s in shape)
    th = ((np.arange(n_th) + 0.5) / n_th) ** 2 * (0.5 * np.pi)
    td = (np.arange(n_td) + 0.5) / n_td * (0.5 * np.pi)
    pd = (np.arange(n_pd) + 0.5) / n_pd * np.pi
    th_g, td_g, pd_g = (g.ravel() for g in np.meshgrid(th, td, pd, indexing="ij"))
    d = np.stack([np.sin(td_g) * np.cos(pd_g), np.sin(td_g) * np.sin(pd_g), np.cos(td_g)], axis=1)
    ct, st = np.cos(th_g), np.sin(th_g)
    wi = np.stack([d[:, 0] * ct + d[:, 2] * st, d[:, 1], d[:, 2] * ct - d[:, 0] * st], axis=1)
    h = np.stack([st, np.zeros_like(st), ct], axis=1)
    wo = 2.0 * np.sum(h * wi, axis=1, keepdims=True) * h - wi
    return wi, wo


def tabulate_merl(
    fn: Callable[[np.ndarray, np.ndarray], np.ndarray],
    shape: tuple[int, int, int] = MERL_SHAPE,
) -> np.ndarray:
    """Tabulate an analytic BRDF ``fn(wi (m, 3), wo (m, 3)) -> (m, 3)`` at the MERL bin centres
    (:func:`merl_bin_directions`). returns : (3, n_th, n_td, n_pd) float64."""
    wi, wo = merl_bin_directions(shape)
    vals = np.empty((wi.shape[0], 3))
    step = 1 << 18
    for lo in range(0, wi.shape[0], step):  # bounded memory for fn's temporaries
        v = np.asarray(fn(wi[lo : lo + step], wo[lo : lo + step]), dtype=np.float64)
        if v.shape != (min(step, wi.shape[0] - lo), 3):
            raise ShapeError(f"fn must return (m, 3) values, got {v.shape}")
        vals[lo : lo + step] = v
    return np.ascontiguousarray(vals.T.reshape(3, *shape))


# --------------------------------------------------------------------------------------------
# cellular (Worley) shader
# --------------------------------------------------------------------------------------------

_M1 = np.uint64(0x9E3779B97F4A7C15)
_M2 = np.uint64(0xC2B2AE3D27D4EB4F)
_M3 = np.uint64(0x165667B19E3779F9)
_S1 = np.uint64(0xBF58476D1CE4E5B9)
_S2 = np.uint64(0x94D049BB133111EB)


def _hash_u64(ix: np.ndarray, iy: np.ndarray, seed: np.ndarray, salt: int) -> np.ndarray:
    """Deterministic 64-bit hash per integer cell (splitmix64 finaliser over the cell
    coordinates, the seed and a salt). int64 arrays of broadcastable shapes -> uint64."""
    x = np.atleast_1d(np.asarray(ix, dtype=np.int64)).view(np.uint64) * _M1
    x ^= np.atleast_1d(np.asarray(iy, dtype=np.int64)).view(np.uint64) * _M2
    sd = np.atleast_1d(np.asarray(seed, dtype=np.int64)).view(np.uint64)
    x ^= (sd + np.uint64(salt)) * _M3
    x ^= x >> np.uint64(30)
    x *= _S1
    x ^= x >> np.uint64(27)
    x *= _S2
    x ^= x >> np.uint64(31)
    return x


def _hash_cells(ix: np.ndarray, iy: np.ndarray, seed: np.ndarray, salt: int) -> np.ndarray:
    """Uniform [0, 1) float64 per integer cell (top 53 bits of ``_hash_u64``)."""
    return (_hash_u64(ix, iy, seed, salt) >> np.uint64(11)).astype(np.float64) * 2.0**-53


def _feature_offsets(ix: np.ndarray, iy: np.ndarray, seed: np.ndarray) -> tuple[np.ndarray, ...]:
    """The Worley feature point of each cell relative to its corner: (u, v) in [0, 1)^2, the
    high and low 32 bits of one hash (one hash per cell instead of two). float64 arrays."""
    h = _hash_u64(ix, iy, seed, 0)
    u = (h >> np.uint64(32)).astype(np.float64) * 2.0**-32
    v = (h & np.uint64(0xFFFFFFFF)).astype(np.float64) * 2.0**-32
    return u, v


def _feature_points(ix: np.ndarray, iy: np.ndarray, seed: np.ndarray) -> tuple[np.ndarray, ...]:
    """Absolute feature points (ix + u, iy + v) of cells, float64 arrays."""
    u, v = _feature_offsets(ix, iy, seed)
    return u + ix, v + iy


_NEIGHBOURS = np.array([(dx, dy) for dy in (-1, 0, 1) for dx in (-1, 0, 1)], dtype=np.int64)


def worley(points: Any, seed: Any = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Worley (1996) cellular noise with one feature point per unit cell.

    Each integer cell (i, j) holds the feature point (i, j) + (u, v), (u, v) from a seeded hash;
    each query checks its own and the 8 neighbouring cells (a loop over the 9 offsets, each
    vectorized over all queries, keeping running nearest / second-nearest distances).
    3 x 3 cells give F1 exactly and F2 in all but rare configurations (a feature point two cells
    away can be nearer than the 3 x 3 second-nearest) — the usual Worley trade-off.

    points : (n, 2) float64 (uv * cellScale); seed : () or (n,) int
    returns : f1 (n,) float64, f2 (n,) float64 (nearest and second-nearest feature distances),
        cell (n, 2) int64 (the cell of the nearest feature point). Non-finite points get
        f1 = f2 = NaN and cell (0, 0).
    """
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 2:
        raise ShapeError(f"points must be (n, 2), got {pts.shape}")
    n = pts.shape[0]
    seed_a = np.asarray(seed, dtype=np.int64)
    if seed_a.ndim > 1 or (seed_a.ndim == 1 and seed_a.shape[0] not in (1, n)):
        raise ShapeError(f"seed must be () or ({n},), got {seed_a.shape}")
    f1 = np.empty(n)
    f2 = np.empty(n)
    cell = np.empty((n, 2), dtype=np.int64)
    finite: np.ndarray = np.all(np.isfinite(pts), axis=1)
    for lo in range(0, n, _CHUNK):
        hi = min(lo + _CHUNK, n)
        p = np.where(finite[lo:hi, None], pts[lo:hi], 0.0)
        base = np.floor(p).astype(np.int64)  # (b, 2)
        frac = p - base  # (b, 2) position inside the own cell
        sd = seed_a.reshape(1) if seed_a.size == 1 else seed_a[lo:hi]  # (b|1,)
        d1 = np.full(hi - lo, np.inf)  # running nearest / second-nearest squared distances
        d2 = np.full(hi - lo, np.inf)
        arg = np.zeros(hi - lo, dtype=np.int64)
        for k, (ox, oy) in enumerate(_NEIGHBOURS):  # the 3 x 3 cells, vectorized over b
            fx, fy = _feature_offsets(base[:, 0] + ox, base[:, 1] + oy, sd)
            fx += ox - frac[:, 0]  # feature - query, relative to the own cell: no large
            fy += oy - frac[:, 1]  # coordinates, so no cancellation far from the origin
            dk = fx * fx
            dk += fy * fy
            nearer = dk < d1
            np.minimum(d2, np.where(nearer, d1, dk), out=d2)
            np.copyto(d1, dk, where=nearer)
            np.copyto(arg, k, where=nearer)
        f1[lo:hi] = np.sqrt(d1)
        f2[lo:hi] = np.sqrt(d2)
        cell[lo:hi] = base + _NEIGHBOURS[arg]
    f1[~finite] = np.nan
    f2[~finite] = np.nan
    cell[~finite] = 0
    return f1, f2, cell


def _cellular_params(params: Mapping[str, Any], n: int) -> dict[str, np.ndarray]:
    unknown = set(params) - set(CELLULAR_DEFAULTS)
    if unknown:
        raise SettingsError(
            f"unknown cellular inputs {sorted(unknown)}; expected {sorted(CELLULAR_DEFAULTS)}"
        )
    get = {**CELLULAR_DEFAULTS, **params}
    p = {k: _color(get[k], n, k) for k in ("borderColor", "cellColorA", "cellColorB")}
    for k in ("cellScale", "borderWidth", "borderRoughness"):
        p[k] = _scalar(get[k], n, k)
    seed = np.asarray(get["seed"])
    if not np.issubdtype(seed.dtype, np.integer) and not np.all(seed == np.round(seed)):
        raise SettingsError(f"cellular seed must be an integer, got {get['seed']!r}")
    p["seed"] = _scalar(seed, n, "seed").astype(np.int64)
    if np.any(p["cellScale"] <= 0):
        raise SettingsError(f"cellScale must be > 0, got min {p['cellScale'].min()}")
    return p


def _uv(uv: Any) -> np.ndarray:
    a = np.asarray(uv, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 2:
        raise ShapeError(f"uv must be (n, 2) float64, got shape {a.shape}")
    return a


def _cells(p: Mapping[str, np.ndarray], uv: np.ndarray) -> tuple[np.ndarray, ...]:
    seed = p["seed"] if p["seed"].shape[0] > 1 else p["seed"][0]
    return worley(uv * p["cellScale"][:, None], seed)


def cellular_mask(params: Mapping[str, Any], uv: Any) -> np.ndarray:
    """(n,) bool: True on cell borders, F2 - F1 < borderWidth (distances in cell units).

    params : cellular inputs (``CELLULAR_DEFAULTS``); uv : (n, 2) float64
    """
    uv = _uv(uv)
    p = _cellular_params(params, uv.shape[0])
    f1, f2, _ = _cells(p, uv)
    return (f2 - f1) < p["borderWidth"]


def cellular_cell_id(params: Mapping[str, Any], uv: Any) -> np.ndarray:
    """(n,) int64 id of the cell (nearest feature point) under each uv: the cell's integer
    coordinates (i, j) packed as (i mod 2^32) * 2^32 + (j mod 2^32)."""
    uv = _uv(uv)
    p = _cellular_params(params, uv.shape[0])
    _, _, cell = _cells(p, uv)
    return _pack_cell(cell)


def _pack_cell(cell: np.ndarray) -> np.ndarray:
    u = cell.astype(np.int64).view(np.uint64) & np.uint64(0xFFFFFFFF)
    return ((u[:, 0] << np.uint64(32)) | u[:, 1]).view(np.int64)


def _cell_color(p: Mapping[str, np.ndarray], cell: np.ndarray) -> np.ndarray:
    seed = np.broadcast_to(p["seed"], cell.shape[:1])
    t = _hash_cells(cell[:, 0], cell[:, 1], seed, 2)[:, None]
    return p["cellColorA"] + t * (p["cellColorB"] - p["cellColorA"])


def cellular_color(params: Mapping[str, Any], uv: Any) -> np.ndarray:
    """(n, 3) float64 Lambertian albedo of the cell under each uv: cellColorA + t (cellColorB -
    cellColorA) with t in [0, 1) a seeded hash of the cell, so neighbouring cells differ."""
    uv = _uv(uv)
    p = _cellular_params(params, uv.shape[0])
    _, _, cell = _cells(p, uv)
    return _cell_color(p, cell)


def _cellular_split(
    p: Mapping[str, np.ndarray], uv: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-uv part of the cellular shader: border (m,) bool, cell colour (m, 3), finite (m,)."""
    f1, f2, cell = _cells(p, uv)
    finite = ~np.isnan(f1)
    return (f2 - f1) < p["borderWidth"], _cell_color(p, cell), finite


def _cellular_shade(
    border: np.ndarray,
    color: np.ndarray,
    finite: np.ndarray,
    border_color: np.ndarray,
    border_roughness: np.ndarray,
    wi: np.ndarray,
    wo: np.ndarray,
    eps: float,
) -> np.ndarray:
    """Per-row shading: border (n,) bool, color (n, 3), finite (n,), border_color (1|n, 3),
    border_roughness (1|n,), wi/wo (n, 3) -> (n, 3)."""
    out = lambert(color, wi, wo, eps=eps)
    out[~finite] = 0.0  # non-finite uv: no defined cell, no reflectance
    if np.any(border):
        sel = np.flatnonzero(border)
        bc = border_color if border_color.shape[0] == 1 else border_color[sel]
        br = border_roughness if border_roughness.shape[0] == 1 else border_roughness[sel]
        out[sel] = ggx_conductor(bc, br, wi[sel], wo[sel], eps=eps)
    return out


def cellular(
    params: Mapping[str, Any], uv: Any, wi: Any, wo: Any, *, eps: float = TOL.grazing_cos
) -> np.ndarray:
    """The cloisonne-like procedural shader of seed 000, Sec. 5 (Fig. 7): a cellular texture
    (Worley 1996) over uv * cellScale; inside a cell a Lambertian BRDF with the cell's colour
    (:func:`cellular_color`); on the borders (:func:`cellular_mask`) a sharp metallic GGX lobe
    (:func:`ggx_conductor` with F0 = borderColor, roughness = borderRoughness) standing in for the
    seed's measured gold-metallic-paint BRDF.

    params : cellular inputs; uv : (n, 2) float64; wi, wo : (n, 3) float64
    returns : (n, 3) float64 (0 where uv is not finite)
    """
    wi, wo = _dirs(wi, wo)
    uv = _uv(uv)
    n = wi.shape[0]
    if uv.shape[0] != n:
        raise ShapeError(f"uv must be ({n}, 2) to match wi, got {uv.shape}")
    p = _cellular_params(params, n)
    border, color, finite = _cellular_split(p, uv)
    return _cellular_shade(
        border, color, finite, p["borderColor"], p["borderRoughness"], wi, wo, eps
    )


# --------------------------------------------------------------------------------------------
# textures
# --------------------------------------------------------------------------------------------


def _wrap(i: np.ndarray, size: int, mode: str) -> tuple[np.ndarray, np.ndarray | None]:
    """Texel indices -> (in-range indices, valid mask or None)."""
    if mode == "repeat":
        return np.mod(i, size), None
    if mode == "clamp":
        return np.clip(i, 0, size - 1), None
    if mode == "mirror":
        j = np.mod(i, 2 * size)
        return np.where(j >= size, 2 * size - 1 - j, j), None
    # black: texels outside the image are 0 (blend with black within half a texel of the edge)
    valid = (i >= 0) & (i < size)
    return np.clip(i, 0, size - 1), valid


def sample_texture(tex: model.Texture, uv: Any) -> np.ndarray:
    """Bilinearly filtered texture lookup, UsdUVTexture semantics.

    Texel (row r, column c) of ``tex.pixels`` (row 0 = top) has its centre at
    s = (c + 0.5) / w, t = 1 - (r + 0.5) / h, so uv (0, 0) is the bottom-left corner of the image
    (USD convention). Wrap modes per axis: repeat, clamp, mirror (mirrored repeat), black (0
    outside [0, 1]). Output = scale * texel + bias per channel (UsdUVTexture ``scale``,
    ``bias``, first c of the 4 components).

    tex : model.Texture with pixels (h, w, c); uv : (n, 2) float64
    returns : (n, c) float64
    """
    uv = _uv(uv)
    pix = np.asarray(tex.pixels)
    if pix.ndim == 2:
        pix = pix[:, :, None]
    if pix.ndim != 3 or pix.shape[0] == 0 or pix.shape[1] == 0 or pix.shape[2] == 0:
        raise ShapeError(f"texture {tex.path!r}: pixels must be (h, w, c), got {pix.shape}")
    for axis, mode in (("wrapS", tex.wrap_s), ("wrapT", tex.wrap_t)):
        if mode not in _WRAP_MODES:
            raise SettingsError(
                f"texture {tex.path!r}: {axis} {mode!r} not one of {list(_WRAP_MODES)}"
            )
    h, w, c = pix.shape
    if c > 4:
        raise ShapeError(f"texture {tex.path!r}: at most 4 channels, got {c}")
    n = uv.shape[0]
    if n == 0:
        return np.zeros((0, c))
    x = uv[:, 0] * w - 0.5
    y = (1.0 - uv[:, 1]) * h - 0.5
    x0f = np.floor(x)
    y0f = np.floor(y)
    fx = (x - x0f)[:, None]
    fy = (y - y0f)[:, None]
    x0 = x0f.astype(np.int64)
    y0 = y0f.astype(np.int64)
    cols = [_wrap(x0, w, tex.wrap_s), _wrap(x0 + 1, w, tex.wrap_s)]
    rows = [_wrap(y0, h, tex.wrap_t), _wrap(y0 + 1, h, tex.wrap_t)]
    out = np.zeros((n, c))
    for (r, rv), wy in ((rows[0], 1.0 - fy), (rows[1], fy)):
        for (col, cv), wx in ((cols[0], 1.0 - fx), (cols[1], fx)):
            v = pix[r, col].astype(np.float64)  # (n, c)
            wgt = wy * wx
            if rv is not None:
                wgt = wgt * rv[:, None]
            if cv is not None:
                wgt = wgt * cv[:, None]
            out += v * wgt
    scale = np.resize(np.asarray(tex.scale, dtype=np.float64), 4)[:c]
    bias = np.resize(np.asarray(tex.bias, dtype=np.float64), 4)[:c]
    out *= scale
    out += bias
    return out


# --------------------------------------------------------------------------------------------
# the dispatcher
# --------------------------------------------------------------------------------------------

_COLOR_INPUTS = frozenset(
    {"diffuseColor", "specularColor", "borderColor", "cellColorA", "cellColorB", "normal"}
)
_MODELS = ("lambert", "phong", "preview", "merl", "cellular")
_DEFAULTS: Mapping[str, Mapping[str, Any]] = {
    "lambert": LAMBERT_DEFAULTS,
    "phong": PHONG_DEFAULTS,
    "preview": model.PREVIEW_DEFAULTS,
    "cellular": CELLULAR_DEFAULTS,
    "merl": MERL_DEFAULTS,
}
#: inputs that only make sense as constants (never sampled from a texture)
_CONSTANT_INPUTS = frozenset({"seed", "cellScale", "useSpecularWorkflow", "file", "table"})


def _input(
    material: model.Material, name: str, n: int, uv: np.ndarray | None
) -> tuple[Any, bool]:
    """A material input: (value, textured). The texture sampled at uv ((n, 3) colour or (n,)
    scalar, textured=True) when the input is textured, else the constant, else the model's
    default (textured=False, the raw value)."""
    tex = material.textures.get(name)
    if tex is not None and name not in _CONSTANT_INPUTS:
        if uv is None:
            raise ShapeError(
                f"material {material.path!r}: input {name!r} is textured ({tex.path}); "
                f"uv (n, 2) is required, got None"
            )
        v = sample_texture(tex, uv)  # (n, c)
        if name in _COLOR_INPUTS:
            return (v[:, :3] if v.shape[1] >= 3 else np.repeat(v[:, :1], 3, axis=1)), True
        return v[:, 0], True
    if name in material.params:
        return material.params[name], False
    return _DEFAULTS[material.model][name], False


def _inputs(
    material: model.Material,
    names: Sequence[str],
    uv: np.ndarray | None,
    rows: np.ndarray | None,
) -> dict[str, Any]:
    """Resolve inputs once per uv row (textures sampled at uv (m, 2)), then gather the
    textured ones to the evaluation rows (rows (n,) int into uv, or None for rows = uv rows)."""
    m = 1 if uv is None else uv.shape[0]
    out = {}
    for name in names:
        v, textured = _input(material, name, m, uv)
        out[name] = np.take(v, rows, axis=0) if (textured and rows is not None) else v
    return out


def _check_model(material: model.Material) -> None:
    if material.model not in _MODELS:
        raise SettingsError(
            f"material {material.path!r}: unknown BRDF model {material.model!r}, expected one "
            f"of {list(_MODELS)}"
        )


def _merl_table(material: model.Material) -> np.ndarray:
    if "table" in material.params:
        return np.asarray(material.params["table"], dtype=np.float64)
    if "file" in material.params:
        return _merl_table_from_file(os.fspath(material.params["file"]))
    raise SettingsError(
        f"material {material.path!r}: merl model needs params 'table' or 'file', got "
        f"{sorted(material.params)}"
    )


def evaluate(
    material: model.Material,
    wi: Any,
    wo: Any,
    uv: Any = None,
    *,
    sample_index: Any = None,
    eps: float = TOL.grazing_cos,
) -> np.ndarray:
    """Evaluate a material's BRDF.

    Picks the model from ``material.model``; each input comes from
    ``material.textures[name]`` sampled at uv (bilinear, :func:`sample_texture`), else from
    ``material.params[name]``, else from the model's defaults. Colour inputs take the first 3
    texture channels (a 1- or 2-channel texture is read as grey), scalar inputs the first.

    material : model.Material; wi, wo : (n, 3) float64 local-frame unit vectors
    uv : (n, 2) float64 or None (required for textured inputs and the cellular model); with
        ``sample_index`` it is (m, 2), one row per surface sample
    sample_index : (n,) int into uv, or None. The CPM layout (many direction pairs per sample):
        textures and the cellular pattern are then evaluated once per sample (m rows) and
        gathered, instead of once per (sample, direction pair) row.
    returns : (n, 3) float64, 1/sr
    raises SettingsError (naming material.path) for an unknown model, ShapeError for bad shapes
    """
    _check_model(material)
    wi, wo = _dirs(wi, wo)
    n = wi.shape[0]
    uv_a = None if uv is None else _uv(uv)
    rows = _rows_index(sample_index, n, uv_a)
    if uv_a is not None and rows is None and uv_a.shape[0] != n:
        raise ShapeError(f"uv must be ({n}, 2) to match wi, got {uv_a.shape}")
    kind = material.model
    if kind == "lambert":
        p = _inputs(material, ("diffuseColor",), uv_a, rows)
        return lambert(p["diffuseColor"], wi, wo, eps=eps)
    if kind == "phong":
        p = _inputs(material, ("diffuseColor", "specularColor", "exponent"), uv_a, rows)
        return phong(p["diffuseColor"], p["specularColor"], p["exponent"], wi, wo, eps=eps)
    if kind == "preview":
        return preview_surface(_inputs(material, _PREVIEW_BRDF_INPUTS, uv_a, rows), wi, wo,
                               eps=eps)
    if kind == "merl":
        scale = _scalar(_inputs(material, ("scale",), uv_a, rows)["scale"], n, "scale")
        return merl_lookup(_merl_table(material), wi, wo, eps=eps) * scale[:, None]
    # cellular: the pattern once per uv row, the shading per evaluation row
    if uv_a is None:
        raise ShapeError(f"material {material.path!r}: the cellular model needs uv (n, 2)")
    m = uv_a.shape[0]
    p = _cellular_params(_inputs(material, tuple(CELLULAR_DEFAULTS), uv_a, None), m)
    border, color, finite = _cellular_split(p, uv_a)
    bc, br = p["borderColor"], p["borderRoughness"]
    if rows is not None:
        border, color, finite = border[rows], color[rows], finite[rows]
        bc = bc if bc.shape[0] == 1 else bc[rows]
        br = br if br.shape[0] == 1 else br[rows]
    return _cellular_shade(border, color, finite, bc, br, wi, wo, eps)


def _rows_index(sample_index: Any, n: int, uv: np.ndarray | None) -> np.ndarray | None:
    if sample_index is None:
        return None
    rows = np.asarray(sample_index)
    if rows.shape != (n,) or not (np.issubdtype(rows.dtype, np.integer) or n == 0):
        raise ShapeError(f"sample_index must be ({n},) int, got {rows.shape} {rows.dtype}")
    if uv is None:  # no per-sample inputs to gather: every row uses the constants
        return None
    rows = rows.astype(np.int64)
    m = uv.shape[0]
    if n and (rows.min() < 0 or rows.max() >= m):
        raise ShapeError(
            f"sample_index must lie in [0, {m - 1}] (uv has {m} rows), got "
            f"[{rows.min()}, {rows.max()}]"
        )
    return rows


_PREVIEW_BRDF_INPUTS = (
    "diffuseColor",
    "specularColor",
    "useSpecularWorkflow",
    "metallic",
    "roughness",
    "clearcoat",
    "clearcoatRoughness",
    "ior",
)

#: stratified cosine-weighted directions for the MERL normal-incidence albedo (deterministic)
_ALBEDO_GRID = 128


def diffuse_albedo(material: model.Material, uv: Any = None) -> np.ndarray:
    """The albedo a normal-map baker bakes for this material (what Blender / Substance /
    xNormal put in an albedo map next to the normal map; DESIGN.md "Rendering").

    preview: diffuseColor * (1 - metallic) (metallic workflow) or diffuseColor (specular);
    lambert, phong: diffuseColor (kd); cellular: the cell colour under uv; merl: the
    directional albedo at normal incidence, integral f_r(wi, n) (n.wi) dwi (stratified
    128 x 128 cosine-weighted quadrature), i.e. the Lambertian rho with the same normal-incidence
    reflectance, times ``scale``.

    material : model.Material; uv : (n, 2) float64 or None (then n = 1)
    returns : (n, 3) float64
    """
    _check_model(material)
    uv_a = None if uv is None else _uv(uv)
    n = 1 if uv_a is None else uv_a.shape[0]
    kind = material.model
    if kind in ("lambert", "phong"):
        d = _inputs(material, ("diffuseColor",), uv_a, None)["diffuseColor"]
        return np.broadcast_to(_color(d, n, "diffuseColor"), (n, 3)).copy()
    if kind == "preview":
        p = _inputs(material, ("diffuseColor", "metallic", "useSpecularWorkflow"), uv_a, None)
        d = _color(p["diffuseColor"], n, "diffuseColor")
        m = np.clip(_scalar(p["metallic"], n, "metallic"), 0.0, 1.0)
        wf = _scalar(p["useSpecularWorkflow"], n, "useSpecularWorkflow")
        out = np.where(wf[:, None] != 0.0, d, d * (1.0 - m[:, None]))
        return np.broadcast_to(out, (n, 3)).copy()
    if kind == "cellular":
        if uv_a is None:
            raise ShapeError(f"material {material.path!r}: the cellular model needs uv (n, 2)")
        return cellular_color(_inputs(material, tuple(CELLULAR_DEFAULTS), uv_a, None), uv_a)
    # merl
    g = (np.arange(_ALBEDO_GRID) + 0.5) / _ALBEDO_GRID
    u = np.stack(np.meshgrid(g, g, indexing="ij"), axis=-1).reshape(-1, 2)
    wi = cosine_hemisphere(u)
    wo = np.broadcast_to(np.array([0.0, 0.0, 1.0]), wi.shape)
    rho = np.pi * merl_lookup(_merl_table(material), wi, wo).mean(axis=0)
    scale = _scalar(_inputs(material, ("scale",), uv_a, None)["scale"], n, "scale")[:, None]
    return np.broadcast_to(rho[None, :] * scale, (n, 3)).copy()


def shading_normal(material: model.Material, uv: Any = None) -> np.ndarray:
    """Tangent-space shading normal of a material: UsdPreviewSurface's ``normal`` input
    ("Expects normal in tangent space [(-1,-1,-1), (1,1,1)]"; a normal map is connected
    through a UsdUVTexture whose scale (2, 2, 2, 1) and bias (-1, -1, -1, 0) do the remapping,
    so the sampled value is used as is), normalised. (0, 0, 1) for the other models, and where
    the value is not finite, has zero length or points below the tangent plane (z <= 0).

    :func:`evaluate` does not apply it: the caller owns the shading frame (build it with
    ``frames.tangent_frames(normal_world, tangent_world)`` and pass directions in it), so that
    the cosine terms and the BRDF use the same normal.

    material : model.Material; uv : (n, 2) float64 or None (then n = 1)
    returns : (n, 3) float64 unit vectors in the (t, b, n) frame of the surface
    """
    _check_model(material)
    uv_a = None if uv is None else _uv(uv)
    n = 1 if uv_a is None else uv_a.shape[0]
    up = np.zeros((n, 3))
    up[:, 2] = 1.0
    if material.model != "preview":
        return up
    v = np.broadcast_to(_color(_input(material, "normal", n, uv_a)[0], n, "normal"), (n, 3))
    length = np.linalg.norm(v, axis=1, keepdims=True)
    ok = np.isfinite(length[:, 0]) & (length[:, 0] > TOL.brdf_eps) & (v[:, 2] > 0.0)
    return np.where(ok[:, None], v / np.where(ok[:, None], length, 1.0), up)


def evaluate_by_face(
    materials: Sequence[model.Material],
    material_index: Any,
    wi: Any,
    wo: Any,
    uv: Any = None,
    *,
    sample_index: Any = None,
    eps: float = TOL.grazing_cos,
) -> np.ndarray:
    """Evaluate many (sample, direction-pair) entries with a material per entry: groups by
    material index (a loop over the few materials present, vectorized within each).

    materials : sequence of model.Material; material_index : (n,) int
    wi, wo : (n, 3) float64; uv : (n, 2) float64 or None
    sample_index : (n,) int or None; when given, uv is (m, 2) per surface sample and
        textures / the cellular pattern are evaluated once per sample (see :func:`evaluate`)
    returns : (n, 3) float64
    """
    wi, wo = _dirs(wi, wo)
    n = wi.shape[0]
    idx = np.asarray(material_index)
    if idx.shape != (n,) or not (np.issubdtype(idx.dtype, np.integer) or idx.size == 0):
        raise ShapeError(f"material_index must be ({n},) int, got {idx.shape} {idx.dtype}")
    idx = idx.astype(np.int64)
    uv_a = None if uv is None else _uv(uv)
    rows = _rows_index(sample_index, n, uv_a)
    if uv_a is not None and rows is None and uv_a.shape[0] != n:
        raise ShapeError(f"uv must be ({n}, 2) to match wi, got {uv_a.shape}")
    out = np.zeros((n, 3), dtype=np.float64)
    if n == 0:
        return out
    lo, hi = int(idx.min()), int(idx.max())
    if lo < 0 or hi >= len(materials):
        raise ShapeError(
            f"material_index must lie in [0, {len(materials) - 1}], got [{lo}, {hi}]"
        )
    order = np.argsort(idx, kind="stable")
    bounds = np.flatnonzero(np.diff(idx[order])) + 1
    for group in np.split(order, bounds):  # one group per material present
        mat = materials[int(idx[group[0]])]
        if rows is None:
            out[group] = evaluate(
                mat, wi[group], wo[group], None if uv_a is None else uv_a[group], eps=eps
            )
            continue
        # only the samples this material uses: resolve inputs on them, then gather
        used, local = np.unique(rows[group], return_inverse=True)
        out[group] = evaluate(
            mat, wi[group], wo[group], None if uv_a is None else uv_a[used],
            sample_index=local, eps=eps,
        )
    return out
