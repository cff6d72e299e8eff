"""A coarse level's a_vis for its fit: from the children's maps against the seed's per-level
rebuild from every dense sample (BakeSettings.avis_coarse), time beside error.

    .venv/bin/python benchmarks/avis_coarse.py cylinder:full:32 --json coarse.json

(or `benchmarks/avis_methods.py --coarse SCENE:SIZE:ATLAS[,...]`). For each scene it
bakes twice in one artifact store (geometry and the a_vis stage shared, only the cpm stages
differ) and reports, per variant, the cpm stages' wall seconds and every level's held-out SNR
(median, p5: what the fit gains or loses); then, on a seeded sample of texels of every coarse
level (every texel where there are few), the seed's rebuild (`cpm.dense.avis_sums`: rays from
every dense sample) against the children's maps read at the texel's view grid
(`stages.avis.fit_avis_o`), each timed, with the relative L2 error of the latter per texel
(over the grid's directions) against the former.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from schemas.settings import BakeSettings
from texelbake.cpm.dense import LevelPass, avis_sums, dense_of
from texelbake.pipeline.run import bake
from texelbake.stages.avis import fit_avis_o
from texelbake.stages.context import StageContext
from texelbake.testscenes import write_scene

SAMPLE = 64  # texels per level compared directly


def _bake(src: Path, work: Path, settings: BakeSettings) -> dict:
    import json

    out = work / f"out_{settings.avis_coarse}"
    t0 = time.perf_counter()
    root = bake(src, out, settings, workdir=work / "store", progress=False, jobs=2)
    wall = time.perf_counter() - t0
    rep = json.loads((Path(root).parent / "report.json").read_text())
    sec = rep.get("stage_seconds", {})
    return {"wall_s": wall, "cpm_s": sec.get("cpm", 0.0) + sec.get("cpm_top", 0.0),
            "levels": [{"level": lv["level"], "p50": lv["snr_heldout_db"].get("p50"),
                        "p5": lv["snr_heldout_db"].get("p5")} for lv in rep["levels"]]}


def _direct(ctx: StageContext, rng: np.random.Generator) -> list[dict]:
    """Per coarse level: seconds of the two ways on a seeded texel sample, and the error."""
    s = ctx.settings
    src = ctx.fit_inputs()
    per_row = s.atlas_resolution // s.shard_texels
    rows = []
    for level in range(1, ctx.n_levels):
        n_l = s.atlas_resolution >> level
        geo = src.geo
        occupied = np.unique((geo["sample_row"] >> level) * n_l + (geo["sample_col"] >> level))
        texels = np.sort(rng.choice(occupied, min(SAMPLE, occupied.size), replace=False))
        lp = LevelPass.of(src, level)
        t0 = time.perf_counter()
        dense, dseg = dense_of(lp, texels)
        ref, _ = avis_sums(lp, texels, dense, dseg)
        t_dense = time.perf_counter() - t0
        t0 = time.perf_counter()
        if level >= ctx.tile_levels:
            got = fit_avis_o(ctx, level, texels, None)
        else:  # one call per tile holding sampled texels
            side_l = s.shard_texels >> level
            r, c = np.divmod(texels, n_l)
            tile = (r // side_l) * per_row + c // side_l
            got = np.zeros_like(ref)
            for t in np.unique(tile):  # a loop over tiles
                m = tile == t
                got[m] = fit_avis_o(ctx, level, texels[m], int(t))
        t_child = time.perf_counter() - t0
        norm = np.linalg.norm(ref, axis=1)
        ok = norm > 0
        rel = np.linalg.norm(got - ref, axis=1)[ok] / norm[ok]
        rows.append({"level": level, "texels": int(texels.size),
                     "dense_s": t_dense, "children_s": t_child,
                     "rel_median": float(np.median(rel)), "rel_p95": float(np.percentile(rel, 95)),
                     "rel_max": float(rel.max())})
    return rows


def coarse_table(specs: list[str], work: Path) -> list[dict]:
    """Both variants on every `SCENE:SIZE:ATLAS` of specs; prints one table per scene."""
    out = []
    for spec in specs:  # a loop over scenes
        name, size, atlas = spec.split(":")
        w = work / f"{name}_{size}_{atlas}"
        src = write_scene(name, w / "src" / f"{name}_{size}.usda", size)
        base = {"atlas_resolution": int(atlas),
                "shard_texels": min(int(atlas), BakeSettings().shard_texels)}
        runs = {v: _bake(src, w, BakeSettings(**base, avis_coarse=v))
                for v in ("dense", "children")}
        ctx = StageContext.create(w / "store", src, BakeSettings(**base, avis_coarse="children"))
        direct = _direct(ctx, np.random.default_rng(0))
        print(f"\n{spec}: cpm stages {runs['dense']['cpm_s']:.1f} s (dense) against "
              f"{runs['children']['cpm_s']:.1f} s (children); bake wall "
              f"{runs['dense']['wall_s']:.1f} / {runs['children']['wall_s']:.1f} s")
        print(f"{'level':>5} {'held-out p50 dense/children':>28} {'p5 dense/children':>19} "
              f"{'texels':>6} {'dense s':>8} {'children s':>10} {'rel med':>8} {'rel p95':>8} "
              f"{'rel max':>8}")
        for i, d in enumerate(runs["dense"]["levels"]):
            c = runs["children"]["levels"][i]
            dr = next((x for x in direct if x["level"] == d["level"]), None)
            tail = (f"{dr['texels']:>6} {dr['dense_s']:>8.3f} {dr['children_s']:>10.3f} "
                    f"{dr['rel_median']:>8.3%} {dr['rel_p95']:>8.3%} {dr['rel_max']:>8.3%}"
                    if dr else "")
            print(f"{d['level']:>5} {_f(d['p50']):>13} / {_f(c['p50']):<12} "
                  f"{_f(d['p5']):>8} / {_f(c['p5']):<8} {tail}")
        out.append({"scene": spec, "runs": runs, "direct": direct})
    return out


def _f(x) -> str:
    return "n/a" if x is None else f"{x:.2f}"


def main() -> None:
    import argparse
    import json

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("specs", help="'SCENE:SIZE:ATLAS[,...]', e.g. cylinder:full:32")
    ap.add_argument("--json", type=Path, help="write the rows as JSON here")
    ap.add_argument("--work", type=Path, default=Path("bench_out/avis_coarse"))
    args = ap.parse_args()
    rows = coarse_table(args.specs.split(","), args.work)  # prints its table
    if args.json:
        args.json.write_text(json.dumps({"coarse": rows}, indent=1))


if __name__ == "__main__":
    main()
