"""What splits a level's fitted finest texels into many candidates: the groups that
`texelbake.cpm.cluster` would make of their dense samples under all its keys, without each key
in turn, and with the samples' own visibility patterns on the directions above a cosine in
place of the visibility keys (the light share those directions drop beside it). A key whose
removal collapses the groups is where the candidates' count comes from.

    python benchmarks/cluster_keys.py --scene bolt --atlas 128 [--stride 4] [--json PATH]

Ingest and geometry run once (cached in --workdir); then level 0's classes on every
`--stride`-th occupied texel, and the samples of the texels they send to the fit, with their
visibility on every training direction (their own rays, as the classes cast them).
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np
from cpm_cpu import stages_asset

from schemas.settings import BakeSettings
from texelbake import stages
from texelbake.cpm import cluster
from texelbake.cpm.classify import REASONS, visibility_patterns
from texelbake.cpm.dense import LevelPass, dense_of
from texelbake.cpm.level import texel_ids
from texelbake.cpm.level_by_need import classes_bounded
from texelbake.io.atomic import atomic_json

#: cosines above which the pattern key is tried alone
COS_CUTS = (0.1, 0.2, 0.3, 0.5)


def count(cols: list[np.ndarray]) -> int:
    return len(np.unique(np.stack(cols, axis=1), axis=0))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scene", default="bolt")
    ap.add_argument("--size", default="full", choices=["small", "full"])
    ap.add_argument("--atlas", type=int, default=128)
    ap.add_argument("--stride", type=int, default=4)
    ap.add_argument("--workdir", type=Path, default=None)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    work = args.workdir or Path(tempfile.mkdtemp(prefix="cluster_keys_"))
    work.mkdir(parents=True, exist_ok=True)
    s = BakeSettings(atlas_resolution=args.atlas)
    ctx = stages.StageContext.create(work / "store", stages_asset(args.scene, args.size, work), s)
    stages.run_ingest(ctx, 0)
    stages.run_geometry(ctx, 0)
    src = ctx.fit_inputs()
    texels = np.unique(texel_ids(src.geo, args.atlas, 0))
    texels = texels[texels >= 0][::args.stride]
    lp = LevelPass.of(src, 0)
    dense, dseg = dense_of(lp, texels)
    cls = classes_bounded(lp, texels, dense, dseg)
    fit = np.flatnonzero(~(cls.exact | cls.grouped))
    rows = np.flatnonzero(np.isin(dseg, fit))
    reasons = {k: int((cls.reason[fit] == v).sum()) for k, v in REASONS.items()}
    k = cluster.group_keys(lp, texels, dense[rows], dseg[rows], cls.pattern[rows])
    every = [c for v in k.values() for c in v]
    res = {"scene": args.scene, "atlas": args.atlas, "stride": args.stride,
           "fitted_texels": int(fit.size), "fitted_reasons": reasons, "samples": int(rows.size),
           "groups": count(every),
           "without": {name: count([c for n, v in k.items() if n != name for c in v])
                       for name in k if name not in ("texel", "material")},
           "texel_material_normals": count(k["texel"] + k["material"] + k["normals"])}
    vis, _ = visibility_patterns(lp, texels, dense, dseg, rows)
    z = np.r_[lp.dirs["dirs_i"][:, 2], lp.dirs["dirs_o"][:, 2]].clip(0.0)
    # the samples' own patterns in place of both visibility keys (the classes' groups and, where
    # they cast no ray, the position cells)
    base = [c for n, v in k.items() if n not in ("pattern", "position") for c in v]
    res["pattern_above_cos"] = []
    for cut in COS_CUTS:  # a loop over a few cut-offs
        on = z > cut
        bits = np.packbits(vis[:, on], axis=1).astype(np.int64)
        res["pattern_above_cos"].append({"cos": cut, "directions": int(on.sum()),
                                         "dropped_light_share": float(z[~on].sum() / z.sum()),
                                         "groups": count(base + list(bits.T))})
    print(f"{args.scene} {args.atlas}² level 0, every {args.stride}th texel: {res['fitted_texels']}"
          f" fitted texels ({', '.join(f'{n} {c}' for n, c in reasons.items() if c)}), "
          f"{res['samples']} samples")
    print(f"groups under every key: {res['groups']}; material and normal cells alone: "
          f"{res['texel_material_normals']}")
    for name, c in res["without"].items():
        print(f"  without {name:9s} {c:8d}")
    for e in res["pattern_above_cos"]:
        print(f"  own pattern on the {e['directions']} directions above cos {e['cos']} (dropping "
              f"{e['dropped_light_share']:.1%} of the light): {e['groups']}")
    if args.json:
        atomic_json(args.json, res)


if __name__ == "__main__":
    main()
