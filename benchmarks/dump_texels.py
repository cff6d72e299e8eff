"""Dump real scene texels (R on the training grid, R on the held-out grid, a_vis rows) for
`benchmarks/column_sampling.py --npz`.

    python benchmarks/dump_texels.py --scene cylinder --size full --texels 6 --out texels.npz
    python benchmarks/column_sampling.py --npz texels.npz --json cs_cylinder.json

The matrices are built exactly as the bake builds them (texelbake.stages: the same samples,
visibility by rays against M_org, BRDF in each sample's frame, shading cosine for light and
geometric cosine for view), for a seeded random choice of occupied finest texels.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np

from schemas.settings import BakeSettings
from texelbake import stages
from texelbake.cpm.level import brdf_grid, direction_sets, texel_ids, visibility_cos, world_dirs
from texelbake.testscenes import write_scene


def texel_matrices(ctx: stages.StageContext, texel: int, dirs_i: np.ndarray,
                   dirs_o: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """R (n_i n_o, m, 3) and a_vis rows (n_i n_o,) of one finest texel on a product grid."""
    src = ctx.fit_inputs()
    geo = src.geo
    n = ctx.settings.atlas_resolution
    frames = geo["frames_L0"]
    samples = np.flatnonzero(texel_ids(geo, n, 0) == texel)
    tex = np.full(len(samples), texel)
    vi = visibility_cos(src, samples, world_dirs(frames, tex, dirs_i))
    vo = visibility_cos(src, samples, world_dirs(frames, tex, dirs_o),
                                "geometric")
    live = (vi.T[:, None, :] > 0) & (vo.T[None, :, :] > 0)
    f = brdf_grid(src, samples, world_dirs(frames, tex, dirs_i),
                          world_dirs(frames, tex, dirs_o), live)
    area = geo["sample_area"][samples]
    R = (f * (vi.T[:, None, :, None] * vo.T[None, :, :, None])
         * area[None, None, :, None]).reshape(len(dirs_i) * len(dirs_o), -1, 3)
    avis_rows = np.tile(vo.T @ area, len(dirs_i))
    return R, avis_rows, float(area.sum())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="cylinder")
    ap.add_argument("--size", default="full", choices=["small", "full"])
    ap.add_argument("--texels", type=int, default=6)
    ap.add_argument("--atlas", type=int, default=32)
    ap.add_argument("--spt", type=int, default=32)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--m1-faces", type=int, default=0, help="BakeSettings.m1_faces (0: auto)")
    args = ap.parse_args()
    work = Path(tempfile.mkdtemp(prefix="texelbake-dump-"))
    scene = write_scene(args.scene, work / f"{args.scene}.usda", args.size)
    settings = BakeSettings(atlas_resolution=args.atlas, shard_texels=min(16, args.atlas),
                            samples_per_texel=args.spt, n_light_dirs=64, n_view_dirs=64,
                            m1_faces=args.m1_faces)
    ctx = stages.StageContext.create(work, scene, settings)
    stages.run_ingest(ctx)
    stages.run_geometry(ctx)
    geo = ctx.geometry()
    counts = np.bincount(texel_ids(geo, args.atlas, 0), minlength=args.atlas ** 2)
    occupied = np.flatnonzero(counts >= 8)
    rng = np.random.default_rng(args.seed)
    picks = np.sort(rng.choice(occupied, size=min(args.texels, occupied.size), replace=False))
    dirs = direction_sets(settings)
    out = {}
    for t, texel in enumerate(picks):  # a handful of texels
        R, avis, area = texel_matrices(ctx, int(texel), dirs["dirs_i"], dirs["dirs_o"])
        Rh, avis_h, _ = texel_matrices(ctx, int(texel), dirs["held_i"], dirs["held_o"])
        out.update({f"R_{t}": R, f"avis_{t}": avis, f"R_heldout_{t}": Rh,
                    f"avis_heldout_{t}": avis_h, f"texel_area_{t}": np.float64(area)})
        print(f"texel {texel}: m = {R.shape[1]}, d = {R.shape[0]}, held-out d = {Rh.shape[0]}")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    np.savez(args.out, **out)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
