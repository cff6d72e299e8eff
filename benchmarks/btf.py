"""BTF level-of-detail benchmark (issue 5; seed 001).

Inputs: baked BTFs as .npz files (keys `btf` (d, h, w, 3), `dirs_i` (d, 3), `dirs_o` (d, 3) —
the f_r of every finest texel on the direction grid, written by the CPM pipeline) and/or
`--synthetic`: a deterministic 64 x 64 texel BTF on the Bonn UBO2003 sampling (81 light x 81
view directions: theta 0, 15, 30, 45, 60, 75 degrees with 1, 6, 12, 18, 20, 24 phi samples), the
seed's size (80,621,568 bytes as 8-bit RGB), rendered from a bumpy two-material height field
with shadowing, masking and parallax (`texelbake.btf.synthetic`).

Per input: one build with the default settings (8, 2, 2 components, lambda_max by the stop
rule) -> compression ratio, per-channel MSE (avg/min/max over direction images, values scaled to
[0, 1]), seconds per stage; then the seed's Fig. 6: a full build for each n in --n (Y
components), time and error side by side, plotted. With --compare-pca, the level-1 PCA problem
is also solved by both solvers (exact Gram eigh vs randomized) for time and error.

    .venv/bin/python benchmarks/btf.py --synthetic --json out/btf.json [baked.npz ...]
    .venv/bin/python benchmarks/btf.py --bake-scenes --atlas 32 --json out/btf.json

--bake-scenes runs the pipeline's ingest, geometry and CPM stages with btf=True on the four test
scenes (slow: 4-25 minutes per scene at a 32^2 atlas on this shared machine) and benchmarks the
collected f_r tables; the .npz files stay in --bake-dir for reruns (`BTF_BAKE`: the CPM fit
is kept cheap, it does not change f̄).

Measured 2026-11-21 (benchmarks/results/btf.json; 64² bakes of the four small scenes, 64 x 64
direction grid = 4096 pairs, 2.5-4.6 min each; synthetic 64² x 6561):

| input      | seed's 8/2/2 f32 | Y MSE avg | n=4 f32 (Y MSE)  | 8/2/2 f16 (Y MSE) | build s |
|------------|-----------------:|----------:|-----------------:|------------------:|--------:|
| cylinder   |           39.90x |   0.00064 | 59.5x (0.00103)  | 78.8x (0.00064)   |    1.08 |
| wall       |           40.43x |   0.00444 | 60.6x (0.00715)  | 80.9x (0.00444)   |    1.08 |
| bolt       |           39.90x |   0.00647 | 59.5x (0.00702)  | 78.8x (0.00647)   |    1.05 |
| cloisonne  |           39.90x |   0.00302 | 59.5x (0.01078)  | 78.8x (0.00302)   |    1.06 |
| synthetic  |           43.90x |   0.00238 | 65.8x (0.00336)  | 87.8x (0.00238)   |    2.23 |

(39.90x: the Y mean is kept as a table of 4096 floats where the Phong fit wants a lobe
sharper than the grid resolves, `compress.resolvable_alpha`.)
At float32 the ratio is fixed by the shapes (43.898x at the seed's 64² x 6561, 40.43x at
4096 pairs: the eigen maps grow with the pairs); the bar (>= 43.9x at a Y MSE within the
seed's 0.0137-0.0359) is met on every baked BTF by n = 4 (and n = 2) at float32 and by the
seed's components with half-float maps, all below the seed's lowest error.
"""

from __future__ import annotations

import argparse
import json
import platform
import resource
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from texelbake.btf.bake import fill_uncovered  # noqa: E402
from texelbake.btf.compress import BTFSettings, to_ycbcr_planes  # noqa: E402
from texelbake.btf.laplacian import reduce  # noqa: E402
from texelbake.btf.pca import pca_batched  # noqa: E402
from texelbake.btf.report import (  # noqa: E402
    btf_report,
    error_vs_components,
    plot_error_vs_components,
)
from texelbake.btf.synthetic import synthetic_btf  # noqa: E402

SEED_REFERENCE = {
    "compression_ratio": 43.9,
    "mse_Y_avg_range": [0.0137, 0.0359],
    "raw_bytes": 80_621_568,
    "build_seconds_bar": 20.0,
}


def load_npz(path: Path):
    """(btf, dirs_i, dirs_o, covered or None) from an .npz (optional key `covered` (h, w) bool:
    atlas texels with data; the others are pull-push filled and left out of the errors)."""
    with np.load(path) as z:
        missing = {"btf", "dirs_i", "dirs_o"} - set(z.files)
        if missing:
            raise SystemExit(f"{path}: missing keys {sorted(missing)} (has {z.files})")
        covered = z["covered"].astype(bool) if "covered" in z.files else None
        return z["btf"].astype(np.float32), z["dirs_i"], z["dirs_o"], covered


#: bake settings of --bake-scenes besides the atlas: the BTF is f̄ (Eq. 7 on the training grid,
#: every sample of the texel), which the CPM fit does not change, so the characteristic point
#: search is kept cheap (c_max 8, one trial, a small held-out grid); 32 samples per texel
BTF_BAKE = {"samples_per_texel": 32, "c_max": 8, "n_trials": 1, "n_heldout": 16}


def bake_scene_btf(name: str, atlas: int, workdir: Path) -> Path:
    """Bake test scene `name` through the pipeline's ingest, geometry and CPM stages with
    btf=True and collect the finest level's f_r tables into `<workdir>/<name><atlas>.npz`
    (keys btf, dirs_i, dirs_o, covered). Tiles already in the artifact store are reused, so an
    interrupted run resumes. Reads the CPM level arrays through `texelbake.stages.cpm.level_key` until the
    pipeline's own BTF stage (`stages.run_btf`) is wired.
    """
    from schemas.settings import BakeSettings
    from texelbake import stages
    from texelbake import testscenes as scenes
    from texelbake.btf.bake import btf_from_texels
    from texelbake.cpm.level import direction_sets
    from texelbake.pipeline.plan import n_tiles
    from texelbake.pipeline.run import run_shard
    from texelbake.stages.cpm import level_key

    folder = workdir / f"{name}{atlas}"
    folder.mkdir(parents=True, exist_ok=True)
    asset = scenes.write_scene(name, folder / "scene.usda", "small")
    s = BakeSettings(atlas_resolution=atlas, shard_texels=min(atlas, 16), btf=True, **BTF_BAKE)
    work = folder / "work"
    t0 = time.perf_counter()
    for stage in ("ingest", "geometry"):
        run_shard(work, asset, s, stage, 0)
    ctx = stages.StageContext.create(work, asset, s)
    ids, fbar, valid = [], [], []
    for tile in range(n_tiles(s)):  # one CPM shard per tile
        run_shard(work, asset, s, "cpm", tile)
        arrays = ctx.store.read_arrays(level_key(ctx, 0, tile))
        ids.append(arrays["texel"])
        fbar.append(arrays["fbar"])
        valid.append(arrays["valid"])
    ids_all, fbar_all, ok = np.concatenate(ids), np.concatenate(fbar), np.concatenate(valid)
    dirs = direction_sets(s)
    n_i, n_o = len(dirs["dirs_i"]), len(dirs["dirs_o"])
    dirs_i = np.repeat(dirs["dirs_i"], n_o, axis=0)  # the CPM grid's row = i * n_o + o
    dirs_o = np.tile(dirs["dirs_o"], (n_i, 1))
    btf, _ = btf_from_texels(fbar_all, ids_all, atlas)
    _, covered = btf_from_texels(fbar_all[ok], ids_all[ok], atlas)
    out = workdir / f"{name}{atlas}.npz"
    np.savez(out, btf=btf, dirs_i=dirs_i, dirs_o=dirs_o, covered=covered)
    print(f"baked {name} at {atlas}^2 in {time.perf_counter() - t0:.0f} s: {out} "
          f"({int(covered.sum())} texels with data)")
    return out


def compare_pca(btf: np.ndarray, settings: BTFSettings) -> dict:
    """Level-1 Y/Cb/Cr PCA by both solvers: seconds and squared error against the optimum."""
    planes = to_ycbcr_planes(btf)  # (3, h, w, d)
    lev1 = np.stack([reduce(planes[c]) for c in range(3)])  # F_1 as a stand-in of L_1's shape
    del planes
    x = lev1.reshape(3, -1, lev1.shape[-1])
    out = {"shape": list(x.shape)}
    for method in ("exact", "randomized"):
        t0 = time.perf_counter()
        res = pca_batched(x, settings.n_components, method=method,
                          oversample=settings.pca_oversample,
                          power_iters=settings.pca_power_iters, seed=settings.seed)
        secs = time.perf_counter() - t0
        rec = np.einsum("btn,bnd->btd", res.weights, res.components.astype(np.float64))
        out[method] = {"seconds": secs, "sq_error": float(((rec - x) ** 2).sum())}
    out["error_ratio_randomized_over_exact"] = (
        out["randomized"]["sq_error"] / max(out["exact"]["sq_error"], 1e-300))
    return out


def run_input(name: str, btf, dirs_i, dirs_o, args, covered=None) -> dict:
    settings = BTFSettings(pca_method=args.pca_method)
    print(f"\n== {name}: {btf.shape[0]} pairs, {btf.shape[1]} x {btf.shape[2]} texels, "
          f"{btf.nbytes / 1e6:.0f} MB float32")
    if covered is not None:
        print(f"{int(covered.sum())} of {covered.size} texels covered by the atlas; the rest "
              "pull-push filled and not counted in the errors")
        btf = fill_uncovered(btf, covered)
    maps, rep = btf_report(btf, dirs_i, dirs_o, settings, texel_mask=covered)
    sec = rep["seconds"]
    print(f"build {sec['build_total']:.2f} s wall ({rep['cpu_seconds_build']:.2f} s CPU): "
          + ", ".join(f"{k} {v:.2f}" for k, v in sec.items() if k not in ("build_total",)))
    print(f"lambda_max {rep['top_level']}, PCA {rep['pca_methods']}, mean {rep['mean_models']}; "
          f"{rep['fit_message']}")
    print(f"compression {rep['compression_ratio']:.3f}x (8-bit raw {rep['raw_bytes_8bit']} B / "
          f"{rep['compressed_bytes']} B; float32 raw: {rep['compression_ratio_float32']:.1f}x; "
          f"LUT {rep['lut_bytes']} B extra)")
    for ch, m in rep["mse"].items():
        print(f"  MSE {ch:2s}: avg {m['avg']:.5f}  min {m['min']:.5f}  max {m['max']:.5f}")
    del maps
    rows = error_vs_components(btf, dirs_i, dirs_o, args.n, settings, texel_mask=covered)
    print(f"{'n':>4} {'seconds':>8} {'cpu s':>8} {'ratio':>8} {'Y avg':>9} {'Y min':>9} "
          f"{'Y max':>9} {'Cb avg':>9} {'Cr avg':>9}")
    for r in rows:
        m = r["mse"]
        print(f"{r['n']:>4} {r['seconds']:>8.2f} {r['cpu_seconds']:>8.2f} "
              f"{r['compression_ratio']:>8.2f} {m['Y']['avg']:>9.5f} {m['Y']['min']:>9.5f} "
              f"{m['Y']['max']:>9.5f} {m['Cb']['avg']:>9.5f} {m['Cr']['avg']:>9.5f}")
    plot = Path(args.json).with_name(f"{Path(args.json).stem}_{name}_components.png") \
        if args.json else Path(f"btf_{name}_components.png")
    plot_error_vs_components(rows, plot, title=f"{name}: Y error vs components (Fig. 6)")
    print(f"plot: {plot}")
    result = {
        "compression_ratio": rep["compression_ratio"],
        "mse": rep["mse"],
        "seconds": rep["seconds"],
        "cpu_seconds_build": rep["cpu_seconds_build"],
        "report": rep,
        "components": rows,
        "plot": str(plot),
    }
    half = BTFSettings(pca_method=args.pca_method, storage="float16")
    _, rep16 = btf_report(btf, dirs_i, dirs_o, half, texel_mask=covered)
    result["float16_storage"] = {k: rep16[k] for k in ("compression_ratio", "mse", "seconds",
                                                        "compressed_bytes")}
    print(f"float16 maps: {rep16['compression_ratio']:.2f}x, MSE Y avg "
          f"{rep16['mse']['Y']['avg']:.5f} (Cb {rep16['mse']['Cb']['avg']:.5f}, Cr "
          f"{rep16['mse']['Cr']['avg']:.5f}), build {rep16['seconds']['build_total']:.2f} s")
    result["bar"] = bar_verdict(rep, rows, rep16)
    b = result["bar"]
    print(f"bar (>= {SEED_REFERENCE['compression_ratio']}x at Y MSE avg <= "
          f"{SEED_REFERENCE['mse_Y_avg_range'][1]}): "
          + ("met by " + ", ".join(f"{c['config']} ({c['compression_ratio']:.1f}x, Y "
                                   f"{c['y_mse_avg']:.5f})" for c in b["met_by"])
             if b["ratio_ok"] else "not met")
          + f"; the seed's settings (8/2/2 float32): {rep['compression_ratio']:.2f}x")
    if args.compare_pca:
        result["pca_solvers_level1"] = compare_pca(btf, settings)
        c = result["pca_solvers_level1"]
        print(f"level-1 PCA {c['shape']}: exact {c['exact']['seconds']:.2f} s, randomized "
              f"{c['randomized']['seconds']:.2f} s, error ratio "
              f"{c['error_ratio_randomized_over_exact']:.5f}")
    return result


def bar_verdict(rep: dict, rows: list[dict], rep16: dict) -> dict:
    """The issue's bar: a compression ratio >= the seed's 43.9x at a Y MSE (avg over direction
    images) no worse than the seed's range (<= 0.0359), reached by some configuration printed
    here: the seed's settings (n = 8, 2, 2, float32 maps), the sweep over n (float32), or
    half-float maps. At float32 the ratio is fixed by the shapes (the eigen maps grow with the
    number of direction pairs: 40.4x at 64^2 texels x 4096 pairs, 43.898x at the seed's 6561),
    so the verdict names the configurations that reach it, strictly, with their errors."""
    cap = SEED_REFERENCE["mse_Y_avg_range"][1]
    configs = [("n=8/2/2 float32 (seed)", rep)]
    configs += [(f"n={r['n']} float32", r) for r in rows]
    configs.append(("n=8/2/2 float16", rep16))
    met = [{"config": name, "compression_ratio": r["compression_ratio"],
            "y_mse_avg": r["mse"]["Y"]["avg"]} for name, r in configs
           if r["compression_ratio"] >= SEED_REFERENCE["compression_ratio"]
           and r["mse"]["Y"]["avg"] <= cap]
    return {
        "ratio_ok": bool(met),
        "met_by": met,
        "seed_settings_ratio": rep["compression_ratio"],
        "y_mse_ok": rep["mse"]["Y"]["avg"] <= cap,
        "time_ok": rep["seconds"]["build_total"] <= SEED_REFERENCE["build_seconds_bar"],
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("inputs", nargs="*", type=Path, help=".npz files with btf, dirs_i, dirs_o")
    ap.add_argument("--synthetic", action="store_true", help="add the 64x64x81x81 synthetic BTF")
    ap.add_argument("--bake-scenes", nargs="*", default=None, metavar="SCENE",
                    help="bake these test scenes (cylinder wall bolt cloisonne; none listed = "
                         "all four) through the pipeline's CPM stage and add their BTFs")
    ap.add_argument("--atlas", type=int, default=32, help="atlas resolution of --bake-scenes")
    ap.add_argument("--bake-dir", type=Path, default=Path("out/btf_bakes"))
    ap.add_argument("--size", type=int, default=64, help="synthetic texels per side")
    ap.add_argument("--save-synthetic", type=Path, default=None, help="also write it as .npz")
    ap.add_argument("--n", type=int, nargs="+", default=[2, 4, 8, 16])
    ap.add_argument("--pca-method", default="auto", choices=["auto", "exact", "randomized"])
    ap.add_argument("--compare-pca", action="store_true")
    ap.add_argument("--json", type=str, default=None, help="write the results here")
    args = ap.parse_args(argv)
    if args.bake_scenes is not None:
        from texelbake.testscenes import SCENE_NAMES

        for name in args.bake_scenes or SCENE_NAMES:
            args.inputs.append(bake_scene_btf(name, args.atlas, args.bake_dir))
    if not args.inputs and not args.synthetic:
        ap.error("give .npz inputs, --bake-scenes and/or --synthetic")
    results = {}
    for path in args.inputs:
        btf, di, do, covered = load_npz(path)
        results[path.stem] = run_input(path.stem, btf, di, do, args, covered)
        del btf
    if args.synthetic:
        t0 = time.perf_counter()
        btf, di, do = synthetic_btf(args.size)
        print(f"synthetic BTF generated in {time.perf_counter() - t0:.1f} s")
        if args.save_synthetic:
            np.savez(args.save_synthetic, btf=btf, dirs_i=di, dirs_o=do)
        results["synthetic"] = run_input("synthetic", btf, di, do, args)
    out = {
        "inputs": results,
        "seed_reference": SEED_REFERENCE,
        "machine": {"platform": platform.platform(), "python": platform.python_version(),
                    "max_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024},
    }
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(out, indent=2, sort_keys=True))
        print(f"\nJSON: {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
