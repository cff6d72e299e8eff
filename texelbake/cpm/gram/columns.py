"""The columns of one texel's F = diag(1/a_vis) R read a block at a time (seed 000 §4.1's
n_batch batches: memory bounded whatever the texel's width).

`gram.fit.fit_split` only ever reads blocks of at most n_batch columns of a wide texel and
their sums; `Columns` gives it those blocks from an array it holds or from a function that
builds them (the batched level fit), with the same arithmetic either way.
"""

from __future__ import annotations

import numpy as np


class Columns:
    """F (ch, m, d) of a texel wider than n_batch columns, read a block of columns at a time
    (`fit_split`'s only access): `block(cols)` gives F[:, cols] (ch, len(cols), d). The CPM
    stage builds a wide texel's blocks from its samples when asked (a 6,162-sample
    texel's F was 0.6 GB); an array is wrapped with `of_array`, so a wide texel's arithmetic
    is the same whether its F is held or built. Sums over columns go by blocks of n_batch in
    order; the last block asked for is kept (the channels of one step read it in turn)."""

    def __init__(self, block, shape: tuple[int, int, int], n_batch: int,
                 total: np.ndarray | None = None) -> None:
        self._block = block
        self.shape = tuple(int(x) for x in shape)
        self.n_batch = int(n_batch)
        self._last: tuple[bytes, np.ndarray] | None = None
        self._total = total

    @classmethod
    def of_array(cls, F: np.ndarray, n_batch: int) -> Columns:
        return cls(lambda cols: F[:, cols], F.shape, n_batch)

    def take(self, cols: np.ndarray) -> np.ndarray:
        """F[:, cols] (ch, len(cols), d)."""
        cols = np.asarray(cols, dtype=np.int64)
        key = cols.tobytes()
        if self._last is None or self._last[0] != key:
            self._last = (key, self._block(cols))
        return self._last[1]

    def __getitem__(self, idx: tuple) -> np.ndarray:
        c, cols = idx  # F[c, cols]: a channel (or slice of channels) of a block
        return self.take(cols)[c]

    def sum_over(self, cols: np.ndarray) -> np.ndarray:
        """Σ over `cols` of F[:, col], (ch, d): blocks of n_batch summed in order."""
        acc = None
        for b0 in range(0, cols.size, self.n_batch):  # loop over column blocks
            part = self.take(cols[b0:b0 + self.n_batch]).sum(axis=1)
            acc = part if acc is None else acc + part
        return acc if acc is not None else np.zeros(self.shape[::2])

    def sum(self, axis: int) -> np.ndarray:
        """F.sum(axis=1) (ch, d) over every column (as the fit's assembly reads an array's), kept."""
        if axis != 1:
            raise ValueError("Columns sums over its columns only (axis=1)")
        if self._total is None:
            self._total = self.sum_over(np.arange(self.shape[1], dtype=np.int64))
        return self._total


class SelectionRows:
    """The selection matrix S of a wide texel, a block at a time: the luminance
    Σ_c lw_c F_c, or one channel F_c, of the columns asked for."""

    def __init__(self, F: Columns, lw: np.ndarray | None, chan: int = 0) -> None:
        self.F, self.lw, self.chan = F, lw, chan

    def __getitem__(self, cand: np.ndarray) -> np.ndarray:
        block = self.F.take(cand)
        if self.lw is None:
            return block[self.chan]
        return np.tensordot(self.lw, block, axes=(0, 0))

__all__ = ["Columns", "SelectionRows"]
