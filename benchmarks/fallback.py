"""The UsdPreviewSurface fallback judged in another renderer: per asset and LOD, the original
and that LOD with each fallback variant the bake holds, rendered in Blender 5.0.1 (Cycles,
headless bpy, the dcc virtualenv) from one camera and sun at the LOD's switch distance, and the
same LOD in texelbake's own `preview-surface` mode against its `gt` reference.

    python benchmarks/fallback.py --json benchmarks/results/fallback.json
        [--assets cylinder bolt ...] [--size full] [--resolution 256] [--samples 256]
        [--tb-spp 16] [--tb-ref-spp 256] [--renders DIR] [--no-blender]
        [--variants averaged ...]

Assets: the four generated scenes at `--size` (full), the Teapot and BoxAnimated.usdz from
../shared/assets, and by name only `teapot_fancy` (the Teapot's "Fancy" model variant: an ARM
texture's roughness and metallic). Each is baked once per fallback variant (`FALLBACKS`: a column name and the
BakeSettings that select it; adding a variant is one line there) at `BAKE` (a light CPM that
leaves the geometry and the filtered maps — all the fallback reads — as at defaults; printed).

Blender: each LOD N >= 1 exported with `texelbake export --lod N` (.usdz), imported with
Blender's USD importer at its defaults beside the original, rendered by
tests/blender/import_render.py through tests/helpers/dcc (Cycles CPU, `--resolution`² pixels,
`--samples` per pixel, no denoiser, no adaptive sampling, fixed seed; one sun plus a dim world;
the film transparent) with the camera where the original's bounding-box diagonal covers the
LOD's switch size in pixels (`lod_switch_px`; at 256² LOD1's 256 px fill the frame). The
original there is what Blender makes of the source (its UsdPreviewSurface where it has one:
Blender cannot evaluate texelbake's own shaders and shows their stand-in, listed per row as
`blender_stand_ins`), without coplanar overlapping twin triangles
(`tests.helpers.dcc.without_twin_triangles`: Cycles renders their overlap black; the
as-shipped figures stay under `as_shipped`). The original rendered again under a second Cycles
seed gives the noise floor (`psnr_floor_db`, `flip_floor`, per asset and LOD). The JSON's
notes say, per asset and LOD, where the fitted fallback misses the 3 dB bar, the floor, and
what Blender's reference is (`bar_notes`). texelbake: `preview-surface` (what a USD viewer
without texelbake's shader shows: each LOD's fallback as authored) at `--tb-spp` against `gt`
(the original's true materials) at `--tb-ref-spp`, the same resolution, auto-framed so the
bounding sphere's diameter covers the switch size (its own camera and lights: the two
renderers' figures are each against their own reference, not against each other), and beside it
texelbake's `cpm` mode from the same view at the same spp (the bake's CPM at `BAKE`, lighter
than the defaults).

Figures per (asset, LOD, variant), over the object's pixels (`metrics.object_mask`: the union
of both silhouettes, dilated by a pixel): PSNR (dB, linear radiance, peak the reference's;
Blender's 8-bit sRGB PNGs decoded to linear), FLIP (`metrics.flip_map`, mean over the object),
silhouette IoU (alpha or coverage >= 0.5) and the object's mean radiance over its own
silhouette as a ratio to the original's (the bolt's acceptance: within 25 %). Screenshots
(original | the as-shipped original where twins were removed | each variant, per asset and
LOD) go to `--renders` (default: `<json stem>_renders/` beside the JSON).

Measured (benchmarks/results/fallback.json: one invocation, `python benchmarks/fallback.py --json
benchmarks/results/fallback.json`; scenes full size; bakes at `BAKE`; Cycles 256² at 256 spp,
no denoiser; texelbake preview-surface 16 spp on the LOD's own mesh against gt 256 spp, 256²).
PSNR (dB) and FLIP over the object, IoU, mean radiance as a ratio to the original's, and
Cycles' noise floor (the original under a second seed), and texelbake's cpm at the same view:

| asset        | LOD | px  | variant  | Blender PSNR | FLIP  | IoU   | mean | floor | tb PSNR | FLIP  | IoU   | mean | cpm PSNR | FLIP  |
|--------------|----:|----:|----------|-------------:|------:|------:|-----:|------:|--------:|------:|------:|-----:|---------:|------:|
| cylinder     |   1 | 256 | averaged |        24.54 | 0.259 | 1.000 | 0.98 |  49.1 |   23.05 | 0.259 | 0.999 | 1.00 |    36.94 | 0.033 |
| cylinder     |   1 | 256 | fitted   |        24.57 | 0.258 | 1.000 | 1.01 |  49.1 |   22.93 | 0.265 | 0.999 | 1.02 |    36.94 | 0.033 |
| cylinder     |   2 |  64 | averaged |        24.50 | 0.305 | 0.996 | 1.01 |  47.8 |   19.55 | 0.365 | 0.996 | 1.07 |    30.30 | 0.062 |
| cylinder     |   2 |  64 | fitted   |        24.83 | 0.302 | 0.996 | 1.03 |  47.8 |   19.73 | 0.354 | 0.996 | 1.11 |    30.30 | 0.062 |
| wall         |   1 | 256 | averaged |        25.52 | 0.157 | 0.999 | 0.99 |  45.1 |   22.51 | 0.165 | 0.999 | 1.00 |    35.98 | 0.028 |
| wall         |   1 | 256 | fitted   |        19.62 | 0.333 | 0.999 | 0.80 |  45.1 |   18.73 | 0.313 | 0.999 | 0.83 |    35.98 | 0.028 |
| wall         |   2 |  64 | averaged |        20.05 | 0.222 | 0.953 | 1.03 |  40.2 |   16.97 | 0.276 | 0.950 | 1.13 |    30.41 | 0.049 |
| wall         |   2 |  64 | fitted   |        19.11 | 0.283 | 0.953 | 0.84 |  40.2 |   18.49 | 0.176 | 0.950 | 0.92 |    30.41 | 0.049 |
| bolt         |   1 | 256 | averaged |        32.83 | 0.083 | 1.000 | 1.05 |  44.0 |   42.33 | 0.026 | 0.998 | 1.06 |    52.12 | 0.009 |
| bolt         |   1 | 256 | fitted   |        32.32 | 0.151 | 1.000 | 0.90 |  44.0 |   43.41 | 0.030 | 0.998 | 0.94 |    52.12 | 0.009 |
| bolt         |   2 |  64 | averaged |        17.47 | 0.261 | 0.995 | 0.78 |  29.0 |   24.92 | 0.297 | 0.995 | 0.67 |    37.40 | 0.045 |
| bolt         |   2 |  64 | fitted   |        17.25 | 0.287 | 0.995 | 0.71 |  29.0 |   25.70 | 0.298 | 0.995 | 0.58 |    37.40 | 0.045 |
| cloisonne    |   1 | 256 | averaged |        20.13 | 0.302 | 0.996 | 0.96 |  57.5 |   43.91 | 0.349 | 0.996 | 1.14 |    57.75 | 0.024 |
| cloisonne    |   1 | 256 | fitted   |        19.57 | 0.390 | 0.996 | 1.01 |  57.5 |   43.90 | 0.441 | 0.996 | 1.19 |    57.75 | 0.024 |
| cloisonne    |   2 |  64 | averaged |        21.17 | 0.236 | 0.985 | 0.96 |  55.3 |   33.64 | 0.255 | 0.982 | 1.13 |    23.78 | 0.047 |
| cloisonne    |   2 |  64 | fitted   |        20.43 | 0.364 | 0.985 | 1.03 |  55.3 |   33.55 | 0.415 | 0.982 | 1.21 |    23.78 | 0.047 |
| teapot       |   1 | 256 | averaged |        30.09 | 0.155 | 0.982 | 1.00 |  46.3 |   37.35 | 0.098 | 0.996 | 1.00 |    49.78 | 0.012 |
| teapot       |   1 | 256 | fitted   |        26.37 | 0.264 | 0.982 | 0.92 |  46.3 |   35.03 | 0.217 | 0.996 | 0.93 |    49.78 | 0.012 |
| teapot       |   2 |  64 | averaged |        25.39 | 0.281 | 0.969 | 0.92 |  42.9 |   25.06 | 0.258 | 0.981 | 0.93 |    31.32 | 0.040 |
| teapot       |   2 |  64 | fitted   |        23.63 | 0.349 | 0.969 | 0.86 |  42.9 |   23.91 | 0.326 | 0.981 | 0.88 |    31.32 | 0.040 |
| box_animated |   1 | 256 | averaged |        23.17 | 0.136 | 0.998 | 1.02 |  55.1 |   23.98 | 0.099 | 0.998 | 1.01 |    47.29 | 0.004 |
| box_animated |   1 | 256 | fitted   |        21.55 | 0.155 | 0.998 | 0.99 |  55.1 |   21.92 | 0.118 | 0.998 | 0.98 |    47.29 | 0.004 |

texelbake's `cpm` (the last two columns, the bake's maps at `BAKE`) is 24–58 dB where its
`preview-surface` is 17–44; below it only on the cloisonne's LOD2 (23.8 against 33.6 dB).
The fitted fallback (the averaged inputs with a held-out-chosen diffuse gain) is nowhere 3 dB
better than averaged (Blender −5.9 to +0.3 dB, texelbake −3.8 to +1.5), so averaged stays the
default; the JSON's notes give, per asset and LOD, the gain in each renderer, the noise floor,
the fit's per-texel residual beside the averaged inputs' and the targets' noise (it lowers the
residual over the direction set where it loses in the image: docs/decisions.md says why). The
fit costs 17–34 s of export (`export_seconds`, fitted minus averaged). The bolt's mean radiance
in Blender is within 25 % of the original's with the averaged fallback at both LODs (1.05,
0.78), with the fitted one at LOD1 (0.90), not at LOD2 (0.71). Blender's cloisonne original is
the scene's one-colour stand-in (Blender cannot evaluate texelbake's cellular shader): those
rows measure the stand-in (the LOD with its base colour replaced by the stand-in's scores 26.8 /
29.9 dB at LOD1 / LOD2). Why Blender's figures were far below texelbake's before (noise floor,
specularColor as Specular Tint, BoxAnimated's twins, the stand-in) and where the bolt's LOD2 and
the Teapot's LOD1 lose: docs/decisions.md. The bolt's LOD2 texelbake mean (0.67) is 16 spp
sampling its normal map's sparkles: 0.82 at `--tb-spp 256`, 0.89 at 1024 (docs/decisions.md).
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from schemas.settings import BakeSettings
from texelbake.asset import load_asset
from texelbake.io.images import read_pixels, srgb_to_linear
from texelbake.pipeline.run import bake
from texelbake.render import metrics
from texelbake.testscenes import write_scene

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))
ASSETS = ROOT.parent / "shared" / "assets"
SCENES = ("cylinder", "wall", "bolt", "cloisonne")
#: fallback variant (a column) -> the BakeSettings fields that select it
FALLBACKS: dict[str, dict[str, Any]] = {
    "averaged": {},  # today's fallback: averaged inputs, widened roughness, normal map, AO
    "fitted": {"fallback": "fitted"},  # the averaged inputs with a held-out-chosen gain
}
#: the bakes: a light CPM (the fallback maps come from the geometry and filtered-map stages,
#: which these fields leave as at defaults)
BAKE = {"samples_per_texel": 8, "n_light_dirs": 8, "n_view_dirs": 8, "n_heldout": 16,
        "c_max": 8}
TB_FOV_DEG = 27.0  # texelbake.trace.camera.auto_frame's default field of view


def image_figures(img: np.ndarray, ref: np.ndarray, cov_img: np.ndarray, cov_ref: np.ndarray
                  ) -> dict[str, float]:
    """PSNR / FLIP over the object, silhouette IoU and the mean-radiance ratio of one render
    (linear (h, w, 3), coverage (h, w) in [0, 1]) against the original's."""
    mask = metrics.object_mask(cov_ref >= 0.5, cov_img >= 0.5)
    err = metrics.object_errors(img, ref, mask)
    a, b = cov_ref >= 0.5, cov_img >= 0.5
    union = int(np.logical_or(a, b).sum())
    mean_ref = float(ref[a].mean()) if a.any() else float("nan")
    mean_img = float(img[b].mean()) if b.any() else float("nan")
    return {"psnr_db_object": round(float(err["psnr_db_object"]), 3),
            "flip_object": round(float(err["flip_mean_object"]), 4),
            "iou": round(int(np.logical_and(a, b).sum()) / union, 4) if union else 1.0,
            "object_pixels": int(err["object_pixels"]),
            "mean_radiance": round(mean_img, 5), "mean_radiance_original": round(mean_ref, 5),
            "mean_ratio": round(mean_img / mean_ref, 4) if mean_ref > 0 else float("nan")}


def _png(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Linear RGB (colour over black: OpenImageIO hands associated alpha) and alpha."""
    px = read_pixels(path)[0].astype(np.float64)
    return srgb_to_linear(px[..., :3]).astype(np.float64), px[..., 3]


def bake_variants(name: str, src: Path, work: Path, variants: dict[str, dict[str, Any]]
                  ) -> dict[str, dict[str, Any]]:
    """{variant: {"root", "seconds", "switch_px", "export_seconds"}}: one bake per fallback
    variant."""
    out = {}
    for variant, fields in variants.items():  # a loop over the few variants
        settings = BakeSettings(**{**BAKE, **fields})
        dest = work / f"{name}_{variant}"
        t0 = time.perf_counter()
        root = bake(src, dest, settings, progress=False,
                    workdir=dest.with_name(dest.name + "_work"))
        seconds = time.perf_counter() - t0
        report = json.loads((root.parent / "report.json").read_text())
        levels = report["lods"]["levels"]
        px = [lv["switch_px"] if lv["switch_px"] is not None else
              settings.lod_switch_px[min(i, len(settings.lod_switch_px) - 1)]
              for i, lv in enumerate(levels)]
        run = json.loads((root.parent / "run.json").read_text())
        # the export stage holds the fit: fitted minus averaged export is the fit's cost
        out[variant] = {"root": root, "seconds": round(seconds, 1), "switch_px": px,
                        "export_seconds": run["stage_seconds"].get("export")}
    return out


def blender_lod(name: str, src: Path, bakes: dict[str, dict[str, Any]], lod: int, px: float,
                renders: Path, args: argparse.Namespace) -> dict[str, dict[str, float]] | str:
    """Blender's figures of each variant at LOD `lod` ({variant: figures}), or why not run.

    The reference is the original without its twin triangles (`without_twin_triangles`; the
    as-shipped original's figures are kept under "as_shipped" when it has some); the
    original rendered again under another Cycles seed gives the noise floor
    (`psnr_floor_db`, `flip_floor`: what the same scene scores against itself)."""
    import pytest

    from tests.helpers.dcc import import_and_render, side_by_side, without_twin_triangles
    from texelbake.usd.export import export_lod

    ref_src, n_twins = without_twin_triangles(src, renders / name / "original_without_twins.usda")
    files: dict[str, Path] = {"original": ref_src, "original_seed1": ref_src}
    if n_twins:
        files["original_as_shipped"] = src
    for variant, b in bakes.items():
        root = b["root"]
        files[variant] = export_lod(root, lod, root.parent.with_name(
            f"{root.parent.name}_export") / f"lod{lod}.usdz")
    try:
        got = import_and_render(files, renders / name / f"lod{lod}", resolution=args.resolution,
                                samples=args.samples, diag_px=px, timeout=3600.0,
                                seeds={"original_seed1": 1})
    except (Exception, pytest.fail.Exception, pytest.skip.Exception) as e:
        return f"Blender not run: {str(e).splitlines()[0]}"
    pngs = {k: Path(got["files"][k]["png"]) for k in files}
    ref, a_ref = _png(pngs["original"])
    again, a_again = _png(pngs["original_seed1"])
    floor = image_figures(again, ref, a_again, a_ref)
    out = {}
    for variant in bakes:
        img, a_img = _png(pngs[variant])
        out[variant] = image_figures(img, ref, a_img, a_ref)
        out[variant]["render_seconds"] = round(got["files"][variant]["render_seconds"], 1)
        out[variant]["psnr_floor_db"] = floor["psnr_db_object"]
        out[variant]["flip_floor"] = floor["flip_object"]
        out[variant]["twin_triangles_removed"] = n_twins
        if n_twins:
            shipped, a_shipped = _png(pngs["original_as_shipped"])
            out[variant]["as_shipped"] = image_figures(img, shipped, a_img, a_shipped)
    side_by_side([pngs[k] for k in files if k != "original_seed1"], renders / f"{name}_lod{lod}.png")
    return out


def texelbake_lod(root: Path, lod: int, px: float, args: argparse.Namespace
                  ) -> dict[str, Any]:
    """texelbake's preview-surface against its gt at the switch distance of `lod`, and its
    cpm mode's figures beside it ("cpm")."""
    from texelbake.render.cpm import choose_mesh
    from texelbake.render.frame import render_frame
    from texelbake.render.preview_surface import render_preview_surface
    from texelbake.render.scene import load_scene, resolve_camera

    scene = load_scene(root)
    res = args.resolution
    # auto_frame's distance factor f puts the camera at f R / sin(atan(tan(fov/2))); the
    # bounding sphere's diameter 2R then covers R res / (dist tan(fov/2)) pixels = px when
    # f = res cos(atan(tan(fov/2))) / px
    tan_x = math.tan(math.radians(TB_FOV_DEG) / 2.0)
    factor = res * math.cos(math.atan(tan_x)) / px
    cam = resolve_camera(scene, factor, res, res)
    gt = render_frame(scene, "gt", cam, args.tb_ref_spp, 1000)
    # the LOD judged, whatever mesh the camera's projected error would select
    t0 = time.perf_counter()
    img, _, cov = render_preview_surface(scene, cam, args.tb_spp, 0, lod=lod - 1)
    seconds = time.perf_counter() - t0
    fig = image_figures(img, gt.image, np.asarray(cov, dtype=np.float64),
                        np.asarray(gt.coverage, dtype=np.float64))
    fig["mesh"] = f"M{lod}"
    fig["mesh_by_error"] = f"M{choose_mesh(scene, cam, 1.0) + 1}"  # what the mode would pick
    fig["seconds"] = round(seconds, 3)
    # beside it, texelbake's own maps at the same view and spp (the bake's CPM at `BAKE`)
    cpm = render_frame(scene, "cpm", cam, args.tb_spp, 0)
    fig["cpm"] = image_figures(cpm.image, gt.image, np.asarray(cpm.coverage, np.float64),
                               np.asarray(gt.coverage, dtype=np.float64))
    return fig


def asset_cases(work: Path, size: str, assets: list[str] | None) -> dict[str, Path]:
    """The benchmark's assets by name: the generated scenes asked for (all when `assets` is
    empty) written at `size` under `work`, then the Teapot and BoxAnimated from
    ../shared/assets (their paths; a caller skips one that is missing)."""
    cases: dict[str, Path] = {}
    for name in SCENES:
        if not assets or name in assets:
            cases[name] = write_scene(name, work / f"{name}.usda", size)
    cases["teapot"] = ASSETS / "Teapot" / "Teapot.usd"
    cases["box_animated"] = ASSETS / "BoxAnimated.usdz"
    if assets and "teapot_fancy" in assets:  # asked for by name only (a copy of the folder)
        cases["teapot_fancy"] = fancy_teapot(work)
    return cases


def fancy_teapot(work: Path) -> Path:
    """The Teapot with its `modelVariant` "Fancy" selected (an ARM texture: roughness and a
    metallic gold trim beside porcelain): a layer that references a copy of the asset's
    folder (texelbake reads only paths inside the asset's own folder)."""
    dest = work / "teapot_fancy"
    if not dest.exists():
        shutil.copytree(ASSETS / "Teapot", dest / "Teapot")
    layer = dest / "teapot_fancy.usda"
    layer.write_text('#usda 1.0\n(\n    defaultPrim = "Teapot"\n    metersPerUnit = 1\n'
                     '    upAxis = "Y"\n)\n\ndef Xform "Teapot" (\n'
                     '    prepend references = @./Teapot/Teapot.usd@\n'
                     '    variants = {\n        string modelVariant = "Fancy"\n    }\n'
                     '    prepend variantSets = "modelVariant"\n)\n{\n}\n')
    return layer


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--json", type=Path, help="write the rows here")
    ap.add_argument("--size", default="full")
    ap.add_argument("--assets", nargs="*", help="subset of the asset names")
    ap.add_argument("--resolution", type=int, default=256)
    ap.add_argument("--samples", type=int, default=256, help="Cycles samples per pixel")
    ap.add_argument("--tb-spp", type=int, default=16, help="preview-surface eye rays per px")
    ap.add_argument("--tb-ref-spp", type=int, default=256, help="gt eye rays per pixel")
    ap.add_argument("--renders", type=Path, help="keep the renders and screenshots here")
    ap.add_argument("--no-blender", action="store_true", help="skip the Blender columns")
    ap.add_argument("--variants", nargs="*", choices=list(FALLBACKS),
                    help="subset of the fallback variants (default: all)")
    args = ap.parse_args()
    args.fallbacks = {k: v for k, v in FALLBACKS.items()
                      if not args.variants or k in args.variants}
    work = Path(tempfile.mkdtemp(prefix="fallback_bench_"))
    cases = asset_cases(work, args.size, args.assets)
    renders = args.renders or (args.json.parent / f"{args.json.stem}_renders" if args.json
                               else work / "renders")
    print(f"bake settings (BakeSettings defaults otherwise): {BAKE}; variants: "
          f"{args.fallbacks}")
    print(f"Blender: Cycles CPU {args.resolution}^2, {args.samples} spp, no denoiser; "
          f"texelbake: preview-surface {args.tb_spp} spp against gt {args.tb_ref_spp} spp")
    rows: list[dict[str, Any]] = []
    notes: list[str] = []
    order = args.assets or list(cases)  # the order asked for
    for name in order:
        src = cases.get(name)
        if src is None or not src.is_file():
            notes.append(f"{name}: {src} is missing, skipped")
            continue
        if renders.exists() and (renders / name).exists():
            shutil.rmtree(renders / name)
        bakes = bake_variants(name, src, work, args.fallbacks)
        first = next(iter(bakes.values()))
        # what Blender shows for the original: UsdPreviewSurface, or the stand-in a material
        # with a texelbake shader carries on its universal output
        stand_ins = sorted({m.model for m in load_asset(src).materials} - {"preview"})
        for lod, px in enumerate(first["switch_px"], start=1):
            bl = "--no-blender" if args.no_blender else blender_lod(
                name, src, bakes, lod, px, renders, args)
            if isinstance(bl, str):
                notes.append(f"{name} LOD{lod}: {bl}")
            for variant, b in bakes.items():
                rows.append({"asset": name, "lod": lod, "switch_px": px, "variant": variant,
                             "bake_seconds": b["seconds"],
                             "export_seconds": b["export_seconds"],
                             "blender_stand_ins": stand_ins,
                             "blender": None if isinstance(bl, str) else bl[variant],
                             "texelbake": texelbake_lod(b["root"], lod, px, args),
                             "fit": _fit_entry(b["root"], lod)})
            _print_row_block(rows[-len(bakes):])
        if args.json:  # after every asset: a long run interrupted keeps what it measured
            _write_json(args, rows, notes)
    print()
    _print_table(rows)
    for n in notes:
        print(n)
    bolt = [r for r in rows if r["asset"] == "bolt"]
    for r in bolt:
        for who in ("blender", "texelbake"):
            if r[who]:
                print(f"bolt LOD{r['lod']} {r['variant']} ({who}): object mean radiance "
                      f"{r[who]['mean_radiance']:.4f} vs original {r[who]['mean_radiance_original']:.4f}"
                      f" (ratio {r[who]['mean_ratio']:.3f}; the fitted fallback's bar: 0.75-1.25)")
    print(f"screenshots (original | the original as shipped, where twins were removed | "
          f"{' | '.join(args.fallbacks)}): {renders}/<asset>_lod<N>.png")
    if args.json:
        _write_json(args, rows, notes)


def _fit_entry(root: Path, lod: int) -> dict[str, Any] | None:
    """The bake's report of the fitted gain of LOD `lod` (its level, λ, held-out ratio and
    the per-texel residual's summary), None for a fallback without a fit."""
    fit = json.loads((root.parent / "report.json").read_text())["fallback"].get("fit")
    return fit["gain"][lod - 1] if fit else None


def bar_notes(rows: list[dict[str, Any]]) -> list[str]:
    """Per asset and LOD with Blender's figures: fitted minus averaged PSNR in each renderer
    against the 3 dB bar, with Cycles' noise floor and what Blender's reference is."""
    out = []
    by: dict[tuple[str, int], dict[str, dict[str, Any]]] = {}
    for r in rows:
        by.setdefault((r["asset"], r["lod"]), {})[r["variant"]] = r
    for (asset, lod), v in by.items():  # a loop over the few (asset, LOD) pairs
        if not {"averaged", "fitted"} <= set(v) or not v["averaged"]["blender"]:
            continue
        a, f = v["averaged"], v["fitted"]
        gain = {who: round(f[who]["psnr_db_object"] - a[who]["psnr_db_object"], 2)
                for who in ("blender", "texelbake")}
        bl = a["blender"]
        ref = ("the original" if not bl.get("twin_triangles_removed") else
               f"the original without its {bl['twin_triangles_removed']} twin triangles "
               f"(as shipped: averaged {bl['as_shipped']['psnr_db_object']:.2f} dB, mean "
               f"{bl['as_shipped']['mean_ratio']:.2f}x)")
        if a.get("blender_stand_ins"):
            ref += (f"; Blender shows the UsdPreviewSurface stand-in for "
                    f"{', '.join(a['blender_stand_ins'])}, not the material the LOD was baked from")
        verdict = "clears" if gain["blender"] >= 3.0 else "below"
        res = (f["fit"] or {}).get("residual") or {}
        why = ""
        if res.get("fitted"):  # what the preview surface leaves per texel, beside the noise
            why = (f"; per-texel residual of the fit (median) {res['fitted']['p50']:.2f} vs "
                   f"averaged {res['averaged']['p50']:.2f}, target noise "
                   f"{res['target_noise'].get('p50', float('nan')):.2f}, "
                   f"{res['texels_above_flag']} of {res['texels']} texels above "
                   f"{res['flag']}")
        out.append(f"{asset} LOD{lod}: fitted minus averaged {gain} dB: {verdict} the 3 dB bar; "
                   f"Blender noise floor {bl['psnr_floor_db']:.1f} dB (averaged "
                   f"{bl['psnr_db_object']:.2f}){why}; Blender's reference: {ref}")
    return out


def _write_json(args: argparse.Namespace, rows: list[dict[str, Any]], notes: list[str]) -> None:
    notes = [*notes, *bar_notes(rows)]
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps({
        "size": args.size, "bake": BAKE, "fallbacks": args.fallbacks,
        "blender": {"engine": "CYCLES", "device": "CPU", "resolution": args.resolution,
                    "samples": args.samples, "denoiser": False},
        "texelbake": {"mode": "preview-surface", "spp": args.tb_spp,
                      "reference": "gt", "ref_spp": args.tb_ref_spp},
        "rows": rows, "notes": notes}, indent=1, sort_keys=True, default=str))


def _fmt(fig: dict[str, Any] | None) -> str:
    if not fig:
        return f"{'-':>8}{'-':>7}{'-':>7}{'-':>7}"
    floor = f"{fig['psnr_floor_db']:>7.1f}" if "psnr_floor_db" in fig else ""
    return (f"{fig['psnr_db_object']:>8.2f}{fig['flip_object']:>7.3f}{fig['iou']:>7.3f}"
            f"{fig['mean_ratio']:>7.2f}{floor}")


def _print_row_block(rows: list[dict[str, Any]]) -> None:
    for r in rows:
        cpm = (r["texelbake"] or {}).get("cpm")
        print(f"  {r['asset']} LOD{r['lod']} ({r['switch_px']:g} px) {r['variant']}: "
              f"Blender {_fmt(r['blender'])} | texelbake {_fmt(r['texelbake'])}"
              f" | cpm {_fmt(cpm)}", flush=True)


def _print_table(rows: list[dict[str, Any]]) -> None:
    head = (f"{'asset':<13}{'lod':>4}{'px':>6} {'variant':<10}|{'Blender PSNR':>13}{'FLIP':>7}"
            f"{'IoU':>7}{'mean':>7}{'floor':>7} |{'tb PSNR':>9}{'FLIP':>7}{'IoU':>7}{'mean':>7}"
            f"{'mesh':>6} |{'cpm PSNR':>9}{'FLIP':>7}{'IoU':>7}{'mean':>7}")
    print(head)
    for r in rows:
        tb = r["texelbake"]
        print(f"{r['asset']:<13}{r['lod']:>4}{r['switch_px']:>6g} {r['variant']:<10}|"
              f"{_fmt(r['blender']):>41} |{_fmt(tb)}{str(tb.get('mesh')):>6} |"
              f"{_fmt(tb.get('cpm'))}")


if __name__ == "__main__":
    main()
