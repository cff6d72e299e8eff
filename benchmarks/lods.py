"""LODs chosen by geometric error (issue 22): per asset and LOD the triangle count, the
two-sided Hausdorff distance to M_org relative to the bounding-box diagonal beside its bound,
the switch size, and the bake's seconds (geometry stage and total).

    python benchmarks/lods.py --json bench_out/lods.json
    python benchmarks/lods.py --mode atlas --json bench_out/lods_atlas.json   # before issue 22

Assets: the four generated scenes at `--size` (small), the Teapot and BoxAnimated.usdz from
../shared/assets. Bakes with BakeSettings() defaults except `--mode` and, with `--fast`, a
light CPM (8 samples per texel, 8 x 8 directions, c_max 8) that leaves the geometry stage as
at defaults (it depends only on the atlas resolution, samples per texel and the LOD fields).
The Blender columns (issue 22's acceptance): each LOD exported with `texelbake export --lod N`
(.usdz), imported with Blender 5.0.1's USD importer at its defaults and rendered beside the
original from one camera and sun (tests/blender/import_render.py through tests/helpers/dcc: Cycles
CPU, 160 px, 32 samples, deterministic): `MAD` is the mean absolute difference over the
object's pixels (8-bit sRGB as displayed, [0, 1]) and `IoU` the silhouettes' overlap. Per asset
PASS needs LOD1 IoU >= 0.95, LOD1 MAD <= 0.10 and every LOD within its Hausdorff bound; a FAIL
names what missed. Renders (and a side-by-side row.png per asset) go to `--renders DIR`
(default: beside the JSON, else the work folder). `--no-blender` skips these columns.

At defaults (2026-11-26, benchmarks/results/lods.json; bake s on a 2-core machine at load 3-10):

    asset         lod   tris   H/diag    bound  ok switch px   method  geom s  bake s     MAD     IoU
    cylinder        1    200   0.0000   0.0039   y       256      qem    1.16    58.5   0.019   1.000
    wall            1    360   0.0000   0.0039   y       256 original    1.82    83.8   0.009   1.000
    bolt            1    648   0.0000   0.0039   y       256      qem    2.78   120.4   0.035   1.000
    cloisonne       1    512   0.0038   0.0039   y       256      qem    4.16   256.7   0.049   0.996
    cloisonne       2     96   0.0137   0.0156   y        64      qem    4.16   256.7   0.055   0.981
    teapot          1   1340   0.0030   0.0039   y       256      qem   26.01   505.2   0.014   0.996
    teapot          2    428   0.0119   0.0156   y        64      qem   26.01   505.2   0.024   0.985
    box_animated    1     71   0.0027   0.0039   y       256      qem    7.32   340.3   0.098   0.998

All six PASS this bar. The quality gate (a separate verdict, printed after the table and in
each row's `quality_missed`) missed on the cloisonne in that run (CPM level 3's held-out SNR p5
-7.7 dB against the -6 dB floor), which had the coarse levels' dense refit on by default (an
experiment since removed, docs/decisions.md); without it all six pass it (`--no-blender`,
benchmarks/results/lods_gate.json, bakes of 39-61 s at load 1.5-3; the LODs and fallback maps
the Blender columns see do not depend on that setting). Read with care: Blender cannot evaluate texelbake's cellular shader, so its
"original" cloisonne is plain pink while the LOD's fallback shows the baked cells; most of
BoxAnimated's 0.095 is the original's own dark triangles in Cycles, which no LOD reproduces
(they stay with its custom normals cleared and flat shading: they come from its geometry).
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

from schemas.settings import BakeSettings
from texelbake.pipeline.run import bake
from texelbake.testscenes import write_scene

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))
ASSETS = ROOT.parent / "shared" / "assets"
SCENES = ("cylinder", "wall", "bolt", "cloisonne")
IOU_MIN, MAD_MAX = 0.95, 0.10  # the bar on LOD1 (tests/dcc/test_blender_import.py: why)
FAST = {"samples_per_texel": 8, "n_light_dirs": 8, "n_view_dirs": 8, "n_heldout": 16,
        "c_max": 8}


def run(asset: str, src: Path, out: Path, settings: BakeSettings) -> list[dict]:
    t0 = time.perf_counter()
    root = bake(src, out, settings, progress=False, workdir=out.with_name(out.name + "_work"))
    total = time.perf_counter() - t0
    report = json.loads((root.parent / "report.json").read_text())
    lods = report["lods"]
    rows = []
    for i, lv in enumerate(lods["levels"], start=1):
        rows.append({
            "asset": asset, "lod": i, "triangles": lv["triangles"],
            "hausdorff_rel": lv["hausdorff_rel"], "bound_rel": lv["bound_rel"],
            "within_bound": lv["within_bound"], "switch_px": lv["switch_px"],
            "method": lv["method"], "enclosed": lv["enclosed"],
            "geometry_seconds": json.loads((root.parent / "run.json").read_text())[
                "stage_seconds"].get("geometry"),
            "bake_seconds": round(total, 3),
            "atlas_is_lod1": lods.get("atlas_mesh", {}).get("is_lod1"),
            "stopped": lods.get("stopped", ""),
            "quality_missed": report.get("quality", {}).get("missed", []),
            "blender_mad": None, "blender_iou": None,
        })
    return rows


def blender_columns(asset: str, src: Path, root: Path, rows: list[dict], renders: Path) -> str:
    """Fill each row's blender_mad / blender_iou; returns "" or why they are not measured."""
    import pytest

    from tests.helpers.dcc import compare_renders, import_and_render, side_by_side
    from texelbake.usd.export import export_lod

    files = {"original": src}
    for r in rows:
        files[f"lod{r['lod']}"] = export_lod(root, r["lod"], root.parent.with_name(
            f"{asset}_export") / f"lod{r['lod']}.usdz")
    try:
        got = import_and_render(files, renders / asset, resolution=160, samples=32)
    except (Exception, pytest.fail.Exception, pytest.skip.Exception) as e:
        return f"Blender not run: {str(e).splitlines()[0]}"
    ref = got["files"]["original"]["png"]
    for r in rows:
        c = compare_renders(ref, got["files"][f"lod{r['lod']}"]["png"])
        r["blender_mad"], r["blender_iou"] = round(c["mad"], 4), round(c["iou"], 4)
    side_by_side([Path(got["files"][k]["png"]) for k in files], renders / asset / "row.png")
    return ""


def verdict(rows: list[dict]) -> tuple[bool, list[str]]:
    """PASS/FAIL of one asset against the issue's bar, with what missed."""
    why = []
    lod1 = rows[0]
    if lod1["blender_iou"] is None:
        why.append("Blender columns not measured")
    else:
        if lod1["blender_iou"] < IOU_MIN:
            why.append(f"LOD1 IoU {lod1['blender_iou']:.3f} < {IOU_MIN}")
        if lod1["blender_mad"] > MAD_MAX:
            why.append(f"LOD1 MAD {lod1['blender_mad']:.3f} > {MAD_MAX}")
    for r in rows:
        if r["within_bound"] is False:
            why.append(f"LOD{r['lod']} Hausdorff {r['hausdorff_rel']:.4f} > bound "
                       f"{r['bound_rel']:.4f}")
    return not why, why


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--json", type=Path, help="write the rows here")
    ap.add_argument("--size", default="small")
    ap.add_argument("--mode", choices=("error", "atlas"), default="error")
    ap.add_argument("--fast", action="store_true", help="light CPM (geometry as at defaults)")
    ap.add_argument("--assets", nargs="*", help="subset of the asset names")
    ap.add_argument("--renders", type=Path, help="keep the Blender renders here")
    ap.add_argument("--no-blender", action="store_true", help="skip the Blender columns")
    args = ap.parse_args()
    settings = BakeSettings(lod_mode=args.mode, **(FAST if args.fast else {}))
    work = Path(tempfile.mkdtemp(prefix="lods_bench_"))
    cases: dict[str, Path] = {}
    for name in SCENES:
        cases[name] = write_scene(name, work / f"{name}.usda", args.size)
    cases["teapot"] = ASSETS / "Teapot" / "Teapot.usd"
    cases["box_animated"] = ASSETS / "BoxAnimated.usdz"
    renders = args.renders or (args.json.parent / "lods_renders" if args.json
                               else work / "renders")
    rows: list[dict] = []
    not_measured: dict[str, str] = {}
    for name, src in cases.items():
        if args.assets and name not in args.assets:
            continue
        if not src.is_file():
            print(f"{name}: {src} is missing, skipped")
            continue
        out = work / f"{name}_baked"
        got = run(name, src, out, settings)
        if args.no_blender:
            not_measured[name] = "--no-blender"
        else:
            root = next(out.glob("*_baked.usda"))
            if renders.exists() and (renders / name).exists():
                shutil.rmtree(renders / name)
            not_measured[name] = blender_columns(name, src, root, got, renders)
        rows.extend(got)
    head = (f"{'asset':<13}{'lod':>4}{'tris':>7}{'H/diag':>9}{'bound':>9}{'ok':>4}"
            f"{'switch px':>10}{'method':>9}{'geom s':>8}{'bake s':>8}{'MAD':>8}{'IoU':>8}")
    print(f"lod_mode={args.mode} fast={args.fast} size={args.size}")
    print(head)
    for r in rows:
        bound = "-" if r["bound_rel"] is None else f"{r['bound_rel']:.4f}"
        ok = "-" if r["within_bound"] is None else ("y" if r["within_bound"] else "N")
        px = "-" if r["switch_px"] is None else f"{r['switch_px']:g}"
        print(f"{r['asset']:<13}{r['lod']:>4}{r['triangles']:>7}{r['hausdorff_rel']:>9.4f}"
              f"{bound:>9}{ok:>4}{px:>10}{r['method']:>9}{r['geometry_seconds']:>8.2f}"
              f"{r['bake_seconds']:>8.1f}"
              + ("       -       -" if r["blender_mad"] is None else
                 f"{r['blender_mad']:>8.3f}{r['blender_iou']:>8.3f}"))
    verdicts = {}
    for name in dict.fromkeys(r["asset"] for r in rows):
        ok, why = verdict([r for r in rows if r["asset"] == name])
        if not_measured.get(name):
            why = [not_measured[name]] + [w for w in why if "not measured" not in w]
        verdicts[name] = {"pass": ok, "why": why}
        print(f"{name}: {'PASS' if ok else 'FAIL'}"
              f" (LOD1 IoU >= {IOU_MIN}, MAD <= {MAD_MAX}, Hausdorff within bound)"
              + ("" if ok else ": " + "; ".join(why)))
    if not args.no_blender:
        print(f"renders (original, LOD1, LOD2 side by side: <asset>/row.png): {renders}")
    for r in rows:
        if r["lod"] == 1 and r["stopped"]:
            print(f"{r['asset']}: {r['stopped']}")
        if r["lod"] == 1:
            missed = r["quality_missed"]
            print(f"{r['asset']}: quality gate {'missed: ' + '; '.join(missed) if missed else 'passed'}")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"mode": args.mode, "fast": args.fast,
                                         "size": args.size,
                                         "settings": settings.model_dump(), "rows": rows,
                                         "bar": {"lod1_iou_min": IOU_MIN,
                                                 "lod1_mad_max": MAD_MAX},
                                         "verdicts": verdicts},
                                        indent=1, sort_keys=True))


if __name__ == "__main__":
    main()
