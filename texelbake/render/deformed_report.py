"""`texelbake render BAKED --warp SPEC` / `--time T`: a deformed frame of a baked asset in
each mode of `texelbake.render.deformed`, against the reference gt of the deformed M_org,
written as images and `deformed_report.json`:

    {"scene", "warp", "width", "height", "camera", "reference": {"mode": "gt", "spp",
     "seconds"}, "modes": {mode: {"seconds", "spp", "psnr_db_object", ... (as
     `render.report`)}}}

The warp comes from a spec string (`deform.warps.parse_warp`, placed on the rest bounding
box) or from the asset's own animation at a time code (`warp_at_time`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from texelbake.deform.skinbind import transforms_at
from texelbake.deform.warps import AffineWarp, MeshWarp, SkinnedMeshWarp, Warp, parse_warp
from texelbake.errors import SettingsError
from texelbake.io.images import write_exr, write_png
from texelbake.model import AssetModel
from texelbake.render.deformed import deform_scene
from texelbake.render.frame import DEFORMED_MODES, render_deformed
from texelbake.render.report import _entry, _write_json
from texelbake.render.scene import describe_camera, load_scene, resolve_camera


def warp_at_time(asset: AssetModel, time: float) -> Warp:
    """Ψ of the asset's own animation at `time`: its time-sampled points (UsdSkel skinning
    is evaluated by ingest into these), linearly interpolated between the two nearest time
    codes and clamped to the first / last, as a `MeshWarp` from the rest points (the points
    the bake saw). An asset with at most one time sample does not deform: the identity."""
    codes = np.asarray(asset.time_codes, dtype=np.float64)
    if not np.isfinite(time):
        raise SettingsError(f"field 'time': must be finite, got {time}")
    if codes.shape[0] <= 1:
        return AffineWarp(np.eye(3), np.zeros(3), name=f"time:{time:g} (static asset)",
                          scale=asset.bbox_diag)
    t = float(np.clip(time, codes[0], codes[-1]))
    k = int(np.clip(np.searchsorted(codes, t, side="right") - 1, 0, codes.shape[0] - 2))
    a = (t - codes[k]) / (codes[k + 1] - codes[k])
    pts = (1.0 - a) * asset.points_over_time[k] + a * asset.points_over_time[k + 1]
    if asset.skin is not None:  # the LODs bound to the skeleton follow its transforms
        return SkinnedMeshWarp(asset.points, pts, asset.faces, name=f"time:{time:g}",
                               scale=asset.bbox_diag,
                               transforms=transforms_at(asset.skin, codes, t),
                               rest_transforms=asset.skin.rest)
    return MeshWarp(asset.points, pts, asset.faces, name=f"time:{time:g}",
                    scale=asset.bbox_diag)


def render_deformed_report(baked_root: str | Path, out_dir: str | Path, *,
                           warp: str | None = None, time: float | None = None,
                           modes: tuple[str, ...] | str = ("gt", "cpm", "cpm-naive",
                                                           "normalmap"),
                           width: int = 256, height: int = 256, spp: int = 4,
                           ref_spp: int = 256, camera: object = None, seed: int = 0) -> Path:
    """Render the deformed frame in each mode and the reference; write `<mode>.exr/.png`,
    `reference.exr/.png` and `deformed_report.json` into out_dir; return the report's
    path. Exactly one of warp / time."""
    if (warp is None) == (time is None):
        raise SettingsError("fields 'warp' and 'time': give exactly one")
    if isinstance(modes, str):
        modes = tuple(m.strip() for m in modes.split(",") if m.strip())
    bad = [m for m in modes if m not in DEFORMED_MODES]
    if bad or not modes:
        raise SettingsError(f"field 'modes': a deformed frame renders some of "
                            f"{DEFORMED_MODES}, got {modes!r}")
    modes = tuple(sorted(set(modes), key=DEFORMED_MODES.index))
    scene = load_scene(baked_root)
    psi = (parse_warp(warp, scene.asset.bounds) if warp is not None
           else warp_at_time(scene.asset, float(time)))  # type: ignore[arg-type]
    d = deform_scene(scene, psi)
    cam = resolve_camera(scene, camera, width, height)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    ref = render_deformed(d, "gt", cam, ref_spp, seed + 1)
    write_exr(out / "reference.exr", ref.image)
    write_png(out / "reference.png", ref.image)
    entries: dict[str, Any] = {}
    cpm_seconds = None
    for mode in modes:  # a loop over the few modes
        kw: dict[str, Any] = {}
        if mode == "equal-time" and cpm_seconds is not None:
            kw["budget_seconds"] = cpm_seconds
        render_deformed(d, mode, cam, spp, seed, **kw)  # warm (as report.compare_modes)
        res = render_deformed(d, mode, cam, spp, seed, **kw)
        if mode == "cpm":
            cpm_seconds = res.seconds
        write_exr(out / f"{mode}.exr", res.image)
        write_png(out / f"{mode}.png", res.image)
        entries[mode] = _entry(res, ref, None)
        if "fallback_fraction" in res.extras:
            entries[mode]["fallback_fraction"] = round(float(res.extras["fallback_fraction"]), 4)
    report = {"scene": scene.baked.name, "warp": psi.name, "width": width, "height": height,
              "camera": describe_camera(scene, camera),
              "reference": {"mode": "gt", "spp": ref_spp, "seconds": round(ref.seconds, 4)},
              "object_pixels": int((ref.coverage > 0).sum()) if ref.coverage is not None
              else 0,
              "default_lights": scene.default_lights, "modes": entries}
    path = out / "deformed_report.json"
    _write_json(path, report)
    return path
