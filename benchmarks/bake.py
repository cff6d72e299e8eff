"""The whole CPM bake of one scene: time per stage beside the error it reaches.

    python benchmarks/bake.py --scene cylinder --size full --json bench_out/bake.json

Bakes with `texelbake bake`'s defaults (BakeSettings()) unless `--atlas` / `--spt` say
otherwise; the header says which fields are not defaults and the JSON records the full
settings (issue 3's acceptance setting was `--atlas 32 --spt 32`). Prints per-stage seconds, rays/s, in-sample and held-out SNR (finest
level and every level), the a_vis error against a 6 x 64^2 ray-traced reference on a sample of
texels beside the baked resolution, and (with --sweep) the speed-against-error trade of the
main knobs (samples per texel, direction count, a_vis resolution), each varied alone.
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from schemas.settings import BakeSettings
from texelbake import stages
from texelbake.cpm import avis as avis_mod
from texelbake.cpm.avis.table import avis_table_from
from texelbake.cpm.level import texel_ids
from texelbake.payload import read_baked
from texelbake.pipeline import bake
from texelbake.scenes import write_scene

JOBS = 2  # processes for the sharded stages: this machine's cores


def avis_reference_error(root: Path, ctx: stages.StageContext, n_texels: int = 24,
                         res_ref: int = 64, seed: int = 0) -> dict:
    """Relative L2 error of the baked a_vis table against a 6 x res_ref^2 reference computed
    with rays from the same samples, on a random sample of occupied finest texels."""
    baked = read_baked(root)
    level = baked.levels[0]
    table = avis_table_from(level)
    geo = ctx.geometry()
    n = ctx.settings.atlas_resolution
    tex = texel_ids(geo, n, 0)
    occupied = np.flatnonzero(np.bincount(tex, minlength=n * n))
    rng = np.random.default_rng(seed)
    pick = np.sort(rng.choice(occupied, size=min(n_texels, occupied.size), replace=False))
    sel = np.flatnonzero(np.isin(tex, pick))
    local = np.searchsorted(pick, tex[sel])
    caster = ctx.caster()
    t0 = time.perf_counter()
    ref = avis_mod.avis_cube_maps(
        geo["sample_pos"][sel], geo["sample_gnrm"][sel], geo["sample_area"][sel], local,
        len(pick), None, res_ref, caster.occluded, ray_eps=1e-5 * caster.bbox_diag,
        dtype=np.float64,
    )  # (t, 6, r, r) world directions
    ref_seconds = time.perf_counter() - t0
    dirs_w = avis_mod.cube_directions(res_ref).reshape(-1, 3)  # (6 r^2, 3)
    frames = level["frames"][pick]  # (t, 3, 3)
    dirs_t = np.einsum("tij,dj->tdi", frames, dirs_w).reshape(-1, 3)
    texels = np.repeat(pick, len(dirs_w))
    a, _ = table.evaluate(texels, dirs_t)
    a = a.reshape(len(pick), -1)
    r = ref.reshape(len(pick), -1)
    per_texel = np.linalg.norm(a - r, axis=1) / np.maximum(np.linalg.norm(r, axis=1), 1e-300)
    return {"texels": int(len(pick)), "reference_resolution": res_ref,
            "baked_resolution": int(ctx.settings.avis_resolution),
            "rel_error_mean": float(per_texel.mean()), "rel_error_max": float(per_texel.max()),
            "reference_seconds": ref_seconds}


def run_one(scene: Path, settings: BakeSettings, out: Path, with_avis_ref: bool) -> dict:
    if out.exists():
        shutil.rmtree(out)
    t0 = time.perf_counter()
    root = bake(scene, out, settings, progress=False, jobs=JOBS, workdir=out / ".work")
    total = time.perf_counter() - t0
    report = json.loads((out / "report.json").read_text())
    rays = report["rays"]["cpm"] + report["rays"]["avis"]  # counted in every process
    l0 = report["levels"][0]
    result = {
        "total_seconds": total,
        "stage_seconds": report["stage_seconds"],
        "rays_cast": int(rays),
        "rays_per_second": rays / max(report["stage_seconds"].get("cpm", 0)
                                      + report["stage_seconds"].get("cpm_top", 0)
                                      + report["stage_seconds"].get("avis", 0)
                                      + report["stage_seconds"].get("avis_top", 0), 1e-9),
        "heldout_snr_db_mean": l0["snr_heldout_db"].get("mean"),
        "heldout_snr_db_p5": l0["snr_heldout_db"].get("p5"),
        "insample_snr_db_mean": l0["snr_insample_db"].get("mean"),
        "c_mean": l0["c"].get("mean"),
        "avis_rel_error_mean": l0["avis"]["rel_error"],
        "levels": [{"level": lv["level"], "texels_valid": lv["texels_valid"],
                    "c_mean": lv["c"].get("mean"),
                    "insample_db": lv["snr_insample_db"].get("mean"),
                    "heldout_db": lv["snr_heldout_db"].get("mean")} for lv in report["levels"]],
    }
    if with_avis_ref:
        ctx = stages.StageContext.create(out / ".work", scene, settings)
        ref = avis_reference_error(root, ctx)
        result["avis_vs_reference"] = ref
        result["avis_rel_error_mean"] = ref["rel_error_mean"]
    return result


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="cylinder")
    ap.add_argument("--size", default="full", choices=["small", "full"])
    ap.add_argument("--json", type=Path)
    ap.add_argument("--atlas", type=int, default=None,
                    help="finest texels per side (default: the bake's default)")
    ap.add_argument("--spt", type=int, default=None,
                    help="samples per finest texel (default: the bake's default)")
    ap.add_argument("--sweep", action="store_true", help="also vary each main knob alone")
    ap.add_argument("--workdir", type=Path, default=None)
    ap.add_argument("--compare-hierarchy", action="store_true",
                    help="also bake with hierarchy='dense' (the seed) and print both per level")
    args = ap.parse_args()
    work = args.workdir or Path(tempfile.mkdtemp(prefix="texelbake-bench-"))
    scene = write_scene(args.scene, work / f"{args.scene}_{args.size}.usda", args.size)
    base: dict = {}
    if args.atlas is not None:
        base.update(atlas_resolution=args.atlas,
                    shard_texels=min(BakeSettings().shard_texels, args.atlas))
    if args.spt is not None:
        base["samples_per_texel"] = args.spt
    settings = BakeSettings(**base)
    defaults = BakeSettings().model_dump()
    changed = sorted(k for k, v in settings.model_dump().items()
                     if v != defaults[k] and k != "shard_texels")
    main_run = run_one(scene, settings, work / "main", with_avis_ref=True)
    print(f"\n{args.scene} ({args.size}), {settings.atlas_resolution}x"
          f"{settings.atlas_resolution} texels, {settings.n_light_dirs}x{settings.n_view_dirs} "
          f"pairs, c_max {settings.c_max}, eps {settings.eps_db:g} dB; bake settings: "
          f"{'texelbake bake defaults' if not changed else 'NON-DEFAULT ' + ', '.join(changed)}")
    print(f"{'stage':<10} {'seconds':>8}")
    for k, v in main_run["stage_seconds"].items():
        print(f"{k:<10} {v:>8.2f}")
    print(f"{'total':<10} {main_run['total_seconds']:>8.2f}   rays {main_run['rays_cast']:.3g} "
          f"({main_run['rays_per_second'] / 1e6:.2f} M rays per second of cpm + avis stage time)")
    print(f"level 0: SNR in-sample {main_run['insample_snr_db_mean']:.1f} dB, held-out "
          f"{main_run['heldout_snr_db_mean']:.1f} dB (p5 {main_run['heldout_snr_db_p5']:.1f}), "
          f"c mean {main_run['c_mean']:.1f}")
    ref = main_run["avis_vs_reference"]
    print(f"a_vis: baked 6x{ref['baked_resolution']}^2 Haar vs 6x{ref['reference_resolution']}^2 "
          f"reference on {ref['texels']} texels: rel error mean {ref['rel_error_mean']:.3f} "
          f"(max {ref['rel_error_max']:.3f})")
    print(f"{'level':>5} {'valid':>6} {'c':>6} {'in dB':>7} {'ho dB':>7}")
    for lv in main_run["levels"]:
        print(f"{lv['level']:>5} {lv['texels_valid']:>6} {lv['c_mean'] or 0:>6.1f} "
              f"{lv['insample_db'] or float('nan'):>7.1f} {lv['heldout_db'] or float('nan'):>7.1f}")
    out = {"scene": args.scene, "size": args.size, **main_run, "sweep": [],
           "bake_settings": json.loads(settings.model_dump_json()),
           "bake_settings_non_default": changed}
    if args.compare_hierarchy:
        dense = run_one(scene, BakeSettings(**{**base, "hierarchy": "dense"}), work / "dense",
                        with_avis_ref=False)
        print(f"\nhierarchy: children (default) {main_run['stage_seconds'].get('cpm', 0) + main_run['stage_seconds'].get('cpm_top', 0):.1f} s"
              f" vs dense (seed) {dense['stage_seconds'].get('cpm', 0) + dense['stage_seconds'].get('cpm_top', 0):.1f} s of cpm stages")
        print(f"{'level':>5} {'children c':>10} {'ho dB':>7} {'dense c':>8} {'ho dB':>7}")
        for a, b in zip(main_run["levels"], dense["levels"], strict=True):
            print(f"{a['level']:>5} {a['c_mean'] or 0:>10.1f} {a['heldout_db'] or float('nan'):>7.1f} "
                  f"{b['c_mean'] or 0:>8.1f} {b['heldout_db'] or float('nan'):>7.1f}")
        out["dense"] = dense
    if args.sweep:
        print(f"\n{'knob':<20} {'value':>6} {'seconds':>8} {'ho dB':>7} {'avis err':>8}")
        for knob, values in (("samples_per_texel", (16, 32, 64)),
                             ("n_light_dirs", (16, 32, 64)),
                             ("avis_resolution", (8, 16, 32))):
            for v in values:
                extra = {knob: v}
                if knob == "n_light_dirs":
                    extra["n_view_dirs"] = v
                r = run_one(scene, BakeSettings(**{**base, **extra}), work / f"{knob}-{v}",
                            with_avis_ref=knob == "avis_resolution")
                print(f"{knob:<20} {v:>6} {r['total_seconds']:>8.1f} "
                      f"{r['heldout_snr_db_mean']:>7.1f} {r['avis_rel_error_mean']:>8.3f}")
                out["sweep"].append({"knob": knob, "value": v, **r})
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(out, indent=2, default=float))
        print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
