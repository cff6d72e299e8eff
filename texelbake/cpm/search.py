"""The search for a texel's points (seed 000 §4.1 with DMM06 Table 2), written once for both
fitting paths: for a probed c, n_trials draws of c columns from the Table 2 probabilities,
each draw's weights fitted and scored by the SNR of Eq. 7, the best kept (`search_c`); the
bisection on [k, c_max] keeps the half holding the smallest c that reaches eps_db. A trial is
a function of the drawn columns, so the per-texel path scores draws on R itself or on the
reduced system, and the batched path on the reduced system from Grams (`reduced_trial`).
A selection wider than n_batch columns is made in batches (`select_batched`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np

from texelbake.cpm.column_sampling import fit_weights, sample_columns
from texelbake.cpm.texel_fit import FitCounts, FitParams, GroupFit

#: a trial: drawn columns (c,) int64 -> (alpha (c, ch_g) float64, SNR of Eq. 7 in dB)
Trial = Callable[[np.ndarray], tuple[np.ndarray, float]]
#: one channel's reduced least squares (A (r, m), t (r,), rest >= 0): ||A a - t||^2 + rest is
#: the residual of Eq. 7 for the weights a of any columns (`gram.linalg.reduced_system`)
Reduced = tuple[np.ndarray, np.ndarray, float]


def reduced_trial(red: Sequence[Reduced], signal: float, weights: str) -> Trial:
    """The trial of a draw in the reduced space: per channel NNLS (or the seed's clamp) on
    A[:, cols] against t, the SNR signal / (sum of residuals + rests).

    red : one `Reduced` per channel of the group; signal : sum over the group's channels of
    ||Eq. 7||^2 on the valid rows; weights : "nnls" | "clamp"."""
    def trial(local: np.ndarray) -> tuple[np.ndarray, float]:
        alpha = np.zeros((local.size, len(red)))  # (c, ch_g)
        noise = 0.0
        for g, (A, t, rest) in enumerate(red):  # loop over <= 3 channels
            C = A[:, local]  # (r, c)
            alpha[:, g] = fit_weights(C, t, weights)  # type: ignore[arg-type]
            r = C @ alpha[:, g] - t
            noise += float(r @ r) + rest
        if noise <= 0.0:
            return alpha, math.inf
        if signal <= 0.0:
            return alpha, -math.inf
        return alpha, 10.0 * math.log10(signal / noise)
    return trial


def search_c(
    p: np.ndarray, k: int, trial: Trial, rng: np.random.Generator, c_max: int,
    params: FitParams, counts: FitCounts | None = None,
) -> tuple[np.ndarray, np.ndarray, bool]:
    """Seed 000 §4.1's bisection on c in [k, c_max] (c = c_max when c_max < k): for a probed c,
    params.n_trials draws of c columns (`sample_columns` on p, with replacement, so a draw may
    hold fewer distinct columns), each scored by `trial`, the best SNR kept (a draw seen before
    is not solved again); the interval keeps the half holding the smallest c whose best draw
    reaches params.eps_db.

    p : (m,) float64 Table 2 probabilities; k : psi-rank; rng : the texel's generator
    returns (columns (c,) int64 into p, alpha (c, ch_g) float64, capped)"""
    cache: dict[int, tuple[np.ndarray, np.ndarray, float]] = {}

    def best_of_trials(c: int) -> tuple[np.ndarray, np.ndarray, float]:
        if c not in cache:
            if counts is not None:
                counts.probes += 1
            best: tuple[np.ndarray, np.ndarray, float] | None = None
            seen: set[bytes] = set()
            for _ in range(params.n_trials):  # loop over a handful of randomized trials
                local = sample_columns(p, c, rng)
                key = local.tobytes()
                if key in seen:  # same draw again: same fit, skip the solve
                    continue
                seen.add(key)
                if counts is not None:
                    counts.draws += 1
                alpha, snr = trial(local)
                if best is None or snr > best[2]:
                    best = (local, alpha, snr)
            if best is None:  # unreachable: n_trials >= 1 (FitParams)
                raise ValueError(f"n_trials must be >= 1, got {params.n_trials}")
            cache[c] = best
        return cache[c]

    capped = c_max < k
    lo, hi = (c_max, c_max) if capped else (k, c_max)
    while lo < hi:  # seed 000 §4.1: bisection with the median as the probe
        mid = (lo + hi) // 2
        if best_of_trials(mid)[2] >= params.eps_db:
            hi = mid
        else:
            lo = mid + 1
    cols, alpha, _ = best_of_trials(lo)
    return cols, alpha, capped


def select_batched(
    cand: np.ndarray, c_max: int, params: FitParams,
    direct: Callable[[np.ndarray, np.ndarray, int], GroupFit | None],
) -> GroupFit | None:
    """Seed 000 §4.1's batches: a selection among more than params.n_batch candidate columns
    fits contiguous batches of n_batch (sample order, spatially coherent) each on its own
    partial sum with c_max capped at n_batch // 2; the union of their points is the new pool
    (reduced again the same way while it exceeds n_batch), which is fitted against the sum
    over all of cand with c_max. A pool is at most ceil(m'/n_batch) n_batch/2 < m' columns, so
    the recursion ends.

    cand : (m',) int64 candidate columns; direct(pool, cand, c_max) : the selection among pool
        for the target summed over cand (None: that selection cannot be made, passed on)"""
    if cand.size > params.n_batch:
        c_batch = min(params.c_max, params.n_batch // 2)
        pools = []
        for b0 in range(0, cand.size, params.n_batch):  # loop over batches
            got = select_batched(cand[b0:b0 + params.n_batch], c_batch, params, direct)
            if got is None:
                return None
            pools.append(got.cols)
        pool = np.unique(np.concatenate(pools)).astype(np.int64)
        if pool.size > params.n_batch:
            got = select_batched(pool, c_batch, params, direct)
            if got is None:
                return None
            pool = got.cols
        return direct(pool, cand, c_max)
    return direct(cand, cand, c_max)


__all__ = ["Reduced", "Trial", "reduced_trial", "search_c", "select_batched"]
