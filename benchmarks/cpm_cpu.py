"""CPU seconds of the CPM fit, per level, in one process, beside the held-out SNR it reaches: the
quick loop for issue 15's throughput work (the cpm stage without the farm, the a_vis stage or
export; `benchmarks/bake.py` times the whole bake).

    python benchmarks/cpm_cpu.py --scene cylinder --atlas 32 [--set KEY=VALUE ...] [--tiles 0,5]
        [--seeds 0,1,2] [--json PATH]
    python benchmarks/cpm_cpu.py --compare A.json B.json ...   # --seeds results side by side

Ingest and geometry run once (untimed, cached in --workdir); then every tile's levels and the
top levels are fitted in order, exactly as `run_cpm_tile` / `run_cpm_top` do (the tiles' sums for the
top levels, `top_level_sums`, timed as the top level's work), each `fit_level`
call timed with `time.process_time()` (CPU seconds of this process: the machine is shared, so
wall time is not comparable between runs). Prints per level: texels fitted, CPU seconds,
texels per CPU second, held-out SNR median and p5, the skip counts (what the fit did not
model fully), a digest of the level's arrays (equal digests: byte-identical results), the
intervals of the median and p5 as the bake report gives them, and the rays cast. No a_vis stage
runs: every coarse level's a_vis comes from its dense samples' rays (`avis_coarse="dense"`'s).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import tempfile
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np

from schemas.settings import BakeSettings
from texelbake import stages
from texelbake.cpm.assemble import heldout_stats
from texelbake.cpm.dense import dense_sums
from texelbake.cpm.level import concat_levels, level_candidates, texel_ids, tile_texels
from texelbake.cpm.texel_fit import FitCounts
from texelbake.estimate import costmodel
from texelbake.io.atomic import atomic_json
from texelbake.pipeline.process import setup_bake_process
from texelbake.stages import cpm as cpm_stage
from texelbake.stages.cpm import fit_level


def _parse_set(items: list[str]) -> dict:
    out: dict = {}
    for it in items:
        k, v = it.split("=", 1)
        try:
            out[k] = json.loads(v)
        except json.JSONDecodeError:
            out[k] = v
    return out


def digest(arrays: dict[str, np.ndarray]) -> str:
    h = hashlib.sha256()
    for k in sorted(arrays):
        if k == "rays":
            continue
        a = np.ascontiguousarray(arrays[k])
        h.update(k.encode() + str(a.dtype).encode() + str(a.shape).encode() + a.tobytes())
    return h.hexdigest()[:16]


#: (module, function) pairs timed by --breakdown (CPU seconds summed over calls; nested parts
#: are included in their callers)
BREAKDOWN = (
    ("texelbake.cpm.level_batched", "avis_sums"),
    ("texelbake.cpm.level_batched", "_fit_chunk"),
    ("texelbake.cpm.level_batched", "build_R"),
    ("texelbake.cpm.build_r", "brdf_product"),
    ("texelbake.cpm.build_r", "visibility_cos"),
    ("texelbake.cpm.level_batched", "fit_many"),
    ("texelbake.cpm.gram.fit", "identical_columns"),
    ("texelbake.cpm.gram.fit", "unmerge"),
    ("texelbake.cpm.gram.fit", "select_groups"),
    ("texelbake.cpm.gram.fit", "top_eighs"),
    ("texelbake.cpm.gram.fit", "fit_texel_gram"),
    ("texelbake.cpm.gram.fit", "reduced_system"),
    ("texelbake.cpm.gram.fit", "search_c"),
    ("texelbake.cpm.gram.fit", "_assemble"),
    ("texelbake.cpm.level_batched", "heldout_from_samples"),
    ("texelbake.cpm.level_by_need", "heldout_from_samples"),  # the classed texels' truth
    ("texelbake.cpm.level_batched", "_choose_lobes"),
    ("texelbake.cpm.level_batched", "widen_fit"),
    ("texelbake.cpm.level_batched", "wider_wins"),
    ("texelbake.cpm.level_batched", "validation_truth"),
    ("texelbake.cpm.level_by_need", "classes_bounded"),
    ("texelbake.cpm.level_by_need", "_stored_arrays"),
    ("texelbake.cpm.level_by_need", "cluster_candidates"),
    ("texelbake.cpm.level_by_need", "lobes_bounded"),
)


#: per-level sums recorded for the cost model's calibration: candidates on cheap (Lambert /
#: Phong) and costly materials, m^2, m^3, dense samples on cheap / costly materials, texels
FEATURES = ("m_cheap", "m_costly", "m2", "m3", "dense_cheap", "dense_costly", "texels")


#: the level `run` is fitting, for --breakdown's per-level sums
CURRENT = {"level": -1}
#: --breakdown's CPU seconds per level and part: {level: {part: seconds}}
BY_LEVEL: dict[int, dict[str, float]] = {}


def install_breakdown() -> dict[str, list[float]]:
    """Wrap the BREAKDOWN functions with process-time accumulators (CPU seconds, calls; and
    per level in BY_LEVEL)."""
    import importlib

    acc: dict[str, list[float]] = {}
    for mod_name, fn in BREAKDOWN:
        mod = importlib.import_module(mod_name)
        inner = getattr(mod, fn)
        key = fn if fn not in acc else f"{mod_name}.{fn}"
        acc[key] = [0.0, 0]

        def wrapped(*a, _inner=inner, _key=key, **k):
            c0 = time.process_time()
            try:
                return _inner(*a, **k)
            finally:
                dt = time.process_time() - c0
                acc[_key][0] += dt
                acc[_key][1] += 1
                lv = BY_LEVEL.setdefault(CURRENT["level"], {})
                lv[_key] = lv.get(_key, 0.0) + dt
        setattr(mod, fn, wrapped)
    return acc


def run(scene: str, size: str, settings: BakeSettings, work: Path,
        tiles: list[int] | None = None) -> dict:
    setup_bake_process()  # as every bake process (texelbake.pipeline.run.run_shard)
    asset = stages_asset(scene, size, work)
    ctx = stages.StageContext.create(work / "store", asset, settings)
    stages.run_ingest(ctx, 0)
    stages.run_geometry(ctx, 0)
    src = ctx.fit_inputs()
    s = settings
    n_tiles = (s.atlas_resolution // s.shard_texels) ** 2
    tiles = list(range(n_tiles)) if tiles is None else tiles
    per_level: dict[int, list] = {}
    counts = FitCounts()  # the batched fit's search work (probes of c, draws solved, merges)

    tex_l = {lv: texel_ids(src.geo, s.atlas_resolution, lv) for lv in range(ctx.n_levels)}
    costly = np.array([m.model not in ("lambert", "phong") for m in src.materials], bool)
    mat = np.asarray(src.geo["sample_mat"], np.int64)
    feats: dict[int, np.ndarray] = {}

    top = cpm_stage.has_top(ctx) and len(tiles) == n_tiles
    top_sums = cpm_stage.empty_top_sums(ctx) if top else {}
    sums_cpu: dict[int, float] = {}
    inner_sums = cpm_stage.top_level_sums

    def timed_sums(src_, level, texels, samples):
        """A top level's share of a tile's sums (`run_cpm_tile`'s `top_sums` calls it per top
        level), timed as that level's work. With a_vis from the dense samples, as every coarse
        level here: this benchmark runs no a_vis stage, whose maps a bake's top levels read
        (`avis_coarse="children"`), and sums without a_vis would leave every top texel
        invalid."""
        CURRENT["level"] = level
        c0 = time.process_time()
        out = dense_sums(src_, level, texels, samples)
        sums_cpu[level] = sums_cpu.get(level, 0.0) + time.process_time() - c0
        return out

    def timed(level, texels, cands):
        CURRENT["level"] = level
        c0 = time.process_time()
        out = fit_level(src, level, texels, cands, top_sums.get(level), counts)
        per_level.setdefault(level, []).append((time.process_time() - c0, out))
        # the cost model's sizes of this call (texelbake.estimate.costmodel): per texel m candidates
        # and n dense samples, split by material cost (Lambert / Phong vs the rest)
        pos = np.searchsorted(np.sort(texels), cands.texel)
        m = np.bincount(pos, minlength=len(texels)).astype(float)
        mg = np.bincount(pos, weights=costly[mat[cands.sample]].astype(float),
                         minlength=len(texels))
        dense_sel = np.isin(tex_l[level], texels)
        dpos = np.searchsorted(np.sort(texels), tex_l[level][dense_sel])
        nd = np.bincount(dpos, minlength=len(texels)).astype(float)
        ndg = np.bincount(dpos, weights=costly[mat[dense_sel]].astype(float),
                          minlength=len(texels))
        has = nd > 0
        f = np.array([(m - mg).sum(), mg.sum(), (m * m).sum(), (m ** 3).sum(),
                      (nd - ndg).sum(), ndg.sum(), float(has.sum())])
        feats[level] = feats.get(level, 0) + f
        return out

    tops = []
    for t in tiles:  # loop over tiles, as the farm's shards
        if top:  # the tile's sums for the top levels, added in tile order as cpm_top does
            cpm_stage.top_level_sums = timed_sums
            try:
                cpm_stage.add_tile_sums(ctx, top_sums, t, cpm_stage.top_sums(ctx, t))
            finally:
                cpm_stage.top_level_sums = inner_sums
        children = grandchildren = None
        for level in range(ctx.tile_levels):
            texels = tile_texels(s.atlas_resolution, s.shard_texels, t, level)
            cands = level_candidates(src, level, texels, children, grandchildren)
            grandchildren, children = children, timed(level, texels, cands)
        tops.append((grandchildren, children))
    if len(tiles) == n_tiles:
        children = concat_levels([c for _, c in tops])
        grandchildren = (concat_levels([g for g, _ in tops]) if tops[0][0] is not None
                         else None)
        for level in range(ctx.tile_levels, ctx.n_levels):
            n_l = s.atlas_resolution >> level
            texels = np.arange(n_l * n_l, dtype=np.int64)
            cands = level_candidates(src, level, texels, children, grandchildren)
            grandchildren, children = children, timed(level, texels, cands)
    levels = []
    for level in sorted(per_level):
        runs = per_level[level]
        # a top level's work includes the tiles' sums for it (`run_cpm_tile`'s `top_sums`)
        cpu = sum(r[0] for r in runs) + sums_cpu.get(level, 0.0)
        data = concat_levels([r[1] for r in runs])
        v = data["valid"]
        ho = data["snr_ho"][v].astype(np.float64)
        ho = ho[np.isfinite(ho)]
        skip = data["skip"][v] if "skip" in data else np.zeros(0, np.int8)  # per_texel: none
        levels.append({
            "level": level, "texels": int(v.sum()), "cpu_seconds": cpu,
            "sums_cpu_seconds": sums_cpu.get(level, 0.0),
            "texels_per_cpu_second": float(v.sum()) / max(cpu, 1e-9),
            "heldout_db_median": float(np.median(ho)) if ho.size else None,
            "heldout_db_p5": float(np.percentile(ho, 5)) if ho.size else None,
            "c_mean": float(data["c"][v].mean()) if v.any() else None,
            # intervals of the median and p5 as the report's (`heldout_stats`): the measured
            # texels as a sample of the level's occupied texels in the whole atlas
            "heldout": heldout_stats(data["snr_ho"][v], int(np.unique(tex_l[level]).size)),
            "rays": int(data["rays"].sum()) if "rays" in data else None,
            "skip_counts": {str(int(k)): int(n) for k, n in
                            zip(*np.unique(skip, return_counts=True), strict=True)},
            "digest": digest(data),
            "sizes": dict(zip(FEATURES, feats[level].tolist(), strict=True)),
        })
    if len(tiles) == n_tiles:
        # the cost model's prediction of each level, by term, priced on the coefficients'
        # machine, as the bake makes it (from the placed samples and the sampled classes):
        # what `calibrate_costmodel.py --parts` scales each group of terms by
        for lv, pred in zip(levels, model_levels(ctx), strict=True):
            lv["model_seconds"], lv["model_terms"] = pred["seconds"], pred["terms"]
    return {"scene": scene, "size": size, "settings": json.loads(settings.model_dump_json()),
            "tiles": tiles, "levels": levels, "trial_counts": counts.as_dict(),
            "cpu_seconds": sum(lv["cpu_seconds"] for lv in levels),
            "model_coefficients": asdict(costmodel.Coefficients())}


def model_levels(ctx: stages.StageContext) -> list[dict]:
    """The cost model's per-level CPU seconds of the fit and their terms (`costmodel.TERMS`)
    for this bake, at the coefficients' machine (no speed factor), on the inputs the bake's
    own estimate prices (`pipeline.estimate.estimate_inputs`)."""
    from texelbake.pipeline.estimate import estimate_inputs

    return costmodel.estimate(ctx.settings, 1, **estimate_inputs(ctx)).per_level


def stages_asset(scene: str, size: str, work: Path) -> Path:
    from texelbake.testscenes import write_scene

    if Path(scene).suffix in (".usd", ".usda", ".usdc", ".usdz"):  # an asset file (the Teapot)
        if not Path(scene).is_file():
            raise SystemExit(f"--scene {scene}: no such USD file")
        return Path(scene).resolve()
    path = work / f"{scene}_{size}.usda"
    if not path.exists():
        write_scene(scene, path, size)
    return path


def print_table(res: dict) -> None:
    print(f"{res['scene']} ({res['size']}) {res['settings']['atlas_resolution']}^2, "
          f"CPU seconds of fit_level (process time), total {res['cpu_seconds']:.2f} s")
    print(f"trials: {res['trial_counts']}")
    print(f"{'lvl':>3} {'texels':>6} {'cpu s':>8} {'tex/cpu s':>9} {'ho med':>7} "
          f"{'ho p5':>7} {'c':>6}  skips            digest            "
          f"{'med 95% CI':>15} {'p5 95% CI':>15} {'rays':>10}")
    for lv in res["levels"]:
        def f(x):
            return float("nan") if x is None else x

        def ci(key, lv=lv):
            lo, hi = lv.get("heldout", {}).get(key, (float("nan"),) * 2)
            return f"[{lo:6.2f},{hi:6.2f}]"
        print(f"{lv['level']:>3} {lv['texels']:>6} {lv['cpu_seconds']:>8.2f} "
              f"{lv['texels_per_cpu_second']:>9.2f} {f(lv['heldout_db_median']):>7.2f} "
              f"{f(lv['heldout_db_p5']):>7.2f} {f(lv['c_mean']):>6.1f}  "
              f"{json.dumps(lv['skip_counts']):<16} {lv['digest']}  {ci('p50_ci'):>15} "
              f"{ci('p5_ci'):>15} {lv.get('rays') or 0:>10}")


def seed_summary(runs: list[dict]) -> list[dict]:
    """Per level, across the runs (one per seed): CPU seconds summed, and the held-out median
    and p5 of each run as median, min and max."""
    out = []
    for level in sorted({lv["level"] for r in runs for lv in r["levels"]}):
        rows = [lv for r in runs for lv in r["levels"] if lv["level"] == level]
        med = [lv["heldout_db_median"] for lv in rows if lv["heldout_db_median"] is not None]
        p5 = [lv["heldout_db_p5"] for lv in rows if lv["heldout_db_p5"] is not None]
        out.append({
            "level": level, "runs": len(rows), "cpu_seconds": sum(lv["cpu_seconds"] for lv in rows),
            "texels": sum(lv["texels"] for lv in rows),
            "heldout_db_median": {"median": float(np.median(med)), "min": min(med),
                                  "max": max(med)} if med else None,
            "heldout_db_p5": {"median": float(np.median(p5)), "min": min(p5),
                              "max": max(p5)} if p5 else None,
        })
    return out


def print_seed_summary(res: dict) -> None:
    print(f"across seeds {res['seeds']}: per level, the runs' held-out median and p5 (dB) as "
          "median [min, max]")
    print(f"{'lvl':>3} {'texels':>7} {'cpu s':>8} {'tex/cpu s':>9}  {'ho median':<26} ho p5")
    for lv in res["summary"]:
        def span(x):
            return ("n/a" if x is None else
                    f"{x['median']:7.2f} [{x['min']:7.2f}, {x['max']:7.2f}]")
        print(f"{lv['level']:>3} {lv['texels']:>7} {lv['cpu_seconds']:>8.2f} "
              f"{lv['texels'] / max(lv['cpu_seconds'], 1e-9):>9.2f}  "
              f"{span(lv['heldout_db_median']):<26} {span(lv['heldout_db_p5'])}")


def compare(paths: list[Path]) -> None:
    """Side by side, per level, the median over seeds of each --seeds JSON's held-out median and
    p5 and its CPU seconds; each file is named by its stem and the settings in which it differs
    from the first file's."""
    docs = [json.loads(p.read_text()) for p in paths]
    for p, d in zip(paths, docs, strict=True):
        if "summary" not in d:
            raise SystemExit(f"{p}: not a --seeds result (no 'summary')")
    base = docs[0]["runs"][0]["settings"]
    levels = sorted({lv["level"] for d in docs for lv in d["summary"]})
    print(f"{'run':<64} {'cpu s':>7}  " + " ".join(f"{'L' + str(v) + ' med/p5':>13}" for v in levels))
    for p, d in zip(paths, docs, strict=True):
        st = d["runs"][0]["settings"]
        diff = ",".join(f"{k}={st[k]}" for k in sorted(st) if k != "seed" and st.get(k) != base.get(k))
        by = {lv["level"]: lv for lv in d["summary"]}
        cells = []
        for v in levels:  # loop over levels
            lv = by.get(v)
            if lv is None or lv["heldout_db_median"] is None:
                cells.append(f"{'n/a':>13}")
                continue
            cells.append(f"{lv['heldout_db_median']['median']:6.1f}/{lv['heldout_db_p5']['median']:<6.1f}")
        cpu = sum(lv["cpu_seconds"] for lv in d["summary"]) / max(len(d["seeds"]), 1)
        name = f"{p.stem} {diff}".strip()
        print(f"{name:<64} {cpu:>7.1f}  " + " ".join(cells))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="cylinder",
                    help="a generated scene's name, or the path of a USD asset")
    ap.add_argument("--size", default="full", choices=["small", "full"])
    ap.add_argument("--atlas", type=int, default=32)
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--tiles", default=None, help="comma-separated tile ids (default: all)")
    ap.add_argument("--workdir", type=Path, default=None)
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--seeds", default=None,
                    help="comma-separated BakeSettings.seed values: one fit per seed (the seed "
                    "draws the dense samples and the fit's columns) and a table of each level's "
                    "held-out median and p5 across them (their spread is the noise a "
                    "comparison of single bakes cannot see)")
    ap.add_argument("--breakdown", action="store_true",
                    help="also time the fit's parts (process time per function)")
    ap.add_argument("--compare", type=Path, nargs="+", default=None, metavar="JSON",
                    help="print earlier --seeds results side by side (per level, the median over "
                    "seeds of the held-out median/p5; CPU s per seed) and exit")
    args = ap.parse_args()
    if args.compare:
        compare(args.compare)
        return
    acc = install_breakdown() if args.breakdown else None
    work = args.workdir or Path(tempfile.mkdtemp(prefix="texelbake-cpmcpu-"))
    work.mkdir(parents=True, exist_ok=True)
    fields = {"atlas_resolution": args.atlas,
              "shard_texels": min(BakeSettings().shard_texels, args.atlas),
              **_parse_set(args.set)}
    settings = BakeSettings(**fields)
    tiles = [int(x) for x in args.tiles.split(",")] if args.tiles else None
    if args.seeds:
        seeds = [int(x) for x in args.seeds.split(",")]
        runs = []
        for seed in seeds:  # loop over whole fits
            runs.append(run(args.scene, args.size, settings.model_copy(update={"seed": seed}),
                            work, tiles))
            print_table(runs[-1])
        res = {"seeds": seeds, "runs": runs, "summary": seed_summary(runs)}
        print_seed_summary(res)
    else:
        res = run(args.scene, args.size, settings, work, tiles)
        print_table(res)
    if acc is not None and not args.seeds:
        res["breakdown"] = {k: {"cpu_seconds": v[0], "calls": int(v[1])} for k, v in acc.items()}
        print(f"{'part (CPU s, nested parts inside callers)':<44} {'cpu s':>8} {'share':>6} "
              f"{'calls':>7}")
        for k, v in acc.items():
            print(f"{k:<44} {v[0]:>8.2f} {100 * v[0] / max(res['cpu_seconds'], 1e-9):>5.1f}% "
                  f"{int(v[1]):>7}")
        res["breakdown_by_level"] = {str(lv): parts for lv, parts in sorted(BY_LEVEL.items())}
        keys = list(acc)
        print("per level (CPU s): " + " ".join(f"{k[:10]:>10}" for k in keys))
        for lv, parts in sorted(BY_LEVEL.items()):
            print(f"{lv:>17}: " + " ".join(f"{parts.get(k, 0.0):>10.2f}" for k in keys))
    if args.json:
        from texelbake.estimate import machinespeed

        # the machine the seconds were measured on (calibrate_costmodel.py prices the runs
        # on it): the reference workload after the fit, so the fit's timings are not disturbed
        res["machine_speed"] = machinespeed.this_machine().to_dict()
        args.json.parent.mkdir(parents=True, exist_ok=True)
        atomic_json(args.json, res)


if __name__ == "__main__":
    main()
