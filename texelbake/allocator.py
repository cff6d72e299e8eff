"""The C allocator's policy in a bake process: freed memory is kept for reuse, not unmapped.

A bake allocates and frees arrays of tens of MB to GB per chunk of texels (R, the BRDF grid,
ray batches, a_vis cube maps). glibc serves every block above M_MMAP_THRESHOLD (at most 32 MiB)
with its own mmap and unmaps it on free, so the next chunk's arrays are fresh pages again: a
page fault and a zeroed page per 4 KiB, every chunk. On the farm's virtual machines that is
worse: freed guest memory is handed back to the host (free page reporting), and touching it
again costs a host fault. Measured on this project's Firecracker VM (2026-11-28,
docs/profile.md "Freed memory kept"): a fresh GB first touched in 4.7 s against 0.24 s for a
reused one; `benchmarks/cpm_cpu.py` on the full cylinder at 32² spent 11.0 s in the kernel
with glibc's defaults and 2.5 s with this policy, the fit 90 -> 81 CPU s, same digests.

`keep_freed_memory()` sets mallopt(M_MMAP_MAX, 0) (large blocks come from the heap) and
mallopt(M_TRIM_THRESHOLD, INT_MAX) (the heap's freed top is kept): a process's resident memory
then stays at its peak instead of falling back after each chunk; the peak itself is bounded as
before (the chunks are, issue 15 item 5). No Python library sets the C allocator's options, so
this is the few lines of ctypes glibc documents (mallopt(3)). It is a no-op off glibc, and
TEXELBAKE_MALLOC=system leaves glibc's defaults.
"""

from __future__ import annotations

import ctypes
import os
import platform

#: mallopt(3) parameters (glibc malloc.h)
M_TRIM_THRESHOLD = -1
M_MMAP_MAX = -4
INT_MAX = 2**31 - 1

_STATE: dict[str, bool] = {}


def keep_freed_memory() -> bool:
    """Apply the policy once per process; returns whether it is in force."""
    if "applied" in _STATE:
        return _STATE["applied"]
    applied = False
    if os.environ.get("TEXELBAKE_MALLOC", "keep").strip().lower() != "system" \
            and platform.system() == "Linux" and platform.libc_ver()[0] == "glibc":
        libc = ctypes.CDLL(None)
        ok_mmap = libc.mallopt(M_MMAP_MAX, 0)
        ok_trim = libc.mallopt(M_TRIM_THRESHOLD, INT_MAX)
        applied = bool(ok_mmap) and bool(ok_trim)
    _STATE["applied"] = applied
    return applied
