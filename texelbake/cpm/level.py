"""Fitting one CPM level over a set of texels (seed 000 §3.2–3.3): R built from visibility
rays against M_org and the BRDFs of the samples, one `fit_texel` per texel, the held-out SNR,
and the candidates of a coarse level (its children's points, or all dense samples).

Inputs are the geometry stage's arrays (`FitInputs.geo`: samples, texel assignment, frames),
a ray caster over M_org and the asset's materials; outputs are plain arrays per level, CSR by
texel (`offsets`), which the cpm stage stores per tile.

Per-texel randomness is seeded by (settings.seed, level, texel), never by shard, so the result
does not depend on how texels are sharded.
"""

from __future__ import annotations

import hashlib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import torch
from threadpoolctl import threadpool_limits

from schemas.settings import BakeSettings
from texelbake import brdf as brdf_mod
from texelbake.cpm.fit import fit_texel
from texelbake.cpm.matrix import avis_floor, filtered_reflectance, snr_db
from texelbake.geometry import directions
from texelbake.geometry.basis import grid_to_local, grid_to_world, tangent_frames
from texelbake.geometry.raycast import RayCaster
from texelbake.geometry.texels import morton
from texelbake.model import Material
from texelbake.tol import TOL

_TAG_LIGHT, _TAG_VIEW, _TAG_HELD_I, _TAG_HELD_O = 0x11, 0x22, 0x33, 0x44


@dataclass(frozen=True)
class FitInputs:
    """What fitting a level reads: the bake settings, the geometry stage's arrays, a ray caster
    over M_org (all objects of the asset) and the asset's materials."""

    settings: BakeSettings
    geo: Mapping[str, np.ndarray]
    caster: RayCaster
    materials: Sequence[Material]


def texel_ids(geo: Mapping[str, np.ndarray], n: int, level: int,
              samples: np.ndarray | None = None) -> np.ndarray:
    """(m,) int64 flat texel id of every sample at `level` (row * N_l + col); with `samples`,
    of those samples only."""
    n_l = n >> level
    row, col = geo["sample_row"], geo["sample_col"]
    if samples is not None:
        row, col = row[samples], col[samples]
    return (row >> level) * n_l + (col >> level)


def samples_in(geo: Mapping[str, np.ndarray], n: int, level: int,
               texels: np.ndarray) -> np.ndarray:
    """(k,) int64 ids of the samples of `texels` (flat ids at `level`), ascending, as
    `np.flatnonzero(np.isin(texel_ids(geo, n, level), texels))` gives them. Read from the
    geometry stage's Z-order index (`sample_zorder`, `texel_zoffsets`): a texel at level l is
    one run of 4^l finest codes, so only these texels' ids are read, not every sample's texel
    (artifacts from before the index: that scan)."""
    texels = np.unique(np.asarray(texels, dtype=np.int64))
    if "sample_zorder" not in geo:
        return np.flatnonzero(np.isin(texel_ids(geo, n, level), texels))
    zoff = geo["texel_zoffsets"]
    r, c = np.divmod(texels, n >> level)
    first = morton(r << level, c << level)
    lo, hi = zoff[first], zoff[first + (1 << (2 * level))]
    size = hi - lo
    if not size.sum():
        return np.zeros(0, np.int64)
    # the runs' positions in sample_zorder, concatenated: lo_j, lo_j + 1, ..., hi_j - 1
    pos = np.arange(int(size.sum()), dtype=np.int64) - np.repeat(np.cumsum(size) - size, size)
    pos += np.repeat(lo, size)
    order = geo["sample_zorder"]
    # runs sorted by position: a mapped index is read front to back
    return np.sort(np.asarray(order[np.sort(pos)], dtype=np.int64))


def tile_texels(n: int, s: int, tile: int, level: int) -> np.ndarray:
    """Flat ids at `level` of the texels inside tile `tile` (tiles of s x s finest texels)."""
    tiles_per_row = n // s
    tr, tc = divmod(int(tile), tiles_per_row)
    side = s >> level
    n_l = n >> level
    rows = tr * side + np.arange(side)
    cols = tc * side + np.arange(side)
    return (rows[:, None] * n_l + cols[None, :]).ravel().astype(np.int64)


def direction_sets(settings: BakeSettings) -> dict[str, np.ndarray]:
    """The texel-frame direction sets of the bake: the N_i x N_o training grid and a held-out
    product grid of independent directions (16 x 16 by default: n_heldout pairs)."""
    s = settings
    n_h = max(1, int(round(np.sqrt(s.n_heldout)))) if s.n_heldout else 0
    return {
        "dirs_i": directions.hemisphere_directions(s.n_light_dirs, seed=s.seed * 1000 + _TAG_LIGHT),
        "dirs_o": directions.hemisphere_directions(s.n_view_dirs, seed=s.seed * 1000 + _TAG_VIEW),
        "held_i": directions.heldout_pairs(n_h, seed=s.seed * 1000 + _TAG_HELD_I)[0],
        "held_o": directions.heldout_pairs(n_h, seed=s.seed * 1000 + _TAG_HELD_O)[1],
    }


@dataclass
class PointSet:
    """Candidate (or characteristic) points: samples of M_org with per-channel weights."""

    sample: np.ndarray  # (p,) int64 index into the geometry samples
    weight: np.ndarray  # (p, 3) float64 area-like weight per channel
    texel: np.ndarray  # (p,) int64 texel id (at the level being fitted)

    def take(self, idx: np.ndarray) -> PointSet:
        return PointSet(self.sample[idx], self.weight[idx], self.texel[idx])


def visibility_cos(
    src: FitInputs,
    sample: np.ndarray,
    dirs_world: np.ndarray,
    cosine: str = "shading",
) -> np.ndarray:
    """V(x, w) (n . w)+ for samples x and per-sample world directions.

    sample : (p,) int64; dirs_world : (p, D, 3) float64
    cosine : "shading" — (n_s . w)+ with the interpolated shading normal, for light directions
        (irradiance, as the `gt` renderer shades); "geometric" — (n_g . w)+ with the triangle's
        normal, for view directions (projected area, Eq. 3, as `texelbake.cpm.avis` defines a_vis), so that
        R's view factor and a_vis agree and a flat Lambertian texel is reproduced exactly.
    returns : (p, D) float64 — visibility by rays against M_org times the clamped cosine; zero
        below the geometric or the shading horizon.
    """
    p, n_dirs = dirs_world.shape[:2]
    if p == 0 or n_dirs == 0:
        return np.zeros((p, n_dirs))
    geo = src.geo
    pos = geo["sample_pos"][sample]
    gn = geo["sample_gnrm"][sample]
    sn = geo["sample_nrm"][sample]
    cos_g = np.einsum("pk,pdk->pd", gn, dirs_world)  # (p, D)
    cos_s = np.einsum("pk,pdk->pd", sn, dirs_world)
    caster = src.caster
    live = (cos_g > TOL.grazing_cos) & (cos_s > TOL.grazing_cos)
    pi, di = np.nonzero(live)
    # offset once per sample; the caster pairs origins and directions into its float32 rays
    origins = pos + (TOL.ray_offset * caster.bbox_diag) * gn
    occ = caster.occluded_pairs(origins, dirs_world.reshape(-1, 3), pi, pi * n_dirs + di)
    cos = cos_s if cosine == "shading" else cos_g
    # the live entries kept whole, only the occluded ones scattered (most rays escape)
    out = np.where(live, cos, 0.0)
    out[pi[occ], di[occ]] = 0.0
    return out


def segment_sum(values: np.ndarray, seg: np.ndarray, n_seg: int, axis: int) -> np.ndarray:
    """Sum `values` along `axis` over runs of equal, ascending segment ids seg -> n_seg rows."""
    shape = list(values.shape)
    shape[axis] = n_seg
    out = np.zeros(shape, dtype=np.float64)
    if seg.size == 0:
        return out
    starts = np.flatnonzero(np.r_[True, seg[1:] != seg[:-1]])
    sums = np.add.reduceat(values, starts, axis=axis)
    idx: list[slice | np.ndarray] = [slice(None)] * values.ndim
    idx[axis] = seg[starts]
    out[tuple(idx)] = sums
    return out


def world_dirs(frames: np.ndarray, texel: np.ndarray, dirs_local: np.ndarray) -> np.ndarray:
    """(p, D, 3) world directions of texel-frame `dirs_local` (D, 3) for points in `texel`."""
    return grid_to_world(frames[texel], dirs_local)


def brdf_grid(
    src: FitInputs,
    sample: np.ndarray,
    wi_world: np.ndarray,
    wo_world: np.ndarray,
    live: np.ndarray,
) -> np.ndarray:
    """f_r(x_j, wi, wo) in each sample's own shading frame, on a product of direction sets.

    sample : (p,); wi_world : (p, A, 3); wo_world : (p, B, 3); live : (A, B, p) bool — entries
    whose visibility-cosine product is zero are not evaluated.
    returns : (A, B, p, 3) float64
    """
    geo = src.geo
    frames = tangent_frames(geo["sample_nrm"][sample])  # (p, 3, 3)
    wi_loc = grid_to_local(frames, wi_world)  # (A, p, 3)
    wo_loc = grid_to_local(frames, wo_world)  # (B, p, 3)
    a_idx, b_idx, p_idx = np.nonzero(live)
    out = np.zeros(live.shape + (3,))
    if a_idx.size:
        out[a_idx, b_idx, p_idx] = brdf_mod.evaluate_by_face(
            src.materials,
            geo["sample_mat"][sample][p_idx],
            wi_loc[a_idx, p_idx],
            wo_loc[b_idx, p_idx],
            geo["sample_uv"][sample],
            sample_index=p_idx,
        )
    return out


def texel_seed(seed: int, level: int, texel: int) -> int:
    return int.from_bytes(
        hashlib.sha256(f"{seed}/{level}/{texel}".encode()).digest()[:4], "little"
    )


# --------------------------------------------------------------------------- characteristic points


def fit_level(
    src: FitInputs,
    level: int,
    texels: np.ndarray,
    candidates: PointSet,
) -> dict[str, np.ndarray]:
    """Characteristic points of `texels` at `level` chosen among `candidates` (seed 000 §3.3).

    The reference of each texel is its candidates' summation term (Eq. 9 with the candidates'
    per-channel weights); a_vis(w_o) comes from *all* dense samples of the texel (Eq. 3 on the
    same visibility); held-out SNR compares against the brute-force Eq. 7 over all samples.
    returns : arrays for this level: texel (t,), offsets (t+1,), point sample ids (p,), point
        weights (p, 3) float32, k, c, snr_in, snr_ho (t,), mode (t,) int8, valid (t,) bool,
        and when settings.btf, fbar (t, d, 3) float32 (Eq. 7 on the training grid).
    """
    # Per-texel matrices are small (d x m, m ~ tens to hundreds): BLAS and torch thread pools
    # only add contention (measured on a loaded 2-core machine: a 1024 x 16 SVD takes 1.5 ms on
    # 1 torch thread and 78 ms on 2; a 4096 x 256 QR went from milliseconds to minutes with
    # multi-threaded OpenBLAS). Parallelism comes from shards / worker processes instead.
    torch.set_num_threads(1)
    caster = src.caster
    rays0 = caster.rays_cast
    with threadpool_limits(limits=1):
        out = _fit_level(src, level, texels, candidates)
    out["rays"] = np.array([caster.rays_cast - rays0], np.int64)  # work done, for rays/s
    return out


def _fit_level(
    src: FitInputs,
    level: int,
    texels: np.ndarray,
    candidates: PointSet,
) -> dict[str, np.ndarray]:
    s = src.settings
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
        fit = fit_texel(
            R, avis_rows, psi=s.psi, eps_db=s.eps_db, c_max=s.c_max, n_trials=s.n_trials,
            weights=s.weights, colour=s.colour, decorrelation_threshold=s.decorrelation_threshold,
            seed=texel_seed(s.seed, level, int(texel)), n_batch=s.n_batch, texel_area=texel_area,
            small=s.small_texels,
        )
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
            stats["snr_ho"][t] = heldout_snr(
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


def heldout_snr(
    src, dirs, frames, texel, samples, held_vc, area, pts, w_eff, pts_held_vc, texel_area
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


def level_candidates(
    src: FitInputs, level: int, texels: np.ndarray, children: dict[str, np.ndarray] | None
) -> PointSet:
    """Candidates of `texels` at `level`: all dense samples (level 0, or hierarchy="dense"), or
    the union of the children's weighted characteristic points (hierarchy="children")."""
    geo = src.geo
    n = src.settings.atlas_resolution
    if level == 0 or src.settings.hierarchy == "dense" or children is None:
        idx = samples_in(geo, n, level, texels)
        area = geo["sample_area"][idx]
        return PointSet(idx, np.repeat(area[:, None], 3, axis=1),
                        texel_ids(geo, n, level, idx))
    counts = np.diff(children["offsets"])
    child_tex = np.repeat(children["texel"], counts)  # (p,) child texel ids at level-1
    n_c = n >> (level - 1)
    r, c = np.divmod(child_tex, n_c)
    parent = (r >> 1) * (n_c >> 1) + (c >> 1)
    return PointSet(
        children["point_sample"].astype(np.int64),
        children["point_weight"].astype(np.float64),
        parent.astype(np.int64),
    )


def concat_levels(parts: list[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """Concatenate per-tile results of one level (CSR offsets re-based)."""
    out: dict[str, np.ndarray] = {}
    base = 0
    offs = [np.zeros(1, np.int64)]
    for p in parts:
        offs.append(p["offsets"][1:] + base)
        base += int(p["offsets"][-1])
    out["offsets"] = np.concatenate(offs)
    for k in parts[0]:
        if k == "rays":
            out[k] = np.array([sum(int(p[k].sum()) for p in parts if k in p)], np.int64)
        elif k != "offsets":
            out[k] = np.concatenate([p[k] for p in parts])
    return out


def sort_by_texel(data: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    order = np.argsort(data["texel"], kind="stable")
    counts = np.diff(data["offsets"])[order]
    starts = data["offsets"][:-1][order]
    # the CSR ranges in the new texel order, gathered without a loop per texel
    base = np.cumsum(counts) - counts
    point_idx = (np.arange(int(counts.sum())) - np.repeat(base, counts)
                 + np.repeat(starts, counts))
    out = {k: v[order] for k, v in data.items()
           if k not in ("offsets", "point_sample", "point_weight", "rays")}
    if "rays" in data:
        out["rays"] = data["rays"]
    out["offsets"] = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    out["point_sample"] = data["point_sample"][point_idx.astype(np.int64)]
    out["point_weight"] = data["point_weight"][point_idx.astype(np.int64)]
    return out
