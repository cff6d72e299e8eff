"""A coarse level's a_vis for its fit from a subset of a texel's dense samples
(BakeSettings.avis_fit_samples) against every sample (the seed's §4.1, `avis_fit_samples=0`):
CPU seconds beside the error, per level, on a seeded sample of texels.

    .venv/bin/python benchmarks/avis_fit_samples.py cylinder:full:512 bolt:full:512 \
        --caps 4096,16384 --json benchmarks/results/avis_fit_samples.json

For each scene (geometry built once in --workdir) and each coarse level it draws a few
occupied texels (seeded), sums a_vis on the view grid over every dense sample
(`cpm.dense.avis_sums` at cap 0) and, for each cap, over the systematic subset the bake casts
from (`truth_sample.avis_samples`: every ceil(n / cap)-th of the texel's Z-order run, scaled by
area), and over a seeded draw of the same expected count (`truth_sample.truth_samples`, the
held-out truth's draw) for comparison. Errors per texel: relative L2 over the grid's
directions; per direction: |error| / a_vis where a_vis is at least 5 % of the texel's
largest (the grazing directions a fit divides by). CPU seconds are process time of the
a_vis sums alone.
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

import numpy as np
from cpm_cpu import stages_asset  # a sibling: benchmarks/ is on sys.path when run

from schemas.settings import BakeSettings
from texelbake import stages
from texelbake.cpm.dense import LevelPass, avis_parts, avis_scale, dense_of
from texelbake.cpm.level import texel_counts
from texelbake.cpm.truth_sample import truth_samples
from texelbake.io.atomic import atomic_json
from texelbake.pipeline.process import setup_bake_process

#: texels drawn per level (all where a level has fewer)
PER_LEVEL = {3: 16, 4: 12, 5: 8, 6: 4, 7: 2, 8: 1, 9: 1}


def _errors(est: np.ndarray, full: np.ndarray) -> dict:
    l2 = np.linalg.norm(est - full, axis=1) / np.maximum(np.linalg.norm(full, axis=1), 1e-300)
    on = full > 0.05 * full.max(axis=1, keepdims=True)
    per = np.abs(est - full)[on] / full[on]
    return {"l2_median_pct": 100 * float(np.median(l2)), "l2_max_pct": 100 * float(l2.max()),
            "dir_p99_pct": 100 * float(np.percentile(per, 99)) if per.size else 0.0,
            "dir_max_pct": 100 * float(per.max()) if per.size else 0.0}


def run_scene(spec: str, caps: list[int], work: Path, seed: int) -> dict:
    scene, size, atlas = spec.split(":")
    n = int(atlas)
    settings = BakeSettings(atlas_resolution=n, shard_texels=min(32, n), avis_coarse="dense",
                            avis_fit_samples=0)
    wd = work / f"{scene}_{size}_{n}"
    asset = stages_asset(scene, size, wd)
    ctx = stages.StageContext.create(wd / "store", asset, settings)
    stages.run_ingest(ctx, 0)
    stages.run_geometry(ctx, 0)
    every = ctx.fit_inputs()
    rng = np.random.default_rng(seed)
    rows = []
    for level in range(3, ctx.n_levels):  # loop over coarse levels
        n_l = n >> level
        allt = np.arange(n_l * n_l, dtype=np.int64)
        counts = texel_counts(every.geo, n, level, allt)
        occ = allt[counts > 0]
        k = min(PER_LEVEL.get(level, 1), occ.size)
        tex = np.sort(rng.choice(occ, k, replace=False))
        lp = LevelPass.of(every, level)
        dense, dseg = dense_of(lp, tex)
        c0 = time.process_time()
        full, area, _ = avis_parts(lp, tex, dense, dseg)
        t_full = time.process_time() - c0
        row = {"level": level, "texels": int(k),
               "samples_median": float(np.median(counts[tex])), "full_cpu_s": t_full, "caps": {}}
        for cap in caps:
            src = dataclasses.replace(every, settings=every.settings.model_copy(
                update={"avis_fit_samples": cap}))
            lpc = LevelPass.of(src, level)
            c0 = time.process_time()
            sub, _, area_avis = avis_parts(lpc, tex, dense, dseg)
            t_sub = time.process_time() - c0
            est = sub * avis_scale(area, area_avis)[:, None]
            drawn = truth_samples(src, level, tex, dense, dseg, cap)
            dr, _, a_dr = avis_parts(lp, tex, dense[drawn], dseg[drawn])
            row["caps"][str(cap)] = {
                "cpu_s": t_sub, "systematic": _errors(est, full),
                "seeded_draw": _errors(dr * avis_scale(area, a_dr)[:, None], full)}
        rows.append(row)
        print(_line(spec, row), flush=True)
    return {"scene": spec, "levels": rows}


def _line(spec: str, row: dict) -> str:
    parts = [f"{spec} L{row['level']} texels {row['texels']:2d} samples/texel "
             f"{row['samples_median']:9.0f} every sample {row['full_cpu_s']:6.2f} s"]
    for cap, r in row["caps"].items():
        s, d = r["systematic"], r["seeded_draw"]
        parts.append(f"cap {cap}: {r['cpu_s']:6.2f} s, L2 med/max {s['l2_median_pct']:.3f}/"
                     f"{s['l2_max_pct']:.3f} %, dir p99/max {s['dir_p99_pct']:.2f}/"
                     f"{s['dir_max_pct']:.2f} % (seeded draw L2 med {d['l2_median_pct']:.3f} %)")
    return " | ".join(parts)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scenes", nargs="+", help="SCENE:SIZE:ATLAS, e.g. cylinder:full:512")
    ap.add_argument("--caps", default="4096,16384")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--workdir", default="bench_out/avis_fit_samples")
    ap.add_argument("--json")
    args = ap.parse_args()
    setup_bake_process()
    caps = [int(c) for c in args.caps.split(",")]
    res = {"what": "a coarse fit's a_vis from a subset of samples against every sample",
           "caps": caps,
           "scenes": [run_scene(s, caps, Path(args.workdir), args.seed) for s in args.scenes]}
    if args.json:
        atomic_json(Path(args.json), res)


if __name__ == "__main__":
    main()
