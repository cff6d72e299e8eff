"""Texels classed by need against the seed's fit of every texel, on one level's tiles: the
seconds of the cpm stage's `fit_level` (classes and fit), the exact, grouped and lobe texels,
and the held-out SNR and stored points of each class, for `texel_classes="by_need"` with
`lobe_class="validated"` ("lobes"), `"by_need"` alone and `"points"` on the same geometry; the
"points" run also scores the seed's fit on the texels by need groups, and the two later runs
("fit_on_lobe") their fit of the texels the first stored as lobes.

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
from texelbake.cpm.level_by_need import EXACT_SKIP, GROUPED_SKIP, LOBE_SKIP
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
    # every texel of the fitted tiles measured (the bake measures a seeded sample of the
    # level's, most of them in other tiles)
    s = BakeSettings(atlas_resolution=args.atlas, shard_texels=min(16, args.atlas),
                     heldout_texels=0)
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
    grouped_texels: set[int] = set()
    lobe_texels: set[int] = set()
    modes = {"lobes": {"texel_classes": "by_need", "lobe_class": "validated"},
             "by_need": {"texel_classes": "by_need"}, "points": {"texel_classes": "points"}}
    for mode, update in modes.items():  # the three paths, same tiles
        src_m = dataclasses.replace(src, settings=s.model_copy(update=update))
        sec, cpu = 0.0, 0.0
        cls: dict[str, list] = {k: [] for k in ("exact", "grouped", "lobe", "fitted",
                                                "seed_on_grouped", "fit_on_lobe")}
        pts: dict[str, list] = {k: [] for k in cls}
        for tile in tiles:  # loop over tiles
            texels = tile_texels(args.atlas, s.shard_texels, tile, 0)
            cands = level_candidates(src_m, 0, texels, None)
            t, c = time.perf_counter(), time.process_time()
            res = fit_level(src_m, 0, texels, cands)
            sec += time.perf_counter() - t
            cpu += time.process_time() - c  # less sensitive to the other processes' load
            v = res["valid"].astype(bool)
            e = v & (res["skip"] == EXACT_SKIP)
            g = v & (res["skip"] == GROUPED_SKIP)
            lo = v & (res["skip"] == LOBE_SKIP)
            if mode == "by_need":
                grouped_texels |= set(res["texel"][g].tolist())
            lobe_texels |= set(res["texel"][lo].tolist())
            on_g = v & np.isin(res["texel"], list(grouped_texels)) if mode == "points" \
                else np.zeros_like(v)
            on_l = v & np.isin(res["texel"], list(lobe_texels)) if mode != "lobes" \
                else np.zeros_like(v)
            for name, sel in (("exact", e), ("grouped", g), ("lobe", lo),
                              ("fitted", v & ~e & ~g & ~lo), ("seed_on_grouped", on_g),
                              ("fit_on_lobe", on_l)):
                cls[name] += res["snr_ho"][sel].tolist()
                pts[name] += res["c"][sel].tolist()
        out[mode] = {"seconds": sec, "cpu_seconds": cpu} | {
            f"{k}_texels": len(v) for k, v in cls.items()} | {
            f"snr_heldout_{k}": percentiles(np.array(v), SNR_EXACT_DB) for k, v in cls.items()} | {
            f"points_mean_{k}": float(np.mean(v)) if v else None for k, v in pts.items()} | {
            "snr_heldout_all": percentiles(np.array(cls["exact"] + cls["grouped"]
                                                    + cls["lobe"] + cls["fitted"]),
                                           SNR_EXACT_DB)}
        for name in cls:
            a = out[mode][f"snr_heldout_{name}"]
            if not cls[name]:
                continue
            print(f"{args.scene} {args.atlas}^2 L0 {len(tiles)} tiles  {mode:8s} {name:16s} "
                  f"{len(cls[name]):5d} texels, {out[mode][f'points_mean_{name}']:6.1f} points, "
                  f"held-out median {a.get('p50', np.nan):7.2f} p5 {a.get('p5', np.nan):7.2f} "
                  f"min {a.get('min', np.nan):7.2f} dB",
                  flush=True)
        a = out[mode]["snr_heldout_all"]
        print(f"{args.scene} {args.atlas}^2 L0 {mode:8s} {sec:8.1f} s ({cpu:7.1f} CPU s)  "
              f"held-out all: median {a.get('p50', float('nan')):7.2f} "
              f"p5 {a.get('p5', float('nan')):7.2f} dB", flush=True)
    if args.json:
        args.json.write_text(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
