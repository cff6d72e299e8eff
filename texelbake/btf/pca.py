"""Batched PCA of Laplacian BRDFs (seed 001, §3.2, Eq. 4).

One problem per (level, channel): a data matrix X (t texels x d direction pairs) whose rows
are the texels' Laplacian BRDFs. The n leading right singular vectors e_j (d,) are the eigen
Laplacian BRDFs, the weights are the projections d_j(p) = <X[p], e_j>, and

    X ~ sum_j d_j(p) e_j                                          (Eq. 4)

No mean is subtracted here: the Laplacian levels are zero-mean by construction (the seed's
mu_k = 0) and the caller subtracts the fitted top-level mean (Eqs. 5-6) before calling.

Several problems of the same shape (the three YCbCr channels of one level) go through torch's
batched linear algebra in one call. Two solvers:

* "exact": eigen-decomposition (torch.linalg.eigh, float64) of the Gram matrix of the smaller
  side (t x t or d x d). Components whose eigenvalue is below `eps * max eigenvalue` are
  dropped (set to zero): their v = X^T u / s would be dominated by rounding.
* "randomized": Halko, Martinsson & Tropp's randomized range finder with `power_iters` power
  iterations and `oversample` extra columns, the large products in the data dtype (float32 for
  the 64 x 64 x 6561 BTF), the small QR/SVD factorizations in float64, the Gaussian test matrix
  drawn from a seeded torch.Generator (hand-written rather than torch.svd_lowrank because that
  one draws from torch's *global* RNG and keeps every step in the input dtype).

Components are sign-normalised (the entry of largest magnitude is positive, ties to the lowest
index) so reruns and the two solvers agree up to rounding. The weights are recomputed as the
projection of X on the float32-rounded components, so they are the least-squares weights for
exactly the basis that is stored.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from texelbake.errors import SettingsError, ShapeError
from texelbake.tol import TOL

METHODS = ("auto", "exact", "randomized")


@dataclass(frozen=True, eq=False)
class PCAResult:
    """weights : (b, t, n_max) float64; components : (b, n_max, d) float32 (rows unit or zero);
    singular_values : (b, n_max) float64 (0 for dropped components); n_effective : (b,) int64
    number of non-zero components per problem; method : solver used."""

    weights: np.ndarray
    components: np.ndarray
    singular_values: np.ndarray
    n_effective: np.ndarray
    method: str


def sign_normalize(components: torch.Tensor) -> torch.Tensor:
    """Flip each row so its largest-magnitude entry is positive (first index on ties).

    components : (b, n, d) tensor -> (b, n, d) same dtype; zero rows are left unchanged.
    """
    idx = torch.argmax(components.abs(), dim=-1, keepdim=True)  # (b, n, 1), first maximum
    pivot = torch.gather(components, -1, idx)  # (b, n, 1)
    sign = torch.where(pivot < 0, -1.0, 1.0).to(components.dtype)
    return components * sign


def choose_method(t: int, d: int, n_max: int, *, oversample: int, exact_max: int) -> str:
    """"exact" when the smaller side is at most `exact_max` or the randomized sketch would not
    be smaller than it; "randomized" otherwise."""
    small = min(t, d)
    if small <= exact_max or n_max + oversample >= small:
        return "exact"
    return "randomized"


def _exact(x: torch.Tensor, n_max: int, eps: float) -> tuple[torch.Tensor, torch.Tensor]:
    """x : (b, t, d) -> (components (b, n_max, d) float64, singular values (b, n_max))."""
    b, t, d = x.shape
    x64 = x.to(torch.float64)
    if t <= d:
        gram = x64 @ x64.mT  # (b, t, t)
    else:
        gram = x64.mT @ x64  # (b, d, d)
    if not bool(torch.isfinite(gram).all()):  # the Gram is small; NaN/Inf in x propagate here
        raise ShapeError("PCA data contains NaN or Inf")
    evals, evecs = torch.linalg.eigh(gram)  # ascending
    evals = torch.flip(evals, dims=[-1])[:, :n_max]  # (b, n)
    evecs = torch.flip(evecs, dims=[-1])[:, :, :n_max]  # (b, t|d, n)
    top = evals[:, :1].clamp_min(0.0)
    valid = evals > eps * top
    valid &= evals > TOL.energy_floor
    sing = torch.sqrt(evals.clamp_min(0.0)) * valid
    if t <= d:
        comps = evecs.mT @ x64  # (b, n, d) = s * v^T
        comps = comps / torch.where(valid, sing, 1.0)[:, :, None]
    else:
        comps = evecs.mT.contiguous()  # (b, n, d)
    comps = comps * valid[:, :, None]
    return comps, sing


def _randomized(
    x: torch.Tensor, n_max: int, oversample: int, power_iters: int, seed: int, eps: float
) -> tuple[torch.Tensor, torch.Tensor]:
    b, t, d = x.shape
    q = min(n_max + oversample, t, d)
    gen = torch.Generator().manual_seed(int(seed))
    omega = torch.randn((b, d, q), generator=gen, dtype=torch.float64).to(x.dtype)  # (b, d, q)

    def orth(m: torch.Tensor) -> torch.Tensor:
        return torch.linalg.qr(m.to(torch.float64)).Q.to(x.dtype)

    basis = orth(x @ omega)  # (b, t, q)
    for _ in range(power_iters):
        basis = orth(x @ orth(x.mT @ basis))
    small = (basis.mT @ x).to(torch.float64)  # (b, q, d)
    if not bool(torch.isfinite(small).all()):
        raise ShapeError("PCA data contains NaN or Inf")
    _, s, vh = torch.linalg.svd(small, full_matrices=False)  # s: (b, q), vh: (b, q, d)
    s = s[:, :n_max]
    vh = vh[:, :n_max]
    valid = (s * s > eps * (s[:, :1] ** 2)) & (s * s > TOL.energy_floor)
    return vh * valid[:, :, None], s * valid


def pca_batched(
    x: np.ndarray | torch.Tensor,
    n_components: int | Sequence[int],
    *,
    method: str = "auto",
    oversample: int = 8,
    power_iters: int = 4,
    exact_max: int = 512,
    seed: int = 0,
    eps: float = TOL.pca_eig_rcond,
    store_dtype: str = "float32",
) -> PCAResult:
    """Uncentred PCA (truncated SVD) of b data matrices of one shape, in one batched call.

    x : (b, t, d) float32|float64, rows are texels, columns direction pairs
    n_components : n for every problem, or one n per problem; problems with fewer texels or
        directions than n get min(n, t, d) non-zero components, the rest are zero rows
    method : "auto" | "exact" | "randomized" (see module docstring)
    store_dtype : "float32" | "float16": the components are rounded to this storage precision
        (and returned as float32 holding those values) before the weights are projected
    returns : PCAResult with n_max = max(n_components) columns / rows
    """
    xt = torch.as_tensor(np.asarray(x) if not isinstance(x, torch.Tensor) else x)
    if xt.ndim != 3:
        raise ShapeError(f"PCA data must be (b, t, d), got shape {tuple(xt.shape)}")
    if xt.dtype not in (torch.float32, torch.float64):
        xt = xt.to(torch.float64)
    b, t, d = xt.shape
    if isinstance(n_components, int | np.integer):
        ns = [int(n_components)] * b
    else:
        ns = [int(v) for v in n_components]
    if len(ns) != b or min(ns, default=1) < 0:
        raise SettingsError(f"n_components must be >= 0, one per problem ({b}), got {ns}")
    if store_dtype not in ("float32", "float16"):
        raise SettingsError(f"store_dtype must be 'float32' or 'float16', got {store_dtype!r}")
    if method not in METHODS:
        raise SettingsError(f"PCA method must be one of {METHODS}, got {method!r}")
    n_max = max(ns, default=0)
    if b == 0 or n_max == 0 or t == 0 or d == 0:
        return PCAResult(
            np.zeros((b, t, n_max)),
            np.zeros((b, n_max, d), np.float32),
            np.zeros((b, n_max)),
            np.zeros(b, np.int64),
            "exact" if method == "auto" else method,
        )
    n_solve = min(n_max, t, d)
    used = method if method != "auto" else choose_method(
        t, d, n_solve, oversample=oversample, exact_max=exact_max
    )
    with torch.no_grad():
        if used == "exact":
            comps, sing = _exact(xt, n_solve, eps)
        else:
            comps, sing = _randomized(xt, n_solve, oversample, power_iters, seed, eps)
        keep = torch.arange(n_solve)[None, :] < torch.as_tensor(ns)[:, None]  # (b, n)
        comps = sign_normalize(comps * keep[:, :, None])
        sing = sing * keep
        comps32 = comps.to(getattr(torch, store_dtype)).to(torch.float32)
        weights = xt @ comps32.to(xt.dtype).mT  # (b, t, n): projections on the stored basis
    weights_np = np.zeros((b, t, n_max))
    comps_np = np.zeros((b, n_max, d), np.float32)
    sing_np = np.zeros((b, n_max))
    weights_np[:, :, :n_solve] = weights.to(torch.float64).numpy()
    comps_np[:, :n_solve] = comps32.numpy()
    sing_np[:, :n_solve] = sing.numpy()
    n_eff = (sing_np > 0).sum(axis=1).astype(np.int64)
    return PCAResult(weights_np, comps_np, sing_np, n_eff, used)
