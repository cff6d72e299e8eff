"""Passes over every dense sample a chunk at a time (memory bounded per worker
whatever the atlas size).

The geometry stage (`geometry.build`), the export's preview maps and its filtered maps reduce
per-sample quantities to per-texel sums. `bincount_continued` adds a chunk to running sums so
that the result equals one `np.bincount` over all samples bit for bit: the running sums enter
the chunk's bincount first, and bincount adds its weights in order. `sample_rows` copies a
chunk of the geometry artifact's (memory-mapped) arrays and gives their pages back, so a pass
over a 10 GB artifact does not leave it in the process' resident set.
"""

from __future__ import annotations

import mmap
from collections.abc import Iterator, Mapping, Sequence

import numpy as np


def bincount_continued(total: np.ndarray, idx: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """total + np.bincount(idx, weights, minlength=len(total)), summed as one bincount over
    every chunk so far would sum it (in sample order); returns a new (n,) float64 array."""
    n = total.shape[0]
    return np.bincount(np.concatenate([np.arange(n, dtype=np.int64), idx]),
                       weights=np.concatenate([total, weights]), minlength=n)


def chunk_ranges(m: int, chunk: int) -> Iterator[tuple[int, int]]:
    """[a, b) of consecutive chunks of at most `chunk` of m rows."""
    for a in range(0, int(m), max(int(chunk), 1)):  # loop over chunks (memory bound)
        yield a, min(a + int(chunk), int(m))


def _mapping(arr: np.ndarray) -> mmap.mmap | None:
    base: object = arr
    while base is not None:  # up the view chain to the np.memmap, if any
        mm = getattr(base, "_mmap", None)
        if isinstance(mm, mmap.mmap):
            return mm
        base = getattr(base, "base", None)
    return None


def release(arr: np.ndarray) -> None:
    """Drop the resident pages of the read-only file mapping behind `arr` (if any) from this
    process: they are clean file pages, read back from the page cache or the disk when touched
    again. Without it a pass over a mapped artifact keeps all of it resident."""
    mm = _mapping(arr)
    if mm is not None and hasattr(mmap, "MADV_DONTNEED"):
        mm.madvise(mmap.MADV_DONTNEED)


def sample_rows(geo: Mapping[str, np.ndarray], names: Sequence[str], a: int, b: int
                ) -> dict[str, np.ndarray]:
    """Rows a..b of the named per-sample arrays, copied; their mapped pages released."""
    out = {}
    for name in names:
        out[name] = np.array(geo[name][a:b])
        release(geo[name])
    return out
