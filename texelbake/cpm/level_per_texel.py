"""One CPM level fitted one texel at a time on its matrix R (seed 000 §3.2–3.3, the seed's
loop; `BakeSettings.fit_method="per_texel"`): R from visibility rays against M_org and the
BRDFs of the candidates, one `fit.fit_texel` per texel, the held-out SNR against brute-force
Eq. 7 over all the texel's dense samples. Same arrays as `level_batched.fit_level_batched`.
"""

from __future__ import annotations

import numpy as np

from texelbake.cpm.cell_table import cell_fbar, direction_cells
from texelbake.cpm.dense import LevelPass, avis_sums, dense_of, inv_avis, positions
from texelbake.cpm.fit import fit_texel
from texelbake.cpm.level import (
    FitInputs,
    PointSet,
    brdf_grid,
    direction_sets,
    samples_in,
    texel_ids,
    texel_seed,
    visibility_cos,
    world_dirs,
)
from texelbake.cpm.matrix import avis_floor, filtered_reflectance, snr_db
from texelbake.cpm.texel_fit import FitParams


def fit_level_per_texel(
    src: FitInputs,
    level: int,
    texels: np.ndarray,
    candidates: PointSet,
) -> dict[str, np.ndarray]:
    """Characteristic points of `texels` at `level` chosen among `candidates` (seed 000 §3.3),
    one `fit_texel` per texel on its R.

    The reference of each texel is its candidates' summation term (Eq. 9 with the candidates'
    per-channel weights); a_vis(w_o) comes from *all* dense samples of the texel (Eq. 3 on the
    same visibility); held-out SNR compares against the brute-force Eq. 7 over all samples.
    returns : arrays for this level: texel (t,), offsets (t+1,), point sample ids (p,), point
        weights (p, 3) float32, k, c, snr_in, snr_ho (t,), mode (t,) int8, valid (t,) bool,
        and when settings.btf, fbar (t, d, 3) float32 (Eq. 7 on the training grid).
    """
    s = src.settings
    params = FitParams.of(s)
    geo = src.geo
    n = s.atlas_resolution
    dirs = direction_sets(s)
    frames = geo[f"frames_L{level}"]
    # all dense samples of these texels (for a_vis and the held-out truth), ascending
    samp_all = samples_in(geo, n, level, texels)
    tex_all = texel_ids(geo, n, level, samp_all)
    n_i, n_o = len(dirs["dirs_i"]), len(dirs["dirs_o"])
    n_hi = len(dirs["held_i"])
    # one batch of rays per direction set for the whole tile
    view_vc = visibility_cos(
        src, samp_all, world_dirs(frames, tex_all, dirs["dirs_o"]), "geometric"
    )
    held_vc = np.concatenate([
        visibility_cos(src, samp_all, world_dirs(frames, tex_all, dirs["held_i"])),
        visibility_cos(
            src, samp_all, world_dirs(frames, tex_all, dirs["held_o"]), "geometric"
        ),
    ], axis=1)
    cand_light_vc = visibility_cos(
        src, candidates.sample, world_dirs(frames, candidates.texel, dirs["dirs_i"])
    )
    # candidates are dense samples of these texels; samp_all is sorted (np.nonzero)
    cand_rows = np.searchsorted(samp_all, candidates.sample)
    cand_view_vc = view_vc[cand_rows]
    area_all = geo["sample_area"][samp_all]

    # group samples and candidates by texel (stable order)
    order_all = np.argsort(tex_all, kind="stable")
    order_cand = np.argsort(candidates.texel, kind="stable")
    bounds_all = np.searchsorted(tex_all[order_all], np.stack([texels, texels + 1]))
    bounds_cand = np.searchsorted(candidates.texel[order_cand], np.stack([texels, texels + 1]))

    out_pts: list[np.ndarray] = []
    out_w: list[np.ndarray] = []
    offsets = [0]
    stats = {k: np.zeros(len(texels)) for k in ("k", "c", "snr_in", "snr_ho")}
    mode = np.zeros(len(texels), np.int8)
    valid = np.zeros(len(texels), bool)
    fbar_all = np.zeros((len(texels), n_i * n_o, 3), np.float32) if s.btf else None
    for t, texel in enumerate(texels):  # one SVD/bisection per texel: inherent to the method
        rows_all = order_all[bounds_all[0, t]:bounds_all[1, t]]
        rows_c = order_cand[bounds_cand[0, t]:bounds_cand[1, t]]
        if rows_all.size == 0 or rows_c.size == 0:
            offsets.append(offsets[-1])
            stats["snr_in"][t] = stats["snr_ho"][t] = np.nan
            continue
        cset = candidates.take(rows_c)
        vi = cand_light_vc[rows_c]  # (m, n_i)
        vo = cand_view_vc[rows_c]  # (m, n_o)
        live = (vi.T[:, None, :] > 0) & (vo.T[None, :, :] > 0)  # (n_i, n_o, m)
        wi_w = world_dirs(frames, cset.texel, dirs["dirs_i"])
        wo_w = world_dirs(frames, cset.texel, dirs["dirs_o"])
        f = brdf_grid(src, cset.sample, wi_w, wo_w, live)  # (n_i, n_o, m, 3)
        R = (f * (vi.T[:, None, :, None] * vo.T[None, :, :, None])
             * cset.weight[None, None, :, :]).reshape(n_i * n_o, -1, 3)
        avis_o = view_vc[rows_all].T @ area_all[rows_all]  # (n_o,)
        avis_rows = np.tile(avis_o, n_i)
        texel_area = float(area_all[rows_all].sum())
        fit = fit_texel(R, avis_rows, params, seed=texel_seed(s.seed, level, int(texel)),
                        texel_area=texel_area)
        # effective weight of a point: alpha times its candidate weight (Eq. 10 with dA folded in)
        w_eff = fit.weights.astype(np.float64) * cset.weight[fit.columns]
        out_pts.append(cset.sample[fit.columns])
        out_w.append(w_eff)
        offsets.append(offsets[-1] + len(fit.columns))
        stats["k"][t], stats["c"][t] = fit.k, fit.c
        stats["snr_in"][t] = fit.snr_db_insample
        mode[t] = 1 if fit.colour_mode == "per_channel" else 0
        valid[t] = fit.valid
        if fbar_all is not None:
            fbar, _ = filtered_reflectance(
                R.sum(axis=1), avis_rows, avis_floor(texel_area)
            )
            fbar_all[t] = fbar
        # held-out: brute force over all samples vs the characteristic points
        if n_hi and fit.valid:
            stats["snr_ho"][t] = texel_heldout_snr(
                src, dirs, frames, int(texel), samp_all[rows_all], held_vc[rows_all],
                area_all[rows_all], cset.sample[fit.columns],
                w_eff.astype(np.float32).astype(np.float64),  # as stored
                held_vc[np.searchsorted(samp_all, cset.sample[fit.columns])],
                texel_area,
            )
        else:
            stats["snr_ho"][t] = np.nan
    out = {
        "texel": texels.astype(np.int64),
        "offsets": np.asarray(offsets, np.int64),
        "point_sample": np.concatenate(out_pts) if out_pts else np.zeros(0, np.int64),
        "point_weight": (np.concatenate(out_w) if out_w else np.zeros((0, 3))).astype(np.float32),
        "k": stats["k"].astype(np.int32),
        "c": stats["c"].astype(np.int32),
        "snr_in": stats["snr_in"].astype(np.float32),
        "snr_ho": stats["snr_ho"].astype(np.float32),
        "mode": mode,
        "valid": valid,
    }
    if fbar_all is not None:
        out["fbar"] = fbar_all
    return out


def texel_heldout_snr(
    src: FitInputs, dirs: dict[str, np.ndarray], frames: np.ndarray, texel: int,
    samples: np.ndarray, held_vc: np.ndarray, area: np.ndarray, pts: np.ndarray,
    w_eff: np.ndarray, pts_held_vc: np.ndarray, texel_area: float,
) -> float:
    """SNR (dB) of Eq. 7 on the held-out product grid: brute force over all `samples` of the
    texel (weights ΔA) against the characteristic points `pts` (weights w_eff)."""
    n_hi = len(dirs["held_i"])
    tex = np.full(len(samples), texel)
    wi_w = world_dirs(frames, tex, dirs["held_i"])
    wo_w = world_dirs(frames, tex, dirs["held_o"])
    vi, vo = held_vc[:, :n_hi], held_vc[:, n_hi:]
    live = (vi.T[:, None, :] > 0) & (vo.T[None, :, :] > 0)
    f = brdf_grid(src, samples, wi_w, wo_w, live)  # (h_i, h_o, m, 3)
    ref = np.einsum("abmc,am,bm,m->abc", f, vi.T, vo.T, area)
    # the characteristic points are samples too: reuse their rows of f
    pos = np.searchsorted(samples, pts)
    approx = np.einsum("abmc,am,bm,mc->abc", f[:, :, pos], pts_held_vc[:, :n_hi].T,
                       pts_held_vc[:, n_hi:].T, w_eff)
    avis_o = vo.T @ area  # (h_o,)
    eps = avis_floor(texel_area)
    d = ref.shape[0] * ref.shape[1]
    avis_rows = np.tile(avis_o, ref.shape[0])
    f_ref, valid = filtered_reflectance(ref.reshape(d, 3), avis_rows, eps)
    f_apx, _ = filtered_reflectance(approx.reshape(d, 3), avis_rows, eps)
    return float(snr_db(f_ref, f_apx, valid))


def cell_fbar_per_texel(src: FitInputs, texels: np.ndarray, candidates: PointSet) -> np.ndarray:
    """Level 0's cell-averaged f̄ (t, d, 3) float32 (`cell_table`) for the per-texel path, which
    keeps neither a_vis nor the candidates' order: both remade here, in memory-bounded chunks."""
    lp = LevelPass.of(src, 0)
    dense, dseg = dense_of(lp, texels)
    avis_o, area = avis_sums(lp, texels, dense, dseg)
    inv_o = inv_avis(avis_o, area)[1]
    pos_c = positions(texels, candidates.texel)
    order = np.argsort(pos_c, kind="stable")
    order = order[pos_c[order] >= 0]
    return cell_fbar(src, lp.frames, candidates.take(order), pos_c[order], len(texels), lp.dirs,
                     *direction_cells(src.settings, lp.dirs), inv_o, lp.budget)


__all__ = ["cell_fbar_per_texel", "fit_level_per_texel", "texel_heldout_snr"]
