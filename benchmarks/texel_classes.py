"""Texels classed by need against the seed's fit of every texel, on one level's tiles: the
seconds of the cpm stage's `fit_level` (classes and fit), the exact texels, and the held-out
SNR of each class, for `texel_classes="by_need"` and `"points"` on the same geometry.

    python benchmarks/texel_classes.py --scene cylinder --size full --atlas 64 --tiles 4 \
        --json benchmarks/results/texel_classes_cylinder_64.json

`--tiles k` fits every k-th tile of the level (all tiles with 1): the same tiles for both.
Wall and CPU seconds of the fit calls are printed: on a shared machine the CPU ratio is the
figure to trust."""

from __future__ import annotations

import argparse
import dataclasses
import json
import tempfile
import time
from pathlib import Path

import numpy as np

from schemas.settings import BakeSettings
from texelbake import stages
from texelbake.cpm.assemble import SNR_EXACT_DB, percentiles
from texelbake.cpm.level import level_candidates, tile_texels
from texelbake.cpm.level_by_need import EXACT_SKIP
from texelbake.stages.cpm import fit_level
from texelbake.testscenes import write_scene


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="cylinder")
    ap.add_argument("--size", default="full", choices=["small", "full"])
    ap.add_argument("--atlas", type=int, default=64)
    ap.add_argument("--tiles", type=int, default=1, help="fit every k-th tile")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    work = Path(tempfile.mkdtemp(prefix="texel-classes-"))
    scene = Path(args.scene) if Path(args.scene).is_file() else \
        write_scene(args.scene, work / f"{args.scene}.usda", args.size)
    s = BakeSettings(atlas_resolution=args.atlas, shard_texels=min(16, args.atlas))
    ctx = stages.StageContext.create(work / "work", scene, s)
    stages.run_ingest(ctx, 0)
    t0 = time.perf_counter()
    stages.run_geometry(ctx, 0)
    geo_s = time.perf_counter() - t0
    src = ctx.fit_inputs()
    n_tiles = (args.atlas // s.shard_texels) ** 2
    tiles = list(range(0, n_tiles, args.tiles))
    out: dict = {"scene": str(args.scene), "size": args.size, "atlas": args.atlas,
                 "tiles": tiles, "geometry_seconds": geo_s}
    for mode in ("points", "by_need"):  # the two paths, same tiles
        src_m = dataclasses.replace(src, settings=s.model_copy(update={"texel_classes": mode}))
        sec, cpu, ex, ho_ex, ho_pt = 0.0, 0.0, 0, [], []
        for tile in tiles:  # loop over tiles
            texels = tile_texels(args.atlas, s.shard_texels, tile, 0)
            cands = level_candidates(src_m, 0, texels, None)
            t, c = time.perf_counter(), time.process_time()
            res = fit_level(src_m, 0, texels, cands)
            sec += time.perf_counter() - t
            cpu += time.process_time() - c  # less sensitive to the other processes' load
            v = res["valid"].astype(bool)
            e = v & (res["skip"] == EXACT_SKIP)
            ex += int(e.sum())
            ho_ex += res["snr_ho"][e].tolist()
            ho_pt += res["snr_ho"][v & ~e].tolist()
        out[mode] = {"seconds": sec, "cpu_seconds": cpu, "exact_texels": ex, "fitted_texels": len(ho_pt),
                     "snr_heldout_exact": percentiles(np.array(ho_ex), SNR_EXACT_DB),
                     "snr_heldout_fitted": percentiles(np.array(ho_pt), SNR_EXACT_DB),
                     "snr_heldout_all": percentiles(np.array(ho_ex + ho_pt), SNR_EXACT_DB)}
        a = out[mode]["snr_heldout_all"]
        print(f"{args.scene} {args.atlas}^2 L0 {len(tiles)} tiles  {mode:8s} {sec:8.1f} s "
              f"({cpu:7.1f} CPU s)  exact {ex:5d}  fitted {len(ho_pt):5d}  held-out all: median "
              f"{a.get('p50', float('nan')):7.2f} p5 {a.get('p5', float('nan')):7.2f} dB  "
              f"exact min {min(ho_ex) if ho_ex else float('nan'):7.2f} dB", flush=True)
    if args.json:
        args.json.write_text(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
