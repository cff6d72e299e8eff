"""Looking at a bake: `render`, `srf-capture`, `export`, `report`."""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from texelbake.errors import TexelbakeError

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
        print_animation(json.loads(path.read_text()))
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


def print_animation(rep: dict) -> None:
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
    from texelbake.usd.export import export_lod

    print(export_lod(Path(args.file), args.lod, Path(args.output)))
    return 0


def cmd_report(args: argparse.Namespace) -> int:
    from texelbake.render import write_report_plot

    print(write_report_plot(Path(args.dir)))
    return 0


def add_parsers(sub: argparse._SubParsersAction) -> None:
    """The subcommands of this group."""
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
