"""A farm of N workers draining the bake's shards, simulated (`simulate_farm`): what the cost
model's per-shard seconds and the shared store's bandwidth give for a farm of any size
(`benchmarks/farm.py` checks it against real runs)."""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np


@dataclass
class FarmRun:
    """A simulated farm run (`simulate_farm`): seconds from the first shard's start to the
    last one's end, and each part."""

    seconds: float
    workers: int
    shards: int
    tile_seconds: float  # the sharded part (all tiles done)
    serial_seconds: float  # the single shard after the tiles (cpm_top), with its reads
    store_busy_seconds: float  # time the shared store spent transferring
    worker_busy_fraction: float  # compute seconds / (workers x tile_seconds)

    def to_dict(self) -> dict:
        return asdict(self)


def simulate_farm(
    durations: np.ndarray,
    read_bytes: np.ndarray,
    write_bytes: np.ndarray,
    workers: int,
    *,
    bandwidth: float,
    overhead: float = 0.0,
    startup_bytes: float = 0.0,
    serial_seconds: float = 0.0,
    serial_read_bytes: float = 0.0,
    cores: int | None = None,
) -> FarmRun:
    """A discrete-event simulation of `workers` processes draining a queue of shards: each worker takes the next shard (FIFO, prefetch 1), pays the broker/ledger
    `overhead`, reads its inputs from the shared artifact store, computes for its duration and
    writes its outputs; the store is one FIFO server of `bandwidth` bytes/s shared by all
    workers (a network filesystem), so transfers queue when many workers read or write at once.
    A worker's first shard also reads `startup_bytes` (the geometry arrays, cached per process
    after that). After the last tile, one worker runs the serial shard (`serial_seconds`, after
    reading `serial_read_bytes`). With `cores` < workers (one machine oversubscribed) every
    duration is stretched by workers / cores.

    durations, read_bytes, write_bytes : (S,) per shard, in queue order
    returns FarmRun
    """
    import heapq

    dur = np.asarray(durations, dtype=np.float64)
    rb = np.asarray(read_bytes, dtype=np.float64)
    wb = np.asarray(write_bytes, dtype=np.float64)
    n = max(int(workers), 1)
    stretch = max(1.0, n / cores) if cores else 1.0
    heap: list[tuple[float, int, int, int]] = [(0.0, 0, w, -1) for w in range(n)]
    heapq.heapify(heap)
    nxt, store_free, store_busy, compute, end = 0, 0.0, 0.0, 0.0, 0.0
    started = np.zeros(n, dtype=bool)
    READY, READ, WRITE = 0, 1, 2
    while heap:  # loop over events (3 per shard): O(S log n)
        t, kind, w, i = heapq.heappop(heap)
        if kind == READY:
            if nxt < dur.size:
                heapq.heappush(heap, (t + overhead, READ, w, nxt))
                nxt += 1
            continue
        if kind == READ:
            nbytes = rb[i] + (0.0 if started[w] else startup_bytes)
            started[w] = True
            start = max(t, store_free)
            store_free = start + nbytes / bandwidth
            store_busy += nbytes / bandwidth
            compute += dur[i] * stretch
            heapq.heappush(heap, (store_free + dur[i] * stretch, WRITE, w, i))
            continue
        start = max(t, store_free)  # WRITE
        store_free = start + wb[i] / bandwidth
        store_busy += wb[i] / bandwidth
        end = max(end, store_free)
        heapq.heappush(heap, (store_free, READY, w, -1))
    serial = serial_read_bytes / bandwidth + serial_seconds
    return FarmRun(seconds=end + serial, workers=n, shards=int(dur.size), tile_seconds=end,
                   serial_seconds=serial, store_busy_seconds=store_busy + serial_read_bytes
                   / bandwidth, worker_busy_fraction=compute / max(n * end, 1e-12))
