"""Coarse levels refitted to the dense Eq. 7 (issue 11, item 3; `BakeSettings.coarse_target`).

With `hierarchy="children"` a coarse texel's candidates are its children's characteristic
points, and the fit's reference is *their* weighted sum: the children's approximation, not the
texel's Eq. 7. Errors then compound level by level. Measured on the small cylinder at 16²
(benchmarks/bake.py; refits of the stored bake): at level 4 the fit reaches 31.5 dB in-sample
against the children's sum with c_max 256 and still only 11.0 dB held-out against the dense
Eq. 7; more points (c_max) or a higher target (eps_db) change nothing there.

`refit_to_dense` keeps the points the fit chose and solves their weights again, per channel,
by non-negative least squares against the texel's dense Eq. 7 on the training grid
(f_bar = sum over *all* samples of the texel of f V V dA, over a_vis): the same objective the
fit's SNR measures, so the in-sample SNR against the dense reference can only rise. The
texel's in-sample SNR is then reported against the dense reference, and its held-out SNR
measured again (`texelbake.cpm.level.heldout_snr`). Cost: one evaluation of R over every dense
sample of the level (what level 0 builds anyway) plus one NNLS of (d x c) per channel and texel.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import nnls
from threadpoolctl import threadpool_limits

from texelbake.cpm.gram_linalg import normalised_gram, reduced_system
from texelbake.cpm.level import (
    FitInputs,
    PointSet,
    direction_sets,
    heldout_snr,
    samples_in,
    visibility_cos,
    world_dirs,
)
from texelbake.cpm.level_batched import _build_R
from texelbake.cpm.matrix import avis_floor, filtered_reflectance, snr_db

#: dense samples per batch of R (3 x batch x d float64: 3 x 256 x 4096 x 8 B = 25 MB)
_BATCH = 256


#: light-direction folds of the refit's cross-validation (`refit_generalizes`)
REFIT_FOLDS = 4


def validation_fold(n_i: int, n_o: int, folds: int = 2) -> np.ndarray:
    """(n_i n_o,) int: the fold of every row (row = i n_o + o): its light direction i mod
    `folds`. Whole light directions, not random rows, so a fold asks what the held-out pairs
    ask: do the weights hold between the grid's directions."""
    return np.repeat(np.arange(n_i) % int(folds), n_o)


def dense_nnls(A: np.ndarray, f_ref: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """Per channel, the non-negative weights w >= 0 minimising |A_k[rows] w - f_ref[rows, k]|.

    A : (3, d, c) float64, each point's Eq. 7 term per channel; f_ref : (d, 3) the dense Eq. 7;
    rows : (d,) bool. returns : (c, 3) float64 (zeros for a channel whose A is all zero)."""
    out = np.zeros((A.shape[2], 3))
    for ch in range(3):  # loop over colour channels
        a = A[ch][rows]  # (d_rows, c)
        if np.any(a):
            out[:, ch] = nnls(a, f_ref[rows, ch], maxiter=50 * a.shape[1])[0]
    return out


def refit_generalizes(A: np.ndarray, f_ref: np.ndarray, ok: np.ndarray, old_w: np.ndarray,
                      fold: np.ndarray) -> bool:
    """Accept a refit only if, in a cross-validation over the folds of `fold` (weights refitted
    on the other folds' rows, scored on the fold's own rows, squared errors summed over every
    fold), it reproduces the dense Eq. 7 better than the fit's weights `old_w` do.

    NNLS against the dense target raises the in-sample SNR by construction, but with as many
    candidate points as it has it can fit the grid's directions and miss between them (the
    cloisonne's coarse levels: held-out p5 0.5 -> -2.1 dB at level 2, -1.9 -> -7.7 dB at
    level 3 with the unguarded refit, while the medians rose). A cross-validation on the
    training grid decides, so the held-out pairs stay an unbiased measure.
    A : (3, d, c); f_ref : (d, 3); ok : (d,) rows with a_vis above its floor;
    old_w : (c, 3); fold : (d,) int fold per row (`validation_fold`)."""
    old = np.einsum("kdc,ck->dk", A, old_w)
    err_cv = err_old = 0.0
    scored = False
    for k in np.unique(fold):  # loop over the folds (a handful)
        val, train = ok & (fold == k), ok & (fold != k)
        if not val.any() or not train.any():
            continue
        cv = np.einsum("kdc,ck->dk", A, dense_nnls(A, f_ref, train))
        err_cv += float(np.sum((cv[val] - f_ref[val]) ** 2))
        err_old += float(np.sum((old[val] - f_ref[val]) ** 2))
        scored = True
    return err_cv < err_old if scored else True  # nothing to validate on: in-sample alone


#: light-direction folds of the shrunk refit's cross-validation (`shrunk_refit`): more folds
#: than the guard's 4 so that each fold's training rows (7/8 of the grid's light directions)
#: fit nearly as well as the whole grid (the guard's bias against the refit, 2026-11-26)
SHRINK_FOLDS = 8

#: strengths alpha of the shrunk refit, lambda = alpha x the mean diagonal of the training Gram
#: (a column's mean squared norm): 0 is the plain refit; the fit's own weights are the last
#: candidate (alpha = infinity)
SHRINK_ALPHAS = (0.0, 1e-3, 1e-2, 1e-1, 1.0)


def _gram_nnls(G: np.ndarray, b: np.ndarray, tt: float) -> np.ndarray:
    """min ||M w - t||^2 over w >= 0 from G = M^T M, b = M^T t, tt = ||t||^2 (c x c, not
    d x c: the reduced system of `gram_linalg.reduced_system`). Zeros for an all-zero G."""
    if not np.any(np.diag(G) > 0):
        return np.zeros(G.shape[0])
    _, scale = normalised_gram(G)
    A, t, _ = reduced_system(G, scale, b, tt)
    if A.shape[0] == 0:
        return np.zeros(G.shape[0])
    return nnls(A, t, maxiter=50 * G.shape[0])[0]


def _shrunk(G: np.ndarray, b: np.ndarray, tt: float, w0: np.ndarray, alpha: float) -> np.ndarray:
    """argmin over w >= 0 of ||M w - t||^2 + lam ||w - w0||^2, lam = alpha mean(diag G): the
    NNLS of the Gram G + lam I with b + lam w0 (the stacked system [M; sqrt(lam) I] against
    [t; sqrt(lam) w0])."""
    lam = alpha * float(np.mean(np.diag(G)))
    return _gram_nnls(G + lam * np.eye(G.shape[0]), b + lam * w0, tt + lam * float(w0 @ w0))


def shrunk_refit(A: np.ndarray, f_ref: np.ndarray, ok: np.ndarray, old_w: np.ndarray,
                 fold: np.ndarray) -> tuple[np.ndarray, float]:
    """The refit's weights shrunk towards the fit's (`settings.refit_shrink`): per channel
    w = argmin_{w >= 0} ||A_k w - f_k||^2 + lam ||w - w_fit||^2 over the rows `ok`, with one
    strength per texel chosen from `SHRINK_ALPHAS` and the fit's own weights (alpha = inf) by
    cross-validation over the folds of `fold` (weights fitted on the other folds' rows, squared
    errors on the fold's rows summed over folds and channels; ties go to the stronger shrink).

    Why: the plain refit (alpha = 0) raises the coarse levels' held-out medians and lowers their
    tails where NNLS with many points fits the grid's directions and misses between them; the
    guard (`refit_generalizes`) can only say all or nothing, and says nothing too often. A
    ridge towards the fit's weights is the middle the two measurements asked for
    (docs/decisions.md 2026-11-26). In-sample it can only beat the fit's weights: at
    w = w_fit the penalty is 0.
    A : (3, d, c); f_ref : (d, 3); ok : (d,) bool; old_w : (c, 3); fold : (d,) int.
    returns ((c, 3) weights, the chosen alpha; inf when the fit's weights are kept)."""
    c = A.shape[2]
    folds = [k for k in np.unique(fold) if np.any(ok & (fold == k))]
    # per channel and fold: the fold's Gram, A^T f and ||f||^2 (c x c: the folds' training
    # systems are the whole grid's minus the fold's)
    G = np.zeros((3, len(folds), c, c))
    b = np.zeros((3, len(folds), c))
    tt = np.zeros((3, len(folds)))
    for j, k in enumerate(folds):  # loop over folds (eight)
        rows = ok & (fold == k)
        a, f = A[:, rows], f_ref[rows].T  # (3, n, c), (3, n)
        at = a.transpose(0, 2, 1)
        G[:, j] = at @ a  # batched matmul (BLAS): einsum took 27x as long (3 x 512 x 64)
        b[:, j] = (at @ f[:, :, None])[:, :, 0]
        tt[:, j] = np.sum(f * f, axis=1)
    G_all, b_all, tt_all = G.sum(axis=1), b.sum(axis=1), tt.sum(axis=1)

    def fold_err(w: np.ndarray, ch: int, j: int) -> float:
        return float(w @ G[ch, j] @ w - 2.0 * b[ch, j] @ w + tt[ch, j])

    alphas = (*SHRINK_ALPHAS, np.inf)
    err = np.zeros(len(alphas))
    for ch in range(3):  # loop over colour channels
        for j in range(len(folds) if len(folds) > 1 else 0):  # loop over folds
            G_tr, b_tr, tt_tr = G_all[ch] - G[ch, j], b_all[ch] - b[ch, j], tt_all[ch] - tt[ch, j]
            for n, alpha in enumerate(SHRINK_ALPHAS):  # loop over the strengths (five)
                err[n] += fold_err(_shrunk(G_tr, b_tr, tt_tr, old_w[:, ch], alpha), ch, j)
            err[-1] += fold_err(old_w[:, ch], ch, j)
    # the strongest shrink among the smallest errors (reversed: argmin takes the first)
    best = len(alphas) - 1 - int(np.argmin(err[::-1]))
    if len(folds) < 2:  # nothing to validate on: the in-sample refit, as the plain rule
        best = 0
    alpha = float(alphas[best])
    if not np.isfinite(alpha):
        return old_w.copy(), alpha
    w = np.stack([_shrunk(G_all[ch], b_all[ch], tt_all[ch], old_w[:, ch], alpha)
                  for ch in range(3)], axis=1)  # loop over colour channels
    return w, alpha


def refit_to_dense(src: FitInputs, level: int, out: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """`out` of `fit_level` for `level` with every valid texel's point weights refitted to the
    dense Eq. 7 (see the module docstring); snr_in and snr_ho measured against it. A texel
    whose refit would not raise its in-sample SNR against the dense reference keeps its
    weights, and so does one the validation guard refuses (`settings.refit_validation`,
    `refit_generalizes`); with `settings.refit_shrink` the weights are shrunk towards the
    fit's (`shrunk_refit`). Returns a new dict: the same keys plus `refit_rejected` (t,) bool
    and `refit_alpha` (t,) float32, the shrink's strength (inf: the fit's weights kept; nan:
    not shrunk)."""
    with threadpool_limits(limits=1):  # small per-texel solves: see level.fit_level
        return _refit(src, level, out)


def _refit(src: FitInputs, level: int, out: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    s = src.settings
    geo = src.geo
    dirs = direction_sets(s)
    frames = geo[f"frames_L{level}"]
    n_i, n_o = len(dirs["dirs_i"]), len(dirs["dirs_o"])
    texels = np.asarray(out["texel"], np.int64)
    offsets = np.asarray(out["offsets"], np.int64)
    weights = np.asarray(out["point_weight"], np.float64).copy()
    samples = np.asarray(out["point_sample"], np.int64)
    snr_in = np.asarray(out["snr_in"], np.float32).copy()
    snr_ho = np.asarray(out["snr_ho"], np.float32).copy()
    budget = int(s.worker_memory_mb) * 2**20
    rays0 = src.caster.rays_cast
    fold = validation_fold(n_i, n_o, REFIT_FOLDS)
    shrink_fold = validation_fold(n_i, n_o, SHRINK_FOLDS)
    rejected = np.zeros(texels.shape[0], bool)  # refits the validation fold refused
    alphas = np.full(texels.shape[0], np.nan, np.float32)  # the shrunk refit's strengths
    for t, texel in enumerate(texels):  # loop over texels: one dense target and NNLS each
        a, b = offsets[t], offsets[t + 1]
        if not out["valid"][t] or b == a:
            continue
        dense = samples_in(geo, s.atlas_resolution, level, np.array([texel]))
        area = geo["sample_area"][dense]
        # the dense target (3, d) and a_vis on the training grid
        target = np.zeros((3, n_i * n_o))
        for s0 in range(0, dense.size, _BATCH):  # loop over sample batches (memory bound)
            part = PointSet(dense[s0:s0 + _BATCH], np.repeat(area[s0:s0 + _BATCH, None], 3, 1),
                            np.full(min(_BATCH, dense.size - s0), texel))
            target += _build_R(src, frames, part, dirs, budget).sum(axis=1)
        vo = visibility_cos(src, dense, world_dirs(frames, np.full(dense.size, texel),
                                                   dirs["dirs_o"]), "geometric")
        avis_rows = np.tile(vo.T @ area, n_i)  # (d,) row i * n_o + o
        eps = avis_floor(float(area.sum()))
        pts = PointSet(samples[a:b], np.ones((b - a, 3)), np.full(b - a, texel))
        R = _build_R(src, frames, pts, dirs, budget)  # (3, c, d), unit weights
        f_ref, ok = filtered_reflectance(target.T, avis_rows, eps)  # (d, 3)
        if not ok.any():
            continue
        inv = np.where(ok, 1.0 / np.where(ok, avis_rows, 1.0), 0.0)
        A = np.stack([(R[ch] * inv[None, :]).T for ch in range(3)])  # (3, d, c): F per channel
        old_w = weights[a:b].astype(np.float64)
        old = np.einsum("kdc,ck->dk", A, old_w)  # (d, 3): Eq. 7 of the fit's weights
        if s.refit_shrink:
            new_w, alpha = shrunk_refit(A, f_ref, ok, old_w, shrink_fold)
            alphas[t] = alpha
        else:
            new_w = dense_nnls(A, f_ref, ok)
        new = np.einsum("kdc,ck->dk", A, new_w)
        snr_old, snr_new = snr_db(f_ref, old, ok), snr_db(f_ref, new, ok)
        accept = snr_new > snr_old
        if accept and s.refit_validation:
            accept = refit_generalizes(A, f_ref, ok, old_w, fold)
            rejected[t] = not accept
        if accept:
            weights[a:b] = new_w.astype(np.float32)
        snr_in[t] = snr_new if accept else snr_old
        if len(dirs["held_i"]):
            held_dirs = np.concatenate([dirs["held_i"], dirs["held_o"]])
            tex_d = np.full(dense.size, texel)
            n_hi = len(dirs["held_i"])
            hw = world_dirs(frames, tex_d, held_dirs)
            held_vc = np.concatenate([visibility_cos(src, dense, hw[:, :n_hi]),
                                      visibility_cos(src, dense, hw[:, n_hi:], "geometric")],
                                     axis=1)
            order = np.argsort(samples[a:b], kind="stable")
            p_s = samples[a:b][order]
            snr_ho[t] = heldout_snr(src, dirs, frames, int(texel), dense, held_vc, area, p_s,
                                    weights[a:b][order], held_vc[np.searchsorted(dense, p_s)],
                                    float(area.sum()))
    res = dict(out)
    res["point_weight"] = weights.astype(np.float32)
    res["snr_in"] = snr_in
    res["snr_ho"] = snr_ho
    res["refit_rejected"] = rejected
    res["refit_alpha"] = alphas
    if "rays" in out:  # work done, for rays/s: the fit's and the refit's
        res["rays"] = np.asarray(out["rays"], np.int64) + (src.caster.rays_cast - rays0)
    return res
