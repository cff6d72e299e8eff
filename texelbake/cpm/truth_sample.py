"""Which texels and which of their dense samples the held-out and validation truths sum
(`texelbake.cpm.dense`), chosen by stateless seeded keys of (seed, level, texel or sample):
the same texels and samples whichever tile or chunk holds them; and which samples a coarse
texel's fit casts its a_vis rays from (`avis_samples`), every k-th of its Z-order run.

The held-out truth is measured on a seeded sample of each level's texels
(`BakeSettings.heldout_texels`, `measured_texels`); within a measured texel of more than
`BakeSettings.heldout_samples` dense samples it is summed over a seeded subset of them
(`truth_samples`), the validation pairs' truth over a smaller one (`validation_cap`).
"""

from __future__ import annotations

import numpy as np

from texelbake.arrays import concat_ranges, every_kth
from texelbake.cpm.level import FitInputs, texel_counts, zorder_runs
from texelbake.geometry.texels import morton


def _mix64(x: np.ndarray) -> np.ndarray:
    """splitmix64's finalizer on uint64: a stateless random key per index (numpy's generators
    draw sequences, not a value at an arbitrary index, which a texel in any tile needs)."""
    x = np.asarray(x, np.uint64).copy()
    with np.errstate(over="ignore"):
        x ^= x >> np.uint64(30)
        x *= np.uint64(0xBF58476D1CE4E5B9)
        x ^= x >> np.uint64(27)
        x *= np.uint64(0x94D049BB133111EB)
        x ^= x >> np.uint64(31)
    return x


def _texel_keys(seed: int, level: int, first_codes: np.ndarray) -> np.ndarray:
    """(k,) uint64 random keys of level texels named by their first finest Z-order code."""
    salt = _mix64(np.array([(int(seed) << 8) + int(level) + 0x5EED], np.uint64))[0]
    with np.errstate(over="ignore"):
        return _mix64(np.asarray(first_codes, np.uint64) ^ salt)


def _sample_keys(seed: int, level: int, samples: np.ndarray) -> np.ndarray:
    """(n,) uint64 random keys of dense samples at a level (their draw for the truth)."""
    salt = _mix64(np.array([(int(seed) << 8) + int(level) + 0x7A0B], np.uint64))[0]
    with np.errstate(over="ignore"):
        return _mix64(np.asarray(samples, np.uint64) ^ salt)


def truth_samples(src: FitInputs, level: int, texels: np.ndarray, dense: np.ndarray,
                  dseg: np.ndarray, cap: int | None = None) -> np.ndarray:
    """(n,) bool: which of the dense samples `dense` (of texels[dseg]) the held-out truth sums.
    A sample is kept when its seeded key (seed, level, sample id) falls below
    p = heldout_samples (or `cap`) / its texel's samples in the whole atlas, so every tile and
    chunk that holds it agrees (p >= 1, or a cap of 0: every sample). A smaller cap keeps a
    subset of a larger one's samples."""
    k = int(src.settings.heldout_samples if cap is None else cap)
    if k == 0 or dense.size == 0:
        return np.ones(dense.size, bool)
    s = src.settings
    n_t = texel_counts(src.geo, s.atlas_resolution, level, texels)
    p = (k / np.maximum(n_t, 1).astype(np.float64))[dseg]
    u = (_sample_keys(s.seed, level, dense) >> np.uint64(11)).astype(np.float64) * 2.0 ** -53
    return u < p


def measured_texels(src: FitInputs, level: int, texels: np.ndarray) -> np.ndarray:
    """(t,) bool: which of `texels` (flat ids at `level`) carry the held-out measurement, a
    seeded sample of `BakeSettings.heldout_texels` of the level's occupied texels (all of
    them when there are no more than that, or when it is 0). Depends only on (seed, level,
    texel), so every tile and chunk agrees."""
    s, geo = src.settings, src.geo
    texels = np.asarray(texels, np.int64)
    want = int(s.heldout_texels)
    n = int(s.atlas_resolution)
    if want == 0 or texels.size == 0:
        return np.ones(texels.size, bool)
    if "texel_zoffsets" in geo:
        zoff = np.asarray(geo["texel_zoffsets"])
        occupied = np.flatnonzero(np.diff(zoff[::1 << (2 * level)]) > 0) << (2 * level)
    else:  # artifacts from before the Z-order index
        row, col = geo["sample_row"] >> level, geo["sample_col"] >> level
        occupied = np.unique(morton(row << level, col << level))
    if occupied.size <= want:
        return np.ones(texels.size, bool)
    keys = _texel_keys(s.seed, level, occupied)
    threshold = np.partition(keys, want - 1)[want - 1]
    r, c = np.divmod(texels, n >> level)
    return _texel_keys(s.seed, level, morton(r << level, c << level)) <= threshold


#: most dense samples per texel the validation pairs' truth sums (a seeded subset beyond,
#: scaled by area as the held-out truth's): it decides between two sets of points, widened or
#: not, which the held-out truth then measures on its own samples
VALIDATION_SAMPLES = 1024


def validation_cap(heldout_samples: int) -> int:
    """The validation truth's cap: VALIDATION_SAMPLES, or the held-out truth's when that is
    smaller (0: every sample)."""
    return VALIDATION_SAMPLES if heldout_samples == 0 else min(VALIDATION_SAMPLES,
                                                               heldout_samples)


def avis_samples(src: FitInputs, level: int, texels: np.ndarray, dense: np.ndarray,
                 dseg: np.ndarray) -> np.ndarray | None:
    """(n,) bool: which of the dense samples `dense` (of texels[dseg]) a level's fit casts its
    a_vis rays from (`texelbake.cpm.dense.avis_sums`); None: every one. A texel of more than
    k = `BakeSettings.avis_fit_samples` samples in the whole atlas keeps every
    ceil(samples / k)-th of its run of the geometry stage's Z-order index, counted from the
    run's start: systematic sampling, spatially stratified (the run walks the texel's finest
    texels in Z-order, each face's samples in its stratified order), and the same samples
    whichever tile holds them (a tile's share of a top texel may hold none). The held-out
    truth's seeded draw (`truth_samples`) errs several times more on a_vis at the same count,
    and a coarse fit divides by a_vis (`benchmarks/avis_fit_samples.py`)."""
    cap = int(src.settings.avis_fit_samples)
    geo = src.geo
    if cap == 0 or dense.size == 0 or "sample_zorder" not in geo:
        return None
    texels = np.asarray(texels, np.int64)
    lo, hi = zorder_runs(geo, src.settings.atlas_resolution, level, texels)
    stride, count = every_kth(hi - lo, cap)
    big = np.flatnonzero(stride > 1)
    if big.size == 0:
        return None
    ranks = concat_ranges(lo[big], count[big], stride[big])
    chosen = np.sort(np.asarray(geo["sample_zorder"][ranks], np.int64))
    on_big = np.zeros(texels.size, bool)
    on_big[big] = True
    return ~on_big[dseg] | np.isin(dense, chosen)


__all__ = ["VALIDATION_SAMPLES", "avis_samples", "measured_texels", "truth_samples",
           "validation_cap"]
