"""Seconds of the export stage alone, re-run on a finished bake's stored stages, with a digest
of the bundle it writes (equal digests: byte-identical output), so that a change to the export
is timed and checked without baking again.

    texelbake bake cyl.usda -o OUT -j 2 --workdir WORK --set atlas_mode=lod1 --set atlas_cap=128
    python benchmarks/export_time.py OUT/report.json WORK cyl.usda [--repeat 2] \
        [--json benchmarks/results/export_time.json]

The settings come from the bake's report.json (so the stored artifacts' keys match); each run
writes a fresh bundle into `--out` (emptied first; the source referenced, not copied, so the
bundle names the source relative to that folder: compare digests of one `--out`) and prints
its wall and CPU seconds (this process: the export's threads included) and the sha256 of every
file of the bundle, names and bytes, as a table and, with `--json`, as JSON. `TEXELBAKE_COMPRESS_THREADS` sets the compression's
threads as in a bake.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import tempfile
import time
from pathlib import Path

from schemas.settings import BakeSettings
from texelbake import stages
from texelbake.stages.export import export_to


def bundle_digest(folder: Path) -> str:
    """sha256 over every file under `folder` (its relative path, then its bytes), in path
    order."""
    h = hashlib.sha256()
    for p in sorted(folder.rglob("*")):  # a loop over the bundle's files
        if p.is_file():
            h.update(str(p.relative_to(folder)).encode())
            h.update(p.read_bytes())
    return h.hexdigest()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("report", type=Path, help="the bake's report.json")
    ap.add_argument("workdir", type=Path, help="the bake's --workdir")
    ap.add_argument("asset", type=Path, help="the baked source")
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--out", type=Path, default=Path(tempfile.gettempdir()) / "export-time")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    settings = BakeSettings(**json.loads(args.report.read_text())["settings"])
    ctx = stages.StageContext.create(args.workdir, args.asset, settings)
    runs = []
    print(f"{'run':>3} {'wall s':>8} {'CPU s':>8}  bundle sha256")
    for i in range(args.repeat):  # a loop over repeats
        shutil.rmtree(args.out, ignore_errors=True)
        wall, cpu = time.perf_counter(), time.process_time()
        export_to(ctx, args.out, source="reference")
        wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
        runs.append({"wall_seconds": wall, "cpu_seconds": cpu,
                     "bundle_sha256": bundle_digest(args.out)})
        print(f"{i:>3} {wall:>8.2f} {cpu:>8.2f}  {runs[-1]['bundle_sha256'][:16]}")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({
            "report": str(args.report), "asset": str(args.asset),
            "atlas": settings.atlas_resolution, "load": os.getloadavg()[0],
            "compress_threads": os.environ.get("TEXELBAKE_COMPRESS_THREADS", ""),
            "runs": runs}, indent=2) + "\n")
        print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
