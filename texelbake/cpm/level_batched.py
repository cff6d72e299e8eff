"""One CPM level fitted in batches of texels: R for a whole chunk of texels from one BRDF
evaluation, the Gram matrices and their eigendecompositions stacked (`texelbake.cpm.gram.fit`),
the held-out SNR against brute-force Eq. 7 for the chunk from one evaluation per sample batch
(`texelbake.cpm.dense`). Same science and the same per-texel seeds (settings.seed, level,
texel) as the per-texel loop `texelbake.cpm.level_per_texel` (BakeSettings.fit_method =
"per_texel", the seed's variant); a texel's result does not depend on which texels share its
chunk (per-texel GEMMs on contiguous blocks, eigh stacked by size), so neither the farm's
tiling nor the memory bound changes it.

Memory per worker is bounded by BakeSettings.worker_memory_mb: texels are taken in chunks whose
R (d x candidates x 3 with its temporaries) fits, and the dense samples of a chunk (a_vis and
the held-out truth) in sub-batches that fit; a coarse texel with millions of samples (the top
level of a large atlas) is streamed the same way. A texel of more than n_batch candidates (a
crowded level-0 texel: 6,162 samples in one texel of the bolt's collapsed 64² atlas) is fitted
by `gram.fit.fit_split` on its F read a block of n_batch columns at a time (`Columns`), built
from its candidates when asked; only the per-texel fallback (`fit_texel`, when a step needs
the full SVD) still builds a texel's whole R.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial

import numpy as np

from texelbake.cpm.build_r import build_R
from texelbake.cpm.cell_table import cell_fbar, direction_cells
from texelbake.cpm.dense import (
    DenseSums,
    LevelPass,
    avis_scale,
    avis_sums,
    dense_of,
    heldout_from_samples,
    heldout_from_sums,
    heldout_snr,
    inv_avis,
    positions,
)
from texelbake.cpm.fit import fit_texel
from texelbake.cpm.gram.columns import Columns
from texelbake.cpm.gram.fit import GramTexel, correlation_from_sums, fit_many
from texelbake.cpm.level import (
    FitInputs,
    PointSet,
    carries_lobe_var,
    clusters_level0,
    segment_sum,
    texel_seed,
)
from texelbake.cpm.lobe import cell_spread, validation_truth, widen_fit, wider_wins
from texelbake.cpm.texel_fit import FitCounts, FitParams, TexelFit
from texelbake.errors import NumericalError, ShapeError
from texelbake.tol import TOL

#: bytes held per (candidate, row, channel) entry while a chunk is fitted: R and F (float64)
#: and the luminance selection matrix
BYTES_PER_R_ENTRY = 8 * 3
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


@dataclass(frozen=True)
class Chunk:
    """Consecutive texels of a level fitted together: texels (t,) flat ids; cset their
    candidates, grouped by texel (a texel's are a contiguous block), cseg (P,) each
    candidate's texel position in the chunk; n_cand, n_dense (t,) candidates and dense samples
    per texel; avis_o (t, n_o) and area (t,) from the dense samples; base the chunk's first
    texel in the level's results."""

    texels: np.ndarray
    cset: PointSet
    cseg: np.ndarray
    n_cand: np.ndarray
    n_dense: np.ndarray
    avis_o: np.ndarray
    area: np.ndarray
    base: int


def fit_level_batched(
    src: FitInputs, level: int, texels: np.ndarray, candidates: PointSet,
    sums: DenseSums | None = None, counts: FitCounts | None = None,
    avis_o: np.ndarray | None = None,
) -> dict[str, np.ndarray]:
    """`level_per_texel.fit_level_per_texel`'s arrays (and `skip` (t,) int8, `SKIP_CODES`) for
    `texels` (flat ids at `level`) chosen among `candidates`, in memory-bounded chunks. With
    `sums` (`DenseSums` of `texels`, already summed: the top levels' from the tile shards) no
    dense sample is read: a_vis and the held-out truth come from them, the held-out
    approximation from the points themselves. counts : `FitCounts` to add the search's work
    to. avis_o : (t, n_o) a_vis of `texels` on the view grid given by the caller (a coarse
    level's from its children's maps, `stages.avis.fit_avis_o`): no a_vis ray is cast."""
    s = src.settings
    lp = LevelPass.of(src, level)
    d = len(lp.dirs["dirs_i"]) * len(lp.dirs["dirs_o"])
    n_t = len(texels)
    if sums is None:
        samp_all, seg_all = dense_of(lp, texels)  # every texel's dense samples, by texel
        n_dense = np.bincount(seg_all, minlength=n_t)
        cb_all = np.r_[0, np.cumsum(n_dense)]
    elif len(sums.count) != n_t:
        raise ShapeError(f"level {level}: DenseSums of {len(sums.count)} texels for {n_t}")
    else:
        n_dense = sums.count
    pos_c = positions(texels, candidates.texel)
    order_c = np.argsort(pos_c, kind="stable")
    order_c = order_c[pos_c[order_c] >= 0]
    seg_c = pos_c[order_c]
    n_cand = np.bincount(seg_c, minlength=n_t)
    cb_c = np.r_[0, np.cumsum(n_cand)]

    res = _Results(n_t, d if s.btf else 0, s.identical_columns == "merge", carries_lobe_var(s))
    cap = max(lp.budget // (BYTES_PER_R_ENTRY * d * 3), 1)
    # a texel wider than n_batch holds one block of n_batch columns at a time (`Columns`)
    for a, b in chunk_bounds(np.minimum(n_cand, s.n_batch), cap):  # loop over chunks
        rows = order_c[cb_c[a]:cb_c[b]]
        if sums is None:
            dense = samp_all[cb_all[a]:cb_all[b]]
            dseg = seg_all[cb_all[a]:cb_all[b]] - a
            if avis_o is None:
                avis_c, area = avis_sums(lp, texels[a:b], dense, dseg)
            else:
                avis_c = avis_o[a:b]
                area = segment_sum(src.geo["sample_area"][dense], dseg, b - a, 0)
        else:
            area = sums.area[a:b]
            avis_c = sums.avis_o[a:b] * avis_scale(area, sums.area_avis[a:b])[:, None]
        chunk = Chunk(texels[a:b], candidates.take(rows), seg_c[cb_c[a]:cb_c[b]] - a,
                      n_cand[a:b], n_dense[a:b], avis_c, area, a)
        fits = _fit_chunk(lp, chunk, res, counts)
        if res.wide:
            _choose_lobes(lp, chunk, res, fits, partial(
                validation_truth, lp, texels[a:b], None if sums is None else
                sums.rows(slice(a, b)), *((dense, dseg) if sums is None else (None, None))))
        if not len(lp.dirs["held_i"]):
            continue
        smp, pseg, pw, pvar = _points_of(res, fits, a)
        if sums is None:
            held = heldout_from_samples(lp, texels[a:b], dense, dseg, smp, pseg, pw, pvar)
        else:
            held = heldout_from_sums(lp, texels[a:b], sums.rows(slice(a, b)), smp, pseg, pw,
                                     pvar)
        _held_snr(res, fits, area, *held, a)
    return res.arrays(texels)


class _Results:
    def __init__(self, n_t: int, d_btf: int, merged: bool = False, lobe_var: bool = False):
        self.pts: list[list[np.ndarray]] = [[] for _ in range(n_t)]
        self.w: list[list[np.ndarray]] = [[] for _ in range(n_t)]
        # point_lobe="widened" or lobe_class on only: each point's lobe variance per axis
        # (0: a dense sample's own lobe); point_lobe="widened": a texel's widened
        # alternative until it is chosen or not: (fit, var, candidates, skip)
        self.var: list[list[np.ndarray]] | None = [[] for _ in range(n_t)] if lobe_var else None
        self.wide: dict[int, tuple] = {}
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
        if self.var is not None:
            flat_v = [v for vs in self.var for v in vs]
            out["point_var"] = (np.concatenate(flat_v) if flat_v else np.zeros(0)
                                ).astype(np.float32)
        if self.fbar is not None:
            out["fbar"] = self.fbar
        if self.merged is not None:
            out["merged"] = self.merged
        return out


def _fit_chunk(lp: LevelPass, chunk: Chunk, res: _Results, counts: FitCounts | None
               ) -> list[TexelFit | None]:
    """Fit every texel of `chunk` into `res`: the Gram path for the texels it can take
    (`fit_many`), `fit_texel` on the texel's R for the rest; returns the fits (None: a texel
    without candidates or dense samples)."""
    s = lp.src.settings
    params = FitParams.of(s)
    texels, cset, cseg, n_cand = chunk.texels, chunk.cset, chunk.cseg, chunk.n_cand
    if lp.level == 0 and clusters_level0(s) and cset.var is not None:
        # groups of samples (`texelbake.cpm.cluster`; samples carry no lobe variance): a
        # group is no sample, keeping every group is not exact between the grid's directions
        # as keeping every sample is, so the fit chooses among them
        params = dataclasses.replace(params, small="fit")
    n_i = len(lp.dirs["dirs_i"])
    n_t = len(texels)
    valid_o, inv_o = inv_avis(chunk.avis_o, chunk.area)  # (t, n_o)
    avis_rows = np.tile(chunk.avis_o, (1, n_i))  # (t, d): row i * n_o + o
    valid = np.tile(valid_o, (1, n_i))
    bounds = np.r_[0, np.cumsum(n_cand)]  # a texel's candidates are a contiguous block
    # F = diag(1/a_vis) R per channel, (3, P, d), built in one pass with R's channel sums, for
    # the texels of at most n_batch candidates; a wider texel's F is read a block at a time
    # (`Columns`: its memory is n_batch d whatever its width)
    wide = n_cand > s.n_batch
    held = np.flatnonzero(~np.repeat(wide, n_cand))
    Ft, s1_h, s2_h = build_R(lp, cset.take(held), inv_o, cseg[held])
    d = n_i * len(lp.dirs["dirs_o"])
    _check_finite(Ft, cset.texel[held], lp.level)
    s1 = np.zeros((len(cset.sample), 3))
    s2 = np.zeros((len(cset.sample), 3, 3))
    s1[held], s2[held] = s1_h, s2_h
    hb = np.r_[0, np.cumsum(np.where(wide, 0, n_cand))]  # a held texel's block of Ft
    Fs: dict[int, np.ndarray | Columns] = {}
    for t in range(n_t):  # loop over texels: views, and the wide ones' first pass
        if not wide[t]:
            Fs[t] = Ft[:, hb[t]:hb[t + 1]]
            continue
        Fs[t] = _wide_columns(lp, cset, np.arange(bounds[t], bounds[t + 1]), cseg, inv_o, s1,
                              s2)
    sx = segment_sum(s1, cseg, n_t, 0)
    sxx = segment_sum(s2, cseg, n_t, 0)
    if res.fbar is not None and lp.level == 0 and s.btf_table == "cell":
        cells = direction_cells(s, lp.dirs)
        res.fbar[chunk.base:chunk.base + n_t] = cell_fbar(lp.src, lp.frames, cset, cseg, n_t,
                                                          lp.dirs, *cells, inv_o, lp.budget)
    elif res.fbar is not None:  # the coarse levels' tables are not read (the BTF's own pyramid)
        for t in range(n_t):  # loop over texels: one row sum each
            res.fbar[chunk.base + t] = Fs[t].sum(axis=1).T
    # texels for the Gram path (the others are fit_texel's special cases or too wide)
    gram: list[int] = []
    seeds = [texel_seed(s.seed, lp.level, int(texels[t])) for t in range(n_t)]
    for t in range(n_t):  # loop over texels: classification only
        m = bounds[t + 1] - bounds[t]
        if m == 0 or chunk.n_dense[t] == 0:
            continue
        if valid[t].any() and float(np.trace(sxx[t])) > TOL.energy_floor \
                and d >= 2 * min(m, s.n_batch):
            gram.append(t)
    done = dict(zip(gram, fit_many(
        [GramTexel(Fs[t], valid[t], correlation_from_sums(sx[t], sxx[t], d * (bounds[t + 1]
                                                                             - bounds[t])),
                   seeds[t]) for t in gram], params, counts), strict=True))
    fits: list[TexelFit | None] = [None] * n_t
    for t in range(n_t):  # loop over texels
        a, b = bounds[t], bounds[t + 1]
        if b == a or chunk.n_dense[t] == 0:
            continue
        fit, skip = done.get(t, (None, "per_texel"))
        if fit is None:  # fit_texel's special cases, wide texels, Gram route unresolved
            # the texel's R itself, rebuilt (F dropped its rows under the a_vis floor); every
            # entry depends on its candidate only, so this is the R the chunk's F came from
            Rt = build_R(lp, cset.take(np.arange(a, b)))
            fit = fit_texel(Rt.transpose(2, 1, 0), avis_rows[t], params, seed=seeds[t],
                            texel_area=float(chunk.area[t]))
            skip = "per_texel" if (t in done or too_wide(b - a, d, s)) else ""
        fits[t] = fit
        own = cset.take(np.arange(a, b))
        _store(res, chunk.base + t, fit, own, SKIP_CODES[skip],
               None if own.var is None else own.var[fit.columns])
        if lp.src.settings.point_lobe == "widened":  # its alternative, for `_choose_lobes`
            alt = widen_fit(fit, own, cell_spread(lp.src.geo, own, fit), Fs[t], valid[t], lp,
                            partial(_columns_of, lp, inv_o, t))
            if alt is not None:
                res.wide[chunk.base + t] = (*alt, own, SKIP_CODES[skip])
    return fits


def _columns_of(lp: LevelPass, inv_o: np.ndarray, t: int, pts: PointSet) -> np.ndarray:
    """F (3, p, d) of points `pts` of the chunk's texel t."""
    return build_R(lp, pts, inv_o, np.full(len(pts.sample), t))[0]


def _choose_lobes(lp: LevelPass, chunk: Chunk, res: _Results, fits: list[TexelFit | None],
                  truth: Callable[[np.ndarray], tuple[np.ndarray, ...]]) -> None:
    """Store the widened alternative (`res.wide`) of each texel of the chunk whose widened
    points reproduce it better on the validation pairs (`lobe.wider_wins`; `truth(positions)`
    gives those texels' `dense.validation_sums`)."""
    alts = sorted(i for i in res.wide if chunk.base <= i < chunk.base + len(chunk.texels))
    if not alts:
        return
    loc = np.array(alts) - chunk.base
    has = set(loc.tolist())
    own = _points_of(res, [fits[t] if t in has else None for t in range(len(fits))], chunk.base)
    seg = np.searchsorted(loc, own[1])  # the own points' texels among the alternatives'
    wins = wider_wins(lp, chunk.texels[loc], chunk.area[loc], truth(loc),
                      (own[0], seg, own[2], own[3]), [res.wide[i][:3] for i in alts])
    for j in np.flatnonzero(wins):  # loop over the texels whose widened points win
        fit, var, cset, skip = res.wide[alts[j]]
        fits[loc[j]] = fit
        _store(res, alts[j], fit, cset, skip, var)
    for i in alts:  # loop over the chunk's alternatives: chosen or not, done
        del res.wide[i]


def _check_finite(Ft: np.ndarray, texel: np.ndarray, level: int) -> None:
    if not np.all(np.isfinite(Ft)):
        bad = np.unique(texel[np.any(~np.isfinite(Ft), axis=(0, 2))])
        raise NumericalError(f"R of level {level} texels {bad[:8].tolist()} has non-finite entries")


def _wide_columns(lp: LevelPass, cset: PointSet, rows: np.ndarray, cseg: np.ndarray,
                  inv_o: np.ndarray, s1: np.ndarray, s2: np.ndarray) -> Columns:
    """F of the texel whose candidates are cset's `rows` (more than n_batch of them) as
    `Columns`: a block is built from its candidates when the fit asks (every entry depends
    on its candidate only, so a block equals the same columns of the whole F). One first pass
    by blocks of n_batch writes the candidates' channel sums into s1, s2 and keeps Σ F."""
    n_batch = lp.src.settings.n_batch

    def block(cols: np.ndarray) -> np.ndarray:
        r = rows[cols]
        Fb, _, _ = build_R(lp, cset.take(r), inv_o, cseg[r])
        _check_finite(Fb, cset.texel[r], lp.level)
        return Fb

    total = None
    for b0 in range(0, rows.size, n_batch):  # loop over column blocks (memory bound)
        r = rows[b0:b0 + n_batch]
        Fb, s1[r], s2[r] = build_R(lp, cset.take(r), inv_o, cseg[r])
        _check_finite(Fb, cset.texel[r], lp.level)
        part = Fb.sum(axis=1)
        total = part if total is None else total + part
        del Fb
    return Columns(block, (3, rows.size, len(lp.dirs["dirs_i"]) * len(lp.dirs["dirs_o"])),
                   n_batch, total)


def too_wide(m: int, d: int, s) -> bool:
    """A texel too wide for the Gram path (d < 2 min(m, n_batch)) goes to `fit_texel`."""
    return d < 2 * min(m, s.n_batch)


def _store(res: _Results, i: int, fit: TexelFit, cset: PointSet, skip: int,
           var: np.ndarray | None = None) -> None:
    """Texel i's fit (`cset` its candidates) into res, with its points' lobe variances
    (None: 0) where lobes may be widened."""
    w_eff = fit.weights.astype(np.float64) * cset.weight[fit.columns]
    res.pts[i] = [cset.sample[fit.columns]]
    res.w[i] = [w_eff]
    if res.var is not None:
        res.var[i] = [np.zeros(fit.c) if var is None else var]
    res.k[i], res.c[i] = fit.k, fit.c
    res.snr_in[i] = fit.snr_db_insample
    res.mode[i] = 1 if fit.colour_mode == "per_channel" else 0
    res.valid[i] = fit.valid
    res.skip[i] = skip
    if res.merged is not None:
        res.merged[i] = fit.merged


def _points_of(res: _Results, fits, base: int):
    """The characteristic points of the chunk's fitted texels: sample ids, their texel (position
    in the chunk), their weights and their lobes' variances (None: narrow lobes) as stored
    (float32: a texel that keeps all its candidates at their own weights would otherwise
    reproduce the reference bit for bit, +inf dB)."""
    pts, seg, w, var = [], [], [], []
    for t, fit in enumerate(fits):  # loop over texels
        if fit is None or not fit.valid or fit.c == 0:
            continue
        i = base + t
        pts.append(res.pts[i][0])
        seg.append(np.full(len(res.pts[i][0]), t))
        w.append(res.w[i][0].astype(np.float32).astype(np.float64))
        if res.var is not None:
            var.append(res.var[i][0].astype(np.float32).astype(np.float64))
    if not pts:
        return (np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 3)),
                None if res.var is None else np.zeros(0))
    return (np.concatenate(pts), np.concatenate(seg), np.concatenate(w),
            np.concatenate(var) if res.var is not None else None)


def _held_snr(res: _Results, fits: list[TexelFit | None], area: np.ndarray, ref: np.ndarray,
              apx: np.ndarray, avis_h: np.ndarray, base: int) -> None:
    """Every fitted texel's held-out SNR (`dense.heldout_snr`) into res."""
    for t, fit in enumerate(fits):  # loop over texels: one SNR each
        if fit is None or not fit.valid:
            continue
        res.snr_ho[base + t] = heldout_snr(ref[t], apx[t], avis_h[t], area[t])


__all__ = ["SKIP_CODES", "Chunk", "chunk_bounds", "fit_level_batched", "too_wide"]
