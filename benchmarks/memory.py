"""Peak memory per process of a large bake without running all of it (issue 15, item 5): the
geometry stage, then one a_vis and one CPM shard of the tile holding the most samples, each
in a fresh process, with its peak resident set (`ru_maxrss`) and seconds.

    python benchmarks/memory.py --scene cylinder --atlas 512 --json benchmarks/results/memory_512.json

A full 512^2 bake is hours on this machine; its per-process memory is decided by these tasks
(the geometry stage holds every sample; a shard reads the geometry artifact, mapped since
2026-11-27, and fits its tile). Not measured: the top stages (cpm_top, avis_top), which need
every tile first. With `--workdir` kept between runs the geometry is reused (its peak is then
the one recorded in the JSON of the run that built it); a shard's artifacts are removed first,
so it is always fitted. `--set samples_per_texel=4096` crowds every texel (thousands of
candidates each: one texel's F, d x m, is what the fit then holds).
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

_CHILD = """
import json, sys, time
from pathlib import Path
from schemas.settings import BakeSettings
from texelbake.pipeline.run import run_shard
work, usd, settings, stage, shard = sys.argv[1:6]
t = time.perf_counter()
settings = BakeSettings.model_validate_json(settings)
if stage == "filtered":  # the export's filtered maps over every sample (issue 21)
    from texelbake.stages import StageContext
    from texelbake.stages.filtered import run_filtered
    key = run_filtered(StageContext.create(Path(work), Path(usd), settings), 0)
else:
    key = run_shard(Path(work), Path(usd), settings, stage, int(shard))
hwm = next(x for x in open("/proc/self/status") if x.startswith("VmHWM"))
print(json.dumps({"seconds": time.perf_counter() - t, "key": key,
                  "peak_rss_mib": int(hwm.split()[1]) / 1024}))
"""


def run_task(work: Path, usd: Path, settings, stage: str, shard: int) -> dict:  # noqa: ANN001
    out = subprocess.run([sys.executable, "-c", _CHILD, str(work), str(usd),
                          settings.model_dump_json(), stage, str(shard)],
                         check=True, capture_output=True, text=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def fullest_tile(work: Path, geometry_key: str, atlas: int, side: int) -> tuple[int, int]:
    from texelbake.cpm.level import texel_ids
    from texelbake.io.store import ArtifactStore

    geo = ArtifactStore(work / "artifacts").read_arrays(
        geometry_key, lambda n: n in ("sample_row", "sample_col"), mmap=True)
    level = side.bit_length() - 1  # a tile of side^2 finest texels is one texel of this level
    counts = np.bincount(texel_ids(geo, atlas, level), minlength=(atlas // side) ** 2)
    return int(np.argmax(counts)), int(counts.max())


def main() -> None:
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from bake import scene_file

    from schemas.settings import BakeSettings
    from texelbake.stages import StageContext

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="cylinder",
                    help="a generated scene's name, or the path of a USD file")
    ap.add_argument("--atlas", type=int, default=512)
    ap.add_argument("--workdir", type=Path, default=None)
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--filtered", action="store_true",
                    help="also the export's filtered maps (every sample, AO rays: not a shard)")
    ap.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                    help="a BakeSettings field (JSON value), e.g. samples_per_texel=4096")
    args = ap.parse_args()
    base: dict = {"atlas_resolution": args.atlas}
    for item in args.set:
        key, _, value = item.partition("=")
        try:
            base[key] = json.loads(value)
        except json.JSONDecodeError:
            base[key] = value
    work = args.workdir or Path(tempfile.mkdtemp(prefix="tb-memory-"))
    work.mkdir(parents=True, exist_ok=True)
    usd = scene_file(args.scene, "full", work)
    settings = BakeSettings(**base)
    ctx = StageContext.create(work, usd, settings)
    rows = []
    built = not ctx.store.exists(ctx.geometry_key())
    r = run_task(work, usd, settings, "geometry", 0)
    rows.append({"task": "geometry", "shard": 0, **r, "reused": not built})
    tile, samples = fullest_tile(work, ctx.geometry_key(), args.atlas, settings.shard_texels)
    for stage in ("avis", "cpm"):
        for p in (work / "artifacts").glob(f"*/{stage}-*/*tile{tile:05d}-*"):
            p.unlink()
        rows.append({"task": stage, "shard": tile, **run_task(work, usd, settings, stage, tile)})
    if args.filtered:
        for p in (work / "artifacts").glob("*/filtered-*/*.npz"):
            p.unlink()
        rows.append({"task": "filtered", "shard": 0,
                     **run_task(work, usd, settings, "filtered", 0)})
    geo_bytes = ctx.store.path(ctx.geometry_key()).stat().st_size
    print(f"{usd.name}, atlas {args.atlas}^2, shard_texels {settings.shard_texels}: "
          f"{geo_bytes / 2**30:.2f} GiB geometry artifact; fullest tile {tile} "
          f"({samples} samples)")
    print(f"  {'task':10s} {'shard':>6s} {'seconds':>8s} {'peak RSS MiB':>13s}")
    for row in rows:
        note = " (reused: its peak is the run that built it)" if row.get("reused") else ""
        print(f"  {row['task']:10s} {row['shard']:6d} {row['seconds']:8.1f} "
              f"{row['peak_rss_mib']:13.0f}{note}")
    if args.json:
        args.json.write_text(json.dumps({
            "scene": args.scene, "atlas": args.atlas, "set": args.set,
            "geometry_bytes": geo_bytes,
            "fullest_tile": tile, "tile_samples": samples, "tasks": rows,
            "max_rss_self_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
            "when": time.strftime("%Y-%m-%d %H:%M:%S")}, indent=2) + "\n")
        print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
