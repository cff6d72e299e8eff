"""Array idioms several stages share, each vectorized over whole arrays: the positions of
concatenated index runs (CSR ranges) and the distinct rows of a 2-D array by a lexsort of its
columns."""

from __future__ import annotations

import numpy as np


def concat_ranges(starts: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """(sum(counts),) int64 the runs [starts_j, starts_j + counts_j) concatenated in order
    (the entries of CSR rows gathered without a loop per row)."""
    starts = np.asarray(starts, np.int64)
    counts = np.asarray(counts, np.int64)
    return (np.arange(int(counts.sum()), dtype=np.int64)
            - np.repeat(np.cumsum(counts) - counts, counts) + np.repeat(starts, counts))


def unique_rows(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`np.unique(a, axis=0, return_inverse=True)` of an (n, k) array whose equal values are
    equal bits (integers; floats without NaN or -0.0): the same rows in the same order, the
    inverse flat, by a lexsort of the columns, ~4x faster than numpy's sort of rows as
    structured items."""
    order = np.lexsort(a.T[::-1])
    srt = a[order]
    new = np.r_[True, (srt[1:] != srt[:-1]).any(axis=1)] if a.shape[0] else np.zeros(0, bool)
    inv = np.empty(a.shape[0], np.int64)
    inv[order] = np.cumsum(new) - 1
    return srt[new], inv


__all__ = ["concat_ranges", "unique_rows"]
