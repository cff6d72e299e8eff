"""Baking in this process: `bake`, `demo`."""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

from texelbake.cli.args import add_settings_args, settings_from_args
from texelbake.cli.render import print_animation

# the embedded default of `texelbake demo`: small enough for a laptop in well under a minute
DEMO_SETTINGS = {
    "atlas_resolution": 32,
    "shard_texels": 16,
    "samples_per_texel": 16,
    "n_light_dirs": 32,
    "n_view_dirs": 32,
    "n_heldout": 64,
    "c_max": 32,
    "btf": True,
}


#: frames of the arm's animated preview in `texelbake demo` (time codes 0, 3, ..., 24)
DEMO_FRAMES = 9


def _duration(seconds: float | None) -> str:
    """Seconds as a person reads them: 45 s, 12 min, 9.3 h."""
    if seconds is None:
        return "?"
    if seconds < 120:
        return f"{seconds:.0f} s"
    if seconds < 7200:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h"


def _print_summary(root: Path) -> None:
    report = json.loads((root.parent / "report.json").read_text())
    run = root.parent / "run.json"  # this run's seconds (texelbake.stages.write_run)
    total = json.loads(run.read_text()).get("total_seconds", 0) if run.is_file() else 0
    print(f"baked: {root}")
    print(f"report: {root.parent / 'report.json'}  (total {total:.1f} s, {run.name})")
    # "merged": candidates fitted as copies of identical others (identical_columns="merge")
    print(f"{'level':>5} {'texels':>7} {'valid':>6} {'c mean':>7} {'SNR in':>7} {'SNR ho':>7} "
          f"{'ho p5':>6} {'avis err':>8} {'merged':>7}")
    for lv in report["levels"]:
        merged = (lv.get("merged") or {}).get("candidates")
        print(f"{lv['level']:>5} {lv['texels']:>7} {lv['texels_valid']:>6} "
              f"{lv['c'].get('mean', 0):>7.1f} {lv['snr_insample_db'].get('mean', float('nan')):>7.1f} "
              f"{lv['snr_heldout_db'].get('mean', float('nan')):>7.1f} "
              f"{lv['snr_heldout_db'].get('p5', float('nan')):>6.1f} "
              f"{lv['avis']['rel_error']:>8.3f} {'-' if merged is None else merged:>7}")
    for s in report.get("skipped", []):
        print(f"skipped {s['stage']}: {s['reason']}")
    for w in report.get("warnings", []):
        print(f"warning: {w}")
    for i, lod in enumerate(report.get("lods", {}).get("levels", []), start=1):
        bound = "" if lod.get("bound") is None else f" (bound {lod['bound_rel']:.4f})"
        print(f"LOD{i}: {lod['triangles']} triangles, Hausdorff / diagonal "
              f"{lod['hausdorff_rel']:.4f}{bound}, {lod['method']}")
    if report.get("lods", {}).get("stopped"):
        print(f"LOD chain: {report['lods']['stopped']}")
    cpm = report.get("cpm_atlas") or {}
    if cpm.get("max_px"):
        line = (f"CPM atlas {cpm['resolution']}² (atlas_mode {cpm.get('mode', 'fixed')}"
                + (f", cap {cpm['cap']}²{': reached' if cpm.get('cap_reached') else ''}"
                   if cpm.get("mode") == "lod1" else "")
                + f"): its maps serve the asset up to {cpm['max_px']:.0f} px across (larger "
                f"on screen: M_org)")
        if cpm.get("for_lod1") and cpm["for_lod1"] > cpm["resolution"]:
            line += (f"; to serve LOD1's switch size it would need {cpm['for_lod1']}², "
                     f"{cpm['cost_ratio']:.0f}x this bake's cost by the cost model")
            if cpm.get("projected_seconds_for_lod1"):
                line += f" (~{_duration(cpm['projected_seconds_for_lod1'])})"
        print(line)


def cmd_bake(args: argparse.Namespace) -> int:
    from texelbake.pipeline.run import bake

    settings = settings_from_args(args)
    root = bake(Path(args.file), Path(args.output), settings, progress=not args.quiet,
                jobs=args.jobs, workdir=Path(args.workdir) if args.workdir else None,
                source="copy" if args.copy_source else "reference")
    _print_summary(root)
    if args.usdz:
        from texelbake.usd.package import pack_usdz

        print(f"packed: {pack_usdz(root)}")
    return _quality_status(root, args.accept_below_target)


def _quality_status(root: Path, accept: bool) -> int:
    """0, or QUALITY_EXIT naming every missed target on stderr (texelbake.stages.quality) unless
    the caller accepts a below-target bake on purpose."""
    from texelbake.stages.quality import QUALITY_EXIT

    quality = json.loads((root.parent / "report.json").read_text()).get("quality", {})
    missed = quality.get("missed", [])
    if not missed:
        return 0
    word = "accepted (--accept-below-target)" if accept else "missed"
    for m in missed:
        print(f"texelbake: quality target {word}: {m}", file=sys.stderr)
    return 0 if accept else QUALITY_EXIT


def cmd_demo(args: argparse.Namespace) -> int:
    """Bake generated scenes in one process (no servers) and say where the results are."""
    from texelbake.pipeline.run import bake
    from texelbake.testscenes import write_scene

    out = Path(args.out)
    settings = settings_from_args(args, DEMO_SETTINGS)
    names = args.scenes.split(",")
    for name in names:
        t0 = time.perf_counter()
        if name == "arm":  # skinned (UsdSkel): its LODs are bound to the skeleton
            from texelbake.testscenes.arm import write_arm

            scene = write_arm(out / "scenes" / "arm_small.usda", "small")
        else:
            scene = write_scene(name, out / "scenes" / f"{name}_small.usda", "small")
        root = bake(scene, out / name, settings, progress=True, jobs=os.cpu_count() or 1)
        print(f"\n== {name} ({time.perf_counter() - t0:.1f} s)")
        _print_summary(root)
        if args.previews:
            try:
                from texelbake.render import render_previews
            except ImportError:
                print("previews: the renderer is not available in this build")
            else:
                files = render_previews(root, out / name / "previews", size="small")
                print(f"previews: {out / name / 'previews'} ({len(files)} files: gt, cpm, "
                      f"normalmap, equal-time, btf, differences, mip levels, point density)")
                if name == "arm":  # its animation, beside the stills
                    from texelbake.render.deformed_anim import render_animation

                    anim = render_animation(root, out / name / "previews", frames=DEMO_FRAMES)
                    print("animation tiles, left to right: reference gt, cpm (through L), "
                          "cpm-naive (L = I), normalmap (tangent frame on the deformed M1)")
                    print_animation(json.loads(anim.read_text()))
                    print(f"animation: {anim.parent / 'animation.gif'}, "
                          f"{anim.parent / 'error_per_frame.png'}")
    print(f"\nresults in {out.resolve()}")
    return 0


def add_parsers(sub: argparse._SubParsersAction) -> None:
    """The subcommands of this group."""
    p = sub.add_parser("bake", help="bake an asset in this process (no servers)")
    p.add_argument("file")
    p.add_argument("-o", "--output", required=True, help="output folder")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    p.add_argument("-j", "--jobs", type=int, default=os.cpu_count() or 1,
                   help="processes for the sharded stages (default: all cores)")
    p.add_argument("--workdir", default=None,
                   help="artifact store (default $TEXELBAKE_WORKDIR or ~/.cache/texelbake); "
                        "the output folder holds the result only")
    p.add_argument("--copy-source", action="store_true",
                   help="copy the source and its files into OUTPUT/source (default: reference "
                        "the source where it lies)")
    p.add_argument("--usdz", action="store_true",
                   help="also pack the result with its source into OUTPUT/<name>_baked.usdz")
    p.add_argument("--accept-below-target", action="store_true",
                   help="exit 0 even when the bake misses a quality target (exit status 3 "
                        "otherwise, naming each LOD or CPM level that missed)")
    add_settings_args(p)
    p.set_defaults(func=cmd_bake)

    p = sub.add_parser("demo", help="bake generated scenes in one process")
    p.add_argument("--out", default="demo_out")
    p.add_argument("--scenes", default="cylinder,wall,bolt,cloisonne,arm",
                   help="comma-separated scene names (default: the four test scenes and the "
                        "skinned arm, whose previews include its animation)")
    p.add_argument("--no-previews", dest="previews", action="store_false")
    add_settings_args(p)
    p.set_defaults(func=cmd_demo)
