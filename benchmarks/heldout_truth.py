"""How close the held-out truth is to the surface it stands for: per level, two disjoint halves
of each measured texel's truth samples, each summed as the truth is (`cpm.dense.held_pass`),
scored against each other with the held-out SNR (`cpm.dense.heldout_snr`).

    python benchmarks/heldout_truth.py --scene ../shared/assets/Teapot/Teapot.usd --atlas 16 \
        [--spt 64] [--texels 64] [--json out.json]

The halves are independent draws of the same texel, so their difference holds twice a half's
noise, four times the whole truth's: the whole truth's SNR against the continuous surface is
about the split-half SNR + 6 dB (a lower bound: the samples are stratified per triangle, a
random half is not). A fit scored against the truth above that figure reproduces the samples'
noise, not the surface. Ingest and geometry only (cached in --workdir); no fit.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np
from cpm_cpu import stages_asset

from schemas.settings import BakeSettings
from texelbake import stages
from texelbake.cpm.dense import (
    LevelPass,
    dense_of,
    held_pass,
    heldout_snr,
    to_texel,
)
from texelbake.cpm.level import segment_sum, texel_ids
from texelbake.cpm.truth_sample import measured_texels, truth_samples
from texelbake.pipeline.process import setup_bake_process

#: the split's seed (any: the halves are a seeded draw per level)
SPLIT_SEED = 7


def split_half(ctx: stages.StageContext, level: int, max_texels: int) -> dict:
    src = ctx.fit_inputs()
    n = ctx.settings.atlas_resolution
    lp = LevelPass.of(src, level)
    tex = np.unique(texel_ids(src.geo, n, level))
    tex = tex[tex >= 0]
    tex = tex[measured_texels(src, level, tex)][:max_texels]
    dense, dseg = dense_of(lp, tex)
    truth = truth_samples(src, level, tex, dense, dseg)
    area = src.geo["sample_area"][dense]
    half = np.random.default_rng([SPLIT_SEED, level]).random(dense.size) < 0.5
    t0 = time.process_time()
    sums = []
    for mask in (half, ~half):
        w = area * truth * mask
        ref, _, avis_h = held_pass(lp, tex, dense, dseg, np.zeros(0, np.int64),
                                   np.zeros(0, np.int64), np.zeros((0, 3)), want_ref=True,
                                   truth_w=w)
        sums.append(to_texel(ref, avis_h, segment_sum(area, dseg, len(tex), 0),
                             segment_sum(w, dseg, len(tex), 0)))
    texel_area = segment_sum(area, dseg, len(tex), 0)
    snr = np.array([heldout_snr(sums[0][0][t], sums[1][0][t],
                                0.5 * (sums[0][1][t] + sums[1][1][t]), float(texel_area[t]))
                    for t in range(len(tex))])  # a loop over the measured texels
    snr = snr[np.isfinite(snr)]
    return {"level": level, "texels": int(len(tex)),
            "samples_per_texel": round(dense.size / max(len(tex), 1), 1),
            "split_half_median_db": round(float(np.median(snr)), 2) if snr.size else None,
            "split_half_p5_db": round(float(np.percentile(snr, 5)), 2) if snr.size else None,
            "cpu_seconds": round(time.process_time() - t0, 2)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="cylinder",
                    help="a generated scene's name (size full), or the path of a USD file")
    ap.add_argument("--atlas", type=int, default=16)
    ap.add_argument("--spt", type=int, default=None, help="samples_per_texel (default: the bake's)")
    ap.add_argument("--texels", type=int, default=64, help="measured texels per level, at most")
    ap.add_argument("--workdir", type=Path, default=None)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    setup_bake_process()
    work = args.workdir or Path(tempfile.mkdtemp(prefix="texelbake-truth-"))
    asset = stages_asset(args.scene, "full", work)
    over = {"atlas_resolution": args.atlas,
            "shard_texels": min(args.atlas, BakeSettings().shard_texels)}
    if args.spt is not None:
        over["samples_per_texel"] = args.spt
    ctx = stages.StageContext.create(work / "store", asset, BakeSettings(**over))
    stages.run_ingest(ctx, 0)
    stages.run_geometry(ctx, 0)
    spt = ctx.settings.samples_per_texel
    print(f"{asset.name}: atlas {args.atlas}², samples_per_texel {spt}")
    print("level  texels  samples/texel  split-half med  p5   (truth vs surface ~ med + 6 dB)")
    rows = []
    for level in range(ctx.n_levels):  # a loop over the levels
        r = split_half(ctx, level, args.texels)
        rows.append(r)
        print(f"{level:>5} {r['texels']:>7} {r['samples_per_texel']:>14} "
              f"{r['split_half_median_db']:>15} {r['split_half_p5_db']:>5}", flush=True)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"scene": str(args.scene), "atlas": args.atlas,
                                         "samples_per_texel": spt, "levels": rows},
                                        indent=1) + "\n")
        print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
