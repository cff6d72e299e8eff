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


# The shrunk refit (`settings.refit_shrink`): the plain refit (alpha = 0) raises the coarse
# levels' held-out medians and lowers their tails where NNLS with many points fits the grid's
# directions and misses between them; the guard (`refit_generalizes`) can only say all or
# nothing, and says nothing too often. A ridge towards the fit's weights, w = argmin_{w >= 0}
# ||A w - f||^2 + lam ||w - w_fit||^2, is the middle the two measurements asked for
# (docs/decisions.md 2026-11-26); in-sample it cannot lose to the fit's weights (the penalty
# is 0 there). Its strength is chosen by cross-validation, once per pool of texels.

#: light-direction folds of the shrunk refit's cross-validation (`shrink_errors`): more folds
#: than the guard's 4 so that each fold's training rows (7/8 of the grid's light directions)
#: fit nearly as well as the whole grid (the guard's bias against the refit, 2026-11-26)
SHRINK_FOLDS = 8

#: texels whose cross-validation errors choose one strength together (`pooled_alpha`): a
#: tile's level or a block of a top level, in texel order; bounds what is held between the two
#: passes (each texel's target and 1/a_vis, (d, 4) float64: 256 x 131 KB = 34 MB). A tile's
#: coarsest level holds one texel (a tile is one shard), so there the choice is the texel's own.
POOL_TEXELS = 256

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


def _fold_systems(A: np.ndarray, f_ref: np.ndarray, ok: np.ndarray, fold: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per channel and fold of `fold` (folds without a row in `ok` dropped): the fold's Gram
    (3, F, c, c), A^T f (3, F, c) and ||f||^2 (3, F) over its rows in `ok`; a fold's training
    system is the sum over the other folds."""
    folds = [k for k in np.unique(fold) if np.any(ok & (fold == k))]
    parts = [_normal_equations(A, f_ref, ok & (fold == k)) for k in folds]  # loop over folds
    c = A.shape[2]
    if not parts:
        return np.zeros((3, 0, c, c)), np.zeros((3, 0, c)), np.zeros((3, 0))
    G, b, tt = (np.stack(x, axis=1) for x in zip(*parts, strict=True))
    return G, b, tt


def _normal_equations(A: np.ndarray, f_ref: np.ndarray, rows: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per channel over `rows`: the Gram A^T A (3, c, c), A^T f (3, c) and ||f||^2 (3,)."""
    a, f = A[:, rows], f_ref[rows].T  # (3, n, c), (3, n)
    at = a.transpose(0, 2, 1)
    # batched matmul (BLAS): einsum took 27x as long (3 x 512 x 64)
    return at @ a, (at @ f[:, :, None])[:, :, 0], np.sum(f * f, axis=1)


def shrink_errors(A: np.ndarray, f_ref: np.ndarray, ok: np.ndarray, old_w: np.ndarray,
                  fold: np.ndarray) -> np.ndarray:
    """The cross-validation errors of every strength of `SHRINK_ALPHAS` and of the fit's own
    weights (last), relative to the texel's signal: for each fold of `fold`, weights fitted
    (`_shrunk`) on the other folds' rows and scored on the fold's, squared errors summed over
    folds and channels, over sum ||f||^2 (so texels of any brightness count alike when pooled).
    All zeros when fewer than two folds have rows (nothing to validate on).
    A : (3, d, c); f_ref : (d, 3); ok : (d,) bool; old_w : (c, 3); fold : (d,) int.
    returns (len(SHRINK_ALPHAS) + 1,) float64."""
    G, b, tt = _fold_systems(A, f_ref, ok, fold)
    n_f = G.shape[1]
    G_all, b_all, tt_all = G.sum(axis=1), b.sum(axis=1), tt.sum(axis=1)
    err = np.zeros(len(SHRINK_ALPHAS) + 1)
    if n_f < 2:
        return err

    def fold_err(w: np.ndarray, ch: int, j: int) -> float:
        return float(w @ G[ch, j] @ w - 2.0 * b[ch, j] @ w + tt[ch, j])

    for ch in range(3):  # loop over colour channels
        for j in range(n_f):  # loop over folds
            G_tr, b_tr, tt_tr = G_all[ch] - G[ch, j], b_all[ch] - b[ch, j], tt_all[ch] - tt[ch, j]
            for n, alpha in enumerate(SHRINK_ALPHAS):  # loop over the strengths (five)
                err[n] += fold_err(_shrunk(G_tr, b_tr, tt_tr, old_w[:, ch], alpha), ch, j)
            err[-1] += fold_err(old_w[:, ch], ch, j)
    return err / max(float(tt_all.sum()), np.finfo(np.float64).tiny)


def pooled_alpha(errors: np.ndarray) -> float:
    """The strength whose summed relative errors over the rows of `errors` (texels, strengths
    + 1) are smallest; ties (and an all-zero table: nothing validated) go to the strongest
    shrink, the fit's own weights (inf) first; so does an empty pool.

    Why pooled: a texel's own eight folds choose noisily, and the choice that helps one texel's
    grid can lose its held-out pairs (the Teapot's worst level-3 texel, 5.2 -> -3.4 dB with a
    strength per texel); one strength for a pool of texels, chosen on all their folds, kept the
    tails of the cloisonne and the Teapot and most of the cylinder's gain (docs/decisions.md
    2026-11-29)."""
    alphas = (*SHRINK_ALPHAS, np.inf)
    errors = np.asarray(errors, np.float64).reshape(-1, len(alphas))
    total = errors.sum(axis=0)
    return float(alphas[len(alphas) - 1 - int(np.argmin(total[::-1]))])


def shrunk_weights(A: np.ndarray, f_ref: np.ndarray, ok: np.ndarray, old_w: np.ndarray,
                   alpha: float) -> np.ndarray:
    """(c, 3): per channel argmin_{w >= 0} ||A_k w - f_k||^2 + lam ||w - old_w_k||^2 over the
    rows `ok`, lam = alpha x the Gram's mean diagonal; alpha = inf returns the fit's weights."""
    if not np.isfinite(alpha):
        return np.asarray(old_w, np.float64).copy()
    G, b, tt = _normal_equations(A, f_ref, ok)
    return np.stack([_shrunk(G[ch], b[ch], float(tt[ch]), old_w[:, ch], alpha)
                     for ch in range(3)], axis=1)  # loop over colour channels


def shrunk_refit(A: np.ndarray, f_ref: np.ndarray, ok: np.ndarray, old_w: np.ndarray,
                 fold: np.ndarray) -> tuple[np.ndarray, float]:
    """One texel's refit shrunk towards the fit's weights, its strength chosen by its own
    cross-validation (a pool of one: `pooled_alpha` of its `shrink_errors`); the stage pools
    `POOL_TEXELS` texels (`refit_to_dense`). returns ((c, 3) weights, alpha)."""
    alpha = pooled_alpha(shrink_errors(A, f_ref, ok, old_w, fold))
    return shrunk_weights(A, f_ref, ok, old_w, alpha), alpha


def refit_to_dense(src: FitInputs, level: int, out: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """`out` of `fit_level` for `level` with every valid texel's point weights refitted to the
    dense Eq. 7 (see the module docstring); snr_in and snr_ho measured against it. A texel
    whose refit would not raise its in-sample SNR against the dense reference keeps its
    weights, and so does one the validation guard refuses (`settings.refit_validation`,
    `refit_generalizes`); with `settings.refit_shrink` the weights are shrunk towards the
    fit's with one strength per pool of `POOL_TEXELS` texels (`shrink_errors`, `pooled_alpha`,
    `shrunk_weights`). Returns a new dict: the same keys plus `refit_rejected` (t,) bool
    and `refit_alpha` (t,) float32, the shrink's strength (inf: the fit's weights kept; nan:
    not shrunk)."""
    with threadpool_limits(limits=1):  # small per-texel solves: see level.fit_level
        return _refit(src, level, out)


def _dense_target(src: FitInputs, level: int, frames: np.ndarray, dirs: dict, texel: int,
                  budget: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The texel's dense Eq. 7 on the training grid (the refit's cost: R over every dense
    sample). returns (f_ref (d, 3), ok (d,) rows with a_vis above its floor, inv (d,) 1/a_vis
    on them and 0 elsewhere)."""
    geo = src.geo
    n_i, n_o = len(dirs["dirs_i"]), len(dirs["dirs_o"])
    dense = samples_in(geo, src.settings.atlas_resolution, level, np.array([texel]))
    area = geo["sample_area"][dense]
    target = np.zeros((3, n_i * n_o))
    for s0 in range(0, dense.size, _BATCH):  # loop over sample batches (memory bound)
        part = PointSet(dense[s0:s0 + _BATCH], np.repeat(area[s0:s0 + _BATCH, None], 3, 1),
                        np.full(min(_BATCH, dense.size - s0), texel))
        target += _build_R(src, frames, part, dirs, budget).sum(axis=1)
    vo = visibility_cos(src, dense, world_dirs(frames, np.full(dense.size, texel),
                                               dirs["dirs_o"]), "geometric")
    avis_rows = np.tile(vo.T @ area, n_i)  # (d,) row i * n_o + o
    f_ref, ok = filtered_reflectance(target.T, avis_rows, avis_floor(float(area.sum())))
    inv = np.where(ok, 1.0 / np.where(ok, avis_rows, 1.0), 0.0)
    return f_ref, ok, inv


def _point_terms(src: FitInputs, frames: np.ndarray, dirs: dict, texel: int, pts: np.ndarray,
                 inv: np.ndarray, budget: int) -> np.ndarray:
    """(3, d, c): each point's Eq. 7 term per channel over a_vis (F of the fit, unit weights)."""
    R = _build_R(src, frames, PointSet(pts, np.ones((pts.size, 3)), np.full(pts.size, texel)),
                 dirs, budget)  # (3, c, d)
    return np.stack([(R[ch] * inv[None, :]).T for ch in range(3)])


def _refit(src: FitInputs, level: int, out: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    s = src.settings
    dirs = direction_sets(s)
    frames = src.geo[f"frames_L{level}"]
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
    todo = [t for t in range(texels.shape[0])
            if out["valid"][t] and offsets[t + 1] > offsets[t]]
    pool = POOL_TEXELS if s.refit_shrink else 1
    for p0 in range(0, len(todo), pool):  # loop over pools of texels (one each unshrunk)
        # pass 1: each texel's dense target (and, shrunk, its cross-validation errors)
        held: dict[int, tuple] = {}
        errors = []
        for t in todo[p0:p0 + pool]:  # loop over texels: one dense target each
            a, b = offsets[t], offsets[t + 1]
            f_ref, ok, inv = _dense_target(src, level, frames, dirs, int(texels[t]), budget)
            if not ok.any():
                continue
            held[t] = (f_ref, ok, inv)
            if s.refit_shrink:
                A = _point_terms(src, frames, dirs, int(texels[t]), samples[a:b], inv, budget)
                errors.append(shrink_errors(A, f_ref, ok, weights[a:b].astype(np.float64),
                                            shrink_fold))
        alpha = pooled_alpha(np.array(errors)) if s.refit_shrink else np.nan
        # pass 2: the weights, the in-sample SNR against the dense target, the held-out SNR
        for t, (f_ref, ok, inv) in held.items():  # loop over the pool's texels
            a, b = offsets[t], offsets[t + 1]
            texel = int(texels[t])
            dense = samples_in(src.geo, s.atlas_resolution, level, np.array([texel]))
            A = _point_terms(src, frames, dirs, texel, samples[a:b], inv, budget)
            old_w = weights[a:b].astype(np.float64)
            if s.refit_shrink:
                new_w = shrunk_weights(A, f_ref, ok, old_w, alpha)
                alphas[t] = alpha
            else:
                new_w = dense_nnls(A, f_ref, ok)
            old = np.einsum("kdc,ck->dk", A, old_w)  # (d, 3): Eq. 7 of the fit's weights
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
                snr_ho[t] = _heldout(src, dirs, frames, texel, dense,
                                     src.geo["sample_area"][dense], samples[a:b], weights[a:b])
    res = dict(out)
    res["point_weight"] = weights.astype(np.float32)
    res["snr_in"] = snr_in
    res["snr_ho"] = snr_ho
    res["refit_rejected"] = rejected
    res["refit_alpha"] = alphas
    if "rays" in out:  # work done, for rays/s: the fit's and the refit's
        res["rays"] = np.asarray(out["rays"], np.int64) + (src.caster.rays_cast - rays0)
    return res


def _heldout(src: FitInputs, dirs: dict, frames: np.ndarray, texel: int, dense: np.ndarray,
             area: np.ndarray, pts: np.ndarray, w: np.ndarray) -> float:
    """The texel's held-out SNR of points `pts` with weights `w` against its dense Eq. 7."""
    held_dirs = np.concatenate([dirs["held_i"], dirs["held_o"]])
    n_hi = len(dirs["held_i"])
    hw = world_dirs(frames, np.full(dense.size, texel), held_dirs)
    held_vc = np.concatenate([visibility_cos(src, dense, hw[:, :n_hi]),
                              visibility_cos(src, dense, hw[:, n_hi:], "geometric")], axis=1)
    order = np.argsort(pts, kind="stable")
    p_s = pts[order]
    return float(heldout_snr(src, dirs, frames, texel, dense, held_vc, area, p_s, w[order],
                             held_vc[np.searchsorted(dense, p_s)], float(area.sum())))
