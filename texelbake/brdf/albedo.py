"""Directional albedo by cosine-weighted Monte Carlo (a check of energy conservation)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from texelbake.errors import ShapeError


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
