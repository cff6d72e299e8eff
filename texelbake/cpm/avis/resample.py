"""A level's a_vis at any view directions from its children's cube maps (seed 000 §3.4, §4.1).

a_vis is additive over disjoint pieces of surface, and a level's world-direction cube maps are
exactly the sums of its children's (`coarsen_level`: no rays). What the fit of a coarse level
needs is a_vis on its own direction grid, given in each texel's frame, which differs from its
children's frames: `avis_at` reads the summed maps there, losslessly stored, by the look-up the
renderer uses (`AvisTable.evaluate`: closed-form texels exact at any direction, ray texels
bilinear over the unoccluded bound times the visible fraction at the four taps). The seed
instead recasts every dense sample's visibility rays at every level (`cpm.dense.avis_sums`,
BakeSettings.avis_coarse = "dense", with avis_fit_samples=0; by default a texel of more
samples casts from a systematic subset of them); the difference between the two is the
look-up's resampling error, measured in benchmarks/avis_methods.py (`--coarse`).
"""

from __future__ import annotations

import numpy as np

from texelbake.cpm.avis.compress import compress_level
from texelbake.cpm.avis.levels import AvisLevel
from texelbake.cpm.avis.table import AvisTable
from texelbake.errors import ShapeError
from texelbake.geometry.basis import grid_to_world


def lossless_table(level: AvisLevel) -> AvisTable:
    """The level's maps as a table that keeps every Haar coefficient (float32 values, no sum
    correction), its frames the identity: `evaluate` then takes world directions."""
    n = level.n_side * level.n_side
    eye = np.broadcast_to(np.eye(3), (n, 3, 3)).copy()
    return compress_level(level, eye, 1.0, correct_sum=False, selection="face")


def avis_at(level: AvisLevel | AvisTable, texels: np.ndarray, frames: np.ndarray,
            dirs_texel: np.ndarray, *, max_queries: int = 1 << 20) -> np.ndarray:
    """a_vis of `texels` at the same directions given in each texel's own frame.

    level : the level's uncompressed maps (`AvisLevel`, texel ids local to it), or their
        `lossless_table` (built once when a level is queried in parts)
    texels : (t,) int64 ids of `level`; frames : (t, 3, 3) float64 their frames (rows t, b, n)
    dirs_texel : (k, 3) float64 unit directions in the texel frame (a fit's view grid)
    max_queries : look-ups per call of the table (memory bound)
    returns : (t, k) float64 >= 0; 0 where the look-up is under the a_vis floor or the texel
        has no samples
    """
    table = lossless_table(level) if isinstance(level, AvisLevel) else level
    t = np.asarray(texels, np.int64).ravel()
    fr = np.asarray(frames, np.float64)
    d = np.asarray(dirs_texel, np.float64)
    if fr.shape != (t.shape[0], 3, 3) or d.ndim != 2 or d.shape[1] != 3:
        raise ShapeError(f"frames must be ({t.shape[0]}, 3, 3) and dirs_texel (k, 3), got "
                         f"{fr.shape} and {d.shape}")
    k = d.shape[0]
    out = np.zeros((t.shape[0], k))
    if t.size == 0 or k == 0:
        return out
    step = max(int(max_queries) // k, 1)
    for a in range(0, t.shape[0], step):  # memory-bounded blocks of texels
        tb = t[a:a + step]
        w = grid_to_world(fr[a:a + step], d).reshape(-1, 3)  # (b * k, 3)
        val, _ = table.evaluate(np.repeat(tb, k), w, floor=0.0)
        out[a:a + step] = val.reshape(tb.shape[0], k)
    return out


__all__ = ["avis_at", "lossless_table"]
