"""A bake process's setup (`texelbake.pipeline.process`): a large array freed and made again reuses the
process's memory instead of faulting in fresh pages, and BLAS runs one thread. Each case runs
in a fresh interpreter (the setup is process-wide and applied once)."""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys

import pytest

pytestmark = pytest.mark.skipif(
    platform.system() != "Linux" or platform.libc_ver()[0] != "glibc",
    reason="mallopt is glibc's",
)

#: one 256 MiB array made, freed and made again; the minor page faults of the second making.
#: Fresh pages fault once per page (4 KiB: 65,536; 2 MiB transparent huge pages: 128); reused
#: heap memory faults not at all.
SNIPPET = """
import json, resource, sys
import numpy as np
from texelbake.pipeline.process import keep_freed_memory
applied = keep_freed_memory()
n = 256 * 2**20 // 8
a = np.ones(n); del a
f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
b = np.ones(n)
f1 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
json.dump({"applied": applied, "faults": f1 - f0, "sum": float(b.sum())}, sys.stdout)
"""


def _run(snippet: str, check: bool = True, **env_values: str) -> subprocess.CompletedProcess:
    """`snippet` in a fresh interpreter with TEXELBAKE_MALLOC and TEXELBAKE_BLAS_THREADS unset
    unless given."""
    env = {k: v for k, v in os.environ.items()
           if k not in ("TEXELBAKE_MALLOC", "TEXELBAKE_BLAS_THREADS")}
    env.update(env_values)
    return subprocess.run([sys.executable, "-c", snippet], env=env, capture_output=True,
                          text=True, check=check, timeout=120)


def test_freed_memory_is_reused():
    kept = json.loads(_run(SNIPPET).stdout)
    assert kept["applied"] is True
    assert kept["sum"] == 256 * 2**20 // 8
    # a few faults at most (the allocator's own bookkeeping), far below one per huge page
    assert kept["faults"] < 32, kept


def test_system_policy_faults_fresh_pages():
    """The measurement can tell: with glibc's defaults the second array is a fresh mmap."""
    system = json.loads(_run(SNIPPET, TEXELBAKE_MALLOC="system").stdout)
    assert system["applied"] is False
    assert system["faults"] >= 100, system


BLAS_SNIPPET = """
import json, sys
from threadpoolctl import threadpool_info
from texelbake.pipeline.process import setup_bake_process
setup_bake_process()
json.dump([i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"], sys.stdout)
"""


def test_one_blas_thread_in_a_bake_process():
    pools = json.loads(_run(BLAS_SNIPPET).stdout)
    assert pools and all(n == 1 for n in pools), pools


def test_blas_threads_setting_must_be_an_integer():
    out = _run(BLAS_SNIPPET, check=False, TEXELBAKE_BLAS_THREADS="two")
    assert out.returncode != 0
    assert "TEXELBAKE_BLAS_THREADS must be an integer, got 'two'" in out.stderr


#: 256 MiB made and freed under the keep policy, then given back: the process's resident
#: anonymous memory (KiB, /proc/self/status) after the free and after the release
RELEASE_SNIPPET = """
import json, sys
import numpy as np
from texelbake.pipeline.process import keep_freed_memory, release_freed_memory
def anon():
    for line in open("/proc/self/status"):
        if line.startswith("RssAnon:"):
            return int(line.split()[1])
keep_freed_memory()
a = np.ones(256 * 2**20 // 8); del a
kept = anon()
released = release_freed_memory()
json.dump({"kept": kept, "after": anon(), "released": released}, sys.stdout)
"""


def test_a_waiting_process_gives_its_freed_memory_back():
    out = json.loads(_run(RELEASE_SNIPPET).stdout)
    assert out["released"] is True
    # the freed 256 MiB stayed resident under the keep policy, and at least 200 MiB of it left
    # with the release (the rest: the interpreter's own heap, unchanged)
    assert out["kept"] - out["after"] >= 200 * 1024, out


def test_nothing_is_released_under_the_system_policy():
    out = json.loads(_run(RELEASE_SNIPPET, TEXELBAKE_MALLOC="system").stdout)
    assert out["released"] is False
