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


def refit_to_dense(src: FitInputs, level: int, out: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """`out` of `fit_level` for `level` with every valid texel's point weights refitted to the
    dense Eq. 7 (see the module docstring); snr_in and snr_ho measured against it. A texel
    whose refit would not raise its in-sample SNR against the dense reference keeps its
    weights, and so does one the validation guard refuses (`settings.refit_validation`,
    `refit_generalizes`). Returns a new dict: the same keys plus `refit_rejected` (t,) bool."""
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
    rejected = np.zeros(texels.shape[0], bool)  # refits the validation fold refused
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
    if "rays" in out:  # work done, for rays/s: the fit's and the refit's
        res["rays"] = np.asarray(out["rays"], np.int64) + (src.caster.rays_cast - rays0)
    return res
