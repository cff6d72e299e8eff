"""Level-0 a_vis from every dense sample against rays that follow the need
(BakeSettings.avis_level0): rays, seconds and error side by side.

    .venv/bin/python benchmarks/avis_level0.py cylinder:full:64,cylinder:full:128,\
bolt:full:64,bolt:full:128 --json benchmarks/results/avis_level0.json

For each scene the geometry stage runs once; then, on a seeded sample of occupied tiles (the
a_vis stage's unit of work, `stages.avis.run_avis_tile`), the tile's level-0 a_vis is built
dense and by need (for every K of --k), each timed, with the rays it cast. The error is per
texel, the relative L2 over the cube's directions of the by-need maps against the dense ones
(`AvisLevel.dense_maps`; texels in closed form are equal in both and left out), at level 0
(all ray texels and the one-sample texels apart) and at the tile's coarsest level (children
summed, what a coarse level's fit reads with avis_coarse="children"). Rays and seconds are
summed over the sampled tiles and extrapolated to the whole level by the share of occupied
tiles sampled.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from schemas.settings import BakeSettings
from texelbake.cpm.avis import avis_level, coarsen_level
from texelbake.cpm.avis.by_need import need_samples
from texelbake.cpm.avis.closed_form import unoccluded_samples
from texelbake.cpm.level import samples_in
from texelbake.stages.context import StageContext
from texelbake.stages.geometry import run_geometry
from texelbake.testscenes import write_scene
from texelbake.tol import TOL


def _rel(got: np.ndarray, ref: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """(r,) relative L2 error of texels `rows` over their cube directions."""
    a = ref[rows].reshape(rows.size, -1) if rows.size else np.zeros((0, 1))
    b = got[rows].reshape(rows.size, -1) if rows.size else np.zeros((0, 1))
    n = np.linalg.norm(a, axis=1)
    ok = n > 0
    return np.linalg.norm(b - a, axis=1)[ok] / n[ok]


def _stats(x: np.ndarray) -> dict:
    if x.size == 0:
        return {"n": 0}
    return {"n": int(x.size), "median": float(np.median(x)),
            "p95": float(np.percentile(x, 95)), "max": float(x.max())}


def _tile_inputs(ctx: StageContext, tile: int):
    s = ctx.settings
    geo = ctx.geometry()
    n, side = s.atlas_resolution, s.shard_texels
    tr, tc = divmod(tile, n // side)
    idx = samples_in(geo, n, side.bit_length() - 1, np.array([tile]))
    local = (geo["sample_row"][idx] - tr * side) * side + (geo["sample_col"][idx] - tc * side)
    return (geo["sample_pos"][idx], geo["sample_gnrm"][idx], geo["sample_area"][idx], local)


def level0_table(spec: str, work: Path, n_tiles: int, ks: list[int], seed: int = 0) -> dict:
    """Dense against by-need on `n_tiles` seeded occupied tiles of one SCENE:SIZE:ATLAS."""
    name, size, atlas = spec.split(":")
    w = work / f"{name}_{size}"
    src = write_scene(name, w / "src" / f"{name}_{size}.usda", size)
    s = BakeSettings(atlas_resolution=int(atlas),
                     shard_texels=min(int(atlas), BakeSettings().shard_texels))
    ctx = StageContext.create(w / "store", src, s)
    t0 = time.perf_counter()
    run_geometry(ctx)
    t_geo = time.perf_counter() - t0
    geo = ctx.geometry()
    side = s.shard_texels
    per_row = s.atlas_resolution // side
    occupied = np.unique((geo["sample_row"] // side) * per_row + geo["sample_col"] // side)
    tiles = np.sort(np.random.default_rng(seed).choice(
        occupied, min(n_tiles, occupied.size), replace=False))
    caster = ctx.caster()
    pts = ctx.asset().points
    eps = TOL.ray_offset * caster.bbox_diag
    variants = [("dense", 0)] + [("by_need", k) for k in ks]
    acc = {v: {"rays": 0, "s": 0.0, "rel0": [], "rel0_one": [], "rel_top": []}
           for v in variants}
    n_one = n_ray = n_samples = 0
    for tile in tiles:  # a loop over the sampled tiles
        pos, nrm, ar, local = _tile_inputs(ctx, int(tile))
        n_samples += pos.shape[0]
        maps = {}
        for mode, k in variants:
            r0, t0 = caster.rays_cast, time.perf_counter()
            lvl = avis_level(pos, nrm, ar, local, side, s.avis_resolution, caster.occluded,
                             pts, ray_eps=eps, samples=mode, k_samples=max(k, 1))
            acc[(mode, k)]["s"] += time.perf_counter() - t0
            acc[(mode, k)]["rays"] += caster.rays_cast - r0
            top = lvl
            while top.n_side > 1:
                top = coarsen_level(top)
            maps[(mode, k)] = (lvl, top)
        ref0, ref_top = maps[("dense", 0)]
        rays_t = ref0.ray_texels
        n_ray += rays_t.size
        # the one-sample texels (the test repeated outside the timing, for the report)
        free = unoccluded_samples(pos, nrm, pts, eps=eps)
        one = need_samples(pos, nrm, ar, local.astype(np.int64), side * side,
                           ~ref0.closed[local] & ~free, caster.occluded, eps=eps).one
        one_t = np.flatnonzero(one)
        n_one += one_t.size
        d0, dt = ref0.dense_maps(), ref_top.dense_maps()
        for v in variants[1:]:
            g0, gt = maps[v][0].dense_maps(), maps[v][1].dense_maps()
            acc[v]["rel0"].append(_rel(g0, d0, rays_t))
            acc[v]["rel0_one"].append(_rel(g0, d0, one_t))
            acc[v]["rel_top"].append(_rel(gt, dt, np.flatnonzero(~ref_top.closed)))
    scale = occupied.size / max(tiles.size, 1)
    rows = []
    for mode, k in variants:
        a = acc[(mode, k)]
        rows.append({
            "variant": mode if mode == "dense" else f"by_need K={k}", "k": k,
            "rays_sampled": int(a["rays"]), "seconds_sampled": a["s"],
            "rays_level_est": int(a["rays"] * scale), "seconds_level_est": a["s"] * scale,
            "rel_level0": _stats(np.concatenate(a["rel0"]) if a["rel0"] else np.zeros(0)),
            "rel_level0_one": _stats(np.concatenate(a["rel0_one"]) if a["rel0_one"]
                                     else np.zeros(0)),
            "rel_tile_top": _stats(np.concatenate(a["rel_top"]) if a["rel_top"]
                                   else np.zeros(0)),
        })
    out = {"scene": spec, "geometry_s": t_geo, "tiles_sampled": int(tiles.size),
           "tiles_occupied": int(occupied.size), "samples_sampled": int(n_samples),
           "ray_texels_sampled": int(n_ray), "one_sample_texels": int(n_one), "rows": rows}
    _print(out)
    return out


def _print(out: dict) -> None:
    print(f"\n{out['scene']}: {out['tiles_sampled']} of {out['tiles_occupied']} tiles, "
          f"{out['samples_sampled']} samples, {out['ray_texels_sampled']} ray texels, "
          f"{out['one_sample_texels']} one-sample; geometry {out['geometry_s']:.0f} s")
    print(f"{'variant':>14} {'rays (tiles)':>13} {'s (tiles)':>9} {'rays (level)':>13} "
          f"{'s (level)':>9} {'L0 med':>7} {'L0 p95':>7} {'L0 max':>7} {'one max':>8} "
          f"{'top med':>8} {'top max':>8}")
    for r in out["rows"]:
        e0, e1, et = r["rel_level0"], r["rel_level0_one"], r["rel_tile_top"]

        def f(d: dict, key: str) -> str:
            return f"{d[key]:.2%}" if d.get("n") else "-"
        print(f"{r['variant']:>14} {r['rays_sampled']:>13,} {r['seconds_sampled']:>9.1f} "
              f"{r['rays_level_est']:>13,} {r['seconds_level_est']:>9.0f} {f(e0, 'median'):>7} "
              f"{f(e0, 'p95'):>7} {f(e0, 'max'):>7} {f(e1, 'max'):>8} {f(et, 'median'):>8} "
              f"{f(et, 'max'):>8}")


def main() -> None:
    import argparse
    import json

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("specs", help="'SCENE:SIZE:ATLAS[,...]', e.g. cylinder:full:64")
    ap.add_argument("--tiles", type=int, default=6, help="occupied tiles sampled per scene")
    ap.add_argument("--k", default="2,4,8", help="K values of by_need, comma separated")
    ap.add_argument("--json", type=Path, help="write the rows as JSON here")
    ap.add_argument("--work", type=Path, default=Path("bench_out/avis_level0"))
    args = ap.parse_args()
    ks = [int(k) for k in args.k.split(",")]
    res = [level0_table(spec, args.work, args.tiles, ks) for spec in args.specs.split(",")]
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"level0": res}, indent=1))


if __name__ == "__main__":
    main()
