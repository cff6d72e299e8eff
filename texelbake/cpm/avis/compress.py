"""A level's a_vis cube maps compressed into the table the renderer reads, a chunk of ray
texels at a time (memory bounded whatever the atlas size).

The table (`AvisTable`) needs two level-wide choices: the common residual tau of the texel
budget (`select_texel_budget`: every texel keeps its largest coefficients until its dropped
share is at most tau, one tau whose counts fit the level's budget) and the per-pixel
parameter of the sum correction (`sum_correction`: the level's total a_vis restored at every
cube pixel). Both are reductions over all texels, so the maps are read in passes, each over
one chunk at a time (a tile of the farm's a_vis stage, or rows of an in-memory level):

1. tau: a histogram of every texel's sorted dropped-share tail on a fixed log grid
   (`TAU_GRID`, 1.4 % steps) gives the level's kept count at every grid value; tau is the
   smallest grid value whose count fits the budget. The exact bisection (`haar.budget_mask`)
   finds the crossing between two grid values: the grid keeps at most the budget, and every
   texel's dropped share is at most 1.4 % above the exact tau (its relative error 0.7 %
   above), `tests/cpm/avis/test_stream.py` measures both against it.
2. The coefficients (kept per chunk: they are the table), and the correction's sums: the
   target total and, for the bounded texels, the corrected total at `C_GRID` values of c.
3. The correction refined: per pixel, `C_REFINE` values inside the grid interval where the
   total crosses the target, then the secant inside the final interval (1/32 wide: c within
   ~1e-4 of the bisection's, below float16's spacing where it is stored, 1e-3 at c in
   [1, 2)).
4. (optional) every texel's error against its uncompressed maps, for the report.

Passes 2 and 3's sums are `correction_sums.CorrectionSums`. Each pass maps its chunks on a
few threads (`chunk_threads.in_order`) and reduces their results in chunk order, so the table
is the same bit for bit whatever the thread count. Peak memory: per thread one chunk's maps
and their ~12 temporaries (`CHUNK_ROWS` rows of 6 res^2 float64: 12.6 MB per array at res
32), the accumulators (C_GRID x 6 res^2), and the kept coefficients; nothing grows with the
level but the table itself.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from texelbake.cpm.avis.chunk_threads import in_order
from texelbake.cpm.avis.closed_form import closed_form_maps
from texelbake.cpm.avis.correction_sums import ChunkSums, CorrectionSums
from texelbake.cpm.avis.levels import AvisLevel
from texelbake.cpm.avis.table import AvisTable, visible_fraction
from texelbake.cpm.haar import (
    HaarCoeffs,
    coeffs_from_mask,
    compress_haar,
    decompress_haar,
    dequantize_values,
    haar_coefficients,
    haar_support_mean,
    quantize_values,
)
from texelbake.errors import SettingsError, ShapeError

#: ray texels per chunk of an in-memory level (6 x 32 x 32 float64 maps: 12.6 MB per array)
CHUNK_ROWS = 256
#: the tau grid: 1e-30 .. 1e6 (shares are fractions of a texel's squared norm: the total is
#: ~1, tau of interest ~1e-4; the exact bisection searched 30 decades below the largest)
TAU_GRID = np.geomspace(1e-30, 1e6, 6001)


@dataclass(frozen=True)
class LevelChunks:
    """A level's a_vis with its ray maps read a chunk at a time.

    level : the AvisLevel's per-texel arrays (n_side, res, closed, bounded, cf, texel_area);
        its `ray_texels` / `ray_maps` are not used
    ray_texels : (r,) int64 the ray texels in table-row order, chunk after chunk
    bounds : (k + 1,) int64 row offsets of the chunks
    read : chunk index -> (bounds[i+1] - bounds[i], 6, res, res) float64 uncompressed maps
    """

    level: AvisLevel
    ray_texels: np.ndarray
    bounds: np.ndarray
    read: Callable[[int], np.ndarray]

    @property
    def n_chunks(self) -> int:
        return int(self.bounds.shape[0] - 1)


@dataclass(frozen=True)
class TableErrors:
    """The table against its uncompressed maps: relative L2 over the level's ray texels'
    cube pixels (`rel_error`) and per ray texel in table-row order (`per_texel`)."""

    rel_error: float
    per_texel: np.ndarray


def chunks_of(level: AvisLevel, rows: int = CHUNK_ROWS) -> LevelChunks:
    """An in-memory level as chunks of `rows` ray texels, in its own (ascending) order."""
    r = int(level.ray_texels.shape[0])
    bounds = np.unique(np.r_[np.arange(0, r, max(int(rows), 1)), r]).astype(np.int64)
    if r == 0:
        bounds = np.zeros(1, np.int64)
    return LevelChunks(level, level.ray_texels, bounds,
                       lambda i: level.ray_maps[bounds[i]:bounds[i + 1]])


def compress_level(level: AvisLevel, frames: np.ndarray, keep_fraction: float, *,
                   correct_sum: bool = True, selection: str = "texel") -> AvisTable:
    """AvisTable of an in-memory level (`compress_chunks` over `chunks_of(level)`).

    frames : (N*N, 3, 3) float64 texel frames of this level (rows t, b, n)
    keep_fraction : Haar coefficients kept, as a fraction of the ray texels' dense cube pixels
    correct_sum : store the level's sum correction (default); False is the seed's plain Haar
        table
    selection : "texel" (default): one budget for the level, spent so that every texel's
        relative error of a_vis is about equal, each coefficient weighted by the U^2 it is
        multiplied with, values float16 relative to a per-texel scale; "face": the seed's
        per-face top fraction (`compress_haar`), float32 values
    """
    return compress_chunks(chunks_of(level), frames, keep_fraction, correct_sum=correct_sum,
                           selection=selection)[0]


def compress_chunks(src: LevelChunks, frames: np.ndarray, keep_fraction: float, *,
                    correct_sum: bool = True, selection: str = "texel", errors: bool = False
                    ) -> tuple[AvisTable, TableErrors | None]:
    """The table of a level read chunk by chunk (module docstring), and with `errors` its
    error against the uncompressed maps (one more pass)."""
    lv = src.level
    n = lv.n_side * lv.n_side
    frames = np.asarray(frames, dtype=np.float64)
    if frames.shape != (n, 3, 3):
        raise ShapeError(f"frames must be ({n}, 3, 3), got {frames.shape}")
    if selection not in ("texel", "face"):
        raise SettingsError(f"avis selection must be 'texel' or 'face', got {selection!r}")
    if not (0.0 < keep_fraction <= 1.0):
        raise SettingsError(f"keep_fraction must be in (0, 1], got {keep_fraction!r}")
    res = lv.res
    r = int(src.ray_texels.shape[0])
    ray_row = np.full(n, -1, dtype=np.int64)
    ray_row[src.ray_texels] = np.arange(r)

    tau = _level_tau(src, keep_fraction) if selection == "texel" and r else 0.0
    parts, scales = [], []
    sums = CorrectionSums(res) if correct_sum and r else None

    def pass2(i: int) -> tuple[HaarCoeffs, np.ndarray | None, ChunkSums | None]:
        c = _chunk(src, i)
        if selection == "face":
            haar, scale = compress_haar(c.stored, keep_fraction), None
        else:
            haar, scale = _select(c, tau)
        part = None if sums is None else sums.of_chunk(c.bounded, c.unocc, c.stored,
                                                        decompress_haar(haar))
        return haar, scale, part

    for haar, scale, part in in_order(pass2, src.n_chunks):  # pass 2, reduced in chunk order
        parts.append(haar)
        if scale is not None:
            scales.append(scale)
        if sums is not None and part is not None:
            sums.add(part)
    haar = _concat(parts, res, r)
    scale = np.concatenate(scales) if scales else np.zeros(0, np.float32)
    maps_c, groups = [], []
    if sums is not None:
        if sums.has_bounded:
            groups.append(0)
            maps_c.append(sums.refine(src.level, src.ray_texels, src.bounds, haar))  # pass 3
        if sums.has_direct:
            groups.append(1)
            maps_c.append(sums.direct())
    # float16: c and m are in [-8, 16] and [-1, 1]; 11 bits move F^exp(c) by < 1e-3 relative
    # and the scale (16 - c) / 8 by <= 1e-3
    correction = (np.stack(maps_c).astype(np.float16) if maps_c
                  else np.zeros(0, np.float16))
    table = AvisTable(res, frames, lv.texel_area, lv.closed, lv.bounded, lv.cf, ray_row, haar,
                      correction, np.asarray(groups, np.uint8), scale)
    return table, (_errors(src, table) if errors else None)


@dataclass
class _Chunk:
    rows: slice  # table rows
    texels: np.ndarray  # (k,) their texels
    raw: np.ndarray  # (k, 6, res, res) uncompressed a_vis
    stored: np.ndarray  # what the table holds: F for bounded texels, a_vis otherwise
    unocc: np.ndarray  # U for bounded texels, ones otherwise
    bounded: np.ndarray  # (k,) bool


def _chunk(src: LevelChunks, i: int) -> _Chunk:
    lv = src.level
    a, b = int(src.bounds[i]), int(src.bounds[i + 1])
    raw = np.asarray(src.read(i), dtype=np.float64)
    if raw.shape != (b - a, 6, lv.res, lv.res):
        raise ShapeError(f"a_vis chunk {i} has maps {raw.shape}, expected "
                         f"({b - a}, 6, {lv.res}, {lv.res})")
    texels = src.ray_texels[a:b]
    frac = lv.bounded[texels]
    stored = raw.copy()
    unocc = np.ones_like(raw)
    if frac.any():
        unocc[frac] = closed_form_maps(lv.cf, lv.res, texels[frac])
        stored[frac] = visible_fraction(raw[frac], unocc[frac])
    return _Chunk(slice(a, b), texels, raw, stored, unocc, frac)


def _shares(c: _Chunk) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per texel of a chunk: Haar coefficients, their shares (flat, (k, 6 res^2)), the shares
    sorted in descending order, the dropped-share tail along that order, and the count of
    non-zero shares. Dropping a coefficient costs about c^2 mean(U^2 over its support) of a_vis
    error (a Haar function's square is flat on its support); over the texel's ||a_vis||^2 it
    is its share of the texel's relative error. The order is a value sort, not an argsort
    (3x faster with numpy's SIMD sort): which coefficients a count keeps is `_top_mask`."""
    k = c.raw.shape[0]
    coef = haar_coefficients(c.stored)
    cost = coef * coef * haar_support_mean(np.square(c.unocc))
    norm2 = np.sum(np.square(c.raw).reshape(k, -1), axis=1)
    share = cost.reshape(k, -1) / np.where(norm2 > 0, norm2, 1.0)[:, None]
    asc = np.sort(share, axis=1)
    tail = np.cumsum(asc, axis=1)[:, ::-1]  # dropped when the first i are kept
    srt = asc[:, ::-1]
    return coef, share, srt, tail, (srt > 0).sum(axis=1)


def _top_mask(share: np.ndarray, srt: np.ndarray, cnt: np.ndarray) -> np.ndarray:
    """(k, n) bool: each row's `cnt` largest shares, ties taken in index order, the same
    entries as the first `cnt` of a stable argsort of -share (every share above the cnt-th
    largest value v, then the first ones equal to v). cnt in [1, n]."""
    v = srt[np.arange(srt.shape[0]), cnt - 1][:, None]
    above = share > v
    need = cnt - above.sum(axis=1)
    at = share == v
    return above | (at & (np.cumsum(at, axis=1) <= need[:, None]))


def _level_tau(src: LevelChunks, keep_fraction: float) -> float:
    """Pass 1: the smallest `TAU_GRID` value whose kept count fits the level's budget
    (ceil(keep_fraction * r * 6 * res^2), at least one per texel); 0 (keep every non-zero
    coefficient) when that fits. A texel keeps max(#(tail > tau), 1): with b the number of
    grid values below a tail value, the level's count at grid value j is the tails with
    b > j plus the texels whose largest tail has b <= j."""
    res = src.level.res
    r = int(src.ray_texels.shape[0])
    budget = max(r, int(np.ceil(keep_fraction * r * 6 * res * res)))
    g = TAU_GRID.shape[0]
    h_all = np.zeros(g + 1, np.int64)
    h_first = np.zeros(g + 1, np.int64)
    keep_all = 0

    def histograms(i: int) -> tuple[np.ndarray, np.ndarray, int]:
        _, _, _, tail, nonzero = _shares(_chunk(src, i))
        return (np.bincount(np.searchsorted(TAU_GRID, tail[tail > 0]), minlength=g + 1),
                np.bincount(np.searchsorted(TAU_GRID, tail[:, 0]), minlength=g + 1),
                int(np.maximum(nonzero, 1).sum()))

    for part_all, part_first, part_keep in in_order(histograms, src.n_chunks):
        h_all += part_all
        h_first += part_first
        keep_all += part_keep
    if keep_all <= budget:
        return 0.0
    above = np.cumsum(h_all[::-1])[::-1]  # above[b]: tails with b' >= b
    count = above[1:] + np.cumsum(h_first)[:-1]  # at grid value j
    fits = np.flatnonzero(count <= budget)
    return float(TAU_GRID[fits[0]] if fits.size else TAU_GRID[-1])


def _select(c: _Chunk, tau: float) -> tuple[HaarCoeffs, np.ndarray]:
    """Pass 2, texel selection: each texel keeps its largest shares until the dropped rest is
    at most tau (at least one; tau = 0: every non-zero one); values float16 relative to the
    texel's largest kept |c| (2 + 2 bytes per coefficient with a uint16 index)."""
    k = c.raw.shape[0]
    coef, share, srt, tail, nonzero = _shares(c)
    cnt = np.clip((tail > tau).sum(axis=1), 1, np.maximum(nonzero, 1))
    mask = _top_mask(share, srt, cnt).reshape(coef.shape)
    peak = np.max(np.abs(np.where(mask, coef, 0.0)).reshape(k, -1), axis=1)
    scale = np.where(peak > 0, peak, 1.0).astype(np.float32)
    deq = dequantize_values(quantize_values(coef.reshape(k, -1), scale[:, None])[0],
                            scale[:, None])
    return coeffs_from_mask(coef, mask, deq.reshape(coef.shape)), scale


def _concat(parts: list[HaarCoeffs], res: int, r: int) -> HaarCoeffs:
    """One HaarCoeffs of the chunks' (in row order)."""
    if not parts:
        return compress_haar(np.zeros((0, 6, res, res)), 1.0)
    offs = [np.zeros(1, np.int64)]
    base = 0
    for p in parts:  # a loop over chunks
        offs.append(p.offsets[1:] + base)
        base += int(p.offsets[-1])
    return HaarCoeffs(res, (r, 6), np.concatenate(offs),
                      np.concatenate([p.indices for p in parts]).astype(np.int32),
                      np.concatenate([p.values for p in parts]).astype(np.float32))


def texel_rel_errors(table_maps: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """Relative L2 error per texel, ||table - ref|| / ||ref|| over each texel's (6, res, res)
    maps (0 where both are zero, inf where only the reference is). table_maps, ref :
    (n, 6, res, res); returns (n,)."""
    n = ref.shape[0]
    diff = np.linalg.norm((table_maps - ref).reshape(n, -1), axis=1)
    norm = np.linalg.norm(ref.reshape(n, -1), axis=1)
    return np.divide(diff, norm, out=np.where(diff > 0, np.inf, 0.0), where=norm > 0)


def _errors(src: LevelChunks, table: AvisTable) -> TableErrors:
    """Pass 4: the table's reconstruction (`AvisTable.ray_texel_maps`) against the maps."""
    per = np.zeros(src.ray_texels.shape[0])
    d2 = n2 = 0.0
    _ = table.row_texels  # built here, once, before the threads read it

    def errors(i: int) -> tuple[slice, float, float, np.ndarray]:
        rows = slice(int(src.bounds[i]), int(src.bounds[i + 1]))
        ref = np.asarray(src.read(i), dtype=np.float64)
        rec = table.ray_texel_maps(rows)
        return (rows, float(np.sum(np.square(rec - ref))), float(np.sum(np.square(ref))),
                texel_rel_errors(rec, ref))

    for rows, part_d2, part_n2, part_per in in_order(errors, src.n_chunks):
        d2 += part_d2
        n2 += part_n2
        per[rows] = part_per
    return TableErrors(float(np.sqrt(d2) / max(np.sqrt(n2), 1e-300)), per)
