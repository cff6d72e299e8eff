"""The top-level mean of the Y channel as a Phong lobe (seed 001, §3.2, Eqs. 5-6).

    mu'(wi, wo) = ka + kd (N.L) + ks (N.H)^alpha                  (Eq. 5)

with N = (0, 0, 1) in the texel frame, L = wi, H = normalize(wi + wo). Cb and Cr use a
constant, the average of their mean vector (Eq. 6). Only direction pairs with both directions
above the horizon (z > TOL.grazing_cos) take part in fits and averages; below the horizon the
model is defined as 0 (a BTF is zero there).

The fit is Levenberg-Marquardt (scipy.optimize.least_squares, method="lm") over
(ka, kd, ks, log alpha): the log keeps alpha positive without bounds (LM takes none). The model
is linear in (ka, kd, ks) for a fixed alpha, so LM first runs on log alpha alone with the three
linear parameters solved by least squares inside the residual (variable projection, Golub &
Pereyra), then polishes all four: this converges from far starts where a plain 4-parameter LM
chases alpha to infinity. The start exponent is x0's, or the best of a log-spaced grid.

Divergence guard: the fit is rejected, and the tabulated mean kept (model "table"), when LM
fails or raises, a parameter is not finite, alpha leaves [TOL.phong_alpha_min,
TOL.phong_alpha_max] (a lobe narrower than any sampling resolves, e.g. chasing one spike) and
dropping the lobe (ks = 0) costs more than `lobe_tolerance` of RMS, or the fit is worse (RMS)
than the best constant. When alpha runs off but the lobe explains nothing (alpha is then
unidentifiable, e.g. a flat mean), the diffuse part ka + kd (N.L) is kept. The reason is in
`PhongFit.message`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from texelbake.errors import ShapeError
from texelbake.tol import TOL

#: |log alpha| is clipped here inside the model so LM can never overflow exp()
_LOG_ALPHA_CLIP = 60.0


@dataclass(frozen=True)
class PhongFit:
    """params : (ka, kd, ks, alpha) float64 (all zero when model == "table");
    model : "phong" | "table"; rms : RMS residual of the kept model over the valid pairs (0 for
    "table", which is exact); rms_fit : RMS of the Phong fit itself (inf if it failed);
    rms_constant : RMS of the best constant; nfev : LM evaluations; message : what happened."""

    params: tuple[float, float, float, float]
    model: str
    rms: float
    rms_fit: float
    rms_constant: float
    nfev: int
    message: str


def above_horizon(wi: np.ndarray, wo: np.ndarray, *, eps: float = TOL.grazing_cos) -> np.ndarray:
    """(d,) bool: both directions strictly above the horizon (z > eps)."""
    wi = np.asarray(wi, dtype=np.float64)
    wo = np.asarray(wo, dtype=np.float64)
    return (wi[..., 2] > eps) & (wo[..., 2] > eps)


def _basis(wi: np.ndarray, wo: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(N.L, N.H, valid), each (d,), zeroed below the horizon."""
    valid = above_horizon(wi, wo)
    h = wi + wo  # (d, 3)
    hn = np.linalg.norm(h, axis=-1)
    n_dot_h = np.divide(h[..., 2], hn, out=np.zeros_like(hn), where=hn > 0)
    n_dot_l = np.where(valid, np.clip(wi[..., 2], 0.0, 1.0), 0.0)
    n_dot_h = np.where(valid, np.clip(n_dot_h, 0.0, 1.0), 0.0)
    return n_dot_l, n_dot_h, valid


def phong_eval(params, wi: np.ndarray, wo: np.ndarray) -> np.ndarray:
    """Eq. 5 at direction pairs.

    params : (ka, kd, ks, alpha); wi, wo : (..., 3) float64 unit, texel frame
    returns : (...) float64, 0 where either direction is at or below the horizon
    """
    wi = np.asarray(wi, dtype=np.float64)
    wo = np.asarray(wo, dtype=np.float64)
    if wi.shape != wo.shape or wi.shape[-1:] != (3,):
        raise ShapeError(f"wi and wo must both be (..., 3), got {wi.shape} and {wo.shape}")
    ka, kd, ks, alpha = (float(v) for v in params)
    n_dot_l, n_dot_h, valid = _basis(wi, wo)
    return np.where(valid, ka + kd * n_dot_l + ks * n_dot_h**alpha, 0.0)


def _linear_params(
    y: np.ndarray, n_dot_l: np.ndarray, n_dot_h: np.ndarray, alpha: float
) -> tuple[np.ndarray, float]:
    a = np.stack([np.ones_like(n_dot_l), n_dot_l, n_dot_h**alpha], axis=1)  # (d, 3)
    coef, *_ = np.linalg.lstsq(a, y, rcond=None)
    return coef, float(np.sum((a @ coef - y) ** 2))


def fit_phong(
    mean: np.ndarray,
    wi: np.ndarray,
    wo: np.ndarray,
    *,
    x0: tuple[float, float, float, float] | None = None,
    alpha_min: float = TOL.phong_alpha_min,
    alpha_max: float = TOL.phong_alpha_max,
    max_nfev: int = 400,
    lobe_tolerance: float = 0.01,
) -> PhongFit:
    """Fit Eq. 5 to a tabulated mean by Levenberg-Marquardt, with the divergence guard.

    mean : (d,) float64 the top-level mean mu(wi, wo) of the Y channel
    wi, wo : (d, 3) float64 unit directions of the pairs, texel frame
    x0 : optional start (ka, kd, ks, alpha); default: best of a grid of exponents
    lobe_tolerance : a diverged exponent is forgiven (ks = 0, diffuse only) when dropping the
        lobe raises the RMS by at most this fraction
    returns : PhongFit
    """
    mean = np.asarray(mean, dtype=np.float64)
    wi = np.asarray(wi, dtype=np.float64)
    wo = np.asarray(wo, dtype=np.float64)
    if mean.ndim != 1 or wi.shape != (mean.shape[0], 3) or wo.shape != wi.shape:
        raise ShapeError(
            f"mean must be (d,) with wi, wo (d, 3); got {mean.shape}, {wi.shape}, {wo.shape}"
        )
    n_dot_l, n_dot_h, valid = _basis(wi, wo)
    valid &= np.isfinite(mean)
    y, nl, nh = mean[valid], n_dot_l[valid], n_dot_h[valid]
    if y.size == 0:
        return PhongFit((0.0,) * 4, "table", 0.0, np.inf, 0.0, 0, "no direction pair above the "
                        "horizon: kept the tabulated mean")
    rms_const = float(np.sqrt(np.mean((y - y.mean()) ** 2)))

    if x0 is None:
        best_sse, best_coef, best_alpha = np.inf, np.zeros(3), 1.0
        for alpha in np.geomspace(1.0, 1000.0, 16):  # 16 exponents: a handful, not per-sample
            coef, sse = _linear_params(y, nl, nh, float(alpha))
            if sse < best_sse:
                best_sse, best_coef, best_alpha = sse, coef, float(alpha)
        start = np.array([*best_coef, np.log(best_alpha)])
    else:
        ka, kd, ks, alpha = (float(v) for v in x0)
        start = np.array([ka, kd, ks, np.log(max(alpha, 1e-300))])

    def resid(p: np.ndarray) -> np.ndarray:
        alpha = np.exp(np.clip(p[3], -_LOG_ALPHA_CLIP, _LOG_ALPHA_CLIP))
        return p[0] + p[1] * nl + p[2] * nh**alpha - y

    def table(reason: str, rms_fit: float, nfev: int) -> PhongFit:
        return PhongFit((0.0,) * 4, "table", 0.0, rms_fit, rms_const, nfev,
                        f"Phong fit rejected ({reason}); kept the tabulated mean")

    def varpro(q: np.ndarray) -> np.ndarray:
        # variable projection: for a given log alpha the best (ka, kd, ks) are linear least
        # squares, so LM searches one well-behaved dimension first
        alpha = np.exp(np.clip(q[0], -_LOG_ALPHA_CLIP, _LOG_ALPHA_CLIP))
        coef, _ = _linear_params(y, nl, nh, alpha)
        return resid(np.array([*coef, q[0]]))

    try:
        with np.errstate(over="ignore", under="ignore", invalid="ignore", divide="ignore"):
            pre = least_squares(varpro, start[3:], method="lm", max_nfev=max_nfev)
            alpha0 = np.exp(np.clip(pre.x[0], -_LOG_ALPHA_CLIP, _LOG_ALPHA_CLIP))
            coef0, _ = _linear_params(y, nl, nh, alpha0)
            start = np.array([*coef0, pre.x[0]])
            sol = least_squares(resid, start, method="lm", max_nfev=max_nfev, x_scale="jac")
    except (ValueError, np.linalg.LinAlgError, FloatingPointError) as exc:
        return table(f"Levenberg-Marquardt raised {type(exc).__name__}: {exc}", np.inf, 0)
    p = sol.x
    alpha = float(np.exp(np.clip(p[3], -_LOG_ALPHA_CLIP, _LOG_ALPHA_CLIP)))
    with np.errstate(over="ignore", invalid="ignore"):
        r = resid(p)
    rms_fit = float(np.sqrt(np.mean(r**2))) if np.all(np.isfinite(r)) else np.inf
    nfev = int(sol.nfev + pre.nfev)
    if not np.all(np.isfinite(p)) or not np.isfinite(rms_fit):
        return table("non-finite parameters", rms_fit, nfev)
    bad = None
    if not alpha_min <= alpha <= alpha_max:
        bad = f"alpha={alpha:.4g} outside [{alpha_min:g}, {alpha_max:g}]: diverged"
    elif sol.status <= 0:
        bad = f"Levenberg-Marquardt did not converge: {sol.message}"
    if bad is not None:
        # An exponent running off is harmless when the lobe explains nothing (ks (N.H)^alpha is
        # then a constant or zero, alpha unidentifiable): keep ka + kd (N.L) if it is within
        # `lobe_tolerance` of the diverged fit's RMS; otherwise the lobe was chasing something
        # (a spike) and the tabulated mean is kept.
        coef = np.linalg.lstsq(np.stack([np.ones_like(nl), nl], axis=1), y, rcond=None)[0]
        rms_diffuse = float(np.sqrt(np.mean((coef[0] + coef[1] * nl - y) ** 2)))
        # (with an absolute floor of 1e-6 x the data's scale: the means come from float32
        # maps, and two fits at that rounding level, e.g. of an exactly diffuse mean, are
        # equal whatever their ratio; measured on a baked Lambertian plane: 6.4e-9 vs 6.1e-9)
        floor = 1e-6 * float(np.max(np.abs(y)))
        if rms_diffuse <= rms_fit * (1.0 + lobe_tolerance) + floor and rms_diffuse <= rms_const:
            params = (float(coef[0]), float(coef[1]), 0.0, 1.0)
            return PhongFit(params, "phong", rms_diffuse, rms_fit, rms_const, nfev,
                            f"Phong lobe unidentifiable ({bad}); kept ka + kd (N.L), "
                            f"RMS {rms_diffuse:.4g}")
        return table(f"{bad}; without the lobe RMS {rms_diffuse:.4g} vs {rms_fit:.4g}",
                     rms_fit, nfev)
    if rms_fit > rms_const * (1.0 + 1e-9):
        return table(f"RMS {rms_fit:.4g} worse than a constant's {rms_const:.4g}", rms_fit, nfev)
    params = (float(p[0]), float(p[1]), float(p[2]), alpha)
    return PhongFit(params, "phong", rms_fit, rms_fit, rms_const, nfev,
                    f"Phong fit: alpha={alpha:.4g}, RMS {rms_fit:.4g} (constant {rms_const:.4g})")
