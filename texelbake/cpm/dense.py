"""What fitting a level reads from its texels' dense samples, apart from the fit itself
(seed 000 §3.2, §3.4): a_vis on the grid's view directions (Eq. 3), the texel areas, and the
held-out truth and approximation of Eq. 7 on the held-out product grid, each a sum over
samples taken in batches bounded by the worker's memory (`LevelPass.budget`).

A coarse texel's sums do not depend on the fit, so a tile shard can sum its own samples for
the texels above it (`DenseSums`, `dense_sums`) and the top shard add the tiles' sums.

The held-out truth is measured on a seeded sample of each level's texels
(`BakeSettings.heldout_texels`, `truth_sample.measured_texels`): the same texels whichever tile or chunk
holds them, every texel of a level that has fewer occupied texels than the sample. A texel
outside the sample has its held-out a_vis NaN and its SNR NaN (not measured), which the
report's percentiles leave out. Within a measured texel of more than
`BakeSettings.heldout_samples` dense samples the truth is summed over a seeded subset of them
(`truth_sample.truth_samples`) and scaled by the texel's area over the subset's (`held_scale`): a coarse
texel's truth costs a bounded number of samples instead of every sample below it, once per
level.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from texelbake.cpm.brdf_product import brdf_product
from texelbake.cpm.level import (
    FitInputs,
    direction_sets,
    samples_in,
    segment_sum,
    texel_dirs,
    texel_ids,
    visibility_cos,
)
from texelbake.cpm.matrix import avis_floor, filtered_reflectance, snr_db
from texelbake.cpm.truth_sample import (
    avis_samples,
    measured_texels,
    truth_samples,
    validation_cap,
)
from texelbake.errors import ShapeError

#: bytes per (dense sample, held-out pair, channel) in the held-out pass
BYTES_PER_HELD_ENTRY = 8 * 12


@dataclass(frozen=True)
class LevelPass:
    """One level's fit inputs as its passes over samples read them: the inputs, the level,
    its texel frames (n_l^2, 3, 3), the direction sets (`direction_sets`) and the memory
    budget in bytes (`BakeSettings.worker_memory_mb`)."""

    src: FitInputs
    level: int
    frames: np.ndarray
    dirs: dict[str, np.ndarray]
    budget: int

    @classmethod
    def of(cls, src: FitInputs, level: int) -> LevelPass:
        s = src.settings
        return cls(src, level, src.geo[f"frames_L{level}"], direction_sets(s),
                   int(s.worker_memory_mb) * 2**20)


#: the held-out pairs' and the validation pairs' keys in `LevelPass.dirs`
HELD_KEYS = ("held_i", "held_o")
VAL_KEYS = ("val_i", "val_o")


@dataclass(frozen=True)
class DenseSums:
    """What the fit needs from a texel's dense samples and that does not depend on the fit:
    per texel the samples' count and area, a_vis on the grid's view directions (Eq. 3) and the
    held-out truth (Eq. 7's numerator on the held-out pairs, a_vis on the held-out view
    directions), summed over the truth's samples (`truth_samples`, their area `area_held`;
    `held_scale` scales it to the texel). Every field is a sum over samples, so the sums of
    disjoint sample sets of the same texels add up to the whole set's (up to the order of the
    floating-point sums): a tile
    shard sums its own samples for the coarse texels above it, and the top shard adds the
    tiles' (`texelbake.stages.cpm`) instead of reading every sample of the atlas again."""

    count: np.ndarray  # (t,) int64
    area: np.ndarray  # (t,)
    avis_o: np.ndarray  # (t, n_o)
    ref: np.ndarray  # (t, h_i, h_o, 3)
    avis_h: np.ndarray  # (t, h_o)
    area_held: np.ndarray  # (t,)
    # the truth on the validation pairs (`level.VALIDATION`, widened lobes only; empty
    # otherwise) over every texel's truth samples, and their area
    val_ref: np.ndarray  # (t, v_i, v_o, 3)
    val_avis: np.ndarray  # (t, v_o)
    val_area: np.ndarray  # (t,)
    # the area of the samples that cast avis_o's rays (`avis_parts`; `avis_scale` scales
    # avis_o to the texel)
    area_avis: np.ndarray  # (t,)

    FIELDS = ("count", "area", "avis_o", "ref", "avis_h", "area_held", "val_ref", "val_avis",
              "val_area", "area_avis")

    def add_row(self, i: int, part: DenseSums) -> None:
        """Add `part`'s one texel into texel i of these sums, in place."""
        for f in self.FIELDS:  # ten fields
            getattr(self, f)[i] += getattr(part, f)[0]

    def rows(self, idx) -> DenseSums:
        return DenseSums(*(getattr(self, f)[idx] for f in self.FIELDS))

    @classmethod
    def zeros(cls, n_t: int, dirs: dict[str, np.ndarray]) -> DenseSums:
        n_o, h_i, h_o = len(dirs["dirs_o"]), len(dirs["held_i"]), len(dirs["held_o"])
        v_i, v_o = len(dirs["val_i"]), len(dirs["val_o"])
        return cls(np.zeros(n_t, np.int64), np.zeros(n_t), np.zeros((n_t, n_o)),
                   np.zeros((n_t, h_i, h_o, 3)), np.zeros((n_t, h_o)), np.zeros(n_t),
                   np.zeros((n_t, v_i, v_o, 3)), np.zeros((n_t, v_o)), np.zeros(n_t),
                   np.zeros(n_t))

    def to_arrays(self, prefix: str) -> dict[str, np.ndarray]:
        """The arrays to store (the validation fields only where there are validation pairs:
        narrow-lobe sums are stored as before)."""
        return {f"{prefix}{f}": getattr(self, f) for f in self.FIELDS
                if not (f.startswith("val_") and self.val_ref.shape[1] == 0)}

    @classmethod
    def from_arrays(cls, arrays, prefix: str) -> DenseSums:
        got = {f: np.asarray(arrays[f"{prefix}{f}"]) for f in cls.FIELDS
               if f"{prefix}{f}" in arrays}
        n_t = len(got["count"])
        got.setdefault("val_ref", np.zeros((n_t, 0, 0, 3)))
        got.setdefault("val_avis", np.zeros((n_t, 0)))
        got.setdefault("val_area", np.zeros(n_t))
        got.setdefault("area_avis", got["area"].copy())  # stored before the subset: all cast
        return cls(**got)


def positions(texels: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """(n,) int64 position of each of ids (n,) in `texels` (any order, unique), -1 when
    absent."""
    order = np.argsort(texels, kind="stable")
    srt = texels[order]
    i = np.clip(np.searchsorted(srt, ids), 0, max(len(srt) - 1, 0))
    hit = (srt[i] == ids) if len(srt) else np.zeros(len(ids), bool)
    return np.where(hit, order[i] if len(srt) else 0, -1)


def dense_of(lp: LevelPass, texels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Every dense sample of `texels` grouped by texel: (samples (n,) int64, ascending within
    a texel; their texel's position in `texels` (n,) int64, ascending)."""
    s = lp.src.settings
    ids = samples_in(lp.src.geo, s.atlas_resolution, lp.level, texels)  # ascending
    pos = positions(texels, texel_ids(lp.src.geo, s.atlas_resolution, lp.level, ids))
    return ids[np.argsort(pos, kind="stable")], np.sort(pos, kind="stable")


def held_scale(area: np.ndarray, area_held: np.ndarray) -> np.ndarray:
    """(t,) the factor from a truth summed over the kept samples (`truth_samples`, of area
    `area_held` (t,)) to the texel (area (t,)): the ratio estimator, exact whenever the texel's
    Eq. 7 terms per unit area are equal (a flat texel's one point) and 1 where every sample is
    kept; NaN where none is (the texel is then not measured)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(area_held > 0, area / area_held, np.nan)


def to_texel(ref: np.ndarray, avis_h: np.ndarray, area: np.ndarray, area_held: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray]:
    """The truth (ref (t, h_i, h_o, 3), avis_h (t, h_o)) summed over the kept samples, scaled
    to each texel (`held_scale`)."""
    scale = held_scale(area, area_held)
    return ref * scale[:, None, None, None], avis_h * scale[:, None]


def inv_avis(avis_o: np.ndarray, area: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(valid (t, n_o) bool, 1 / a_vis (t, n_o), 0 where invalid): a_vis above each texel's
    floor (`avis_floor` of its area (t,))."""
    eps = np.array([avis_floor(a) for a in area])[:, None]
    valid = np.isfinite(avis_o) & (avis_o > eps)
    return valid, np.where(valid, 1.0 / np.where(valid, avis_o, 1.0), 0.0)


def avis_sums(lp: LevelPass, texels: np.ndarray, dense: np.ndarray, dseg: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray]:
    """(a_vis(w_o) (t, n_o), area (t,)) per texel: Eq. 3 on all its dense samples (`dense`,
    their texel positions `dseg` ascending), in sample batches; a texel of more than
    `BakeSettings.avis_fit_samples` samples from a systematic subset of them
    (`truth_sample.avis_samples`), scaled by its area over theirs (`avis_scale`)."""
    avis, area, area_avis = avis_parts(lp, texels, dense, dseg)
    avis *= avis_scale(area, area_avis)[:, None]  # exactly 1 where every sample cast
    return avis, area


def avis_parts(lp: LevelPass, texels: np.ndarray, dense: np.ndarray, dseg: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(a_vis (t, n_o) summed over the samples that cast its rays, area (t,) of every
    sample, area_avis (t,) of those that cast, equal to `area` where every sample casts):
    sums over `dense` that add over disjoint sample sets of the same texels (a tile's share of
    a top texel casts its share of the texel's subset)."""
    src, n_t = lp.src, len(texels)
    n_o = len(lp.dirs["dirs_o"])
    area_all = src.geo["sample_area"][dense]
    area = segment_sum(area_all, dseg, n_t, 0)
    area_avis = area
    keep = avis_samples(src, lp.level, texels, dense, dseg)
    if keep is not None:
        dense, dseg, area_all = dense[keep], dseg[keep], area_all[keep]
        area_avis = segment_sum(area_all, dseg, n_t, 0)
    tex_l = texels[dseg] if dense.size else np.zeros(0, np.int64)
    step = max(lp.budget // (8 * 16 * n_o), 1)
    avis = np.zeros((n_t, n_o))
    for s0 in range(0, dense.size, step):  # loop over sample batches (memory bound)
        sl = slice(s0, s0 + step)
        vc = visibility_cos(src, dense[sl], texel_dirs(lp.frames, tex_l[sl], lp.dirs["dirs_o"]),
                            "geometric")
        avis += segment_sum(vc * area_all[sl, None], dseg[sl], n_t, 0)
    return avis, area, area_avis


def avis_scale(area: np.ndarray, area_avis: np.ndarray) -> np.ndarray:
    """(t,) the factor from a_vis summed over the samples that cast its rays (of area
    `area_avis` (t,)) to the texel (area (t,)): the ratio estimator, exact whenever the
    texel's a_vis per unit area is the same on every sample; 1 where every sample cast (the
    two areas equal bit for bit) or none did (a_vis 0: the texel has no valid direction)."""
    return np.divide(area, area_avis, out=np.ones_like(area), where=area_avis > 0)


def dense_sums(src: FitInputs, level: int, texels: np.ndarray,
               samples: np.ndarray | None = None, *, avis: bool = True) -> DenseSums:
    """`DenseSums` of `texels` (flat ids at `level`) over `samples` (ascending ids of samples
    of those texels; default all of them), in sample batches bounded by worker_memory_mb. The
    same passes as the fit's own (`avis_sums`, `held_pass`), so a texel's sums over all its
    samples equal the fit's. avis=False leaves `avis_o` zero and casts none of its rays (the
    caller has it from the children's maps, BakeSettings.avis_coarse)."""
    lp = LevelPass.of(src, level)
    s, geo = src.settings, src.geo
    texels = np.asarray(texels, np.int64)
    if samples is None:
        samples = samples_in(geo, s.atlas_resolution, level, texels)
    samples = np.asarray(samples, np.int64)
    pos = positions(texels, texel_ids(geo, s.atlas_resolution, level, samples))
    if np.any(pos < 0):
        raise ShapeError(f"dense_sums: samples outside the level {level} texels given")
    order = np.argsort(pos, kind="stable")
    dense, dseg = samples[order], pos[order]
    n_t = len(texels)
    if avis:
        avis_o, area, area_avis = avis_parts(lp, texels, dense, dseg)
    else:
        avis_o = np.zeros((n_t, len(lp.dirs["dirs_o"])))
        area = area_avis = segment_sum(geo["sample_area"][dense], dseg, n_t, 0)
    out = DenseSums.zeros(n_t, lp.dirs)
    ref, avis_h, area_held = out.ref, out.avis_h, out.area_held
    val_ref, val_avis, val_area = out.val_ref, out.val_avis, out.val_area
    if len(lp.dirs["val_i"]):
        val_ref, val_avis, val_area = validation_sums(lp, texels, dense, dseg)
    if len(lp.dirs["held_i"]):
        none = np.zeros(0, np.int64)
        meas = measured_texels(src, level, texels)
        d_m, s_m = dense[meas[dseg]], dseg[meas[dseg]]
        keep = truth_samples(src, level, texels, d_m, s_m)
        d_m, s_m = d_m[keep], s_m[keep]
        ref, _, avis_h = held_pass(lp, texels, d_m, s_m, none, none, np.zeros((0, 3)),
                                   want_ref=True)
        avis_h[~meas] = np.nan
        area_held = segment_sum(geo["sample_area"][d_m], s_m, n_t, 0)
    return DenseSums(np.bincount(dseg, minlength=n_t).astype(np.int64), area, avis_o, ref,
                     avis_h, area_held, val_ref, val_avis, val_area, area_avis.copy())


def validation_sums(lp: LevelPass, texels: np.ndarray, dense: np.ndarray, dseg: np.ndarray,
                    keys: tuple[str, str] = VAL_KEYS
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The truth on the validation pairs (`level.VALIDATION`), or on the pairs of the
    direction sets `keys` of lp.dirs, of every one of `texels` (their dense samples `dense`,
    positions `dseg` ascending), summed over the truth's samples (`truth_samples`): (ref (t,
    v_i, v_o, 3), a_vis (t, v_o), their area (t,)), which `to_texel` scales to each texel;
    at most about VALIDATION_SAMPLES samples per texel."""
    none = np.zeros(0, np.int64)
    keep = truth_samples(lp.src, lp.level, texels, dense, dseg,
                         validation_cap(lp.src.settings.heldout_samples))
    ref, _, avis = held_pass(lp, texels, dense[keep], dseg[keep], none, none, np.zeros((0, 3)),
                             want_ref=True, keys=keys)
    return ref, avis, segment_sum(lp.src.geo["sample_area"][dense[keep]], dseg[keep],
                                  len(texels), 0)


def points_on(lp: LevelPass, texels: np.ndarray, smp: np.ndarray, pseg: np.ndarray,
              pw: np.ndarray, pvar: np.ndarray | None, keys: tuple[str, str]) -> np.ndarray:
    """Eq. 7's numerator of the points alone on the pairs `keys`: (t, a, b, 3)."""
    order = np.lexsort((smp, pseg))
    _, apx, _ = held_pass(lp, texels, smp[order], pseg[order], np.arange(smp.size),
                          pseg[order], pw[order], want_ref=False,
                          pvar=None if pvar is None else pvar[order], keys=keys)
    return apx


def held_pass(lp: LevelPass, texels: np.ndarray, dense: np.ndarray, dseg: np.ndarray,
              pos: np.ndarray, pseg: np.ndarray, pw: np.ndarray, *, want_ref: bool,
              truth_w: np.ndarray | None = None, pvar: np.ndarray | None = None,
              keys: tuple[str, str] = HELD_KEYS) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One pass over `dense` samples (grouped by texel, `dseg` ascending) on the held-out pairs:
    the truth (Eq. 7's numerator `ref` (t, h_i, h_o, 3) and a_vis on the held-out views
    `avis_h` (t, h_o)) when `want_ref`, each sample weighted by `truth_w` (n,) (default its
    area; 0 leaves a sample out of the truth), and the points' approximation `apx`
    (t, h_i, h_o, 3) from the rows at positions `pos` (ascending; texel `pseg`, weights `pw`
    (p, 3), lobes widened by `pvar` (p,) when given: their BRDF evaluated again); on the
    light and view directions `keys` of `lp.dirs` (the held-out pairs, or the validation
    pairs)."""
    src, n_t = lp.src, len(texels)
    d_i, d_o = lp.dirs[keys[0]], lp.dirs[keys[1]]
    h_i, h_o = len(d_i), len(d_o)
    tex_l = texels[dseg] if dense.size else np.zeros(0, np.int64)
    ref = np.zeros((n_t, h_i, h_o, 3))
    apx = np.zeros((n_t, h_i, h_o, 3))
    avis_h = np.zeros((n_t, h_o))
    area_all = src.geo["sample_area"][dense] if truth_w is None else truth_w
    step = max(lp.budget // (BYTES_PER_HELD_ENTRY * h_i * h_o * 3), 1)
    for s0 in range(0, dense.size, step):  # loop over sample batches (memory bound)
        sl = slice(s0, s0 + step)
        smp, seg = dense[sl], dseg[sl]
        wi_d = texel_dirs(lp.frames, tex_l[sl], d_i)  # once per texel of the batch
        wo_d = texel_dirs(lp.frames, tex_l[sl], d_o)
        vi = visibility_cos(src, smp, wi_d)
        vo = visibility_cos(src, smp, wo_d, "geometric")
        wi, wo = wi_d.per_sample, wo_d.per_sample  # (p, h_i, 3), (p, h_o, 3) for the BRDF
        live = (vi.T[:, None, :] > 0) & (vo.T[None, :, :] > 0)
        f = brdf_product(src.geo, src.materials, smp, wi, wo, live)
        f *= vi[None, :, :, None]
        f *= vo[None, :, None, :]  # (3, p, h_i, h_o)
        a_, b_ = np.searchsorted(pos, [s0, s0 + len(smp)])
        if b_ > a_:
            at = pos[a_:b_] - s0
            fp = f[:, at]
            if pvar is not None:  # the points' own lobes, widened
                fp = brdf_product(src.geo, src.materials, smp[at], wi[at], wo[at],
                                  live[:, :, at], var=pvar[a_:b_])
                fp *= vi[at][None, :, :, None]
                fp *= vo[at][None, :, None, :]
            apx += segment_sum(fp * pw.T[:, a_:b_, None, None], pseg[a_:b_],
                               n_t, 1).transpose(1, 2, 3, 0)
        if want_ref:
            avis_h += segment_sum(vo * area_all[sl, None], seg, n_t, 0)
            f *= area_all[sl][None, :, None, None]  # f is not read again: weighted in place
            ref += segment_sum(f, seg, n_t, 1).transpose(1, 2, 3, 0)
    return ref, apx, avis_h


def heldout_from_samples(lp: LevelPass, texels: np.ndarray, dense: np.ndarray,
                         dseg: np.ndarray, smp: np.ndarray, pseg: np.ndarray, pw: np.ndarray,
                         pvar: np.ndarray | None = None
                         ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Held-out (ref, apx, avis_h) of `held_pass` for texels whose dense samples are read:
    brute-force Eq. 7 over all of them against their characteristic points (sample ids smp
    (p,), texel positions pseg (p,), stored weights pw (p, 3), lobe variances pvar (p,) or
    None), each a sample of its texel."""
    # only the texels of the held-out sample (`measured_texels`); the others' a_vis NaN
    meas = measured_texels(lp.src, lp.level, texels)
    keep, pkeep = meas[dseg], meas[pseg]
    dense, dseg, smp, pseg, pw = dense[keep], dseg[keep], smp[pkeep], pseg[pkeep], pw[pkeep]
    pvar = None if pvar is None else pvar[pkeep]
    # the points as positions in `dense`: `dense` is ascending within each texel and dseg
    # ascending, so (texel, sample) keys are sorted
    span = int(max(dense.max(initial=0), smp.max(initial=0))) + 1
    pos = np.searchsorted(dseg * span + dense, pseg * span + smp)
    # the rows the truth sums (`truth_samples`) and the points' own, nothing else evaluated
    truth = truth_samples(lp.src, lp.level, texels, dense, dseg)
    rows = truth.copy()
    rows[pos] = True
    pos = (np.cumsum(rows) - 1)[pos]
    order = np.argsort(pos, kind="stable")
    area = lp.src.geo["sample_area"][dense]
    kept = area * truth  # a sample's weight in the truth: its area, 0 left out
    ref, apx, avis_h = held_pass(lp, texels, dense[rows], dseg[rows], pos[order], pseg[order],
                                 pw[order], want_ref=True, truth_w=kept[rows],
                                 pvar=None if pvar is None else pvar[order])
    n_t = len(texels)
    avis_h[~meas] = np.nan
    ref, avis_h = to_texel(ref, avis_h, segment_sum(area, dseg, n_t, 0),
                           segment_sum(kept, dseg, n_t, 0))
    return ref, apx, avis_h


def heldout_from_sums(lp: LevelPass, texels: np.ndarray, sums: DenseSums, smp: np.ndarray,
                      pseg: np.ndarray, pw: np.ndarray, pvar: np.ndarray | None = None
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`heldout_from_samples` with the truth already summed (`DenseSums`): only the points
    are evaluated."""
    apx = points_on(lp, texels, smp, pseg, pw, pvar, HELD_KEYS)
    ref, avis_h = to_texel(sums.ref, sums.avis_h, sums.area, sums.area_held)
    return ref, apx, avis_h


def heldout_snr(ref: np.ndarray, apx: np.ndarray, avis_h: np.ndarray, area: float) -> float:
    """SNR (dB) of one texel's held-out Eq. 7: ref, apx (h_i, h_o, 3) the summed truth and
    approximation, avis_h (h_o,) a_vis on the held-out views, area its texel area. NaN when
    avis_h is (a texel outside the held-out sample: not measured)."""
    if np.isnan(avis_h).any():
        return float("nan")
    eps = avis_floor(float(area))
    rows = np.tile(avis_h, ref.shape[0])
    f_ref, ok = filtered_reflectance(ref.reshape(-1, 3), rows, eps)
    f_apx, _ = filtered_reflectance(apx.reshape(-1, 3), rows, eps)
    return float(snr_db(f_ref, f_apx, ok))


__all__ = ["BYTES_PER_HELD_ENTRY", "DenseSums", "LevelPass", "avis_parts", "avis_scale",
           "avis_sums", "dense_of",
           "dense_sums", "held_pass", "heldout_from_samples", "heldout_from_sums",
           "held_scale", "points_on", "to_texel", "validation_sums", "HELD_KEYS", "VAL_KEYS",
           "heldout_snr", "inv_avis", "positions"]
