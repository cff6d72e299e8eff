"""LODs chosen by geometric error (issue 22): per asset and LOD the triangle count, the
two-sided Hausdorff distance to M_org relative to the bounding-box diagonal beside its bound,
the switch size, and the bake's seconds (geometry stage and total).

    python benchmarks/lods.py --json bench_out/lods.json
    python benchmarks/lods.py --mode atlas --json bench_out/lods_atlas.json   # before issue 22

Assets: the four generated scenes at `--size` (small), the Teapot and BoxAnimated.usdz from
../shared/assets. Bakes with BakeSettings() defaults except `--mode` and, with `--fast`, a
light CPM (8 samples per texel, 8 x 8 directions, c_max 8) that leaves the geometry stage as
at defaults (it depends only on the atlas resolution, samples per texel and the LOD fields).
The Blender columns of the issue's acceptance (object-pixel difference, silhouette IoU) are not
measured here: Blender is not installed (issue 22, item 5).
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

from schemas.settings import BakeSettings
from texelbake.pipeline import bake
from texelbake.scenes import write_scene

ASSETS = Path(__file__).resolve().parents[2] / "shared" / "assets"
SCENES = ("cylinder", "wall", "bolt", "cloisonne")
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
            "geometry_seconds": report["stage_seconds"].get("geometry"),
            "bake_seconds": round(total, 3),
            "atlas_is_lod1": lods.get("atlas_mesh", {}).get("is_lod1"),
            "stopped": lods.get("stopped", ""),
            "quality_missed": report.get("quality", {}).get("missed", []),
        })
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--json", type=Path, help="write the rows here")
    ap.add_argument("--size", default="small")
    ap.add_argument("--mode", choices=("error", "atlas"), default="error")
    ap.add_argument("--fast", action="store_true", help="light CPM (geometry as at defaults)")
    ap.add_argument("--assets", nargs="*", help="subset of the asset names")
    args = ap.parse_args()
    settings = BakeSettings(lod_mode=args.mode, **(FAST if args.fast else {}))
    work = Path(tempfile.mkdtemp(prefix="lods_bench_"))
    cases: dict[str, Path] = {}
    for name in SCENES:
        cases[name] = write_scene(name, work / f"{name}.usda", args.size)
    cases["teapot"] = ASSETS / "Teapot" / "Teapot.usd"
    cases["box_animated"] = ASSETS / "BoxAnimated.usdz"
    rows: list[dict] = []
    for name, src in cases.items():
        if args.assets and name not in args.assets:
            continue
        if not src.is_file():
            print(f"{name}: {src} is missing, skipped")
            continue
        rows.extend(run(name, src, work / f"{name}_baked", settings))
    head = (f"{'asset':<13}{'lod':>4}{'tris':>7}{'H/diag':>9}{'bound':>9}{'ok':>4}"
            f"{'switch px':>10}{'method':>9}{'geom s':>8}{'bake s':>8}")
    print(f"lod_mode={args.mode} fast={args.fast} size={args.size}")
    print(head)
    for r in rows:
        bound = "-" if r["bound_rel"] is None else f"{r['bound_rel']:.4f}"
        ok = "-" if r["within_bound"] is None else ("y" if r["within_bound"] else "N")
        px = "-" if r["switch_px"] is None else f"{r['switch_px']:g}"
        print(f"{r['asset']:<13}{r['lod']:>4}{r['triangles']:>7}{r['hausdorff_rel']:>9.4f}"
              f"{bound:>9}{ok:>4}{px:>10}{r['method']:>9}{r['geometry_seconds']:>8.2f}"
              f"{r['bake_seconds']:>8.1f}")
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
                                         "settings": settings.model_dump(), "rows": rows},
                                        indent=1, sort_keys=True))


if __name__ == "__main__":
    main()
