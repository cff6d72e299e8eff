"""Executing shading operations against a small LRU cache of reflectance-image blocks
(seed 002 §5.3: a cache of three images suffices once the operations are sorted), in the
sorted or the naive order, with the block reads, time and resident bytes counted.

Bit-identical results whatever the order: each operation's look-up depends on its own
(image, x, y) only (`store.sample_bilinear` is elementwise), it is written to the
operation's own slot, and the slots are summed into the shading points in generation order
(`accumulate`) — so sorted and naive execution give the same bits, which a test checks.

The loop below runs once per *run* of consecutive operations on one image (a block switch):
in sorted order that is at most once per image; the naive order switches images at almost
every operation, which is exactly the cost the seed's reordering removes.
"""

from __future__ import annotations

import time
from collections import OrderedDict
from dataclasses import dataclass, field

import numpy as np

from texelbake.errors import SettingsError
from texelbake.srf import ops as ops_mod
from texelbake.srf.ops import ShadingOps
from texelbake.srf.store import SrfStore, sample_bilinear

#: the seed's cache: three reflectance images
DEFAULT_CAPACITY = 3
EXECUTORS = ("sorted", "naive")


@dataclass
class CacheStats:
    """block_reads : blocks read from disk; runs : block switches; seconds : wall time of
    the execution; peak_resident_bytes : most bytes of blocks held at once."""

    block_reads: int = 0
    runs: int = 0
    seconds: float = 0.0
    peak_resident_bytes: int = 0
    extras: dict[str, float] = field(default_factory=dict)


class BlockCache:
    """An LRU cache of at most `capacity` decoded blocks of a store."""

    def __init__(self, store: SrfStore, capacity: int = DEFAULT_CAPACITY) -> None:
        if int(capacity) < 1:
            raise SettingsError(f"field 'cache_blocks': at least 1, got {capacity}")
        self.store, self.capacity = store, int(capacity)
        self._blocks: OrderedDict[tuple[int, int], object] = OrderedDict()
        self.stats = CacheStats()
        self._resident = 0

    def get(self, camera: int, light: int):
        key = (int(camera), int(light))
        blk = self._blocks.get(key)
        if blk is not None:
            self._blocks.move_to_end(key)
            return blk
        while len(self._blocks) >= self.capacity:
            _, old = self._blocks.popitem(last=False)
            self._resident -= old.nbytes  # type: ignore[attr-defined]
        blk = self.store.read_block(*key)
        self.stats.block_reads += 1
        self._blocks[key] = blk
        self._resident += blk.nbytes
        self.stats.peak_resident_bytes = max(self.stats.peak_resident_bytes, self._resident)
        return blk


def execute(store: SrfStore, ops: ShadingOps, order: np.ndarray,
            capacity: int = DEFAULT_CAPACITY) -> tuple[np.ndarray, CacheStats]:
    """Look up every operation's RGB reflectance in `order` (a permutation of the
    operations). returns (values (n, 3) float64 per operation, stats)"""
    t0 = time.perf_counter()
    cache = BlockCache(store, capacity)
    n = len(ops)
    values = np.zeros((n, 3))
    if n:
        order = np.asarray(order, dtype=np.int64)
        key = ops.camera[order] * store.n_lights + ops.light[order]
        cuts = np.flatnonzero(key[1:] != key[:-1]) + 1
        starts = np.concatenate([[0], cuts])
        stops = np.concatenate([cuts, [n]])
        cache.stats.runs = int(starts.size)
        w, h = store.width, store.height
        for a, b in zip(starts.tolist(), stops.tolist(), strict=True):  # one per block switch
            idx = order[a:b]
            blk = cache.get(ops.camera[idx[0]], ops.light[idx[0]])
            values[idx] = sample_bilinear(blk, ops.x[idx], ops.y[idx], w, h)  # type: ignore[arg-type]
    cache.stats.seconds = time.perf_counter() - t0
    return values, cache.stats


def accumulate(ops: ShadingOps, values: np.ndarray, n_targets: int) -> np.ndarray:
    """Σ over each shading point's operations of weight · value, summed in generation order.
    returns (n_targets, 3) float64"""
    out = np.zeros((int(n_targets), 3))
    np.add.at(out, ops.target, values * ops.weight)
    return out


def shade(store: SrfStore, ops: ShadingOps, n_targets: int, executor: str = "sorted",
          capacity: int = DEFAULT_CAPACITY) -> tuple[np.ndarray, CacheStats]:
    """Colours of n_targets shading points from their operations, executed in the
    `executor`'s order ("sorted": `ops.sorted_order`, the sort's time included; "naive":
    generation order). returns ((n_targets, 3) float64, stats)"""
    if executor not in EXECUTORS:
        raise SettingsError(f"field 'executor': expected one of {EXECUTORS}, got "
                            f"{executor!r}")
    t0 = time.perf_counter()
    order = ops_mod.sorted_order(ops) if executor == "sorted" else ops_mod.naive_order(ops)
    values, stats = execute(store, ops, order, capacity)
    out = accumulate(ops, values, n_targets)
    stats.seconds = time.perf_counter() - t0
    return out, stats

