"""cpm on a coarser M_i: where a hit reads the atlas (`render.cpm.UV_FROM`), A/B on one bake.

    .venv/bin/python benchmarks/uv_from.py --baked BAKED.usda --json out.json
        [--size 512] [--ref-spp 256] [--spp 4,16] [--seeds 6]

At the `lod` view (a finest texel ~0.7 pixel, the renderer's default mesh choice), renders
gt at --ref-spp as the reference, then cpm at each --spp with --seeds seeds for "closest"
(seed 000 §4.1's composite map: M_i's own uvs or the closest atlas-mesh point) and "ray" (the
default: where the eye ray, carried on, meets the atlas mesh), and gt at the same spp for
scale; prints per mode the object PSNR's mean and spread over the seeds and the median
seconds. Measured: docs/decisions.md 2026-11-28 (`benchmarks/results/uv_from_*.json`).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from texelbake.render import metrics
from texelbake.render.frame import render_frame
from texelbake.render.scene import load_scene, lod_camera


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--baked", type=Path, required=True)
    ap.add_argument("--json", type=Path, required=True)
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--ref-spp", type=int, default=256)
    ap.add_argument("--spp", default="4,16")
    ap.add_argument("--seeds", type=int, default=6)
    args = ap.parse_args(argv)
    scene = load_scene(args.baked)
    cam = lod_camera(scene, args.size, args.size)
    ref = render_frame(scene, "gt", cam, args.ref_spp, seed=1000)

    def psnr(res) -> float:
        mask = metrics.object_mask(ref.coverage, res.coverage)
        return float(metrics.object_errors(res.image, ref.image, mask)["psnr_db_object"])

    rows = []
    for spp in (int(s) for s in args.spp.split(",")):
        for label, mode, kw in (("cpm closest", "cpm", {"uv_from": "closest"}),
                                ("cpm ray", "cpm", {"uv_from": "ray"}), ("gt", "gt", {})):
            runs = [render_frame(scene, mode, cam, spp, seed=s, **kw)
                    for s in range(args.seeds)]  # a loop over the few seeds
            db = [psnr(r) for r in runs]
            rows.append({"mode": label, "spp": spp, "psnr_db": round(float(np.mean(db)), 3),
                         "psnr_db_spread": round(float(np.std(db, ddof=1)), 3),
                         "psnr_db_seeds": [round(x, 3) for x in db],
                         "seconds": round(float(np.median([r.seconds for r in runs])), 4),
                         "mesh": runs[0].extras.get("mesh")})
            print(f"{label:<12} {spp:>4} spp  {rows[-1]['psnr_db']:6.2f} ± "
                  f"{rows[-1]['psnr_db_spread']:.2f} dB  {rows[-1]['seconds']:.2f} s  "
                  f"{rows[-1]['mesh'] or ''}", flush=True)
    out = {"baked": str(args.baked), "size": args.size, "ref_spp": args.ref_spp,
           "seeds": args.seeds, "object_pixels": int((ref.coverage > 0).sum()), "rows": rows}
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(out, indent=2))
    return out


if __name__ == "__main__":
    main()
