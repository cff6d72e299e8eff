"""Renders at the sizes the maps serve: every mode with the object at 64, 256 and 512 px.

    .venv/bin/python benchmarks/render.py --object-px 64,256,512 \
        --scenes cylinder,wall,bolt,cloisonne,../shared/assets/Teapot/Teapot.usd \
        --json benchmarks/results/render_sizes.json [--frame 512] [--profile]

Each scene is baked at `texelbake bake`'s defaults (generated scenes at size full; an asset
path is baked as it is), then, for each object size P, seen through its `lod` camera moved
along its axis until the bounding box's diagonal spans P pixels (the measure of
`lod_switch_px`), in a frame of `--frame`² pixels (512² or larger). Every mode (cpm, gt,
equal-time, normalmap, the filtered baselines leadr+ao etc., preview-surface) at 4 eye rays
per pixel against a gt reference at `REF_SPP[P]` (fewer eye rays where the object covers
more pixels: the reference's noise power is 1/4 to 1/16 of gt@4's), PSNR and FLIP over the
object's pixels, the gt sweep and its crossover with cpm@4. `--profile` also profiles gt and
cpm at every size (cProfile, the renderer's own functions by cumulative time). The JSON's
`notes` say where cpm@4 does not beat equal-time or leadr+ao, with the measured reason.
"""

from __future__ import annotations

import cProfile
import io
import pstats
import time
from pathlib import Path

import numpy as np

from schemas.settings import BakeSettings
from texelbake.pipeline.run import bake
from texelbake.render.frame import FILTERED_MODES, MODES, render_frame
from texelbake.render.report import compare_modes
from texelbake.render.scene import load_scene, lod_camera
from texelbake.trace.camera import dolly

#: reference eye rays per pixel by object size (px)
REF_SPP = {64: 64, 256: 32, 512: 16}
SPP = 4


def object_camera(scene, frame: int, px: float):
    """The lod camera moved along its axis until the bounding box diagonal spans px pixels."""
    cam = lod_camera(scene, frame, frame)
    b = np.asarray(scene.asset.bounds, np.float64)
    diag = float(np.linalg.norm(b[1] - b[0]))
    return dolly(cam, b.mean(axis=0), diag / (float(px) * cam.pixel_angle))


def _profile(scene, cam, mode: str, top: int = 12) -> dict:
    prof = cProfile.Profile()
    t0 = time.perf_counter()
    prof.enable()
    render_frame(scene, mode, cam, SPP, 0)
    prof.disable()
    wall = time.perf_counter() - t0
    st = pstats.Stats(prof, stream=io.StringIO())
    rows = []
    for (fname, line, func), (_, _, tt, ct, _) in st.stats.items():  # type: ignore[attr-defined]
        if "texelbake/" in fname or "embree" in fname or "open3d" in fname:
            rows.append({"function": f"{fname.split('texelbake/')[-1]}:{line}:{func}",
                         "cumulative_s": round(ct, 4), "own_s": round(tt, 4)})
    rows.sort(key=lambda r: -r["own_s"])
    return {"mode": mode, "wall_s": round(wall, 4), "top_own": rows[:top]}


def _cull_gain(scene, cam) -> dict:
    """gt@SPP's seconds with the renderer's cull of eye rays that miss the object's box
    (`trace.tracer.culled`, what every mode does) and without it (every eye ray traced and
    shaded, as before it), and whether the images are identical."""
    from texelbake.trace.org import shade_org
    from texelbake.trace.tracer import accumulate

    with_cull = render_frame(scene, "gt", cam, SPP, 0)
    t0 = time.perf_counter()
    img, _, _ = accumulate(cam, SPP, 0, lambda o, d: shade_org(scene, o, d))
    without = time.perf_counter() - t0
    return {"gt_seconds_culled": round(with_cull.seconds, 4),
            "gt_seconds_uncull": round(without, 4),
            "identical": bool(np.array_equal(with_cull.image, img.astype(np.float32))),
            **_draw_gain(scene, cam)}


def _draw_gain(scene, cam) -> dict:
    """gt@SPP and cpm@SPP seconds (the better of 3 frames each) drawing only the traced
    pixels' span of the jitter (`camera.sample_offsets`, what every mode does) and drawing
    the whole frame's as before it, and whether the images are identical."""
    from texelbake.trace import camera as cam_mod

    out: dict = {}
    keep = cam_mod._span_jitter

    def whole(rng, bits, k, n_pixels, pixels):  # the whole frame's draws, then the pixels
        return rng.random((k, n_pixels, 2))[:, pixels]

    for mode in ("gt", "cpm"):
        imgs = []
        for draw, key in ((keep, "skipped"), (whole, "drawn")):
            cam_mod._span_jitter = draw
            try:
                runs = [render_frame(scene, mode, cam, SPP, 0) for _ in range(3)]
            finally:
                cam_mod._span_jitter = keep
            out[f"{mode}_seconds_draws_{key}"] = round(min(r.seconds for r in runs), 4)
            imgs.append(runs[0].image)
        out[f"{mode}_draws_identical"] = bool(np.array_equal(*imgs))
    return out


#: how far equal-time's seconds may be from cpm's for the comparison to count (its frames of
#: a few hundred pixels are dominated by per-call overheads: `trace.tracer.progressive`)
EQUAL_TIME_TOL = 0.05
#: cpm@16 this many dB above cpm@4 says cpm@4's error is mostly noise (4x the eye rays take
#: 6 dB off pure noise and nothing off pure bias; 3 dB is where the two are equal)
NOISE_GAIN_DB = 3.0


def _notes(scene_name: str, px: int, rep: dict) -> list[str]:
    m = rep["modes"]
    cpm = m["cpm"]
    fb = cpm.get("fallback_fraction") or 0.0
    out = []
    eq = rep.get("equal_time") or {}
    if eq and abs(eq["ratio"] - 1.0) > EQUAL_TIME_TOL:  # the comparison's premise
        out.append(f"{scene_name} at {px} px: equal-time took {eq['equal_time_seconds']:.4f} s "
                   f"for cpm's {eq['cpm_seconds']:.4f} s (ratio {eq['ratio']:.2f}, "
                   f"{eq['mean_spp']:g} spp): not equal time, so its comparison with cpm does "
                   f"not hold at this size")
    for other in ("equal-time", "leadr+ao"):
        if other not in m or cpm["psnr_db_object"] > m[other]["psnr_db_object"]:
            continue
        e = m[other]
        if fb > 0.5:
            why = (f"cpm drew {fb:.0%} of its eye rays from M_org (closer than the finest "
                   f"texel of the {rep['atlas']}² maps: they do not serve this size), so it is "
                   f"gt@{SPP} plus the look-ups' cost")
        else:
            c16 = [x for x in rep["sweep"] if x["mode"] == "cpm" and x["spp"] == 16]
            gain = c16[0]["psnr_db_object"] - cpm["psnr_db_object"] if c16 else None
            if gain is not None and gain > NOISE_GAIN_DB and "gt" in m:
                # 4x the eye rays removes noise (+6 dB) but no bias: cpm@4's error is noise,
                # and what loses is its cost per eye ray
                spp = f", {eq['mean_spp']:.0f} eye rays a pixel" if eq and other == "equal-time" \
                    else ""
                why = (f"cpm@{SPP} costs {cpm['seconds'] / m['gt']['seconds']:.1f}x gt@{SPP} "
                       f"(fallback {fb:.0%}){spp}, and its error is mostly noise (cpm@16 "
                       f"{c16[0]['psnr_db_object']:.2f} dB, +{gain:.1f})")
            else:
                why = (f"cpm's error is bias, not noise (fallback {fb:.0%}; cpm@16 "
                       f"{c16[0]['psnr_db_object']:.2f} dB)" if c16
                       else f"cpm's error is bias (fallback {fb:.0%})")
        out.append(f"{scene_name} at {px} px: {other} {e['psnr_db_object']:.2f} dB "
                   f"({e['seconds'] / cpm['seconds']:.2f}x cpm's time) >= cpm@{SPP} "
                   f"{cpm['psnr_db_object']:.2f} dB over {rep['object_pixels']} object "
                   f"pixels — {why}")
    return out


def run(scenes: list[str], sizes: list[int], frame: int, work: Path, profile: bool,
        bake_fn, save=None, overrides: dict | None = None) -> dict:
    """Every scene at every size: the report (JSON-ready) and the printed table; `save(out)`
    after every size (a long run keeps what it measured). `overrides`: the non-default bake
    settings `bake_fn` was given (labelled in the JSON)."""
    out = {"frame": frame, "spp": SPP, "ref_spp": REF_SPP, "sizes": sizes, "scenes": [],
           "notes": [], "bake_settings": "texelbake bake defaults (BakeSettings())"
           if not overrides else f"NON-DEFAULT {overrides}"}
    for name in scenes:  # a loop over scenes
        t0 = time.perf_counter()
        root = bake_fn(name, work)
        bake_s = time.perf_counter() - t0
        scene = load_scene(root)
        label = Path(name).stem if "/" in name else name
        entry = {"scene": label, "atlas": scene.n0, "bake_or_cache_s": round(bake_s, 1),
                 "sizes": []}
        modes = MODES + (tuple(FILTERED_MODES) if scene.baked.filtered else ())
        for px in sizes:  # a loop over object sizes
            cam = object_camera(scene, frame, px)
            ref_spp = REF_SPP.get(px, 64)
            sweep = tuple(s for s in (1, 4, 16, 64) if s <= ref_spp // 4)
            t1 = time.perf_counter()
            rep = compare_modes(scene, cam, spp=SPP, ref_spp=ref_spp, gt_sweep=sweep,
                                cpm_sweep=(16,), modes=modes)
            rep["wall_s"] = round(time.perf_counter() - t1, 1)
            rep["object_px"] = px
            rep["atlas"] = scene.n0
            rep["renderer_cost"] = _cull_gain(scene, cam)
            if profile:
                rep["profile"] = [_profile(scene, cam, m) for m in ("gt", "cpm")]
            notes = _notes(label, px, rep)
            rep["notes"] = notes
            out["notes"] += notes
            entry["sizes"].append(rep)
            _print(label, px, rep)
            if save is not None:
                save({**out, "scenes": out["scenes"] + [entry]})
        out["scenes"].append(entry)
    return out


def _print(label: str, px: int, rep: dict) -> None:
    m = rep["modes"]
    co = rep.get("crossover", {})
    eq = rep.get("equal_time", {})
    print(f"\n{label} at {px} px ({rep['object_pixels']} object px, ref gt@"
          f"{rep['reference']['spp']} {rep['reference']['seconds']:.1f} s, cpm fallback "
          f"{(m['cpm'].get('fallback_fraction') or 0):.0%}, equal-time ratio "
          f"{eq.get('ratio', float('nan')):.3f}, {rep['wall_s']:.0f} s wall)")
    print(f"  {'mode':<16}{'seconds':>9}{'PSNR obj':>10}{'FLIP':>8}")
    for k, e in m.items():
        print(f"  {k:<16}{e['seconds']:>9.3f}{e['psnr_db_object']:>10.2f}{e['flip_mean']:>8.4f}")
    if co.get("gt_spp") is None:
        print(f"  crossover: no gt of the sweep beats cpm@{SPP}")
    else:
        print(f"  crossover: gt@{co['gt_spp']} ({co['gt_psnr_db_object']:.2f} dB, "
              f"{co['seconds_ratio']:.2f}x cpm's time)")
    rc = rep["renderer_cost"]
    print(f"  renderer: gt@{SPP} {rc['gt_seconds_culled']:.3f} s with the cull, "
          f"{rc['gt_seconds_uncull']:.3f} s tracing every eye ray (images identical: "
          f"{rc['identical']})")
    print(f"  jitter drawn for the traced pixels only: gt@{SPP} {rc['gt_seconds_draws_skipped']:.3f}"
          f" s against {rc['gt_seconds_draws_drawn']:.3f} s for the whole frame's, cpm@{SPP} "
          f"{rc['cpm_seconds_draws_skipped']:.3f} against {rc['cpm_seconds_draws_drawn']:.3f} s "
          f"(images identical: {rc['gt_draws_identical'] and rc['cpm_draws_identical']})")
    for p in rep.get("profile", []):
        top = ", ".join(f"{r['function'].rsplit(':', 1)[-1]} {r['own_s']:.2f}"
                        for r in p["top_own"][:4])
        print(f"  profile {p['mode']}: {p['wall_s']:.2f} s; own time: {top}")
    for n in rep["notes"]:
        print(f"  NOTE {n}")


def bake_default(name: str, work: Path, bake_scene, overrides: dict | None = None) -> Path:
    """A generated scene at size full through `bake_scene` (render.py's cache), or an asset
    file baked at the defaults (with `overrides`: those fields changed)."""
    settings = BakeSettings(**(overrides or {}))
    if Path(name).suffix in (".usd", ".usda", ".usdc", ".usdz"):
        out = work / Path(name).stem / f"baked_{settings.digest()[:10]}"
        root = out / f"{Path(name).stem}_baked.usda"
        if root.is_file():
            return root
        return bake(Path(name), out, settings, progress=False, jobs=2)
    return bake_scene(name, work / name, settings, size="full")
