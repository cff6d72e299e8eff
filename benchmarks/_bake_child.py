"""One timed bake for benchmarks/bake.py, run in its own process with PYTHONPATH pointing at the
texelbake tree under test (this one, or an older commit's worktree).

    python benchmarks/_bake_child.py SCENE.usda OUT SETTINGS_JSON TIMINGS.jsonl JOBS [--json PATH]

(--json: the bake's total seconds also written as JSON to PATH, as the parent reads it.)

Wraps the cpm stage's `fit_level` so that every call appends one JSON line to TIMINGS.jsonl:
level, texels fitted (valid), wall and CPU seconds of the call, and the held-out SNR of each
valid texel; since the tile shards sum their samples for the top levels (`top_level_sums`),
those calls too, as their level's work with no texels. The wrapper is installed at import time of this module, so the spawned worker
processes of `bake(jobs > 1)` (multiprocessing "spawn" re-imports the main module) time their
calls too. Works with the package layout of c15cea2 (`texelbake.stages.fit_level`) and of
today (`texelbake.stages.cpm.fit_level`).
"""

from __future__ import annotations

import json
import os
import sys
import time

import numpy as np


def _install() -> None:
    path = os.environ.get("TEXELBAKE_FIT_TIMINGS")
    if not path:
        return
    try:
        import texelbake.stages.cpm as mod  # today's layout
    except ImportError:
        import texelbake.stages as mod  # c15cea2: one stages module
    inner = mod.fit_level

    def timed(src, level, texels, candidates, *rest, **kw):
        w0, c0 = time.perf_counter(), time.process_time()
        out = inner(src, level, texels, candidates, *rest, **kw)
        wall, cpu = time.perf_counter() - w0, time.process_time() - c0
        valid = np.asarray(out["valid"], bool)
        rec = {"level": int(level), "texels": int(valid.sum()), "wall": wall, "cpu": cpu,
               "pid": os.getpid(), "snr_ho": [float(x) for x in np.asarray(out["snr_ho"])[valid]]}
        with open(path, "a") as f:
            f.write(json.dumps(rec) + "\n")
        return out

    mod.fit_level = timed
    if hasattr(mod, "top_level_sums"):  # a top level's sums, made by the tile shards (issue 15)
        sums = mod.top_level_sums

        def timed_sums(src, level, texels, samples):
            w0, c0 = time.perf_counter(), time.process_time()
            out = sums(src, level, texels, samples)
            rec = {"level": int(level), "texels": 0, "wall": time.perf_counter() - w0,
                   "cpu": time.process_time() - c0, "pid": os.getpid(), "snr_ho": []}
            with open(path, "a") as f:
                f.write(json.dumps(rec) + "\n")
            return out

        mod.top_level_sums = timed_sums


_install()

if __name__ == "__main__":
    from pathlib import Path

    from schemas.settings import BakeSettings
    try:
        from texelbake.pipeline.run import bake  # today's layout
    except ImportError:
        from texelbake.pipeline import bake  # 982477e: one pipeline module

    scene, out, settings_json, timings, jobs = sys.argv[1:6]
    summary = sys.argv[7] if len(sys.argv) > 7 and sys.argv[6] == "--json" else None
    os.environ["TEXELBAKE_FIT_TIMINGS"] = timings
    _install()  # this process runs the single-shard stages (cpm_top) itself
    fields = json.loads(settings_json)
    known = set(BakeSettings.model_fields)
    settings = BakeSettings(**{k: v for k, v in fields.items() if k in known})
    t0 = time.perf_counter()
    bake(Path(scene), Path(out), settings, progress=False, jobs=int(jobs))
    import resource

    # peak resident set of this process and of the largest worker it reaped (KiB on Linux)
    peak = max(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss,
               resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)
    result = json.dumps({"total_seconds": time.perf_counter() - t0,
                         "peak_rss_mib": peak / 1024})
    print(result)
    if summary is not None:
        Path(summary).write_text(result)
