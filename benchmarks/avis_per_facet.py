"""a_vis rays from at most k samples per texel and M_org triangle (`avis_samples_per_facet`)
against every dense sample's rays (k = 0, the seed's), on the finest level of a seeded sample of
tiles: seconds, rays, and each ray texel's uncompressed cube maps against the dense ones
(relative L2 error over the 6 res^2 directions, median / p95 / max over texels), error beside
time.

    python benchmarks/avis_per_facet.py --scene cylinder --size full --atlas 128 --k 0,2,4,8

The geometry stage is built once per (scene, atlas) in --workdir (kept between runs).
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np

from schemas.settings import BakeSettings
from texelbake.cpm import avis as avis_mod
from texelbake.cpm.level import samples_in
from texelbake.pipeline.run import run_shard
from texelbake.stages.context import StageContext
from texelbake.testscenes import write_scene
from texelbake.tol import TOL


def scene_file(name: str, size: str, work: Path) -> Path:
    path = Path(name)
    if path.suffix.lower() in (".usd", ".usda", ".usdc", ".usdz"):
        return path.resolve()
    work.mkdir(parents=True, exist_ok=True)
    return write_scene(name, work / f"{name}_{size}.usda", size)


def tile_level(ctx: StageContext, tile: int, k: int) -> tuple[avis_mod.AvisLevel, int, float]:
    """The a_vis stage's finest level of one tile with k samples per facet (0: all)."""
    s = ctx.settings
    geo = ctx.geometry()
    n, side = s.atlas_resolution, s.shard_texels
    tr, tc = divmod(tile, n // side)
    idx = samples_in(geo, n, side.bit_length() - 1, np.array([tile]))
    row, col = geo["sample_row"][idx], geo["sample_col"][idx]
    local = (row - tr * side) * side + (col - tc * side)
    caster = ctx.caster()
    rays0, t0 = caster.rays_cast, time.perf_counter()
    level = avis_mod.avis_level(
        geo["sample_pos"][idx], geo["sample_gnrm"][idx], geo["sample_area"][idx], local, side,
        s.avis_resolution, caster.occluded, ctx.asset().points,
        ray_eps=TOL.ray_offset * caster.bbox_diag, faces=geo["sample_face"][idx], per_facet=k)
    return level, caster.rays_cast - rays0, time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", default="cylinder")
    ap.add_argument("--size", default="full", choices=("small", "full"))
    ap.add_argument("--atlas", type=int, default=128)
    ap.add_argument("--k", default="0,2,4,8,16", help="samples per facet; 0 (every sample) first")
    ap.add_argument("--tiles", type=int, default=6, help="seeded sample of occupied tiles")
    ap.add_argument("--workdir", type=Path, default=None)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    ks = [int(x) for x in args.k.split(",")]
    if ks[0] != 0:
        ks = [0, *ks]
    work = args.workdir or Path(tempfile.mkdtemp(prefix="texelbake-avis-k-"))
    scene = scene_file(args.scene, args.size, work)
    settings = BakeSettings(atlas_resolution=args.atlas, shard_texels=min(8, args.atlas))
    for stage in ("ingest", "geometry"):
        run_shard(work, scene, settings, stage, 0)
    ctx = StageContext.create(work, scene, settings)
    geo = ctx.geometry()
    n, side = args.atlas, settings.shard_texels
    tiles_of = (geo["sample_row"] // side) * (n // side) + geo["sample_col"] // side
    occupied = np.flatnonzero(np.bincount(tiles_of, minlength=(n // side) ** 2))
    rng = np.random.default_rng(0)
    tiles = np.sort(rng.choice(occupied, size=min(args.tiles, occupied.size), replace=False))
    rows = []
    dense = {}
    for k in ks:  # loop over settings
        secs, rays, errs = 0.0, 0, []
        for t in tiles:  # loop over tiles
            level, r, sec = tile_level(ctx, int(t), k)
            secs, rays = secs + sec, rays + r
            maps = level.dense_maps().reshape(side * side, -1)
            if k == 0:
                dense[int(t)] = maps
                continue
            ref = dense[int(t)]
            live = np.flatnonzero(np.linalg.norm(ref, axis=1) > 0)
            err = (np.linalg.norm(maps[live] - ref[live], axis=1)
                   / np.linalg.norm(ref[live], axis=1))
            errs.append(err)
        e = np.concatenate(errs) if errs else np.zeros(1)
        rows.append({"k": k, "seconds": secs, "rays": int(rays), "texels": int(e.size),
                     "rel_err_median": float(np.median(e)),
                     "rel_err_p95": float(np.percentile(e, 95)), "rel_err_max": float(e.max())})
    load = Path("/proc/loadavg").read_text().split()[0]
    print(f"{args.scene} ({args.size}) {n}x{n}, finest level of {len(tiles)} tiles of "
          f"{side}x{side}, a_vis res {settings.avis_resolution}; load (1-min) {load}")
    print(f"{'k':>4} {'seconds':>8} {'rays':>12} {'rays x':>7} {'err med':>8} {'err p95':>8} "
          f"{'err max':>8}")
    for r in rows:  # loop over settings
        print(f"{r['k']:>4} {r['seconds']:>8.2f} {r['rays']:>12d} "
              f"{rows[0]['rays'] / max(r['rays'], 1):>7.1f} {r['rel_err_median']:>8.4f} "
              f"{r['rel_err_p95']:>8.4f} {r['rel_err_max']:>8.4f}")
    if args.json:
        args.json.write_text(json.dumps({"scene": args.scene, "size": args.size, "atlas": n,
                                         "tiles": tiles.tolist(), "load": load, "rows": rows},
                                        indent=2))


if __name__ == "__main__":
    main()
