"""Public entry points of the renderer: `render`, `render_previews`, `render_report`,
`compare_modes` and `write_report_plot` (the diagnostic images are in
`texelbake.render.diagnostics`).

`render_report.json` (written by `render_previews` and by `benchmarks/render.py`)::

    {"scene": name, "width": w, "height": h, "reference": {"mode": "gt", "spp": n, ...},
     "modes": {mode: {"seconds", "rays_cast", "spp", "psnr_db_object", "object_pixels",
                      "delta_e_mean", "delta_e_p95", "flip_mean", "flip_mean_object",
                      "rmse", "psnr_db", "snr_db", "files": [...], ...}},
     "equal_time": {"cpm_seconds", "equal_time_seconds", "ratio", "mean_spp"},
     "crossover": {...} (see `crossover`),
     "sweep": [{"mode", "spp", "eps_db", "seconds", ... the same errors}, ...]}

Errors are against the reference `gt` image (more eye rays per pixel than any other entry).
`psnr_db_object`, ΔE*ab and `flip_mean_object` are over the object's pixels (the union of
the reference's and the entry's coverage, dilated by one pixel: `metrics.object_mask`);
`rmse`, `psnr_db` and `snr_db` are over the whole frame (labelled so in every table: the
black background lifts them); `flip_mean` is FLIP over the frame, as FLIP is defined.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from texelbake.errors import SettingsError, StageError
from texelbake.io.atomic import atomic_path
from texelbake.io.images import write_exr, write_png
from texelbake.render import metrics
from texelbake.render.btf import has_btf_maps
from texelbake.render.diagnostics import (
    density_atlas,
    density_colours,
    density_on_model,
    level_colours,
)
from texelbake.render.frame import EXTRA_MODES, MODES, render_frame
from texelbake.render.scene import RenderScene, describe_camera, load_scene, resolve_camera
from texelbake.trace import camera as cam_mod
from texelbake.trace.tracer import RenderResult

#: preview sizes: (pixels per side, reference spp, gt sweep spp, cpm sweep spp, spp of the
#: compared images)
PREVIEW_SIZES: dict[str, dict[str, Any]] = {
    "small": {"px": 96, "ref_spp": 64, "gt_sweep": (1, 4, 16), "cpm_sweep": (1, 4), "spp": 4},
    "medium": {"px": 256, "ref_spp": 256, "gt_sweep": (1, 4, 16, 64), "cpm_sweep": (1, 4, 16),
               "spp": 4},
    "full": {"px": 512, "ref_spp": 1024, "gt_sweep": (1, 4, 16, 64, 256),
             "cpm_sweep": (1, 4, 16), "spp": 4},
}


def render(baked_root: str | Path, mode: str, *, width: int, height: int, spp: int,
           camera: object = None, out_dir: str | Path | None = None, seed: int = 0,
           **kw: Any) -> RenderResult:
    """Render a baked USD in one mode ("gt", "cpm", "normalmap", "equal-time", or "btf" when
    the bake wrote BTF maps, `BakeSettings.btf`).

    camera : None (the asset's camera, else auto-framed), a `camera.PinholeCamera`, a
        `model.Camera`, or a number (auto-frame at that distance factor)
    out_dir : when given, writes `<mode>.exr` (linear float) and `<mode>.png` (sRGB)
    kw : mode options (cpm: lod_bias, local_light_ratio, max_error_px, filtering,
        footprint "sample"|"pixel", coverage; equal-time: budget_seconds; btf: lod_bias,
        interpolate)
    returns : RenderResult (image (h, w, 3) float32, seconds, rays_cast, spp)
    """
    scene = load_scene(baked_root)
    cam = resolve_camera(scene, camera, width, height)
    res = render_frame(scene, mode, cam, spp, seed, **kw)
    if out_dir is not None:
        out = Path(out_dir)
        write_exr(out / f"{mode}.exr", res.image)
        write_png(out / f"{mode}.png", res.image)
    return res


# --------------------------------------------------------------------------- diagnostics


def _upscale(img: np.ndarray, min_px: int = 256) -> np.ndarray:
    k = max(1, int(math.ceil(min_px / max(img.shape[:2]))))
    return np.repeat(np.repeat(img, k, axis=0), k, axis=1)


# --------------------------------------------------------------------------- previews, report


def _errors(res: RenderResult, ref: RenderResult) -> dict[str, float | int]:
    img, ref_img = res.image, ref.image
    covs = [c for c in (ref.coverage, res.coverage) if c is not None]
    mask = (metrics.object_mask(*covs) if covs
            else metrics.object_mask(ref_img.max(axis=2) > 0))
    lit = float(ref_img.max()) > 0.0  # an all-black reference has no PSNR/SNR: NaN, noted
    return {**metrics.object_errors(img, ref_img, mask), "rmse": metrics.rmse(img, ref_img),
            "psnr_db": metrics.psnr_db(img, ref_img) if lit else float("nan"),
            "snr_db": metrics.snr_db(img, ref_img) if lit else float("nan")}


def _entry(res: RenderResult, ref: RenderResult | None, eps_db: float | None
           ) -> dict[str, Any]:
    e: dict[str, Any] = {"mode": res.mode, "spp": res.spp, "seconds": round(res.seconds, 4),
                         "rays_cast": res.rays_cast}
    if "mean_spp" in res.extras:
        e["mean_spp"] = round(res.extras["mean_spp"], 3)
        e["budget_seconds"] = round(res.extras["budget_seconds"], 4)
    if eps_db is not None and res.mode == "cpm":
        e["eps_db"] = eps_db
    if ref is not None:
        e.update(_errors(res, ref))
    return e


def crossover(sweep: list[dict[str, Any]], spp: int) -> dict[str, Any]:
    """Where brute force starts to beat cpm: the cheapest `gt` entry of the sweep whose
    object PSNR exceeds cpm's at `spp` (cpm's error is mostly bias, which more eye rays do
    not remove, so past some budget gt wins). Returns {"cpm_spp", "cpm_seconds",
    "cpm_psnr_db_object", "gt_spp", "gt_seconds", "gt_psnr_db_object", "seconds_ratio"};
    the gt fields are None when no gt entry of the sweep beats cpm ("beyond the sweep")."""
    cpm = [e for e in sweep if e["mode"] == "cpm" and e["spp"] == spp]
    gts = sorted((e for e in sweep if e["mode"] == "gt" and "psnr_db_object" in e),
                 key=lambda e: e["seconds"])
    if not cpm or "psnr_db_object" not in cpm[0]:
        raise StageError(f"crossover needs cpm at {spp} spp in the sweep")
    c = cpm[0]
    out: dict[str, Any] = {"cpm_spp": spp, "cpm_seconds": c["seconds"],
                           "cpm_psnr_db_object": c["psnr_db_object"], "gt_spp": None,
                           "gt_seconds": None, "gt_psnr_db_object": None,
                           "seconds_ratio": None}
    for g in gts:
        if g["psnr_db_object"] > c["psnr_db_object"]:
            out.update(gt_spp=g["spp"], gt_seconds=g["seconds"],
                       gt_psnr_db_object=g["psnr_db_object"],
                       seconds_ratio=round(g["seconds"] / max(c["seconds"], 1e-12), 3))
            break
    return out


def _eps_db(scene: RenderScene) -> float | None:
    s = scene.baked.metadata.get("settings", {})
    v = s.get("eps_db") if hasattr(s, "get") else None
    return None if v is None else float(v)


def render_previews(baked_root: str | Path, out_dir: str | Path, *, size: str = "small",
                    seed: int = 0) -> list[Path]:
    """Previews of every mode, the diagnostics and `render_report.json` (module docstring)
    for one baked USD. Used by `make demo` (size "small") and the farm's render stage.

    Two views: "near" — the asset's camera (what a user looks at; where the finest texels
    are larger than a pixel the cpm mode falls back to M_org, and mip_levels.png shows it in
    white); "far" — the same view moved back until a finest texel spans about a pixel
    (`scene.lod_camera`), where the characteristic point maps are used; its files carry the
    prefix `far_`. Writes into out_dir, per view: gt_reference, gt, cpm, normalmap,
    equal-time, and btf when the bake wrote BTF maps (.exr linear, .png sRGB); diff_<mode>.png (ΔE*ab against the reference);
    mip_levels.png; and cp_density_atlas.png, cp_density_model.png, render_report.json,
    speed_error.png. Returns the written paths.
    """
    if size not in PREVIEW_SIZES:
        raise SettingsError(f"field 'size': expected one of {sorted(PREVIEW_SIZES)}, got "
                            f"{size!r}")
    cfg = PREVIEW_SIZES[size]
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    scene = load_scene(baked_root)
    px = cfg["px"]
    near = resolve_camera(scene, None, px, px)
    far = resolve_camera(scene, "lod", px, px)
    opts = {"spp": cfg["spp"], "ref_spp": cfg["ref_spp"], "gt_sweep": cfg["gt_sweep"],
            "cpm_sweep": cfg["cpm_sweep"], "seed": seed}
    modes = MODES + (("btf",) if has_btf_maps(scene) else ())
    report = compare_modes(scene, near, out_dir=out, modes=modes, **opts)
    report["camera"] = describe_camera(scene, None)
    report["far"] = compare_modes(scene, far, out_dir=out, prefix="far_", modes=modes, **opts)
    report["far"]["camera"] = describe_camera(scene, "lod")
    report["scene"] = scene.baked.name
    report["size"] = size
    files = [Path(f) for view in (report, report["far"]) for m in view["modes"].values()
             for f in m.get("files", [])]
    files.append(write_png(out / "cp_density_atlas.png",
                           _upscale(density_colours(density_atlas(scene))), srgb=False))
    files.append(write_png(out / "cp_density_model.png", density_on_model(scene, near),
                           srgb=False))
    rep_path = out / "render_report.json"
    _write_json(rep_path, report)
    files.append(rep_path)
    files.append(write_report_plot(out))
    return files


def render_report(baked_root: str | Path, out_dir: str | Path, *,
                  modes: tuple[str, ...] | str = MODES, width: int = 512, height: int = 512,
                  spp: int = 4, ref_spp: int = 1024, camera: object = None,
                  gt_sweep: tuple[int, ...] = (), cpm_sweep: tuple[int, ...] = (),
                  seed: int = 0) -> Path:
    """What `texelbake render BAKED.usda --modes gt,cpm,normalmap,equal-time` does: render
    the reference gt (`ref_spp`) and each mode (`spp`), write their images, difference maps
    and `render_report.json` (module docstring) into out_dir, and the speed-against-error
    plot. modes : tuple or comma-separated string. Returns the report's path."""
    if isinstance(modes, str):
        modes = tuple(m.strip() for m in modes.split(",") if m.strip())
    known = MODES + EXTRA_MODES
    unknown = [m for m in modes if m not in known]
    if unknown or not modes:
        raise SettingsError(f"field 'modes': expected some of {known}, got {modes!r}")
    # equal-time needs the cpm image's time: render cpm first when both are asked for
    modes = tuple(sorted(set(modes), key=known.index))
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    scene = load_scene(baked_root)
    cam = resolve_camera(scene, camera, width, height)
    report = compare_modes(scene, cam, spp=spp, ref_spp=ref_spp, gt_sweep=gt_sweep,
                           cpm_sweep=cpm_sweep, seed=seed, out_dir=out, modes=modes)
    report["scene"] = scene.baked.name
    report["camera"] = describe_camera(scene, camera)
    path = out / "render_report.json"
    _write_json(path, report)
    write_report_plot(out)
    return path


def compare_modes(scene: RenderScene, cam: cam_mod.PinholeCamera, *, spp: int, ref_spp: int,
                  gt_sweep: tuple[int, ...] = (), cpm_sweep: tuple[int, ...] = (),
                  seed: int = 0, out_dir: Path | None = None,
                  modes: tuple[str, ...] = MODES, reference: RenderResult | None = None,
                  prefix: str = "", btf_kw: dict[str, Any] | None = None,
                  **kw: Any) -> dict[str, Any]:
    """Render the reference and every mode, measure their errors (report dict, module
    docstring). Images and difference maps are written to out_dir when given.
    kw : cpm options; btf_kw : btf options (lod_bias, interpolate)."""
    btf_kw = btf_kw or {}
    ref = reference if reference is not None else render_frame(
        scene, "gt", cam, ref_spp, seed + 1000)
    ref_img = ref.image
    eps_db = _eps_db(scene)
    report: dict[str, Any] = {
        "width": cam.width, "height": cam.height, "camera_position": cam.position.tolist(),
        "coverage": float(np.mean(_ref_coverage(ref))),
        "object_pixels": int(np.sum(_ref_coverage(ref))),
        "reference": {"mode": "gt", "spp": ref.spp, "seconds": round(ref.seconds, 4),
                      "rays_cast": ref.rays_cast},
        "modes": {}, "sweep": [],
        # which lights lit the frames: the asset's, or the default rig when it has none
        "lights": [light.path for light in scene.lights],
        "default_lights": bool(getattr(scene, "default_lights", False)),
    }
    if out_dir is not None:
        write_exr(out_dir / f"{prefix}gt_reference.exr", ref_img)
        write_png(out_dir / f"{prefix}gt_reference.png", ref_img)
    results: dict[str, RenderResult] = {}
    for mode in modes:  # a loop over the four modes
        if mode == "equal-time":
            res = render_frame(scene, mode, cam, spp, seed,
                               budget_seconds=results["cpm"].seconds if "cpm" in results
                               else None, **kw)
        else:
            mode_kw = kw if mode == "cpm" else btf_kw if mode == "btf" else {}
            # timed warm: each mode renders the frame once untimed first (first calls pay
            # one-time costs: kernels, imports, lazy tables; the full wall's first cpm frame
            # took 0.46 s against 0.35 s after), as a previewer rendering frame after frame
            render_frame(scene, mode, cam, spp, seed, **mode_kw)
            res = render_frame(scene, mode, cam, spp, seed, **mode_kw)
        results[mode] = res
        entry = _entry(res, ref, eps_db)
        if mode == "cpm":
            entry["mesh"] = res.extras.get("mesh")
            entry["fallback_fraction"] = res.extras.get("fallback_fraction")
        if out_dir is not None:
            files = [str(write_exr(out_dir / f"{prefix}{mode}.exr", res.image)),
                     str(write_png(out_dir / f"{prefix}{mode}.png", res.image))]
            dmap = metrics.difference_map(res.image, ref_img)
            files.append(str(metrics.write_difference_map(
                out_dir / f"{prefix}diff_{mode}.png", dmap)))
            if mode == "cpm":
                files.append(str(write_png(
                    out_dir / f"{prefix}mip_levels.png",
                    level_colours(res.extras["level"], len(scene.baked.levels)), srgb=False)))
            entry["files"] = files
        report["modes"][mode] = entry
        report["sweep"].append({k: v for k, v in entry.items() if k != "files"})
    for s in gt_sweep:
        if s != spp or "gt" not in results:
            report["sweep"].append(_entry(render_frame(scene, "gt", cam, s, seed), ref,
                                          eps_db))
    for s in cpm_sweep:
        if s != spp or "cpm" not in results:
            report["sweep"].append(_entry(render_frame(scene, "cpm", cam, s, seed, **kw),
                                          ref, eps_db))
    if "cpm" in results and "equal-time" in results:
        eq = results["equal-time"]
        report["equal_time"] = {
            "cpm_seconds": round(results["cpm"].seconds, 4),
            "equal_time_seconds": round(eq.seconds, 4),
            "ratio": round(eq.seconds / max(results["cpm"].seconds, 1e-12), 4),
            "mean_spp": round(eq.extras["mean_spp"], 3)}
    if "cpm" in results and any(e["mode"] == "gt" for e in report["sweep"]):
        report["crossover"] = crossover(report["sweep"], spp)
    return report


def _ref_coverage(ref: RenderResult) -> np.ndarray:
    """(h, w) bool: pixels where the reference saw the object."""
    if ref.coverage is not None:
        return ref.coverage > 0
    return ref.image.max(axis=2) > 0


def _write_json(path: Path, obj: Any) -> None:
    from texelbake.io.atomic import atomic_json

    atomic_json(path, _finite(obj))


def _finite(obj: Any) -> Any:
    """JSON has no inf: exact matches are written as the string "inf"."""
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_finite(v) for v in obj]
    if isinstance(obj, float) and not math.isfinite(obj):
        return str(obj)
    return obj


def write_report_plot(report_dir: str | Path) -> Path:
    """Speed against error (matplotlib PNG `speed_error.png` beside `render_report.json`):
    PSNR over the object's pixels (dB) against seconds per frame, one curve per (mode, ε)
    of the sweep, each point labelled with its eye rays per pixel (reports written before
    the object PSNR existed are drawn with their whole-frame PSNR, and the axis says so)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    d = Path(report_dir)
    path = d / "render_report.json"
    if not path.is_file():
        raise StageError(f"no render_report.json in {d}")
    report = json.loads(path.read_text())
    groups: dict[str, list[dict[str, Any]]] = {}
    has_object = any("psnr_db_object" in e for e in report.get("sweep", []))
    metric = "psnr_db_object" if has_object else "psnr_db"
    views = [("", report)] + ([("far: ", report["far"])] if "far" in report else [])
    for label, view in views:
        for e in view.get("sweep", []):
            v = e.get(metric)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and e.get("seconds", 0) > 0):
                continue
            key = label + e["mode"] + (f" (ε = {e['eps_db']:g} dB)" if "eps_db" in e else "")
            groups.setdefault(key, []).append(e)
    fig, ax = plt.subplots(figsize=(6.4, 4.4), dpi=120)
    markers = {"gt": "o", "cpm": "s", "normalmap": "^", "equal-time": "D", "btf": "v"}
    for key in sorted(groups):
        pts = sorted(groups[key], key=lambda e: e["seconds"])
        mode = pts[0]["mode"]
        xs = [e["seconds"] for e in pts]
        ys = [e[metric] for e in pts]
        ax.plot(xs, ys, marker=markers.get(mode, "x"), label=key,
                linestyle="-" if len(pts) > 1 else "none")
        for e in pts:
            ax.annotate(str(e.get("mean_spp", e["spp"])), (e["seconds"], e[metric]), fontsize=7,
                        xytext=(3, 3), textcoords="offset points")
    ax.set_xscale("log")
    ax.set_xlabel("seconds per frame")
    ax.set_ylabel("PSNR against gt over the object (dB)" if has_object
                  else "PSNR against gt, whole frame (dB)")
    ref = report.get("reference", {})
    ax.set_title(f"{report.get('scene', '')} {report.get('width', '')}×"
                 f"{report.get('height', '')}, reference gt at {ref.get('spp', '?')} spp")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    out = d / "speed_error.png"
    with atomic_path(out) as tmp:
        fig.savefig(tmp)
    plt.close(fig)
    return out
