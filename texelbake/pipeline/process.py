"""How a bake process is set up, once: the C allocator keeps freed memory, BLAS runs one thread.

`setup_bake_process()` is called by everything that runs bake stages (`pipeline.run.run_shard`,
`pipeline.run.finalize`, the local `pipeline.run.bake`, and so every Celery task and pool process).

Freed memory kept (`keep_freed_memory`). A bake allocates and frees arrays of tens of MB to GB
per chunk of texels (R, the BRDF grid, ray batches, a_vis blocks). glibc serves every block
above M_MMAP_THRESHOLD (at most 32 MiB) with its own mmap and unmaps it on free, so the next
chunk's arrays are fresh pages: a fault and a zeroed page per 4 KiB, every chunk. On the farm's
virtual machines freed guest memory also goes back to the host (free page reporting), and a
page touched again costs a host fault: a fresh GB took 4.7 s to first touch against 0.24 s for a
reused one (docs/decisions.md). mallopt(M_MMAP_MAX, 0) serves large blocks from the
heap and mallopt(M_TRIM_THRESHOLD, INT_MAX) keeps its freed top: a process's resident memory
stays at its peak between chunks; the peak is bounded as before. No Python
library sets the C allocator's options, so these are the few ctypes lines mallopt(3) documents;
a no-op off glibc. TEXELBAKE_MALLOC=system leaves glibc's defaults.

Freed memory given back where a process only waits (`release_freed_memory`). The local
bake's own process runs the ingest and geometry stages, then waits while its shard processes
run the a_vis and CPM stages: the heap it kept from the geometry stage (~0.3 GB on the Teapot
at 512², beside ~0.3 GB of imports) stayed resident beside theirs. malloc_trim(0) returns
the heap's free pages before the shards start, so a bake's peak is its shard processes' and
not theirs plus the waiting one's (the bake's summed PSS 0.11–0.13 GB lower on the full
cylinder at LOD1's 128² and 512², docs/decisions.md); the export touches fresh pages again
(about a second per 0.3 GB where first touch is slow).

One BLAS thread (`blas_threads`, threadpoolctl). The BLAS products of a bake are small (a
texel's Grams, a_vis blocks) or overlap with Embree's own ray threads, and shards run as one
process per core: OpenBLAS's default of one thread per core then puts two spinning threads per
core beside Embree's and the other shard's. The full cylinder's a_vis stage at 32² on two
processes, runs alternating: 34.2 / 34.9 s with OpenBLAS's default, 23.8 / 22.7 s with one
thread; its 16 tiles in one process 28.6 -> 26.2 s wall and 54.8 -> 35.9 CPU s, bit-identical
(whole bakes on the VM it was measured on varied 1.5x run to run, so they are not quoted). TEXELBAKE_BLAS_THREADS=N sets another count
(0 leaves the library's default). torch's own pool is set to one thread by the CPM stage.
"""

from __future__ import annotations

import ctypes
import functools
import os
import platform

#: mallopt(3) parameters (glibc malloc.h)
M_TRIM_THRESHOLD = -1
M_MMAP_MAX = -4
INT_MAX = 2**31 - 1


@functools.cache
def keep_freed_memory() -> bool:
    """The allocator policy, applied once per process; returns whether it is in force."""
    if os.environ.get("TEXELBAKE_MALLOC", "keep").strip().lower() == "system" \
            or platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return False
    libc = ctypes.CDLL(None)
    ok_mmap = libc.mallopt(M_MMAP_MAX, 0)
    ok_trim = libc.mallopt(M_TRIM_THRESHOLD, INT_MAX)
    return bool(ok_mmap) and bool(ok_trim)


def release_freed_memory() -> bool:
    """Give the heap's free pages back to the system (glibc's malloc_trim(0)) in a process
    that keeps freed memory (`keep_freed_memory`) and is about to wait while others work;
    returns whether any memory was released (False off glibc or under
    TEXELBAKE_MALLOC=system, where glibc's own trimming is in force)."""
    if not keep_freed_memory():
        return False
    return bool(ctypes.CDLL(None).malloc_trim(0))


@functools.cache
def blas_threads() -> int:
    """Limit the BLAS thread pools (OpenBLAS, MKL, BLIS: threadpoolctl finds what is loaded) to
    TEXELBAKE_BLAS_THREADS (default 1), once per process; returns the limit (0: untouched)."""
    raw = os.environ.get("TEXELBAKE_BLAS_THREADS", "1").strip()
    try:
        n = int(raw)
    except ValueError:
        from texelbake.errors import SettingsError

        raise SettingsError(f"TEXELBAKE_BLAS_THREADS must be an integer, got {raw!r}") from None
    if n > 0:
        import numpy  # noqa: F401  (its BLAS must be loaded for threadpoolctl to see it)
        from threadpoolctl import threadpool_limits

        threadpool_limits(limits=n, user_api="blas")
    return max(n, 0)


def setup_bake_process() -> None:
    """Both settings above, once per process."""
    keep_freed_memory()
    blas_threads()
