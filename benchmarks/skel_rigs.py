"""Skinned characters: are the LOD meshes bound to the skeleton, and how far does UsdSkel pose
them from the skinned original? Per asset and LOD, read back by a plain pxr process
(tests/helpers/skel_rigs.py `plain_pxr`: UsdSkel.Cache, ComputeSkinnedPoints, no texelbake
import) at every `--frames` time code:

- `lod_animation` (report.json: usdskel / time_samples) and the report's line when not bound;
- `rest_exact`: max |LOD posed by UsdSkel at the rest time − its rest vertices (p0)| / diag;
- `rest_err`: the LOD vertices' largest distance to the original at the rest time / diag (its
  own simplification error);
- `excess`: max over times and vertices of (distance to the skinned original at t − that
  vertex's distance at rest) / diag: what posing adds;
- `bar_margin`: min over times and vertices of the tests' bar (tests/usd/test_skel_rigs.py:
  κ_t e_rest + 1.05 dev_t + 1e-5 diag) minus the distance, / diag (≥ 0: within the bar);
- `renderer`: max |renderer's deformed LOD (texelbake.render.deformed) − UsdSkel's| / diag;
- bake seconds (load average printed; a 2-core machine is noisy).

    python benchmarks/skel_rigs.py --json bench_out/skel_rigs.json
    python benchmarks/skel_rigs.py --asset CesiumMan.usdz --frames 1,12,24,36,48 --json out.json

Without `--asset`: the test leg (two meshes, joint subsets, geomBindTransforms, a rest pose
that is not the bind pose) and the leg with a static unskinned prop. Bakes with a light CPM
(16² atlas, 8 samples per texel, 8 × 8 directions, c_max 8), LODs by error (defaults).

Measured (load 11-13 on 2 cores; CesiumMan.usdz and RiggedFigure.usdz from usd-wg/assets
test_assets/USDZ, CC-BY 4.0, not in the repository; `--frames 1,12,24,36,48` and `0,30`):

    asset        lod  verts  animation  rest_exact  rest_err   excess  renderer
    leg            1    183    usdskel     8.3e-08    0.0024  1.8e-03   8.3e-08
    leg            2     41    usdskel     4.2e-08    0.0092  1.8e-03   4.7e-08
    leg+prop       1    127    usdskel     7.0e-08    0.0037  1.6e-03   7.0e-08
    leg+prop       2     43    usdskel     3.5e-08    0.0078  4.8e-04   4.6e-08
    CesiumMan      1    467    usdskel     6.7e-08    0.0038  2.3e-03   1.2e-07
    CesiumMan      2    131    usdskel     6.7e-08    0.0098  1.8e-03   9.9e-08
    RiggedFigure   1    130    usdskel     7.4e-08    0.0000  7.4e-08   1.1e-07
    RiggedFigure   2     87    usdskel     7.4e-08    0.0144  3.1e-04   1.2e-07

Every row is within the tests' bar. Before bind-space points, the three public characters'
LODs (and BrainStem's) were time-sampled: their rest pose is not a rigid image of the bind pose.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from schemas.settings import BakeSettings  # noqa: E402
from tests.helpers.skel_rigs import (  # noqa: E402
    blend_deviation,
    original_surface,
    plain_pxr,
    surface_distance,
    write_rig,
)
from texelbake.pipeline.run import bake  # noqa: E402

LIGHT = {"atlas_resolution": 16, "samples_per_texel": 8, "n_light_dirs": 8, "n_view_dirs": 8,
         "n_heldout": 16, "c_max": 8}


def measure(name: str, src: Path, out: Path, frames: tuple[float, ...]) -> list[dict]:
    from texelbake.render.deformed import deform_scene
    from texelbake.render.deformed_report import warp_at_time
    from texelbake.render.scene import load_scene

    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        root = bake(src, out, BakeSettings(**LIGHT), progress=False)
    seconds = time.perf_counter() - t0
    report = json.loads((root.parent / "report.json").read_text())
    got = plain_pxr(root, frames)
    scene = load_scene(root)
    diag = scene.diag
    skinned = report["lod_animation"] == "usdskel"
    v0, f0 = original_surface(got, frames[0])
    lods = sorted((p for p in got["meshes"] if "/Baked/LOD" in p),
                  key=lambda p: int(p.rsplit("LOD", 1)[1]))
    rows = []
    for i, path in enumerate(lods):
        pos = got["meshes"][path]["t"]
        d0 = surface_distance(np.array(pos[str(frames[0])]), v0, f0)
        row = {"asset": name, "lod": i + 1, "vertices": len(d0),
               "lod_animation": report["lod_animation"],
               "not_bound": [w for w in report["warnings"] if "not transferred" in w],
               "rest_exact": float(np.abs(np.array(pos[str(frames[0])])
                                          - scene.baked.meshes[i].vertices).max()) / diag,
               "rest_err": float(d0.max()) / diag, "excess": 0.0, "bar_margin": np.inf,
               "renderer": 0.0, "bake_seconds": round(seconds, 2)}
        for t in frames:  # a loop over the few frames measured
            vt, ft = original_surface(got, t)
            dev, kappa = blend_deviation(got, t, frames[0]) if skinned else (0.0, 1.5)
            dt = surface_distance(np.array(pos[str(t)]), vt, ft)
            bar = kappa * d0 + 1.05 * dev + 1e-5 * diag
            row["excess"] = max(row["excess"], float((dt - d0).max()) / diag)
            row["bar_margin"] = min(row["bar_margin"], float((bar - dt).min()) / diag)
            if skinned:
                d = deform_scene(scene, warp_at_time(scene.asset, t))
                usd = np.array(pos[str(t)])
                row["renderer"] = max(row["renderer"], float(np.abs(
                    d.baked.meshes[i].vertices[: len(usd)] - usd).max()) / diag)
        rows.append(row)
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--asset", type=Path, action="append", default=[],
                    help="a skinned USD asset (repeatable; default: the test leg and prop rigs)")
    ap.add_argument("--frames", default="0,12,24",
                    help="time codes, the first the rest time (default 0,12,24: the rigs')")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    frames = tuple(float(x) for x in args.frames.split(","))
    rows: list[dict] = []
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        cases = [(p.stem, p.resolve()) for p in args.asset] or [
            ("leg", write_rig(work / "leg.usda")),
            ("leg+prop", write_rig(work / "prop.usda", prop=True))]
        for name, src in cases:
            rows += measure(name, src, work / f"{name}_out", frames)
    head = (f"{'asset':10} {'lod':>3} {'verts':>6} {'animation':>12} {'rest_exact':>10} "
            f"{'rest_err':>8} {'excess':>9} {'bar_margin':>10} {'renderer':>9} {'bake s':>7}")
    print(f"load average {os.getloadavg()[0]:.1f}; distances relative to the diagonal")
    print(head)
    for r in rows:
        print(f"{r['asset']:10} {r['lod']:>3} {r['vertices']:>6} {r['lod_animation']:>12} "
              f"{r['rest_exact']:>10.1e} {r['rest_err']:>8.4f} {r['excess']:>9.1e} "
              f"{r['bar_margin']:>10.1e} {r['renderer']:>9.1e} {r['bake_seconds']:>7.1f}")
        for w in r["not_bound"]:
            print(f"    {w}")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"frames": frames, "load_average": os.getloadavg()[0],
                                         "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
