"""The a_vis table's sum correction, streamed (`texelbake.cpm.avis.compress` passes 2 and 3):
per cube pixel, the level's target total and the corrected total at the c values of a grid,
summed a chunk of ray texels at a time, then c refined inside the grid interval that holds
the crossing (`table.sum_correction`'s rule: the bisection it replaces)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from texelbake.cpm.avis.chunk_threads import in_order
from texelbake.cpm.avis.closed_form import closed_form_maps
from texelbake.cpm.avis.correction import _LOG_GAMMA_MAX, _SCALE_SPAN, _power_and_scale
from texelbake.cpm.avis.levels import AvisLevel
from texelbake.cpm.haar import HaarCoeffs, decompress_haar, map_range

#: c values of the correction's first pass over [-8, 16] (every integer: the power's identity
#: c = 0 and its kink at c = 8 are grid values, so no interval straddles the kink and an exact
#: level keeps c = 0 exactly), then points inside the interval that holds the crossing
C_GRID = 25
C_REFINE = 32
_C_LO, _C_HI = -_LOG_GAMMA_MAX, _LOG_GAMMA_MAX + _SCALE_SPAN


class CorrectionTerms:
    """A chunk's bounded texels as the non-zero terms of the corrected total
    sum_t U F~^exp(g(c)) scale(c) (`apply_correction`'s bounded rule), gathered once and
    evaluated at every c of a pass.

    A term is non-zero only where U > 0 and F~ > 0 (half the cube is below a texel's horizon,
    U = 0 there), and a term with F~ = 1 is U whatever c is: only the others take the power.
    The terms are kept in (texel, pixel) order and summed per pixel by `np.bincount`, which
    adds in input order, so every pixel's total is the same sum, bit for bit, as the one
    over the dense (texel, 6, res, res) arrays (which adds texel after texel and adds 0.0
    for the dropped terms).
    """

    def __init__(self, u: np.ndarray, a: np.ndarray) -> None:
        self.shape = u.shape[1:]
        self.n_pix = int(np.prod(self.shape))
        idx = np.flatnonzero((u > 0) & (a > 0))  # row-major: texel after texel
        self.pix = idx % self.n_pix
        self.u = u.reshape(-1)[idx]
        logf = np.log(a.reshape(-1)[idx])
        self.part = np.flatnonzero(logf < 0)  # the terms with F~ < 1
        self.part_u = self.u[self.part]
        self.part_pix = self.pix[self.part]
        self.part_logf = logf[self.part]

    def power_sum(self, g: np.ndarray) -> np.ndarray:
        """sum_t U F~^exp(g) per pixel, g (6, res, res) the power's log-exponent."""
        gamma = np.exp(g).reshape(-1)
        terms = self.u.copy()
        terms[self.part] = self.part_u * np.exp(gamma[self.part_pix] * self.part_logf)
        return np.bincount(self.pix, weights=terms, minlength=self.n_pix).reshape(self.shape)

    def total(self, c: np.ndarray) -> np.ndarray:
        """The corrected total at every pixel for c (6, res, res)."""
        g, scale = _power_and_scale(c)
        return self.power_sum(g) * scale


@dataclass
class ChunkSums:
    """One chunk's share of `CorrectionSums` (None where the chunk has no such texel)."""

    target_b: np.ndarray | None = None
    total_b: list[np.ndarray] | None = None
    target_d: np.ndarray | None = None
    have_d: np.ndarray | None = None


class CorrectionSums:
    """The sum correction's level-wide sums (`table.sum_correction`'s rule, streamed)."""

    def __init__(self, res: int) -> None:
        shape = (6, res, res)
        self.target_b = np.zeros(shape)
        self.grid = np.linspace(_C_LO, _C_HI, C_GRID)
        self.total_b = np.zeros((C_GRID, *shape))
        self.target_d = np.zeros(shape)
        self.have_d = np.zeros(shape)
        self.has_bounded = self.has_direct = False

    def of_chunk(self, bounded: np.ndarray, unocc: np.ndarray, stored: np.ndarray,
                 approx: np.ndarray) -> ChunkSums:
        """Pass 2: one chunk's share of the targets and of the totals on the c grid. bounded
        (k,) bool, unocc U, stored (F for bounded texels, a_vis otherwise) and approx (the
        table's reconstruction of stored): (k, 6, res, res)."""
        b = bounded
        part = ChunkSums()
        if b.any():
            u, a = unocc[b], np.clip(approx[b], 0.0, 1.0)
            part.target_b = np.sum(u * stored[b], axis=0)
            terms = CorrectionTerms(u, a)
            same = None  # the grid values at and above the power's cap share one power sum
            part.total_b = []
            for cv in self.grid:  # a loop over the grid, each over the chunk
                g, scale = _power_and_scale(np.full(u.shape[1:], cv))
                if cv >= _LOG_GAMMA_MAX:
                    same = terms.power_sum(g) if same is None else same
                    part.total_b.append(same * scale)
                else:
                    part.total_b.append(terms.power_sum(g) * scale)
        if (~b).any():
            part.target_d = np.sum(stored[~b], axis=0)
            part.have_d = np.sum(np.maximum(approx[~b], 0.0), axis=0)
        return part

    def add(self, part: ChunkSums) -> None:
        """A chunk's sums (`of_chunk`) added, in chunk order (the same float sums whatever
        the threads)."""
        if part.target_b is not None and part.total_b is not None:
            self.has_bounded = True
            self.target_b += part.target_b
            self.total_b += np.stack(part.total_b)
        if part.target_d is not None and part.have_d is not None:
            self.has_direct = True
            self.target_d += part.target_d
            self.have_d += part.have_d

    def direct(self) -> np.ndarray:
        """The direct texels' m = sum (a - a~) / sum a~, clipped to [-1, 1] (0 stays 0)."""
        m = np.divide(self.target_d - self.have_d, self.have_d,
                      out=np.zeros_like(self.have_d), where=self.have_d > 0)
        return np.clip(m, -1.0, 1.0).astype(np.float32)

    def refine(self, lv: AvisLevel, ray_texels: np.ndarray, bounds: np.ndarray,
               haar: HaarCoeffs) -> np.ndarray:
        """Pass 3: c per pixel, the total decreasing in c. The grid interval where the total
        crosses the target (a target above the range: c = -8, as the bisection's), then
        C_REFINE points inside it, then the secant inside the final interval."""
        lo, width = self._bracket(self.total_b, self.grid[0], self.grid[1] - self.grid[0])
        if np.all(width == 0):
            return lo.astype(np.float32)
        step = width / C_REFINE
        pts = lo[None] + step[None] * np.arange(C_REFINE + 1)[:, None, None, None]
        tot = np.zeros(pts.shape)

        def totals(i: int) -> np.ndarray | None:
            rows = slice(int(bounds[i]), int(bounds[i + 1]))
            texels = ray_texels[rows]
            b = lv.bounded[texels]
            if not b.any():
                return None
            u = closed_form_maps(lv.cf, lv.res, texels[b])
            a = np.clip(decompress_haar(map_range(haar, rows.start * 6, rows.stop * 6,
                                                (rows.stop - rows.start, 6)))[b], 0.0, 1.0)
            terms = CorrectionTerms(u, a)
            return np.stack([terms.total(pts[j]) for j in range(C_REFINE + 1)])

        for part in in_order(totals, len(bounds) - 1):  # reduced in chunk order
            if part is not None:
                tot += part
        # the secant between the ends of the interval that holds the crossing
        j = np.clip(np.sum(tot > self.target_b[None], axis=0) - 1, 0, C_REFINE - 1)
        t0 = np.take_along_axis(tot, j[None], axis=0)[0]
        t1 = np.take_along_axis(tot, j[None] + 1, axis=0)[0]
        frac = np.clip(np.divide(t0 - self.target_b, t0 - t1, out=np.full(t0.shape, 0.5),
                                 where=t0 > t1), 0.0, 1.0)
        c = lo + step * (j + frac)
        return np.where(width > 0, c, lo).astype(np.float32)

    def _bracket(self, total: np.ndarray, start: float, step: float
                 ) -> tuple[np.ndarray, np.ndarray]:
        """Per pixel the grid interval [lo, lo + width] where total (k, ...) decreasing along
        k crosses the target; width 0 where the target is at or above the first value (c at
        the range's start)."""
        above = np.sum(total > self.target_b[None], axis=0)  # grid values above the target
        lo = start + step * np.maximum(above - 1, 0)
        width = np.where(above == 0, 0.0, step)
        return lo, width
