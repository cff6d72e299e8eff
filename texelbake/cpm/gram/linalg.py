"""The linear algebra of the Gram route (`texelbake.cpm.gram.fit`): eigendecompositions of
selection Grams (all of them stacked by size, or only the top ones of a wide matrix), the
singular values and the Davis-Kahan test read off them, and the trials' reduced least-squares
systems from a channel's Gram."""

from __future__ import annotations

import numpy as np
import scipy.linalg
import scipy.linalg.lapack
import torch

from texelbake.cpm.column_sampling import energy_rank
from texelbake.tol import TOL

EPS64 = float(np.finfo(np.float64).eps)


def batched_eigh(mats: list[np.ndarray]) -> list[tuple[np.ndarray, np.ndarray]]:
    """eigh of many symmetric matrices: stacked by size, one torch.linalg.eigh per size.

    mats : list of (m_i, m_i) float64; returns [(lam (m_i,) ascending, V (m_i, m_i))] in order.
    torch's batched CPU eigh runs LAPACK on each matrix of the stack, so a matrix's result is the
    same whichever matrices share its stack (checked by tests/cpm/test_batched_fit.py)."""
    out: list[tuple[np.ndarray, np.ndarray] | None] = [None] * len(mats)
    by_size: dict[int, list[int]] = {}
    for i, g in enumerate(mats):  # loop over matrices: bucket by size only
        by_size.setdefault(g.shape[0], []).append(i)
    for m, idx in by_size.items():  # loop over distinct sizes
        if m == 0:
            for i in idx:
                out[i] = (np.zeros(0), np.zeros((0, 0)))
            continue
        stack = torch.as_tensor(np.stack([mats[i] for i in idx]))
        lam, vec = torch.linalg.eigh(stack)
        lam_np, vec_np = lam.numpy(), vec.numpy()
        for j, i in enumerate(idx):
            out[i] = (lam_np[j], vec_np[j])
    return out  # type: ignore[return-value]


#: selection Grams wider than this get only their top eigenpairs (`top_eighs`)
SUBSET_MIN_M = 160
#: eigenpairs asked for first; four times more while the psi-rank k needs more than k + 1
SUBSET_START = 32


def top_eighs(mats: list[np.ndarray], psi: float) -> list[tuple[np.ndarray, np.ndarray]]:
    """The eigenpairs of selection Grams that Table 2 reads: all of them (`batched_eigh`) for
    m <= SUBSET_MIN_M; for a wider matrix only its top K, by LAPACK dsyevr (tridiagonal
    reduction, MRRR on the K largest, back-transformation of K vectors: 3-4x faster than the full
    divide and conquer at m = 500, K = 32, one thread), K from SUBSET_START up x4 until K > k,
    the psi-rank of `spectrum` and `energy_rank` with the trace as the total (so s_(k+1), the
    gap `needs_full_svd` tests, is there), or K = m. The psi-rank of the selection matrix is
    small beside m (the cylinder at 32^2: k 1-20 for m 200-1000), and what the fit reads is the
    top k vectors, the singular values down to s_(k+1) and the count of resolved ones above k
    (`column_probabilities`: min(k, rank)), all of which a partial spectrum with K > k gives.
    returns [(lam (K,) ascending, V (m, K))] in order, K = m for the narrow ones."""
    out: list[tuple[np.ndarray, np.ndarray] | None] = [None] * len(mats)
    narrow = [i for i, g in enumerate(mats) if g.shape[0] <= SUBSET_MIN_M]
    for i, eig in zip(narrow, batched_eigh([mats[i] for i in narrow]), strict=True):
        out[i] = eig
    for i, g in enumerate(mats):  # loop over the wide matrices, one LAPACK call or a few each
        if out[i] is not None:
            continue
        m = g.shape[0]
        total = float(np.trace(g))
        K = min(SUBSET_START, m)
        while True:  # loop over at most log4(m / SUBSET_START) + 1 tries
            lam, V = scipy.linalg.eigh(g, subset_by_index=[m - K, m - 1], driver="evr",
                                       check_finite=False)
            if K == m:
                break
            sv, _ = spectrum((lam, V))
            if energy_rank(sv, psi, total) < K:
                break
            K = min(4 * K, m)
        out[i] = (lam, V)
    return out  # type: ignore[return-value]


def normalised_gram(G: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(G / (norms norms^T), scale): the Gram of unit-scaled columns (zero columns stay zero)."""
    norms = np.sqrt(np.maximum(np.diag(G), 0.0))
    scale = np.where(norms > 0, norms, 1.0)
    return G / np.outer(scale, scale), scale


def reduced_system(
    G: np.ndarray, scale: np.ndarray, b: np.ndarray | None = None, tt: float | None = None,
) -> tuple[np.ndarray, np.ndarray, float]:
    """The trials' reduced least squares for one channel from its Gram, by pivoted Cholesky of
    the unit-column Gram (LAPACK dpstrf, rank-revealing with tolerance m eps max diag, the
    resolution `reduced_system_eigh` keeps): Gn[P, P] = U^T U, A = U P^T diag(norms) (r, m),
    U_r^T t = (D^-1 b)[P_r], rest = tt - t^T t. ||A a - t||^2 + rest = ||M a - target||^2 for
    every a (A^T A = G, A^T t = b). 3-4x cheaper than the eigendecomposition (m = 256: 1.1 ms
    against 5.2 ms, m = 512: 7.5 against 27 ms, one thread).

    G : (m, m) Gram M^T M; scale : (m,) column norms (1 for zero columns)
    b : (m,) M^T target and tt = ||target||^2; default target = M 1 (b = G 1, tt = 1^T G 1)
    returns (A (r, m), t (r,), rest >= 0)"""
    m = G.shape[0]
    if b is None:
        b = G.sum(axis=1)
    t2 = float(b.sum()) if tt is None else float(tt)
    Gn = G / np.outer(scale, scale)
    U, piv, rank, _ = scipy.linalg.lapack.dpstrf(Gn, lower=0, tol=-1.0)
    piv = piv[:m] - 1
    r = int(rank)
    if r == 0:
        return np.zeros((0, m)), np.zeros(0), t2
    Ur = np.triu(U[:r])  # (r, m) in pivot order
    A = np.empty((r, m))
    A[:, piv] = Ur
    A *= scale[None, :]
    tq = scipy.linalg.solve_triangular(Ur[:, :r], (b / scale)[piv[:r]], trans="T", lower=False)
    return A, tq, max(t2 - float(tq @ tq), 0.0)


def reduced_system_eigh(
    G: np.ndarray, eig_n: tuple[np.ndarray, np.ndarray], scale: np.ndarray,
    b: np.ndarray | None = None, tt: float | None = None,
) -> tuple[np.ndarray, np.ndarray, float]:
    """The per-texel fit's reduced system (`fit_texel` on R) for one channel from its Gram:
    (A (r, m), t (r,), rest), from the eigendecomposition of the unit-column Gram (the
    per-texel path's algebra; kept as the second method `reduced_system` is tested against).

    b : (m,) M^T target and tt = ||target||^2; default target = M 1 (b = G 1, tt = 1^T G 1)."""
    lam, V = eig_n
    m = G.shape[0]
    keep = lam > max(float(lam[-1]), 0.0) * m * EPS64
    sq = np.sqrt(lam[keep])
    Vk = V[:, keep]
    A = (sq[:, None] * Vk.T) * scale[None, :]
    if b is None:
        b = G.sum(axis=1)  # M^T M 1 = M^T target
    t2 = float(b.sum()) if tt is None else float(tt)
    tq = (Vk.T @ (b / scale)) / sq
    return A, tq, max(t2 - float(tq @ tq), 0.0)


def spectrum(eig: tuple[np.ndarray, np.ndarray], rcond: float = TOL.svd_rcond
             ) -> tuple[np.ndarray, np.ndarray]:
    """Singular values s (descending, unresolved ones 0) and Vt of S from eigh(S^T S), as
    `column_sampling.svd_float64`'s Gram route; eig may hold the top K eigenpairs only
    (`top_eighs`: lam (K,), V (m, K)), the floor is that of the whole (m x m) matrix."""
    lam, V = eig
    m = V.shape[0]
    lam = np.clip(lam[::-1], 0.0, None)
    Vt = np.ascontiguousarray(V[:, ::-1].T)
    s = np.sqrt(lam)
    floor = max(rcond, float(np.sqrt(m * EPS64))) * float(s[0])
    return np.where(s > floor, s, 0.0), Vt


def needs_full_svd(s: np.ndarray, k: int, m: int) -> bool:
    """`column_sampling.top_singular`'s Davis–Kahan test: the Gram route cannot resolve span(V_k)."""
    if not 0 < k <= s.size:
        return False
    gap = s[k - 1] ** 2 - (s[k] ** 2 if k < s.size else 0.0)
    return bool(gap * TOL.gram_subspace <= m * EPS64 * s[0] ** 2)
