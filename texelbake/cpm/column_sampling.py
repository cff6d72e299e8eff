"""Randomized column sampling of the characteristic-point matrix (seed 000, §3.3, Table 2, Eq. 11).

The seed selects characteristic points as columns of R (d x m) with the relative-error column
sampling of Drineas, Mahoney and Muthukrishnan 2006 (DMM06), reproduced as Table 2 of seed 000:

1. SVD R = U Sigma V^T, split into the top k and the remaining rho - k singular triplets
   (rho = rank R).
2. p_i = 1/3 ( ||(V_k)_(i)||^2 / ||V_k||_F^2
             + ||(V_k)_(i)|| ||(Sigma_{rho-k} V_{rho-k}^T)^(i)|| / sum_j (same)
             + ||(Sigma_{rho-k} V_{rho-k}^T)^(i)||^2 / ||Sigma_{rho-k} V_{rho-k}^T||_F^2 ).
   (V_k)_(i) is row i of V_k (the rank-k leverage of column i) and
   (Sigma_{rho-k} V_{rho-k}^T)^(i) is column i of the residual R - R_k expressed in the
   residual left singular basis, so its norm is the norm of column i of R - R_k. The middle term
   is garbled in the seed's PDF; we read it as the product of the two norms normalised to sum to
   one (it is the mixed term of DMM06 and the only reading that is a probability).
3. Draw c columns i.i.d. from p (with replacement, as DMM06), deduplicate: a repeated column
   adds nothing to span(C).

Weights: the seed takes alpha = C^+ R 1 (Eq. 11) and clamps negatives to 0 (§3.3 text);
DESIGN.md's default solves the non-negative least-squares problem min ||C alpha - R 1||,
alpha >= 0, exactly (scipy.optimize.nnls). Both are here so they can be compared.

SVD path (measured by `benchmarks/column_sampling.py --svd` on this shared 2-core machine: CPU
seconds with torch on one thread, min of 3, since wall time under the machine's load is noise;
d = 4096, R = Gaussian rank-60 with spectrum 0.85^r + 1e-4 noise, k ~ 11 at psi = 0.97;
"specular" = the same with five columns scaled by 1e6; p err = max |p - p_full| of the Table 2
probabilities at the psi-rank, s err = max |s_r - s_full_r| / s_1 over r <= k):

    m      full SVD (gesdd)   Gram eigh of R^T R       svd_lowrank (adaptive q, niter 4)
    64     0.007 s            0.005 s  p err 1e-13     (falls back to gram: q > m/4)
    128    0.024-0.033 s      0.012-0.015 s  3e-14     0.055 s  4e-14
    256    0.083-0.088 s      0.043-0.046 s  3e-15     0.11-0.20 s  4e-15
    512    0.36 s             0.16-0.17 s  6e-14       0.32-0.52 s  5e-14
    1024   1.59-1.71 s        0.79-0.83 s  8e-14       0.64-1.05 s  2e-13
    (s err <= 3e-15 for every path and size)

The Gram route squares the condition number: singular values below ~sqrt(eps) * s_max
(~1.5e-8 s_max) are lost to rounding, and so are their singular vectors. Table 2 needs V_k only
for the top k triplets (the psi-energy rank, far above that floor unless psi is within ~1e-16 of
1) and the residual column norms, which column_probabilities takes as ||R_j||^2 - ||(R_k)_j||^2
from exact column energies rather than from the tail triplets; with that, the probabilities agree
with the full SVD to 1e-13 even for the 1e6 specular case, at half the time. So
`svd_float64(R, method="auto")` uses the Gram eigen-decomposition for tall R (d >= 2 m, the usual
case) and the full SVD otherwise; svd_lowrank was not faster at equal accuracy except marginally
for m = 1024 with k ~ 4, so `top_singular(method="auto")` does not pick it (method="lowrank"
remains available for very wide texels with small k).
"""

from __future__ import annotations

from typing import Literal

import numpy as np
import scipy.linalg
import scipy.optimize
import torch

from texelbake.errors import SettingsError, ShapeError
from texelbake.tol import TOL

SvdMethod = Literal["auto", "full", "gram"]


def _as_matrix(name: str, a: np.ndarray) -> np.ndarray:
    a = np.asarray(a, dtype=np.float64)
    if a.ndim != 2:
        raise ShapeError(f"{name} must be a 2-D (d, m) array, got shape {a.shape}")
    return a


def svd_float64(
    R: np.ndarray, method: SvdMethod = "auto", rcond: float = TOL.svd_rcond, *,
    compute_u: bool = True,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Thin SVD of R in float64 through torch.linalg.

    R : (d, m) float (upcast to float64)
    method : "full" (torch.linalg.svd), "gram" (eigh of R^T R, U = R V / s), or "auto" (gram when
        d >= 2 m, see the module docstring for the measurements)
    rcond : for "gram": singular values <= max(rcond, sqrt(m eps)) * s_max are not resolved by
        the Gram route (R^T R has absolute error ~ m eps s_max^2); they are returned as 0 with
        zero U columns, so U s Vt reproduces R to ~sqrt(m eps) ||R||_2 (full: to rounding)
    returns : (U (d, r) float64, s (r,) float64 descending, Vt (r, m) float64), r = min(d, m).
        With compute_u=False the Gram route skips U = R V / s (a d x m x r product Table 2
        does not need) and returns U as an empty (d, 0) array.
    """
    R = _as_matrix("R", R)
    d, m = R.shape
    r = min(d, m)
    if r == 0:
        return np.zeros((d, 0)), np.zeros(0), np.zeros((0, m))
    if method not in ("auto", "full", "gram"):
        raise SettingsError(f"svd method must be 'auto', 'full' or 'gram', got {method!r}")
    use_gram = method == "gram" or (method == "auto" and d >= 2 * m)
    Rt = torch.as_tensor(R)
    if not use_gram:
        U, s, Vt = torch.linalg.svd(Rt, full_matrices=False)
        return U.numpy(), s.numpy(), Vt.numpy()
    G = Rt.T @ Rt  # (m, m)
    lam, V = torch.linalg.eigh(G)  # ascending
    lam = lam.flip(0).clamp(min=0.0)[:r]
    V = V.flip(1)[:, :r]  # (m, r)
    s = lam.sqrt()
    # eigenvalues of R^T R carry an absolute error ~ m eps s_1^2: singular values below
    # sqrt(m eps) s_1 are not resolved by this route and are reported as exact zeros (so the
    # numerical rank stays meaningful), their U columns as zeros
    floor = max(rcond, float(np.sqrt(m * np.finfo(np.float64).eps))) * float(s[0])
    s = torch.where(s > floor, s, torch.zeros_like(s))
    keep = s > 0.0
    inv = torch.where(keep, 1.0 / torch.where(keep, s, torch.ones_like(s)), torch.zeros_like(s))
    if not compute_u:
        return np.zeros((d, 0)), s.numpy(), V.T.contiguous().numpy()
    U = (Rt @ V) * inv[None, :]  # (d, r)
    return U.numpy(), s.numpy(), V.T.contiguous().numpy()


def energy_rank(s: np.ndarray, psi: float, total: float | None = None) -> int:
    """Smallest k with sum_{r<=k} s_r^2 >= psi * ||R||_F^2 (seed 000 §4.1, DESIGN.md).

    s : (r,) float64 singular values, descending (all of them, or the top ones when total is
        given)
    psi : energy fraction in (0, 1]
    total : ||R||_F^2 when s is a partial spectrum; default sum s^2
    returns : k in [1, r]; 0 when the energy is <= TOL.energy_floor (all-zero R). With a partial
        spectrum that does not reach psi, returns r + 1 (more triplets needed).
    """
    s = np.asarray(s, dtype=np.float64).ravel()
    if not 0.0 < psi <= 1.0:
        raise SettingsError(f"psi must be in (0, 1], got {psi}")
    e = s * s
    full = total is None
    total = float(e.sum()) if total is None else float(total)
    if total <= TOL.energy_floor:
        return 0
    cum = np.cumsum(e)
    # relative slack: cum[-1] differs from ||R||_F^2 by rounding; psi = 1 must still hit r
    k = int(np.searchsorted(cum, psi * total * (1.0 - 64 * np.finfo(np.float64).eps))) + 1
    return min(k, s.size) if full else k


def top_singular(
    R: np.ndarray,
    psi: float,
    *,
    method: Literal["auto", "full", "gram", "lowrank"] = "auto",
    oversample: int = 10,
    niter: int = 4,
    seed: int = 0,
    compute_u: bool = True,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """The singular triplets Table 2 needs: at least the top k of R, and k = energy_rank(psi).

    R : (d, m) float64; psi : energy fraction in (0, 1]
    method : "full" / "gram" (see svd_float64), "lowrank" (torch.svd_lowrank with q = k +
        oversample triplets and niter power iterations, q doubled until the psi energy is reached
        within q - oversample triplets; ||R||_F^2 is known exactly from the entries, so k is exact
        without the tail; falls back to "auto" beyond q = min(d, m) / 4), or "auto" = svd_float64's
        auto (gram for tall R, else full; lowrank was not faster, see the module docstring), with
        a full SVD instead whenever the Gram route cannot resolve span(V_k): Davis-Kahan bound
        m eps s_1^2 / (s_k^2 - s_{k+1}^2) > TOL.gram_subspace = 1e-6 (k reaching into singular
        values below ~1e-4 s_1, i.e. psi within ~1e-8 of 1, or a near-degenerate gap at k).
    seed : seed of svd_lowrank's random test matrix (torch RNG forked, global state untouched)
    returns : (U (d, q), s (q,), Vt (q, m), k); q = min(d, m) for full/gram. Pass exact column
        energies to column_probabilities when q < rank (its residual terms need them).
    """
    R = _as_matrix("R", R)
    d, m = R.shape
    total = float(np.sum(R * R))
    if method not in ("auto", "full", "gram", "lowrank"):
        raise SettingsError(f"svd method must be auto/full/gram/lowrank, got {method!r}")
    r_max = min(d, m)
    if method == "lowrank" and r_max > 0 and total > TOL.energy_floor:
        q = min(2 * oversample, r_max)
        Rt = torch.as_tensor(R)
        while 4 * q <= r_max:  # beyond m/4 triplets a full decomposition is cheaper
            with torch.random.fork_rng(devices=[]):
                torch.manual_seed(seed)
                U_t, s_t, V_t = torch.svd_lowrank(Rt, q=q, niter=niter)
            s_np = s_t.numpy()
            k = energy_rank(s_np, psi, total)
            if k + oversample <= q:
                return U_t.numpy(), s_np, V_t.T.contiguous().numpy(), k
            q = 2 * q
        method = "auto"
    U, s, Vt = svd_float64(
        R, "full" if method == "full" else ("gram" if method == "gram" else "auto"),
        compute_u=compute_u,
    )
    k = energy_rank(s, psi, total)
    if method == "auto" and d >= 2 * m and 0 < k <= s.size:
        # the Gram route resolves span(V_k) to ~ m eps s_1^2 / (s_k^2 - s_{k+1}^2) (Davis-Kahan);
        # Table 2 only needs that subspace (its leverage scores are rotation-invariant within
        # it), so keep Gram when that is <= TOL.gram_subspace and redo the full SVD otherwise
        gap = s[k - 1] ** 2 - (s[k] ** 2 if k < s.size else 0.0)
        if gap * TOL.gram_subspace <= m * np.finfo(np.float64).eps * s[0] ** 2:
            U, s, Vt = svd_float64(R, "full")
            k = energy_rank(s, psi, total)
    return U, s, Vt, k


def _numerical_rank(s: np.ndarray, rcond: float) -> int:
    if s.size == 0 or s[0] <= 0.0:
        return 0
    return int(np.count_nonzero(s > rcond * s[0]))


def _leverage_and_residual(
    s: np.ndarray, Vt: np.ndarray, k: int, col_energy: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray]:
    """Squared row norms of V_k (m,) and squared residual column norms ||(R - R_k)_j||^2 (m,)."""
    Vk_t = Vt[:k]  # (k, m)
    lev2 = np.sum(Vk_t * Vk_t, axis=0)  # (m,)
    sv = s[:, None] * Vt  # (r, m): column j is U^T R_j
    if col_energy is None:
        col_energy = np.sum(sv * sv, axis=0)
    top = np.sum(sv[:k] * sv[:k], axis=0)
    res2 = col_energy - top  # (m,)
    # ||R_j||^2 - ||(R_k)_j||^2 cancels: below ~(k + 1) eps ||R_j||^2 it is rounding, not signal
    # (a column inside span(U_k) up to float64). Zeroing it keeps the residual terms from being
    # driven by noise (e.g. the 1e6-scaled columns of a specular lobe).
    noise = TOL.residual_rounding * (k + 1) * np.finfo(np.float64).eps * col_energy
    res2 = np.where(res2 > noise, res2, 0.0)
    return lev2, res2


def column_probabilities(
    U: np.ndarray,
    s: np.ndarray,
    Vt: np.ndarray,
    k: int,
    *,
    col_energy: np.ndarray | None = None,
    rcond: float = TOL.svd_rcond,
) -> np.ndarray:
    """The three-term column probabilities of seed 000 Table 2 (DMM06), see module docstring.

    U : (d, r) float64, s : (r,) float64, Vt : (r, m) float64 — a thin SVD of R (U unused but
        kept in the signature so the call reads like Table 2)
    k : target rank, 0 <= k
    col_energy : optional (m,) float64 exact squared column norms ||R_j||^2; when given the
        residual norms are ||R_j||^2 - ||(R_k)_j||^2 (exact even when the tail of the SVD is
        inaccurate, e.g. from the Gram route); otherwise they come from s and Vt
    returns : (m,) float64, p >= 0, sum p = 1; all zeros when R is all zero (k = 0).

    Degenerate cases (defined, tested):
    - k >= numerical rank rho (s_r > rcond * s_max), or every residual column norm at rounding
      level (||(R - R_k)_j||^2 <= 32 (k + 1) eps ||R_j||^2): the residual terms are 0/0; they
      are defined as 0 and p is renormalised, i.e. p = leverage scores / k.
    - columns whose energy is <= rcond^2 * max column energy (all-zero columns, fully occluded
      samples) get p = 0: they are never drawn. Rounding in V would otherwise give them ~1e-30.
    """
    s = np.asarray(s, dtype=np.float64).ravel()
    Vt = np.asarray(Vt, dtype=np.float64)
    if Vt.ndim != 2 or Vt.shape[0] != s.size:
        raise ShapeError(f"Vt must be (r, m) with r = len(s) = {s.size}, got {Vt.shape}")
    m = Vt.shape[1]
    rho = _numerical_rank(s, rcond)
    k = int(min(max(k, 0), rho))
    if k == 0 or m == 0:
        return np.zeros(m, dtype=np.float64)
    if col_energy is not None:
        col_energy = np.asarray(col_energy, dtype=np.float64).ravel()
        if col_energy.shape != (m,):
            raise ShapeError(f"col_energy must be ({m},), got {col_energy.shape}")
    lev2, res2 = _leverage_and_residual(s[:rho], Vt[:rho], k, col_energy)
    energy = col_energy if col_energy is not None else np.sum((s[:rho, None] * Vt[:rho]) ** 2, 0)
    dead = energy <= rcond * rcond * float(energy.max())
    lev2[dead] = 0.0
    res2[dead] = 0.0
    terms = []
    lev_sum = float(lev2.sum())
    if lev_sum > 0.0:
        terms.append(lev2 / lev_sum)
    res_sum = float(res2.sum())
    # k = rank: the residual terms are 0/0, defined as 0 (also when every residual column norm is
    # at rounding level, see _leverage_and_residual)
    if k < rho and res_sum > 0.0:
        terms.append(res2 / res_sum)
        mix = np.sqrt(lev2 * res2)
        mix_sum = float(mix.sum())
        if mix_sum > 0.0:
            terms.append(mix / mix_sum)
    p = np.sum(terms, axis=0)
    total = float(p.sum())
    return p / total if total > 0.0 else np.zeros(m, dtype=np.float64)


def leverage_probabilities(s: np.ndarray, Vt: np.ndarray, k: int) -> np.ndarray:
    """First term of Table 2 only: p_i = ||(V_k)_(i)||^2 / k (rank-k leverage scores).

    s : (r,) float64, Vt : (r, m) float64, k >= 0
    returns : (m,) float64 summing to 1 (zeros when k = 0 or R = 0)
    """
    s = np.asarray(s, dtype=np.float64).ravel()
    Vt = np.asarray(Vt, dtype=np.float64)
    rho = _numerical_rank(s, TOL.svd_rcond)
    k = int(min(max(k, 0), rho))
    m = Vt.shape[1]
    if k == 0:
        return np.zeros(m, dtype=np.float64)
    lev2 = np.sum(Vt[:k] ** 2, axis=0)
    return lev2 / float(lev2.sum())


def uniform_probabilities(m: int, col_energy: np.ndarray | None = None) -> np.ndarray:
    """Uniform p over the m columns (over the nonzero ones when col_energy (m,) is given).

    returns : (m,) float64 summing to 1, zeros if no column qualifies
    """
    p = np.ones(int(m), dtype=np.float64)
    if col_energy is not None:
        p = (np.asarray(col_energy, dtype=np.float64) > 0.0).astype(np.float64)
    total = float(p.sum())
    return p / total if total > 0 else p


def sample_columns(p: np.ndarray, c: int, rng: np.random.Generator) -> np.ndarray:
    """Draw c column indices i.i.d. from p (with replacement, DMM06), then deduplicate.

    p : (m,) float64 probabilities (need not be exactly normalised; renormalised here)
    c : number of draws, >= 0
    rng : numpy Generator (seeded by the caller)
    returns : (c',) int64 sorted unique indices, c' <= c; empty when c = 0 or p is all zero
    """
    p = np.asarray(p, dtype=np.float64).ravel()
    c = int(c)
    if c < 0:
        raise SettingsError(f"c must be >= 0, got {c}")
    if np.any(~np.isfinite(p)) or np.any(p < 0):
        raise ShapeError("p must be finite and non-negative")
    total = float(p.sum())
    if c == 0 or total <= 0.0:
        return np.zeros(0, dtype=np.int64)
    # inverse-CDF sampling: deterministic for a seeded rng, independent of numpy's choice() impl
    cdf = np.cumsum(p / total)
    cdf[-1] = 1.0
    u = rng.random(c)
    idx = np.searchsorted(cdf, u, side="right")
    idx = np.minimum(idx, p.size - 1)
    # searchsorted never lands on a p = 0 column (its cdf step is empty) except by the clamp
    return np.unique(idx).astype(np.int64)


def pivoted_qr_columns(R: np.ndarray, c: int) -> np.ndarray:
    """First c pivots of column-pivoted QR (scipy.linalg.qr(pivoting=True)), a deterministic
    baseline for column selection.

    R : (d, m) float64
    returns : (min(c, m),) int64 column indices in pivot order; columns with zero norm are
        dropped (QR pivots them last, they add nothing)
    """
    R = _as_matrix("R", R)
    c = int(min(max(int(c), 0), R.shape[1]))
    if c == 0 or R.size == 0:
        return np.zeros(0, dtype=np.int64)
    _, _, piv = scipy.linalg.qr(R, mode="economic", pivoting=True)
    cols = piv[:c].astype(np.int64)
    norms = np.linalg.norm(R[:, cols], axis=0)
    return cols[norms > 0.0]


def fit_weights(
    C: np.ndarray,
    target: np.ndarray,
    method: Literal["nnls", "clamp"] = "nnls",
    rcond: float = TOL.svd_rcond,
) -> np.ndarray:
    """Weights alpha with C alpha ~= target (seed 000 Eq. 10-11).

    C : (d, c) float64, the selected columns of R
    target : (d,) float64, R 1 (the row sums of R)
    method : "nnls" — min ||C alpha - target||_2 s.t. alpha >= 0 (scipy.optimize.nnls, exact);
        "clamp" — the seed's alpha = C^+ target (pseudo-inverse in float64 through torch, relative
        cut-off rcond) with negative entries set to 0.
    returns : (c,) float64, alpha >= 0. Zero columns get alpha = 0. A zero target gives alpha = 0.

    Columns are scaled to unit norm before solving (alpha is scale-covariant per column, and the
    sign constraint is unchanged), which keeps NNLS well conditioned when the columns span a
    dynamic range of 1e6 or more (specular lobes).
    """
    C = _as_matrix("C", C)
    target = np.asarray(target, dtype=np.float64).ravel()
    d, c = C.shape
    if target.shape != (d,):
        raise ShapeError(f"target must be ({d},) to match C {C.shape}, got {target.shape}")
    if method not in ("nnls", "clamp"):
        raise SettingsError(f"weights method must be 'nnls' or 'clamp', got {method!r}")
    alpha = np.zeros(c, dtype=np.float64)
    if c == 0 or d == 0:
        return alpha
    norms = np.linalg.norm(C, axis=0)  # (c,)
    live = norms > 0.0
    if not np.any(live) or not np.any(target != 0.0):
        return alpha
    Cn = C[:, live] / norms[live]  # (d, c_live)
    if method == "nnls":
        # maxiter: scipy's default 3 * c can stop early on degenerate (duplicate) columns
        sol, _ = scipy.optimize.nnls(Cn, target, maxiter=max(50 * Cn.shape[1], 100))
    else:
        pinv = torch.linalg.pinv(torch.as_tensor(Cn), rtol=rcond).numpy()  # (c_live, d)
        sol = np.clip(pinv @ target, 0.0, None)
    alpha[live] = sol / norms[live]
    return alpha


def projection_error(R: np.ndarray, cols: np.ndarray, rcond: float = TOL.svd_rcond) -> float:
    """Relative matrix error ||R - C C^+ R||_F / ||R||_F of a column selection (seed 000 §3.3).

    R : (d, m) float64; cols : (c,) int64
    returns : float in [0, 1]; 0.0 for an all-zero R
    """
    R = _as_matrix("R", R)
    total = float(np.sum(R * R))
    if total <= TOL.energy_floor:
        return 0.0
    cols = np.asarray(cols, dtype=np.int64).ravel()
    if cols.size == 0:
        return 1.0
    # orthonormal basis of span(C) from an SVD of C in float64 (rank-revealing, handles
    # duplicate or zero columns)
    Uc, sc, _ = np.linalg.svd(R[:, cols], full_matrices=False)
    r = _numerical_rank(sc, rcond)
    Q = Uc[:, :r]  # (d, r)
    resid = R - Q @ (Q.T @ R)
    return float(np.sqrt(max(float(np.sum(resid * resid)), 0.0) / total))


def eckart_young_error(s: np.ndarray, c: int) -> float:
    """Best rank-c relative error ||R - R_c||_F / ||R||_F = sqrt(sum_{r>c} s_r^2 / sum s_r^2).

    No selection of c columns can do better (Eckart–Young). s : (r,) float64 descending.
    """
    s = np.asarray(s, dtype=np.float64).ravel()
    e = s * s
    total = float(e.sum())
    if total <= TOL.energy_floor:
        return 0.0
    return float(np.sqrt(max(float(e[int(c) :].sum()), 0.0) / total))
