"""One CPM level fitted in batches of texels (issue 15): R for a whole chunk of texels from one
BRDF evaluation, the Gram matrices and their eigendecompositions stacked
(`texelbake.cpm.gram_fit`), the held-out SNR against brute-force Eq. 7 for the chunk from one
evaluation per sample batch. Same science and the same per-texel seeds (settings.seed, level,
texel) as the per-texel loop `texelbake.cpm.level._fit_level` (BakeSettings.fit_method =
"per_texel", kept as the seed's variant); a texel's result does not depend on which texels share
its chunk (per-texel GEMMs on contiguous blocks, eigh stacked by size), so neither the farm's
tiling nor the memory bound changes it.

Memory per worker is bounded by BakeSettings.worker_memory_mb: texels are taken in chunks whose
R (d x candidates x 3 with its temporaries) fits, and the dense samples of a chunk (a_vis and
the held-out truth) in sub-batches that fit; a coarse texel with millions of samples (the top
level of a large atlas) is streamed the same way. A texel of more than n_batch candidates (a
crowded level-0 texel: 6,162 samples in one texel of the bolt's collapsed 64² atlas) is fitted
by `gram_fit.fit_split` on its F read a block of n_batch columns at a time (`Columns`), built
from its candidates when asked; only the per-texel fallback (`fit_texel`, when a step needs
the full SVD) still builds a texel's whole R.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from threadpoolctl import threadpool_limits

from texelbake.cpm import level as level_mod
from texelbake.cpm.brdf_product import brdf_product
from texelbake.cpm.cell_table import cell_fbar, direction_cells
from texelbake.cpm.columns import Columns
from texelbake.cpm.fit import TexelFit, _empty_fit, fit_texel
from texelbake.cpm.gram_fit import correlation_from_sums, fit_many
from texelbake.cpm.level import (
    FitInputs,
    PointSet,
    direction_sets,
    samples_in,
    segment_sum,
    texel_ids,
    texel_seed,
    visibility_cos,
    world_dirs,
)
from texelbake.cpm.matrix import avis_floor, filtered_reflectance, snr_db
from texelbake.errors import NumericalError, ShapeError
from texelbake.tol import TOL

#: bytes held per (candidate, row, channel) entry while a chunk is fitted: R and F (float64)
#: and the luminance selection matrix
BYTES_PER_R_ENTRY = 8 * 3
#: bytes of temporaries per (sample, direction pair) while the BRDF is evaluated (local
#: directions, the model's intermediates, f): a sample batch uses a quarter of the budget
BYTES_PER_EVAL_ENTRY = 8 * 40
#: bytes per (dense sample, held-out pair, channel) in the held-out pass
BYTES_PER_HELD_ENTRY = 8 * 12

#: how a texel was fitted, as stored in a level's `skip` array: 0 draws and trials, 2 by the
#: per-texel path, 3 every candidate kept (1 is unused)
SKIP_CODES = {"": 0, "split": 0, "per_texel": 2, "all": 3}


def chunk_bounds(sizes: np.ndarray, cap: int) -> list[tuple[int, int]]:
    """Consecutive ranges [a, b) of items whose summed sizes stay <= cap (an item larger than
    cap gets a range of its own)."""
    out, a, acc = [], 0, 0
    for i, sz in enumerate(sizes.tolist()):  # loop over texels: O(1) each
        if i > a and acc + sz > cap:
            out.append((a, i))
            a, acc = i, 0
        acc += sz
    if a < len(sizes):
        out.append((a, len(sizes)))
    return out


def fit_level(
    src: FitInputs, level: int, texels: np.ndarray, candidates: PointSet,
    sums: DenseSums | None = None,
) -> dict[str, np.ndarray]:
    """One level's fit by BakeSettings.fit_method: "batched" (here) or "per_texel"
    (`texelbake.cpm.level.fit_level`, the seed's loop). Same arrays either way.

    sums : the texels' `DenseSums`, already summed (the top levels' from the tile shards,
        `texelbake.stages.cpm`): the fit then reads no dense sample. The per-texel loop
        computes its own."""
    if src.settings.fit_method == "per_texel":
        out = level_mod.fit_level(src, level, texels, candidates)
        if "fbar" in out and level == 0 and src.settings.btf_table == "cell":
            out["fbar"] = _cell_fbar_of(src, texels, candidates)
        return out
    # one BLAS / torch thread: parallelism comes from worker processes (see level.fit_level)
    torch.set_num_threads(1)
    rays0 = src.caster.rays_cast
    with threadpool_limits(limits=1):
        out = fit_level_batched(src, level, texels, candidates, sums)
    out["rays"] = np.array([src.caster.rays_cast - rays0], np.int64)
    return out


@dataclass(frozen=True)
class DenseSums:
    """What the fit needs from a texel's dense samples and that does not depend on the fit:
    per texel the samples' count and area, a_vis on the grid's view directions (Eq. 3) and the
    held-out truth (Eq. 7's numerator on the held-out pairs, a_vis on the held-out view
    directions). Every field is a sum over samples, so the sums of disjoint sample sets of the
    same texels add up to the whole set's (up to the order of the floating-point sums): a tile
    shard sums its own samples for the coarse texels above it, and the top shard adds the
    tiles' (`texelbake.stages.cpm`) instead of reading every sample of the atlas again."""

    count: np.ndarray  # (t,) int64
    area: np.ndarray  # (t,)
    avis_o: np.ndarray  # (t, n_o)
    ref: np.ndarray  # (t, h_i, h_o, 3)
    avis_h: np.ndarray  # (t, h_o)

    FIELDS = ("count", "area", "avis_o", "ref", "avis_h")

    def add_row(self, i: int, part: DenseSums) -> None:
        """Add `part`'s one texel into texel i of these sums, in place."""
        for f in self.FIELDS:  # five fields
            getattr(self, f)[i] += getattr(part, f)[0]

    def rows(self, idx) -> DenseSums:
        return DenseSums(*(getattr(self, f)[idx] for f in self.FIELDS))

    @classmethod
    def zeros(cls, n_t: int, dirs: dict[str, np.ndarray]) -> DenseSums:
        n_o, h_i, h_o = len(dirs["dirs_o"]), len(dirs["held_i"]), len(dirs["held_o"])
        return cls(np.zeros(n_t, np.int64), np.zeros(n_t), np.zeros((n_t, n_o)),
                   np.zeros((n_t, h_i, h_o, 3)), np.zeros((n_t, h_o)))

    def to_arrays(self, prefix: str) -> dict[str, np.ndarray]:
        return {f"{prefix}{f}": getattr(self, f) for f in self.FIELDS}

    @classmethod
    def from_arrays(cls, arrays, prefix: str) -> DenseSums:
        return cls(*(np.asarray(arrays[f"{prefix}{f}"]) for f in cls.FIELDS))


def dense_sums(src: FitInputs, level: int, texels: np.ndarray,
               samples: np.ndarray | None = None) -> DenseSums:
    """`DenseSums` of `texels` (flat ids at `level`) over `samples` (ascending ids of samples
    of those texels; default all of them), in sample batches bounded by worker_memory_mb. The
    same passes as the fit's own (`_avis`, `_held_pass`), so a texel's sums over all its
    samples equal the fit's."""
    s = src.settings
    geo = src.geo
    dirs = direction_sets(s)
    frames = geo[f"frames_L{level}"]
    texels = np.asarray(texels, np.int64)
    budget = int(s.worker_memory_mb) * 2**20
    if samples is None:
        samples = samples_in(geo, s.atlas_resolution, level, texels)
    samples = np.asarray(samples, np.int64)
    pos = _positions(texels, texel_ids(geo, s.atlas_resolution, level, samples))
    if np.any(pos < 0):
        raise ShapeError(f"dense_sums: samples outside the level {level} texels given")
    order = np.argsort(pos, kind="stable")
    dense, dseg = samples[order], pos[order]
    n_t = len(texels)
    avis_o, area = _avis(src, frames, texels, dense, dseg, n_t, dirs, budget)
    out = DenseSums.zeros(n_t, dirs)
    ref, avis_h = out.ref, out.avis_h
    if len(dirs["held_i"]):
        none = np.zeros(0, np.int64)
        ref, _, avis_h = _held_pass(src, frames, texels, dense, dseg, n_t, dirs, budget,
                                    none, none, np.zeros((0, 3)), want_ref=True)
    return DenseSums(np.bincount(dseg, minlength=n_t).astype(np.int64), area, avis_o, ref,
                     avis_h)


def fit_level_batched(
    src: FitInputs, level: int, texels: np.ndarray, candidates: PointSet,
    sums: DenseSums | None = None,
) -> dict[str, np.ndarray]:
    """`texelbake.cpm.level.fit_level`'s arrays (and `skip` (t,) int8, `SKIP_CODES`) for
    `texels`, in memory-bounded chunks. With `sums` (`DenseSums` of `texels`) no dense sample is read: a_vis and the held-out truth
    come from them, the held-out approximation from the points themselves."""
    s = src.settings
    geo = src.geo
    dirs = direction_sets(s)
    frames = geo[f"frames_L{level}"]
    n_i, n_o = len(dirs["dirs_i"]), len(dirs["dirs_o"])
    d = n_i * n_o
    budget = int(s.worker_memory_mb) * 2**20
    n_t = len(texels)
    if sums is None:
        # dense samples of every texel, grouped by texel (position in `texels`)
        ids = samples_in(geo, s.atlas_resolution, level, texels)  # ascending
        pos_ids = _positions(texels, texel_ids(geo, s.atlas_resolution, level, ids))
        samp_all = ids[np.argsort(pos_ids, kind="stable")]
        seg_all = np.sort(pos_ids, kind="stable")
        n_dense = np.bincount(seg_all, minlength=n_t)
        cb_all = np.r_[0, np.cumsum(n_dense)]
    elif len(sums.count) != n_t:
        raise ShapeError(f"level {level}: DenseSums of {len(sums.count)} texels for {n_t}")
    else:
        n_dense = sums.count
    pos_c = _positions(texels, candidates.texel)
    order_c = np.argsort(pos_c, kind="stable")
    order_c = order_c[pos_c[order_c] >= 0]
    seg_c = pos_c[order_c]
    n_cand = np.bincount(seg_c, minlength=n_t)
    cb_c = np.r_[0, np.cumsum(n_cand)]

    res = _Results(n_t, d if s.btf else 0, s.identical_columns == "merge")
    cap = max(budget // (BYTES_PER_R_ENTRY * d * 3), 1)
    # a texel wider than n_batch holds one block of n_batch columns at a time (`Columns`)
    for a, b in chunk_bounds(np.minimum(n_cand, s.n_batch), cap):  # loop over chunks
        rows = order_c[cb_c[a]:cb_c[b]]
        if sums is None:
            dense = samp_all[cb_all[a]:cb_all[b]]
            dseg = seg_all[cb_all[a]:cb_all[b]] - a
            avis_o, area = _avis(src, frames, texels[a:b], dense, dseg, b - a, dirs, budget)
        else:
            avis_o, area = sums.avis_o[a:b], sums.area[a:b]
        fits = _fit_chunk(src, level, texels[a:b], candidates.take(rows), seg_c[cb_c[a]:cb_c[b]] - a,
                          n_cand[a:b], n_dense[a:b], avis_o, area, dirs, res, a, budget)
        if not len(dirs["held_i"]):
            continue
        if sums is None:
            _heldout(src, frames, texels[a:b], dense, dseg, fits, dirs, area, budget, res, a)
        else:
            _heldout_from_sums(src, frames, texels[a:b], fits, dirs, area, budget, res, a,
                               sums.rows(slice(a, b)))
    return res.arrays(texels)


def _cell_fbar_of(src: FitInputs, texels: np.ndarray, candidates: PointSet) -> np.ndarray:
    """Level 0's cell-averaged f̄ (`cell_table`) for the per-texel path, which keeps neither
    a_vis nor the candidates' order: both remade here, in memory-bounded chunks."""
    s = src.settings
    dirs = direction_sets(s)
    frames = src.geo["frames_L0"]
    budget = int(s.worker_memory_mb) * 2**20
    ids = samples_in(src.geo, s.atlas_resolution, 0, texels)
    pos = _positions(texels, texel_ids(src.geo, s.atlas_resolution, 0, ids))
    dense, dseg = ids[np.argsort(pos, kind="stable")], np.sort(pos, kind="stable")
    avis_o, area = _avis(src, frames, texels, dense, dseg, len(texels), dirs, budget)
    inv_o = _inv_avis(avis_o, area)[1]
    pos_c = _positions(texels, candidates.texel)
    order = np.argsort(pos_c, kind="stable")
    order = order[pos_c[order] >= 0]
    return cell_fbar(src, frames, candidates.take(order), pos_c[order], len(texels), dirs,
                     *direction_cells(s, dirs), inv_o, budget)


def _inv_avis(avis_o: np.ndarray, area: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(valid (t, n_o) bool, 1 / a_vis (t, n_o), 0 where invalid): a_vis above each texel's
    floor (`avis_floor` of its area)."""
    eps = np.array([avis_floor(a) for a in area])[:, None]
    valid = np.isfinite(avis_o) & (avis_o > eps)
    return valid, np.where(valid, 1.0 / np.where(valid, avis_o, 1.0), 0.0)


def _positions(texels: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """Position of each id in `texels` (any order, unique), -1 when absent."""
    order = np.argsort(texels, kind="stable")
    srt = texels[order]
    i = np.clip(np.searchsorted(srt, ids), 0, max(len(srt) - 1, 0))
    hit = (srt[i] == ids) if len(srt) else np.zeros(len(ids), bool)
    return np.where(hit, order[i] if len(srt) else 0, -1)


def _avis(src, frames, texels, dense, dseg, n_t, dirs, budget):
    """a_vis(w_o) per texel (Eq. 3 on all dense samples) and texel areas, in sample batches."""
    n_o = len(dirs["dirs_o"])
    tex_l = texels[dseg] if dense.size else np.zeros(0, np.int64)
    area_all = src.geo["sample_area"][dense]
    step = max(budget // (8 * 16 * n_o), 1)
    avis = np.zeros((n_t, n_o))
    for s0 in range(0, dense.size, step):  # loop over sample batches (memory bound)
        sl = slice(s0, s0 + step)
        vc = visibility_cos(src, dense[sl], world_dirs(frames, tex_l[sl], dirs["dirs_o"]),
                            "geometric")
        avis += segment_sum(vc * area_all[sl, None], dseg[sl], n_t, 0)
    area = segment_sum(area_all, dseg, n_t, 0)
    return avis, area


class _Results:
    def __init__(self, n_t: int, d_btf: int, merged: bool = False):
        self.pts: list[list[np.ndarray]] = [[] for _ in range(n_t)]
        self.w: list[list[np.ndarray]] = [[] for _ in range(n_t)]
        self.k = np.zeros(n_t)
        self.c = np.zeros(n_t)
        self.snr_in = np.full(n_t, np.nan)
        self.snr_ho = np.full(n_t, np.nan)
        self.mode = np.zeros(n_t, np.int8)
        self.valid = np.zeros(n_t, bool)
        self.skip = np.zeros(n_t, np.int8)
        self.fbar = np.zeros((n_t, d_btf, 3), np.float32) if d_btf else None
        # candidates fitted as copies of others (identical_columns="merge" only)
        self.merged = np.zeros(n_t, np.int32) if merged else None

    def arrays(self, texels: np.ndarray) -> dict[str, np.ndarray]:
        counts = [sum(len(p) for p in ps) for ps in self.pts]
        flat_p = [p for ps in self.pts for p in ps]
        flat_w = [w for ws in self.w for w in ws]
        out = {
            "texel": texels.astype(np.int64),
            "offsets": np.r_[0, np.cumsum(counts)].astype(np.int64),
            "point_sample": np.concatenate(flat_p).astype(np.int64) if flat_p
            else np.zeros(0, np.int64),
            "point_weight": (np.concatenate(flat_w) if flat_w else np.zeros((0, 3))
                             ).astype(np.float32),
            "k": self.k.astype(np.int32), "c": self.c.astype(np.int32),
            "snr_in": self.snr_in.astype(np.float32), "snr_ho": self.snr_ho.astype(np.float32),
            "mode": self.mode, "valid": self.valid, "skip": self.skip,
        }
        if self.fbar is not None:
            out["fbar"] = self.fbar
        if self.merged is not None:
            out["merged"] = self.merged
        return out


def _build_R(src, frames, cset: PointSet, dirs, budget: int, inv_o: np.ndarray | None = None,
             seg: np.ndarray | None = None):
    """Eq. 9's matrix for every candidate of the chunk, channel-major: (3, P, d) with row
    i * n_o + o. The BRDF is evaluated on sample batches whose temporaries fit a quarter of
    the budget (a sample's entries are independent), so only R itself scales with P.

    With inv_o (t, n_o) (1/a_vis(w_o) of each texel of the chunk, 0 on rows under the floor) and
    seg (P,) (each candidate's texel in the chunk), returns F = diag(1/a_vis) R itself, written
    in the same pass as R (no second P x d array, no second sweep), together with each
    candidate's channel sums of R for `channel_correlation`: (F, s1 (P, 3) = sum over rows of R,
    s2 (P, 3, 3) = R_j^T R_j over rows). Every entry and every per-candidate sum depends only on
    that candidate, so neither the chunk nor the sample batch changes a texel's result."""
    n_i, n_o = len(dirs["dirs_i"]), len(dirs["dirs_o"])
    P = len(cset.sample)
    Rt = np.empty((3, P, n_i * n_o))
    fused = inv_o is not None
    s1 = np.zeros((P, 3))
    s2 = np.zeros((P, 3, 3))
    step = max(budget // 4 // (BYTES_PER_EVAL_ENTRY * n_i * n_o), 1)
    for s0 in range(0, P, step):  # loop over sample batches (memory bound)
        part = cset.take(np.arange(s0, min(s0 + step, P)))
        p = len(part.sample)
        wi = world_dirs(frames, part.texel, dirs["dirs_i"])
        wo = world_dirs(frames, part.texel, dirs["dirs_o"])
        vi = visibility_cos(src, part.sample, wi)
        vo = visibility_cos(src, part.sample, wo, "geometric")
        live = (vi.T[:, None, :] > 0) & (vo.T[None, :, :] > 0)  # (n_i, n_o, p)
        f = brdf_product(src.geo, src.materials, part.sample, wi, wo, live)  # (3, p, n_i, n_o)
        f *= (vi[None, :, :] * part.weight.T[:, :, None])[..., None]
        f *= vo[None, :, None, :]
        f2 = f.reshape(3, p, -1)
        if inv_o is not None and seg is not None:
            s1[s0:s0 + p] = f2.sum(axis=2).T
            s2[s0:s0 + p] = np.matmul(f2.transpose(1, 0, 2), f2.transpose(1, 2, 0))
            f *= inv_o[seg[s0:s0 + p]][None, :, None, :]
        Rt[:, s0:s0 + p] = f2
    if fused:
        return Rt, s1, s2
    return Rt


def _fit_chunk(src, level, texels, cset, cseg, n_cand, n_dense, avis_o, area, dirs, res, base,
               budget) -> list[TexelFit | None]:
    s = src.settings
    n_i = len(dirs["dirs_i"])
    n_t = len(texels)
    valid_o, inv_o = _inv_avis(avis_o, area)  # (t, n_o)
    avis_rows = np.tile(avis_o, (1, n_i))  # (t, d): row i * n_o + o
    valid = np.tile(valid_o, (1, n_i))
    frames = src.geo[f"frames_L{level}"]
    bounds = np.r_[0, np.cumsum(n_cand)]  # a texel's candidates are a contiguous block
    # F = diag(1/a_vis) R per channel, (3, P, d), built in one pass with R's channel sums, for
    # the texels of at most n_batch candidates; a wider texel's F is read a block at a time
    # (`Columns`: its memory is n_batch d whatever its width, issue 15)
    wide = n_cand > s.n_batch
    held = np.flatnonzero(~np.repeat(wide, n_cand))
    Ft, s1_h, s2_h = _build_R(src, frames, cset.take(held), dirs, budget, inv_o, cseg[held])
    d = n_i * len(dirs["dirs_o"])
    _check_finite(Ft, cset.texel[held], level)
    s1 = np.zeros((len(cset.sample), 3))
    s2 = np.zeros((len(cset.sample), 3, 3))
    s1[held], s2[held] = s1_h, s2_h
    hb = np.r_[0, np.cumsum(np.where(wide, 0, n_cand))]  # a held texel's block of Ft
    Fs: dict[int, np.ndarray | Columns] = {}
    for t in range(n_t):  # loop over texels: views, and the wide ones' first pass
        if not wide[t]:
            Fs[t] = Ft[:, hb[t]:hb[t + 1]]
            continue
        rows = np.arange(bounds[t], bounds[t + 1])
        Fs[t] = _wide_columns(src, frames, cset, rows, cseg, dirs, budget, inv_o, level,
                              s.n_batch, s1, s2)
    sx = segment_sum(s1, cseg, n_t, 0)
    sxx = segment_sum(s2, cseg, n_t, 0)
    if res.fbar is not None and level == 0 and s.btf_table == "cell":
        cells = direction_cells(s, dirs)
        res.fbar[base:base + n_t] = cell_fbar(src, frames, cset, cseg, n_t, dirs, *cells, inv_o,
                                              budget)
    elif res.fbar is not None:  # the coarse levels' tables are not read (the BTF's own pyramid)
        for t in range(n_t):  # loop over texels: one row sum each
            res.fbar[base + t] = Fs[t].sum(axis=1).T
    # texels for the Gram path (the others are fit_texel's special cases or too wide)
    gram, corrs = [], []
    for t in range(n_t):  # loop over texels: classification only
        m = bounds[t + 1] - bounds[t]
        if m == 0 or n_dense[t] == 0:
            continue
        if valid[t].any() and float(np.trace(sxx[t])) > TOL.energy_floor \
                and d >= 2 * min(m, s.n_batch):
            gram.append(t)
            corrs.append(correlation_from_sums(sx[t], sxx[t], d * m))
    seeds = [texel_seed(s.seed, level, int(texels[t])) for t in range(n_t)]
    done = dict(zip(gram, fit_many(
        [Fs[t] for t in gram], [valid[t] for t in gram], corrs,
        [seeds[t] for t in gram], psi=s.psi, eps_db=s.eps_db, c_max=s.c_max,
        n_trials=s.n_trials, weights=s.weights, colour=s.colour,
        decorrelation_threshold=s.decorrelation_threshold,
        n_batch=s.n_batch, small=s.small_texels, identical=s.identical_columns,
    ), strict=True))
    fits: list[TexelFit | None] = [None] * n_t
    for t in range(n_t):  # loop over texels
        a, b = bounds[t], bounds[t + 1]
        if b == a or n_dense[t] == 0:
            continue
        fit, skip = done.get(t, (None, "per_texel"))
        if fit is None:  # fit_texel's special cases, wide texels, Gram route unresolved
            # the texel's R itself, rebuilt (F dropped its rows under the a_vis floor); every
            # entry depends on its candidate only, so this is the R the chunk's F came from
            Rt = _build_R(src, frames, cset.take(np.arange(a, b)), dirs, budget)
            fit = fit_texel(Rt.transpose(2, 1, 0), avis_rows[t],
                            texel_area=float(area[t]), seed=seeds[t], psi=s.psi,
                            eps_db=s.eps_db, c_max=s.c_max, n_trials=s.n_trials,
                            weights=s.weights, colour=s.colour,
                            decorrelation_threshold=s.decorrelation_threshold, n_batch=s.n_batch,
                            small=s.small_texels)
            skip = "per_texel" if (t in done or too_wide(b - a, d, s)) else ""
        fits[t] = fit
        _store(res, base + t, fit, cset.take(np.arange(a, b)), SKIP_CODES[skip])
    return fits


def _check_finite(Ft: np.ndarray, texel: np.ndarray, level: int) -> None:
    if not np.all(np.isfinite(Ft)):
        bad = np.unique(texel[np.any(~np.isfinite(Ft), axis=(0, 2))])
        raise NumericalError(f"R of level {level} texels {bad[:8].tolist()} has non-finite entries")


def _wide_columns(src, frames, cset: PointSet, rows: np.ndarray, cseg: np.ndarray, dirs,
                  budget: int, inv_o: np.ndarray, level: int, n_batch: int, s1: np.ndarray,
                  s2: np.ndarray) -> Columns:
    """F of the texel whose candidates are cset's `rows` (more than n_batch of them) as
    `Columns`: a block is built from its candidates when the fit asks (every entry depends
    on its candidate only, so a block equals the same columns of the whole F). One first pass
    by blocks of n_batch writes the candidates' channel sums into s1, s2 and keeps Σ F."""
    def block(cols: np.ndarray) -> np.ndarray:
        r = rows[cols]
        Fb, _, _ = _build_R(src, frames, cset.take(r), dirs, budget, inv_o, cseg[r])
        _check_finite(Fb, cset.texel[r], level)
        return Fb

    total = None
    for b0 in range(0, rows.size, n_batch):  # loop over column blocks (memory bound)
        r = rows[b0:b0 + n_batch]
        Fb, s1[r], s2[r] = _build_R(src, frames, cset.take(r), dirs, budget, inv_o, cseg[r])
        _check_finite(Fb, cset.texel[r], level)
        part = Fb.sum(axis=1)
        total = part if total is None else total + part
        del Fb
    return Columns(block, (3, rows.size, len(dirs["dirs_i"]) * len(dirs["dirs_o"])), n_batch,
                   total)


def too_wide(m: int, d: int, s) -> bool:
    """A texel too wide for the Gram path (d < 2 min(m, n_batch)) goes to `fit_texel`."""
    return d < 2 * min(m, s.n_batch)


def _store(res: _Results, i: int, fit: TexelFit, cset: PointSet, skip: int) -> None:
    w_eff = fit.weights.astype(np.float64) * cset.weight[fit.columns]
    res.pts[i] = [cset.sample[fit.columns]]
    res.w[i] = [w_eff]
    res.k[i], res.c[i] = fit.k, fit.c
    res.snr_in[i] = fit.snr_db_insample
    res.mode[i] = 1 if fit.colour_mode == "per_channel" else 0
    res.valid[i] = fit.valid
    res.skip[i] = skip
    if res.merged is not None:
        res.merged[i] = fit.merged


def _points_of(res: _Results, fits, base: int):
    """The characteristic points of the chunk's fitted texels: sample ids, their texel (position
    in the chunk) and their weights as stored (float32: a texel that keeps all its candidates at
    their own weights would otherwise reproduce the reference bit for bit, +inf dB)."""
    pts, seg, w = [], [], []
    for t, fit in enumerate(fits):  # loop over texels
        if fit is None or not fit.valid or fit.c == 0:
            continue
        i = base + t
        pts.append(res.pts[i][0])
        seg.append(np.full(len(res.pts[i][0]), t))
        w.append(res.w[i][0].astype(np.float32).astype(np.float64))
    if not pts:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 3))
    return np.concatenate(pts), np.concatenate(seg), np.concatenate(w)


def _heldout(src, frames, texels, dense, dseg, fits, dirs, area, budget, res, base):
    """Held-out SNR of every fitted texel of the chunk: brute-force Eq. 7 over all its dense
    samples against its characteristic points, on the held-out product grid (`heldout_snr`)."""
    n_t = len(texels)
    smp, pseg, pw = _points_of(res, fits, base)
    # the points as positions in `dense` (a point is one of its texel's samples): `dense` is
    # ascending within each texel and dseg ascending, so (texel, sample) keys are sorted
    span = int(max(dense.max(initial=0), smp.max(initial=0))) + 1
    pos = np.searchsorted(dseg * span + dense, pseg * span + smp)
    order = np.argsort(pos, kind="stable")
    pos, pseg, pw = pos[order], pseg[order], pw[order]
    ref, apx, avis_h = _held_pass(src, frames, texels, dense, dseg, n_t, dirs, budget, pos,
                                  pseg, pw, want_ref=True)
    _held_snr(res, fits, area, ref, apx, avis_h, base)


def _heldout_from_sums(src, frames, texels, fits, dirs, area, budget, res, base,
                       sums: DenseSums):
    """`_heldout` with the truth already summed (`DenseSums`): only the points are evaluated."""
    n_t = len(texels)
    smp, pseg, pw = _points_of(res, fits, base)
    order = np.lexsort((smp, pseg))
    smp, pseg, pw = smp[order], pseg[order], pw[order]
    _, apx, _ = _held_pass(src, frames, texels, smp, pseg, n_t, dirs, budget,
                           np.arange(smp.size), pseg, pw, want_ref=False)
    _held_snr(res, fits, area, sums.ref, apx, sums.avis_h, base)


def _held_pass(src, frames, texels, dense, dseg, n_t, dirs, budget, pos, pseg, pw, *,
               want_ref: bool):
    """One pass over `dense` samples (grouped by texel, `dseg` ascending) on the held-out pairs:
    the truth (Eq. 7's numerator `ref` and a_vis on the held-out views `avis_h`) when
    `want_ref`, and the points' approximation `apx` from the rows at positions `pos`
    (ascending; texel `pseg`, weights `pw`)."""
    h_i, h_o = len(dirs["held_i"]), len(dirs["held_o"])
    tex_l = texels[dseg] if dense.size else np.zeros(0, np.int64)
    ref = np.zeros((n_t, h_i, h_o, 3))
    apx = np.zeros((n_t, h_i, h_o, 3))
    avis_h = np.zeros((n_t, h_o))
    area_all = src.geo["sample_area"][dense]
    step = max(budget // (BYTES_PER_HELD_ENTRY * h_i * h_o * 3), 1)
    for s0 in range(0, dense.size, step):  # loop over sample batches (memory bound)
        sl = slice(s0, s0 + step)
        smp, seg = dense[sl], dseg[sl]
        vi = visibility_cos(src, smp, world_dirs(frames, tex_l[sl], dirs["held_i"]))
        vo = visibility_cos(src, smp, world_dirs(frames, tex_l[sl], dirs["held_o"]), "geometric")
        live = (vi.T[:, None, :] > 0) & (vo.T[None, :, :] > 0)
        f = brdf_product(src.geo, src.materials, smp,
                         world_dirs(frames, tex_l[sl], dirs["held_i"]),
                         world_dirs(frames, tex_l[sl], dirs["held_o"]), live)  # (h_i, h_o, p, 3)
        f *= vi[None, :, :, None]
        f *= vo[None, :, None, :]  # (3, p, h_i, h_o)
        a_, b_ = np.searchsorted(pos, [s0, s0 + len(smp)])
        if b_ > a_:
            apx += segment_sum(f[:, pos[a_:b_] - s0] * pw.T[:, a_:b_, None, None], pseg[a_:b_],
                               n_t, 1).transpose(1, 2, 3, 0)
        if want_ref:
            avis_h += segment_sum(vo * area_all[sl, None], seg, n_t, 0)
            ref += segment_sum(f * area_all[sl][None, :, None, None], seg, n_t, 1
                               ).transpose(1, 2, 3, 0)
    return ref, apx, avis_h


def _held_snr(res: _Results, fits, area, ref, apx, avis_h, base: int) -> None:
    h_i = ref.shape[1]
    for t, fit in enumerate(fits):  # loop over texels: one SNR each
        if fit is None or not fit.valid:
            continue
        eps = avis_floor(float(area[t]))
        rows = np.tile(avis_h[t], h_i)
        f_ref, ok = filtered_reflectance(ref[t].reshape(-1, 3), rows, eps)
        f_apx, _ = filtered_reflectance(apx[t].reshape(-1, 3), rows, eps)
        res.snr_ho[base + t] = float(snr_db(f_ref, f_apx, ok))


__all__ = ["DenseSums", "chunk_bounds", "dense_sums", "fit_level_batched", "_empty_fit"]
