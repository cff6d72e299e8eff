"""`texelbake` command line: scenes, inspect, bake, demo, render, srf-capture, export, report,
submit, stack.

Heavy modules are imported inside each command so `texelbake --help` is instant.
Exit status: 0 done, 2 error (texelbake.errors), 3 `bake` finished below a quality target
(texelbake.quality; `--accept-below-target` makes it 0), 4 `submit --manifest`: the batch
finished but some item failed or was cancelled (each is printed).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

from texelbake.errors import TexelbakeError

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


def _settings(args: argparse.Namespace, base: dict | None = None):
    from pydantic import ValidationError

    from schemas.settings import BakeSettings

    data = dict(base or {})
    if getattr(args, "settings", None):
        data.update(json.loads(Path(args.settings).read_text()))
    for item in getattr(args, "set", None) or []:
        if "=" not in item:
            raise TexelbakeError(f"--set expects KEY=VALUE, got {item!r}")
        key, value = item.split("=", 1)
        try:
            data[key] = json.loads(value)
        except json.JSONDecodeError:
            data[key] = value
    try:
        return BakeSettings(**data)
    except ValidationError as exc:
        raise TexelbakeError(f"invalid bake settings: {exc}") from exc


def cmd_scenes(args: argparse.Namespace) -> int:
    from texelbake.scenes import SCENE_NAMES, write_scene

    names = SCENE_NAMES if args.name == "all" else (args.name,)
    out = Path(args.output)
    if args.name == "arm":  # the skinned cylinder of seed 002 (texelbake.scenes.arm)
        from texelbake.scenes.arm import write_arm

        print(write_arm(out, args.size))
        return 0
    for name in names:
        path = out / f"{name}_{args.size}.usda" if args.name == "all" else out
        print(write_scene(name, path, args.size))
    return 0


def cmd_inspect(args: argparse.Namespace) -> int:
    from texelbake.scene import describe, load_asset

    print(describe(load_asset(args.file)))
    return 0


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
    print(f"baked: {root}")
    print(f"report: {root.parent / 'report.json'}  (total {report.get('total_seconds', 0):.1f} s)")
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
        line = (f"CPM atlas {cpm['resolution']}²: its maps serve the asset up to "
                f"{cpm['max_px']:.0f} px across (larger on screen: M_org)")
        if cpm.get("for_lod1") and cpm["for_lod1"] > cpm["resolution"]:
            line += (f"; to serve LOD1's switch size it would need {cpm['for_lod1']}², "
                     f"{cpm['cost_ratio']:.0f}x this bake's cost by the cost model")
            if cpm.get("projected_seconds_for_lod1"):
                line += f" (~{_duration(cpm['projected_seconds_for_lod1'])})"
        print(line)


def cmd_bake(args: argparse.Namespace) -> int:
    from texelbake.pipeline import bake

    settings = _settings(args)
    root = bake(Path(args.file), Path(args.output), settings, progress=not args.quiet,
                jobs=args.jobs, workdir=Path(args.workdir) if args.workdir else None,
                source="copy" if args.copy_source else "reference")
    _print_summary(root)
    if args.usdz:
        from texelbake.payload import pack_usdz

        print(f"packed: {pack_usdz(root)}")
    return _quality_status(root, args.accept_below_target)


def _quality_status(root: Path, accept: bool) -> int:
    """0, or QUALITY_EXIT naming every missed target on stderr (texelbake.quality) unless
    the caller accepts a below-target bake on purpose."""
    from texelbake.quality import QUALITY_EXIT

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
    from texelbake.pipeline import bake
    from texelbake.scenes import write_scene

    out = Path(args.out)
    settings = _settings(args, DEMO_SETTINGS)
    names = args.scenes.split(",")
    for name in names:
        t0 = time.perf_counter()
        if name == "arm":  # skinned (UsdSkel): its LODs are bound to the skeleton
            from texelbake.scenes.arm import write_arm

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
                    _print_animation(json.loads(anim.read_text()))
                    print(f"animation: {anim.parent / 'animation.gif'}, "
                          f"{anim.parent / 'error_per_frame.png'}")
    print(f"\nresults in {out.resolve()}")
    return 0


#: the render command's default modes (an undeformed frame)
RENDER_MODES = "gt,cpm,normalmap,equal-time"


def cmd_render(args: argparse.Namespace) -> int:
    from texelbake.render import render_report

    out = Path(args.output) if args.output else Path(args.file).parent / "render"
    if args.animate:  # an animated preview (seed 002 §4; texelbake.render.deformed_anim)
        from texelbake.render.deformed_anim import ANIM_MODES, render_animation

        if args.time is not None:
            from texelbake.errors import SettingsError

            raise SettingsError("fields 'animate' and 'time': an animation spans the asset's "
                                "time codes; give --animate alone or with --warp")
        anim_modes = ANIM_MODES if args.modes == RENDER_MODES else tuple(
            m.strip() for m in args.modes.split(",") if m.strip() and m.strip() != "gt")
        path = render_animation(Path(args.file), out, warp=args.warp, frames=args.animate,
                                modes=anim_modes, spp=args.spp, ref_spp=args.ref_spp)
        _print_animation(json.loads(path.read_text()))
        print(path)
        return 0
    if args.warp is not None or args.time is not None:  # a deformed frame (seed 002 §4)
        from texelbake.render.deformed_report import render_deformed_report

        modes = "gt,cpm,cpm-naive,normalmap" if args.modes == RENDER_MODES else args.modes
        report = render_deformed_report(
            Path(args.file), out, warp=args.warp, time=args.time, modes=modes,
            width=args.width, height=args.height, spp=args.spp, ref_spp=args.ref_spp,
            camera=_camera_arg(args.camera))
        rep = json.loads(report.read_text())
        print(f"warp: {rep['warp']}")
        _print_render_table(rep)
        print_btf_warnings(Path(args.file), rep)
        print(report)
        return 0
    report = render_report(Path(args.file), out, modes=args.modes, width=args.width,
                           height=args.height, spp=args.spp, ref_spp=args.ref_spp,
                           camera=_camera_arg(args.camera))
    rep = json.loads(report.read_text())
    _print_render_table(rep)
    print_btf_warnings(Path(args.file), rep)
    print(report)
    return 0


def print_btf_warnings(baked: Path, rep: dict) -> None:
    """Under a table with a btf mode, the bake's own warnings about its BTF (the report.json
    beside the baked USD: `btf.stage.narrow_lobes`), so a btf figure out of the table's band
    is read as such."""
    if not any(m.startswith("btf") for m in rep.get("modes", {})):
        return
    path = baked.parent / "report.json"
    bake_report = json.loads(path.read_text()) if path.is_file() else {}
    for w in bake_report.get("warnings", []):
        if w.startswith("btf:"):
            print(f"note (from the bake): {w}")


def _print_animation(rep: dict) -> None:
    """Per frame, PSNR over the object's pixels (dB) and seconds of each mode."""
    modes = rep["tiles"][1:]
    print(f"{rep['scene']}: {len(rep['frames'])} frames {rep['width']}x{rep['height']}, "
          f"reference gt at {rep['ref_spp']} spp, modes at {rep['spp']} spp; PSNR obj (dB) / s")
    print(f"{'frame':<28}{'obj px':>7}" + "".join(f"{m:>20}" for m in modes))
    for f in rep["frames"]:
        cells = "".join(f"{f['modes'][m].get('psnr_db_object', float('nan')):>12.2f}"
                        f"{f['modes'][m]['seconds']:>8.3f}" for m in modes)
        print(f"{f['label'][:27]:<28}{f['object_pixels']:>7}{cells}")


def _print_render_table(rep: dict) -> None:
    """Time beside error per mode, over the object's pixels (the report's own figures)."""
    def num(v: object, fmt: str) -> str:
        return format(v, fmt) if isinstance(v, int | float) else str(v)

    lights = "default rig (the asset has none)" if rep.get("default_lights") else "the asset's"
    print(f"reference gt at {rep['reference']['spp']} spp, {rep['width']}x{rep['height']}; "
          f"object {rep.get('object_pixels', '?')} pixels; lights: {lights}; camera: "
          f"{rep.get('camera', '?')}")
    print(f"{'mode':<12}{'spp':>7}{'seconds':>9}{'PSNR obj':>10}{'dE mean':>9}{'FLIP obj':>10}")
    for mode, e in rep["modes"].items():
        spp = num(e.get("mean_spp", e["spp"]), ".2f" if "mean_spp" in e else "d")
        print(f"{mode:<12}{spp:>7}{num(e['seconds'], '.3f'):>9}"
              f"{num(e.get('psnr_db_object'), '.2f'):>10}{num(e.get('delta_e_mean'), '.2f'):>9}"
              f"{num(e.get('flip_mean_object'), '.3f'):>10}")
    if "equal_time" in rep:
        et = rep["equal_time"]
        print(f"equal-time: {et['equal_time_seconds']:.3f} s for cpm's {et['cpm_seconds']:.3f} s "
              f"(ratio {et['ratio']:.3f})")


def _camera_arg(value: str | None):
    if value is None or value == "lod":
        return value
    try:
        return float(value)
    except ValueError as exc:
        raise TexelbakeError(f"--camera must be 'lod' or a distance, got {value!r}") from exc


def cmd_srf_capture(args: argparse.Namespace) -> int:
    from texelbake.render.scene import load_scene
    from texelbake.srf.mode import capture_beside

    t0 = time.perf_counter()
    store = capture_beside(load_scene(Path(args.file)), n_cameras=args.cameras,
                           n_lights=args.lights, size=args.size, spp=args.spp,
                           encoding=args.encoding)
    print(f"{store.n_cameras} cameras x {store.n_lights} lights at {store.width}x"
          f"{store.height} ({store.encoding}) in {time.perf_counter() - t0:.1f} s: {store.path}")
    return 0


def cmd_export(args: argparse.Namespace) -> int:
    from texelbake.lodexport import export_lod

    print(export_lod(Path(args.file), args.lod, Path(args.output)))
    return 0


def cmd_report(args: argparse.Namespace) -> int:
    from texelbake.render import write_report_plot

    print(write_report_plot(Path(args.dir)))
    return 0


#: `texelbake submit --manifest`: the batch finished, and some item failed or was cancelled
EXIT_ITEMS_FAILED = 4


def cmd_submit_manifest(args: argparse.Namespace) -> int:
    from texelbake_client.batch import failed_items, load_manifest, submit_batch

    if args.file or args.settings or args.set:
        raise TexelbakeError("--manifest takes its files and settings from the manifest: "
                             "give no FILE, --settings or --set with it")
    paths = load_manifest(args.manifest).paths
    batch = submit_batch(Path(args.manifest), server=args.server, token=args.token,
                         out_dir=Path(args.output))
    out = Path(args.output)
    print(f"batch {batch['id']}: {batch['state']}; {batch['counts']['succeeded']} of "
          f"{batch['counts']['total']} items succeeded; results in {out}")
    bad = failed_items(batch, paths)
    for line in bad:
        print(f"texelbake: {line}", file=sys.stderr)
    return EXIT_ITEMS_FAILED if bad else 0


def cmd_submit(args: argparse.Namespace) -> int:
    from texelbake_client.submit import submit

    if args.manifest:
        return cmd_submit_manifest(args)
    if not args.file:
        raise TexelbakeError("submit needs a FILE or --manifest FILE")
    settings = _settings(args)
    result = submit(Path(args.file), server=args.server, token=args.token,
                    out_dir=Path(args.output), settings=settings.model_dump())
    print(result)
    return 0


def cmd_stack(args: argparse.Namespace) -> int:
    # the launcher lives next to the service it launches (stdlib only: importing it pulls in
    # neither FastAPI, Celery nor Redis); the CLI is the one place the core reaches for it
    from farm import stack

    if args.action == "up":
        stack.stack_up(Path(args.dir))
    else:
        stack.stack_down(Path(args.dir))
    return 0


def _add_settings_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--settings", help="JSON file of bake settings (schemas.settings.BakeSettings)")
    p.add_argument("--set", action="append", metavar="KEY=VALUE",
                   help="override one bake setting, e.g. --set atlas_resolution=64")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="texelbake", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("scenes", help="write a generated test scene as USD")
    p.add_argument("name", choices=["cylinder", "wall", "bolt", "cloisonne", "all", "arm"])
    p.add_argument("-o", "--output", required=True, help="FILE.usda (or a folder with 'all')")
    p.add_argument("--size", choices=["small", "full"], default="small")
    p.set_defaults(func=cmd_scenes)

    p = sub.add_parser("inspect", help="print what texelbake reads from a USD asset")
    p.add_argument("file")
    p.set_defaults(func=cmd_inspect)

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
    _add_settings_args(p)
    p.set_defaults(func=cmd_bake)

    p = sub.add_parser("demo", help="bake generated scenes in one process")
    p.add_argument("--out", default="demo_out")
    p.add_argument("--scenes", default="cylinder,wall,bolt,cloisonne,arm",
                   help="comma-separated scene names (default: the four test scenes and the "
                        "skinned arm, whose previews include its animation)")
    p.add_argument("--no-previews", dest="previews", action="store_false")
    _add_settings_args(p)
    p.set_defaults(func=cmd_demo)

    p = sub.add_parser("render", help="render a baked USD")
    p.add_argument("file")
    p.add_argument("--modes", default=RENDER_MODES,
                   help="comma-separated: gt, cpm, normalmap, equal-time, btf (bakes with btf on), "
                   "toksvig, toksvig+ao, leadr, leadr+ao, preview-surface (the filtered "
                   "baselines); with --warp/--time also cpm-naive and btf-naive (btf through "
                   "the look-up rotation L, btf-naive without); srf (after srf-capture), "
                   "with --warp/--time also srf-naive")
    p.add_argument("-o", "--output", default=None)
    p.add_argument("--width", type=int, default=256)
    p.add_argument("--height", type=int, default=256)
    p.add_argument("--spp", type=int, default=4, help="eye rays per pixel of each mode")
    p.add_argument("--ref-spp", type=int, default=256, help="eye rays per pixel of the reference")
    p.add_argument("--camera", default=None,
                   help="the asset's camera (default), 'lod', or an auto-frame distance")
    p.add_argument("--warp", default=None, help="render deformed by a procedural warp, e.g. "
                   "twist:angle=90, bend:angle=90, stretch:x=1,y=2,z=1, sine:amplitude=0.1 "
                   "(modes gt, cpm, cpm-naive, normalmap, equal-time)")
    p.add_argument("--time", type=float, default=None,
                   help="render deformed by the asset's own animation at this time code")
    p.add_argument("--animate", type=int, default=0, metavar="FRAMES",
                   help="an animated preview of FRAMES frames (the asset's animation, or a "
                        "sweep of --warp from the identity): animation.gif, "
                        "error_per_frame.png, animation.json")
    p.set_defaults(func=cmd_render)

    p = sub.add_parser("srf-capture", help="capture a reflectance field of a baked asset's "
                       "M_org beside it (for --modes srf)")
    p.add_argument("file")
    p.add_argument("--cameras", type=int, default=216)
    p.add_argument("--lights", type=int, default=44)
    p.add_argument("--size", type=int, default=48, help="capture image size (pixels)")
    p.add_argument("--spp", type=int, default=16, help="eye rays per pixel of a capture image")
    p.add_argument("--encoding", choices=["raw", "pca"], default="raw")
    p.set_defaults(func=cmd_srf_capture)

    p = sub.add_parser("export", help="write one LOD of a baked USD as a self-contained file "
                       "(for tools without variant support)")
    p.add_argument("file")
    p.add_argument("--lod", type=int, required=True, help="0 = the asset as authored, 1..n")
    p.add_argument("-o", "--output", required=True, help="FILE.usdc, .usda or .usdz")
    p.set_defaults(func=cmd_export)

    p = sub.add_parser("report", help="draw the speed-against-error plot of a render folder")
    p.add_argument("dir")
    p.set_defaults(func=cmd_report)

    p = sub.add_parser("submit", help="upload an asset (or a manifest's assets, as one batch) "
                       "to a texelbake server and fetch the result")
    p.add_argument("file", nargs="?")
    p.add_argument("--manifest", help="JSON manifest of many assets (texelbake_client.batch); "
                   f"exit status {EXIT_ITEMS_FAILED} when an item failed")
    p.add_argument("--server", required=True)
    p.add_argument("--token", required=True)
    p.add_argument("-o", "--output", default="result")
    _add_settings_args(p)
    p.set_defaults(func=cmd_submit)

    p = sub.add_parser("stack", help="start/stop redis, the API and workers as local processes")
    p.add_argument("action", choices=["up", "down"])
    p.add_argument("--dir", default="var/stack", help="state folder (pids, logs, database)")
    p.set_defaults(func=cmd_stack)
    return parser


def _show_asset_warnings_plainly() -> None:
    """An asset's warnings on the terminal as "warning: <message>" lines (Python's default
    format adds the file and source line of texelbake's reader, which names nothing in the
    asset); other warnings keep the default format."""
    import warnings

    from texelbake.scene.values import AssetWarning

    default = warnings.formatwarning

    def fmt(message, category, filename, lineno, line=None):
        if issubclass(category, AssetWarning):
            return f"warning: {message}\n"
        return default(message, category, filename, lineno, line)

    warnings.formatwarning = fmt  # type: ignore[assignment]


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    _show_asset_warnings_plainly()
    try:
        return int(args.func(args) or 0)
    except TexelbakeError as exc:
        print(f"texelbake: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
