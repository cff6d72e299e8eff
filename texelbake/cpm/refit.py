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
    texel_ids,
    visibility_cos,
    world_dirs,
)
from texelbake.cpm.level_batched import _build_R
from texelbake.cpm.matrix import avis_floor, filtered_reflectance, snr_db

#: dense samples per batch of R (3 x batch x d float64: 3 x 256 x 4096 x 8 B = 25 MB)
_BATCH = 256


def refit_to_dense(src: FitInputs, level: int, out: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """`out` of `fit_level` for `level` with every valid texel's point weights refitted to the
    dense Eq. 7 (see the module docstring); snr_in and snr_ho measured against it. A texel
    whose refit would not raise its in-sample SNR against the dense reference keeps its
    weights. Returns a new dict (same keys)."""
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
    tex_of_sample = texel_ids(geo, s.atlas_resolution, level)
    budget = int(s.worker_memory_mb) * 2**20
    rays0 = src.caster.rays_cast
    for t, texel in enumerate(texels):  # loop over texels: one dense target and NNLS each
        a, b = offsets[t], offsets[t + 1]
        if not out["valid"][t] or b == a:
            continue
        dense = np.flatnonzero(tex_of_sample == texel)
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
        old = filtered_reflectance(np.einsum("cpd,pc->dc", R, weights[a:b]), avis_rows, eps)[0]
        new_w = np.zeros((b - a, 3))
        for ch in range(3):  # loop over colour channels
            A = (R[ch] * inv[None, :]).T[ok]  # (d_ok, c)
            if np.any(A):
                new_w[:, ch] = nnls(A, f_ref[ok, ch], maxiter=50 * A.shape[1])[0]
        new = filtered_reflectance(np.einsum("cpd,pc->dc", R, new_w), avis_rows, eps)[0]
        snr_old, snr_new = snr_db(f_ref, old, ok), snr_db(f_ref, new, ok)
        if snr_new > snr_old:
            weights[a:b] = new_w.astype(np.float32)
        snr_in[t] = max(snr_new, snr_old)
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
    if "rays" in out:  # work done, for rays/s: the fit's and the refit's
        res["rays"] = np.asarray(out["rays"], np.int64) + (src.caster.rays_cast - rays0)
    return res
