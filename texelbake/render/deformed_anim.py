"""Animated previews of a deformed baked asset: the frames of the
asset's own animation (its time codes' range) or of a warp sweep (a procedural warp grown from
the identity to its full amount), each rendered in the deformed frame's modes beside the
reference gt of the deformed M_org, written next to the stills as

    animation.gif          one tile per mode, left to right: reference, then `modes` in order
    error_per_frame.png    PSNR over the object's pixels against the reference, per mode
    animation.json         {"scene", "source": "time"|"warp", "warp", "width", "height",
                            "spp", "ref_spp", "tiles", "frames": [{"label", "time"|"amount",
                            "object_pixels", "reference_seconds", "modes": {mode: {"seconds",
                            "psnr_db_object", ...}}}]}

One camera for every frame: auto-framed on the union of the deformed M_org's bounds over the
animation, so the motion is seen and not the camera's, with as many pixels across as put a
finest texel at `texel_px` pixels (the `lod` view's footprint: closer, cpm falls back to M_org
and cpm, cpm-naive and gt would be the same image). The GIF shows each pixel as a block of
`zoom`² (nearest); errors are over the rendered pixels.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from texelbake.deform.warps import WARP_PARAMS, Warp, parse_warp, parse_warp_fields
from texelbake.errors import SettingsError
from texelbake.io.atomic import atomic_path
from texelbake.io.images import to_uint8, write_animation
from texelbake.render.deformed import deform_scene
from texelbake.render.deformed_report import warp_at_time
from texelbake.render.frame import DEFORMED_MODES, render_deformed
from texelbake.render.report import _entry
from texelbake.render.scene import RenderScene, load_scene, texel_size
from texelbake.trace import camera as cam_mod

ANIM_MODES = ("cpm", "cpm-naive", "normalmap")

#: per warp, its parameters' identity values: a sweep blends each from these to the spec's
_IDENTITY: dict[str, dict[str, float]] = {
    "twist": {"angle": 0.0}, "bend": {"angle": 0.0}, "sine": {"amplitude": 0.0},
    "stretch": {"x": 1.0, "y": 1.0, "z": 1.0}, "scale": {"s": 1.0},
    "rigid": {"angle": 0.0, "tx": 0.0, "ty": 0.0, "tz": 0.0},
}


def sweep_spec(spec: str, amount: float) -> str:
    """The warp `spec` at `amount` ∈ [0, 1] of its way from the identity: each numeric
    parameter with an identity value (`_IDENTITY`) blended linearly, the others (axes, phase,
    periods) kept."""
    name, prm = parse_warp_fields(spec)
    if not 0.0 <= amount <= 1.0:
        raise SettingsError(f"field 'amount': must be in [0, 1], got {amount}")
    ident = _IDENTITY[name]
    out = []
    for key in WARP_PARAMS[name]:
        v = prm[key]
        if key in ident:
            v = ident[key] + amount * (float(v) - ident[key])  # type: ignore[arg-type]
            out.append(f"{key}={v:.9g}")
        else:
            out.append(f"{key}={v}")
    return f"{name}:{','.join(out)}"


def animation_warps(scene: RenderScene, *, warp: str | None, frames: int
                    ) -> list[tuple[str, float, Warp]]:
    """[(label, time or amount, Ψ)] for each frame: the asset's animation over its time codes'
    range when warp is None (an asset without animation: SettingsError), else the sweep."""
    if frames < 2:
        raise SettingsError(f"field 'frames': an animation needs at least 2, got {frames}")
    if warp is None:
        a = scene.asset
        if not a.has_deformation:
            raise SettingsError("the asset has no animation (at most one time sample); give a "
                                "warp to sweep, e.g. --warp bend:angle=90")
        times = np.linspace(a.time_codes[0], a.time_codes[-1], frames)
        return [(f"time {t:g}", float(t), warp_at_time(a, float(t))) for t in times.tolist()]
    bounds = scene.asset.bounds
    amounts = np.linspace(0.0, 1.0, frames)
    return [(sweep_spec(warp, s), float(s), parse_warp(sweep_spec(warp, s), bounds))
            for s in amounts.tolist()]


def _zoom(img: np.ndarray, k: int) -> np.ndarray:
    return np.repeat(np.repeat(img, k, axis=0), k, axis=1) if k > 1 else img


def _tile(images: list[np.ndarray], gap: int = 2) -> np.ndarray:
    """Side by side, uint8, separated by `gap` white columns."""
    h = images[0].shape[0]
    sep = np.full((h, gap, 3), 255, dtype=np.uint8)
    parts: list[np.ndarray] = []
    for k, im in enumerate(images):
        if k:
            parts.append(sep)
        parts.append(im)
    return np.concatenate(parts, axis=1)


def animation_camera(scene: RenderScene, points: np.ndarray, texel_px: float
                     ) -> cam_mod.PinholeCamera:
    """Auto-framed on `points` (n, 3) (the union of the animation's deformed M_org), square,
    with the pixel count that makes a finest texel `texel_px` pixels at the frame's centre."""
    bounds = np.stack([points.min(0), points.max(0)])
    probe = cam_mod.auto_frame(bounds, 64, 64)
    depth = float(np.linalg.norm(bounds.mean(0) - probe.position))
    width = probe.pixel_angle * 64 * depth * texel_px / max(texel_size(scene), 1e-12)
    n = int(np.clip(math.floor(width), 8, 512))
    return cam_mod.auto_frame(bounds, n, n)


def render_animation(baked_root: str | Path, out_dir: str | Path, *, warp: str | None = None,
                     frames: int = 9, modes: tuple[str, ...] = ANIM_MODES, texel_px: float = 0.7,
                     zoom: int = 0, spp: int = 4, ref_spp: int = 64, fps: float = 4.0,
                     seed: int = 0, exposure: float = 1.0) -> Path:
    """Render the animation (module docstring) into out_dir; return animation.json's path.
    zoom : display block size of the GIF (0: enough for ~160 pixels across)."""
    bad = [m for m in modes if m not in DEFORMED_MODES or m in ("gt", "equal-time")]
    if bad or not modes:
        raise SettingsError(f"field 'modes': an animation renders some of "
                            f"{[m for m in DEFORMED_MODES if m not in ('gt', 'equal-time')]}, "
                            f"got {modes!r}")
    scene = load_scene(baked_root)
    plan = animation_warps(scene, warp=warp, frames=frames)
    deformed = [deform_scene(scene, psi) for _, _, psi in plan]
    pts = np.concatenate([d.asset.points for d in deformed], axis=0)
    cam = animation_camera(scene, pts, texel_px)
    width, height = cam.width, cam.height
    zoom = zoom or max(1, round(160 / width))
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    tiles, records = [], []
    for (label, x, _), d in zip(plan, deformed, strict=True):  # a loop over the few frames
        ref = render_deformed(d, "gt", cam, ref_spp, seed + 1)
        imgs = [_zoom(to_uint8(ref.image, exposure=exposure), zoom)]
        entry: dict[str, Any] = {
            "label": label, ("time" if warp is None else "amount"): x,
            "object_pixels": int((ref.coverage > 0).sum()) if ref.coverage is not None else 0,
            "reference_seconds": round(ref.seconds, 4), "modes": {}}
        for mode in modes:  # a loop over the few modes
            res = render_deformed(d, mode, cam, spp, seed)
            imgs.append(_zoom(to_uint8(res.image, exposure=exposure), zoom))
            e = _entry(res, ref, None)
            entry["modes"][mode] = {k: e[k] for k in ("seconds", "psnr_db_object", "psnr_db")
                                    if k in e}
        tiles.append(_tile(imgs))
        records.append(entry)
    write_animation(out / "animation.gif", tiles, fps=fps)
    report = {"scene": scene.baked.name, "source": "time" if warp is None else "warp",
              "warp": warp, "width": width, "height": height, "zoom": zoom,
              "texel_px": texel_px, "spp": spp, "ref_spp": ref_spp,
              "fps": fps, "tiles": ["reference", *modes], "frames": records}
    path = out / "animation.json"
    with atomic_path(path) as tmp:
        Path(tmp).write_text(json.dumps(report, indent=1, sort_keys=True) + "\n")
    write_error_plot(out)
    return path


def write_error_plot(anim_dir: str | Path) -> Path:
    """`error_per_frame.png` beside animation.json: PSNR over the object's pixels against the
    reference, one curve per mode, against the time code (asset animation) or the warp's
    amount (sweep)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    d = Path(anim_dir)
    rep = json.loads((d / "animation.json").read_text())
    key = "time" if rep["source"] == "time" else "amount"
    fig, ax = plt.subplots(figsize=(6.4, 4.0), dpi=110)
    markers = {"cpm": "s", "cpm-naive": "o", "normalmap": "^", "srf": "v", "srf-naive": "D"}
    for mode in rep["tiles"][1:]:
        xs, ys = [], []
        for f in rep["frames"]:
            v = f["modes"][mode].get("psnr_db_object")
            if isinstance(v, (int, float)) and math.isfinite(v):
                xs.append(f[key])
                ys.append(v)
        ax.plot(xs, ys, marker=markers.get(mode, "x"), label=mode)
    ax.set_xlabel("time code" if key == "time" else f"amount of {rep['warp']}")
    ax.set_ylabel("PSNR against gt over the object (dB)")
    ax.set_title(f"{rep['scene']} {rep['width']}×{rep['height']}: error per frame "
                 f"(reference gt at {rep['ref_spp']} spp, modes at {rep['spp']})")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    out = d / "error_per_frame.png"
    with atomic_path(out) as tmp:
        fig.savefig(tmp, metadata={"Software": None})
    plt.close(fig)
    return out
