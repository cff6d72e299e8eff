"""A pass over a level's chunks on a few threads, reduced in chunk order (the a_vis export's
compression, `texelbake.cpm.avis.compress`): the same float sums as one thread, whatever the
thread count."""

from __future__ import annotations

import os
from collections import deque
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from typing import TypeVar

from texelbake.errors import SettingsError

T = TypeVar("T")


def compress_threads() -> int:
    """Threads of a pass over a level's chunks: TEXELBAKE_COMPRESS_THREADS, else the cores this
    process may run on, at most 4. The export runs after the bake's shard processes are gone,
    and numpy releases the GIL in the array operations that take a chunk's time."""
    raw = os.environ.get("TEXELBAKE_COMPRESS_THREADS", "").strip()
    if raw:
        try:
            n = int(raw)
        except ValueError:
            raise SettingsError(f"TEXELBAKE_COMPRESS_THREADS must be an integer, got {raw!r}"
                                ) from None
        if n < 1:
            raise SettingsError(f"TEXELBAKE_COMPRESS_THREADS must be at least 1, got {n}")
        return n
    return max(1, min(4, len(os.sched_getaffinity(0))))


def in_order(fn: Callable[[int], T], n: int) -> Iterator[T]:
    """fn(0), ..., fn(n - 1) in that order, computed on up to `compress_threads()` threads with
    at most two results per thread waiting: a pass's reduction stays in chunk order (the same
    float sums as one thread) and its memory a few chunks'."""
    k = min(compress_threads(), n)
    if k <= 1:
        yield from map(fn, range(n))
        return
    with ThreadPoolExecutor(max_workers=k) as ex:
        pending: deque[Future[T]] = deque()
        for i in range(n):  # a loop over chunks, each vectorized
            pending.append(ex.submit(fn, i))
            if len(pending) >= 2 * k:
                yield pending.popleft().result()
        while pending:
            yield pending.popleft().result()
