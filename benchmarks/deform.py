"""Appearance under deformation: speed against error of the deformed frame's modes (issue 12
acceptance; seed 002 §4).

    .venv/bin/python benchmarks/deform.py --json out.json
        [--scenes cylinder,bolt,arm] [--scene-size small|full] [--atlas 32] [--size 512]
        [--ref-spp 1024] [--ref-parts 2] [--spp 16] [--seeds 6] [--warp SPEC ...]
        [--btf] [--work DIR]
    .venv/bin/python benchmarks/deform.py --json all.json --merge a.json b.json ...

The `arm` (texelbake.testscenes.arm) is deformed by its own UsdSkel animation at time codes 12
and 24 (bent 45° and 90°) instead of the procedural warps.

Bakes each scene (texelbake.testscenes at `--scene-size`, `--atlas` finest texels per side, the
other settings at their defaults) unless already baked under `--work`, then per warp
(default: bend 90°, twist 90° and the 1:2 anisotropic stretch across the axis, plus a rigid
motion) renders the reference `gt` of the deformed M_org at `--ref-spp` eye rays per pixel —
the mean of `--ref-parts` independent renders, whose mutual PSNR is the reference's own noise
(`reference.noise_psnr_db`: its estimated PSNR against the converged image) — and each mode
at `--spp` with `--seeds` seeds: `cpm` (through the look-up rotation L, Eq. 10, at the
renderer's default look-up: each characteristic point's BRDF directions through its own L,
its shading frame and Ψ's Jacobian at the point, the seed's limit where the impostor is the
surface), `cpm-naive` (no L) and `normalmap` (tangent frame carried by the deformed M1), and
`gt` at `--spp` for scale; `cpm-vertex` is the seed's construction (L of a texel from the
Table 1 parameterization of M1's vertices, interpolated; `cpm` until 2026-11-27),
`cpm-texel` L from each texel's own frame and J at its centroid (`render.deformed.LOOKUPS`),
`cpm-affine` the default's per-point BRDF directions with the texel's view term, projected
areas and a_vis read along J⁻¹ v* instead of L v* (exact for a locally affine Ψ),
`cpm-tri` cpm with the Jacobians of M_org's triangles' constant affine maps
(`deform_scene(jacobian_field="triangle")`, the default before 2026-11-27) instead of Ψ's
vertex Jacobians interpolated; with `--btf` (bakes with `settings.btf`) also `btf`, seed 001's
maps on the deformed M1 through the seed's L at each hit, and `btf-naive` without it. Each
mode is rendered once to warm it, then
once per seed; its `seconds` is the median over the seeds, `psnr_db` the mean and
`psnr_db_spread` the sample standard deviation of the per-seed PSNR over the object's pixels
(`metrics.object_errors`). Why 16 spp and 6 seeds, not the renderer's 4 spp: at the lod
view the object covers ~100-250 pixels, many of them outline pixels, and at 4 spp their
sampling noise decided the rankings (gt itself at 4 spp scored 18-34 dB against its
1024-spp reference; measured on the arm bent 45°: cpm 25.9 ± 1.2 / 33.3 ± 2.2 / 35.2 ± 0.5
dB at 4 / 16 / 64 spp, the normal map 26.4 ± 1.9 / 31.3 ± 0.9 / 32.4 ± 0.2); 16 spp keeps
cpm well over 20x faster than the reference, 64 did not (12x). Camera: the `lod` view of the *deformed* object (the asset's
camera moved back along its axis until a finest texel spans ~0.7 pixel).

Rigid case: the asset rigidly moved with its camera and lights (the same relative view), so
its errors must be the undeformed frame's (the bar: within 0.5 dB). The undeformed frame
("warp": "none") goes through the same renderer with Ψ = identity (tests/
test_render_deformed.py checks a rigidly moved frame against `render.frame` itself).

The bar (issue 12): cpm through L beats cpm-naive and normalmap on every case, is ≥ 20× faster
than the reference, and on rigid motion matches the undeformed error within 0.5 dB. "Beats"
is a paired t-test over the seeds at 5 % (`verdict`: the modes share each seed's sub-pixel
positions); otherwise the case is printed as "tie within noise" (or "loses"), with the
figures, the reference's noise, and where the reference's light sits in two pixels. `pairs`
gives every comparison under the paired rule and under the stricter rule of the first
measurements (the mean difference above the sum of the two spreads). Every claim is printed as holding or not,
with the cases where it fails; the look-up variants against `cpm` follow (not the bar).

Measured: docs/deformation.md "Measured" (benchmarks/results/deform_512.json).

JSON: {"settings", "complete", "cases": [{"scene", "scene_size", "warp", "object_pixels", "m1"
{"triangles", "hausdorff_rel"} (M1 against M_org, from the bake's report: on the generated
scenes M1 is M_org within 1e-5 of the diagonal, so the normal map is traced on the original
geometry, and a claim against it says so), "reference":
{"seconds", "spp", "parts", "half_vs_half_db", "noise_psnr_db", "top2_share"}, "modes":
{mode: {"seconds", "psnr_db", "psnr_db_spread", "psnr_db_seeds", "seeds", "spp",
"object_pixels", "flux_ratio", "fallback_fraction"?}}}], "claims": [{"claim", "holds",
"why"}], "pairs": [{"scene", "warp", "mode", "against", "verdict", "difference_db",
"margin_db", "verdict_spread", "spread_db"}], "lookup_comparisons": [{"scene", "warp", "mode", "against", "verdict",
"difference_db", "spread_db"}]}.
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import hashlib
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from schemas.settings import BakeSettings  # noqa: E402
from texelbake.deform.warps import AffineWarp, parse_warp  # noqa: E402
from texelbake.pipeline.run import bake  # noqa: E402
from texelbake.render import metrics  # noqa: E402
from texelbake.render.deformed import deform_scene  # noqa: E402
from texelbake.render.deformed_report import warp_at_time  # noqa: E402
from texelbake.render.frame import render_deformed  # noqa: E402
from texelbake.render.scene import load_scene, lod_camera  # noqa: E402
from texelbake.testscenes import write_scene  # noqa: E402
from texelbake.trace.camera import PinholeCamera  # noqa: E402

#: the stretch is 1:2 across the axis (y): along it, a cylinder's surface frames do not turn,
#: L = I on every texel and cpm and cpm-naive render identical images (measured 2026-11-27:
#: the same PSNR on every seed), a case that cannot tell look-ups apart
WARPS = ("bend:angle=90", "twist:angle=90", "stretch:x=2,y=1,z=1")
RIGID = "rigid:angle=40,axis=x,tx=0.5,ty=-0.3,tz=0.2"
#: the arm's own animation (texelbake.testscenes.arm): bent 45° at time 12, 90° at 24
ARM_TIMES = ("time:12", "time:24")
MODES = ("cpm", "cpm-affine", "cpm-vertex", "cpm-texel", "cpm-tri", "cpm-naive", "normalmap",
         "gt")
#: with --btf (bakes with settings.btf): seed 001's maps through the seed's L and without it
BTF_MODES = ("btf", "btf-naive")
#: the look-up variants: mode -> `render_deformed`'s lookup
VARIANTS = {"cpm-affine": "affine", "cpm-texel": "texel", "cpm-vertex": "vertex"}


def bake_scene(scene: str, work: Path, atlas: int, size: str, btf: bool = False) -> Path:
    settings = BakeSettings(atlas_resolution=atlas, btf=btf)
    if scene == "arm":  # the skinned cylinder: its own animation, not a procedural warp
        from texelbake.testscenes.arm import write_arm

        src = write_arm(work / "src" / f"arm_{size}.usda", size)
    else:
        src = write_scene(scene, work / "src" / f"{scene}_{size}.usda", size)
    key = hashlib.sha256(settings.model_dump_json().encode()).hexdigest()[:10]
    out = work / f"baked_{scene}_{size}_{key}"
    root = out / f"{scene}_{size}_baked.usda"
    if root.is_file():
        return root
    t0 = time.perf_counter()
    root = bake(src, out, settings, progress=False, jobs=2)
    print(f"baked {scene} ({size}, atlas {atlas}) in {time.perf_counter() - t0:.0f} s",
          flush=True)
    return root


def _errors(res, ref) -> dict:
    mask = metrics.object_mask(ref.coverage, res.coverage)
    e = metrics.object_errors(res.image, ref.image, mask)
    flux = float(ref.image[mask].sum())
    return {"psnr_db": round(float(e["psnr_db_object"]), 3), "object_pixels": e["object_pixels"],
            # the mode's light over the object against the reference's (1: the same total)
            "flux_ratio": round(float(res.image[mask].sum()) / flux, 3) if flux > 0 else None}


def _top2_share(ref) -> float:
    """The share of the reference's light (over the object) in its two brightest pixels: near
    1, the frame's error is decided by where a sub-pixel highlight lands."""
    lum = ref.image.sum(axis=2)[ref.coverage > 0]
    if lum.size == 0 or lum.sum() <= 0:
        return 0.0
    return round(float(np.sort(lum)[-2:].sum() / lum.sum()), 3)


def _stats(xs: list[float]) -> tuple[float, float]:
    """(mean, spread) of per-seed figures; spread: the sample standard deviation (0 for
    one seed)."""
    a = np.asarray(xs, dtype=np.float64)
    return float(a.mean()), float(a.std(ddof=1)) if a.size > 1 else 0.0


def _reference(d, cam, ref_spp: int, ref_parts: int, render_fn):
    """The reference gt as the mean of `ref_parts` independent renders (seeds 1000, 1001, …)
    of ref_spp / ref_parts eye rays each — a ref_spp-ray estimate — and its own noise: the
    parts' mutual PSNR over the object, and from it the reference's estimated PSNR against the
    converged image (two parts: the difference of the halves has √2 σ_half, their mean
    σ_half / √2, i.e. half its RMSE: +6.02 dB)."""
    parts, seconds = [], 0.0
    per = max(1, ref_spp // ref_parts)
    for k in range(ref_parts):  # a loop over the few parts
        r = render_fn(d, "gt", cam, per, 1000 + k)
        parts.append(r)
        seconds += r.seconds
    img = np.mean([r.image.astype(np.float64) for r in parts], axis=0)
    cov = np.mean([r.coverage for r in parts], axis=0)
    ref = dataclasses.replace(parts[0], image=img, coverage=cov, seconds=seconds,
                              spp=per * ref_parts)
    info = {"seconds": round(seconds, 3), "spp": per * ref_parts, "parts": ref_parts}
    if ref_parts == 2:
        mask = metrics.object_mask(cov)
        peak = float(img[mask].max())
        if peak > 0:
            hh = float(metrics.psnr_db(parts[0].image[mask], parts[1].image[mask], peak))
            info["half_vs_half_db"] = round(hh, 2)
            info["noise_psnr_db"] = round(hh + 20.0 * math.log10(2.0), 2)
    return ref, info


def _case(scene_name: str, d, cam, spp: int, ref_spp: int, render_fn, seeds: int = 3,
          ref_parts: int = 2, d_tri=None, modes: tuple[str, ...] = MODES) -> dict:
    """One frame: the reference, then every mode at `seeds` seeds. d_tri: the same frame
    deformed with `jacobian_field="triangle"` (the ``cpm-tri`` mode; its reference is d's: gt
    does not read the field)."""
    ref, ref_info = _reference(d, cam, ref_spp, ref_parts, render_fn)
    out = {}
    for mode in modes:  # a loop over the few modes
        kw = {"lookup": VARIANTS[mode]} if mode in VARIANTS else {}
        scene = d_tri if mode == "cpm-tri" else d
        if scene is None:
            continue

        def run(seed: int, m=mode, kw=kw, scene=scene):
            return render_fn(scene, "cpm" if m in VARIANTS or m == "cpm-tri" else m, cam, spp,
                             seed, **kw)

        run(0)  # warm (the per-frame caches: L, the deformed points)
        runs = [run(s) for s in range(seeds)]  # a loop over the few seeds
        errs = [_errors(r, ref) for r in runs]
        mean, spread = _stats([e["psnr_db"] for e in errs])
        entry = {"seconds": round(float(np.median([r.seconds for r in runs])), 4), "spp": spp,
                 "seeds": seeds, "psnr_db": round(mean, 3), "psnr_db_spread": round(spread, 3),
                 "psnr_db_seeds": [e["psnr_db"] for e in errs],
                 "object_pixels": int(np.median([e["object_pixels"] for e in errs])),
                 "flux_ratio": (round(float(np.mean([e["flux_ratio"] for e in errs])), 3)
                                if all(e["flux_ratio"] is not None for e in errs) else None)}
        if "fallback_fraction" in runs[0].extras:
            entry["fallback_fraction"] = round(float(np.mean(
                [r.extras["fallback_fraction"] for r in runs])), 4)
        out[mode] = entry
    return {"scene": scene_name, "object_pixels": int((ref.coverage > 0).sum()),
            "reference": {**ref_info, "top2_share": _top2_share(ref)}, "modes": out}


def _moved_with(scene, warp):
    """The undeformed scene's lights moved by the rigid warp (p -> A p + b)."""
    a, b = warp.matrix, warp.offset
    s = copy.copy(scene)
    s.lights = tuple(dataclasses.replace(li, direction=a @ li.direction,
                                         position=a @ li.position + b)
                     for li in scene.lights)
    return s


def verdict(a: dict, b: dict) -> tuple[str, float, float]:
    """Whether mode entry `a` beats `b` on one case: ("beats" | "loses" | "tie within noise",
    the mean of the per-seed differences of their PSNR, the margin it must exceed).

    Paired over the seeds: every mode renders seed s with the same sub-pixel positions
    (`camera.sample_offsets` depends on the seed only: common random numbers), so the per-seed
    difference cancels the noise the two images share (where a sub-pixel highlight or an
    outline pixel happens to be sampled) and its own scatter is the noise of the comparison.
    The margin is the one-sided 95 % Student t quantile (n − 1 degrees of freedom) times the
    difference's standard error: "beats" is a paired t-test at 5 %. Identical images (a zero
    difference on every seed) tie. One seed has no scatter to judge by: the margin is then
    the sum of the two modes' spreads (`verdict_spread`)."""
    da, db = a.get("psnr_db_seeds"), b.get("psnr_db_seeds")
    if not da or not db or len(da) != len(db) or len(da) < 2:
        return verdict_spread(a, b)
    from scipy.stats import t as student_t

    diff = np.asarray(da, dtype=np.float64) - np.asarray(db, dtype=np.float64)
    n = diff.size
    dlt = float(diff.mean())
    margin = float(student_t.ppf(0.95, n - 1) * diff.std(ddof=1) / math.sqrt(n))
    return ("beats" if dlt > margin and dlt > 0 else "loses" if dlt < -margin and dlt < 0
            else "tie within noise", dlt, margin)


def verdict_spread(a: dict, b: dict) -> tuple[str, float, float]:
    """The conservative rule of the first measurements (2026-11-25..27), printed beside the
    paired one: the mean difference must exceed the sum of the two modes' per-seed standard
    deviations, a bound that assumes nothing about how the seeds' errors correlate."""
    dlt = a["psnr_db"] - b["psnr_db"]
    spread = a.get("psnr_db_spread", 0.0) + b.get("psnr_db_spread", 0.0)
    return ("beats" if dlt > spread else "loses" if dlt < -spread else "tie within noise",
            dlt, spread)


#: M1 closer to M_org than this (Hausdorff over the bounding-box diagonal) is the original
#: geometry for the normal-map baseline: nothing fine is left for the normal map to carry
M1_IS_ORG = 1e-3


def _m1(baked: Path) -> dict | None:
    """M1's triangles and Hausdorff distance to M_org over the diagonal, from the bake's report."""
    rep = baked.parent / "report.json"
    if not rep.is_file():
        return None
    lv = json.loads(rep.read_text())["lods"]["levels"][0]
    return {"triangles": int(lv["triangles"]), "hausdorff_rel": float(lv["hausdorff_rel"])}


def _claims(cases: list[dict]) -> list[dict]:
    deformed = [c for c in cases if c["warp"] not in ("none", RIGID)]
    out = []

    def claim(text: str, bad: list[str]) -> None:
        out.append({"claim": text, "holds": not bad,
                    "why": "; ".join(bad) if bad else "on every case"})

    def name(c: dict) -> str:
        return f"{_label(c)} {c['warp']}"

    def why(c: dict, other: str) -> str:
        """A case where cpm does not beat `other`: the verdict, the figures, and what the
        measurement says about it (a frame whose light sits in two pixels; gt itself at the
        modes' spp; the reference's own noise)."""
        m, share = c["modes"], c["reference"].get("top2_share", 0.0)
        v, dlt, spread = verdict(m["cpm"], m[other])
        text = (f"{name(c)}: {v} (cpm {m['cpm']['psnr_db']:.2f} ± "
                f"{m['cpm'].get('psnr_db_spread', 0):.2f}, {other} {m[other]['psnr_db']:.2f} ± "
                f"{m[other].get('psnr_db_spread', 0):.2f} dB: paired difference {dlt:+.2f}, "
                f"margin {spread:.2f}")
        noise = c["reference"].get("noise_psnr_db")
        if noise is not None:
            text += f"; reference noise {noise:.1f} dB"
        text += ")"
        if m["cpm"].get("psnr_db_seeds") == m[other].get("psnr_db_seeds"):
            text += (" [identical images: L = I on every texel the frame shows (a warp that "
                     "does not turn the surface's frames), so no look-up can differ]")
        m1 = c.get("m1")
        rest = [r for r in cases if _label(r) == _label(c) and r["warp"] == "none"]
        if other == "normalmap" and m1 and m1["hausdorff_rel"] < M1_IS_ORG and rest:
            rm = rest[0]["modes"]
            text += (f" [M1 is M_org within {m1['hausdorff_rel']:.1e} of the diagonal "
                     f"({m1['triangles']} triangles): the normal map is traced on the original "
                     f"geometry; undeformed it scores {rm['normalmap']['psnr_db']:.2f} dB, gt at "
                     f"the same spp {rm['gt']['psnr_db']:.2f}, cpm {rm['cpm']['psnr_db']:.2f}]")
        if share >= 0.5:
            text += (f" [the reference's 2 brightest pixels hold {share:.0%} of its light (a "
                     f"sub-pixel highlight); light shown: cpm {m['cpm'].get('flux_ratio')}x, "
                     f"{other} {m[other].get('flux_ratio')}x, gt at {m['gt']['spp']} spp "
                     f"{m['gt'].get('flux_ratio')}x scoring {m['gt']['psnr_db']:.2f} dB]")
        return text

    for other in ("cpm-naive", "normalmap"):
        claim(f"cpm beats {other} (PSNR over the object, paired over the seeds: t-test at 5 %)",
              [why(c, other) for c in deformed
               if verdict(c["modes"]["cpm"], c["modes"][other])[0] != "beats"])
    claim("cpm is >= 20x faster than the reference",
          [f"{name(c)}: {c['reference']['seconds'] / c['modes']['cpm']['seconds']:.1f}x"
           for c in deformed
           if c["reference"]["seconds"] < 20.0 * c["modes"]["cpm"]["seconds"]])
    bad = []
    for scene in sorted({_label(c) for c in cases}):  # a scene at each of its sizes
        rest = [c for c in cases if _label(c) == scene and c["warp"] == "none"]
        rig = [c for c in cases if _label(c) == scene and c["warp"] == RIGID]
        if rest and rig:
            dlt = rig[0]["modes"]["cpm"]["psnr_db"] - rest[0]["modes"]["cpm"]["psnr_db"]
            if not abs(dlt) <= 0.5:
                bad.append(f"{scene}: rigid - undeformed = {dlt:+.2f} dB")
    claim("on rigid motion cpm matches the undeformed error within 0.5 dB", bad)
    fb = [f"{name(c)}: {c['modes']['cpm'].get('fallback_fraction', 0):.0%} of cpm's eye rays "
          f"fell back to M_org" for c in cases
          if c["modes"]["cpm"].get("fallback_fraction", 0) > 0.5]
    claim("cpm's images come from the maps (fallback to M_org below 50 %)", fb)
    with_btf = [c for c in deformed if "btf" in c["modes"] and "btf-naive" in c["modes"]]
    if with_btf:  # --btf: does L help seed 001's maps too? (not the issue's bar)
        notes = []
        for c in with_btf:
            v, dlt, spread = verdict(c["modes"]["btf"], c["modes"]["btf-naive"])
            if v != "beats":
                notes.append(f"{name(c)}: {v} (btf {c['modes']['btf']['psnr_db']:.2f}, "
                             f"btf-naive {c['modes']['btf-naive']['psnr_db']:.2f} dB: paired "
                             f"difference {dlt:+.2f}, margin {spread:.2f})")
        claim("btf through L beats btf-naive (paired over the seeds: t-test at 5 %)", notes)
    return out


def _pairs(cases: list[dict]) -> list[dict]:
    """The bar's comparisons on every deformed case under both rules: the paired t-test that
    decides the claims (`verdict`) and the conservative sum-of-spreads rule beside it
    (`verdict_spread`)."""
    out = []
    for c in cases:
        if c["warp"] in ("none", RIGID):
            continue
        for other in ("cpm-naive", "normalmap"):
            v, dlt, margin = verdict(c["modes"]["cpm"], c["modes"][other])
            vs, dlt_s, spread = verdict_spread(c["modes"]["cpm"], c["modes"][other])
            out.append({"scene": c["scene"], "warp": c["warp"], "mode": "cpm", "against": other,
                        "verdict": v, "difference_db": round(dlt, 3),
                        "margin_db": round(margin, 3), "verdict_spread": vs,
                        "spread_db": round(spread, 3)})
    return out


def _lookup_comparisons(cases: list[dict]) -> list[dict]:
    """Not part of the bar: the look-up variants against the paper's (`cpm`, L from M1's
    vertices) on every deformed case, with the same noise rule."""
    out = []
    for c in cases:
        if c["warp"] in ("none", RIGID):
            continue
        for alt in ("cpm-affine", "cpm-vertex", "cpm-texel", "cpm-tri"):
            if alt in c["modes"]:
                v, dlt, spread = verdict(c["modes"][alt], c["modes"]["cpm"])
                out.append({"scene": c["scene"], "warp": c["warp"], "mode": alt,
                            "against": "cpm", "verdict": v, "difference_db": round(dlt, 3),
                            "spread_db": round(spread, 3)})
    return out


def _label(c: dict) -> str:
    """The scene's name, with its size when it is not the generated scenes' small one."""
    size = c.get("scene_size", "small")
    return c["scene"] if size == "small" else f"{c['scene']} ({size})"


def _report(result: dict) -> None:
    cases = result["cases"]
    shown = MODES + tuple(m for m in BTF_MODES if any(m in c["modes"] for c in cases))
    print(f"\n{'scene':<10}{'warp':<44}{'obj px':>7}{'ref s':>8}{'ref nz':>7}"
          + "".join(f"{m + ' s':>13}{m + ' dB':>18}" for m in shown))
    for c in cases:
        row = (f"{_label(c):<10}{c['warp']:<44}{c['object_pixels']:>7}"
               f"{c['reference']['seconds']:>8.1f}"
               f"{c['reference'].get('noise_psnr_db') or float('nan'):>7.1f}")
        for m in shown:
            e = c["modes"].get(m)
            if e is None:
                row += f"{'—':>13}{'—':>18}"
                continue
            row += (f"{e['seconds']:>13.3f}"
                    f"{e['psnr_db']:>12.2f}±{e.get('psnr_db_spread', 0.0):<5.2f}")
        print(row)
    print()
    for cl in result["claims"]:
        print(f"{'HOLDS' if cl['holds'] else 'DOES NOT HOLD'}: {cl['claim']} — {cl['why']}")
    for pr in result.get("pairs", []):
        print(f"  {pr['scene']} {pr['warp']}: cpm {pr['verdict']} {pr['against']} "
              f"({pr['difference_db']:+.2f} dB paired, margin {pr['margin_db']:.2f}; by the "
              f"sum of spreads {pr['spread_db']:.2f}: {pr['verdict_spread']})")
    for cmp_ in result.get("lookup_comparisons", []):
        print(f"  {cmp_['scene']} {cmp_['warp']}: {cmp_['mode']} {cmp_['verdict']} cpm "
              f"({cmp_['difference_db']:+.2f} dB, spread {cmp_['spread_db']:.2f})")


def _write(path: Path, result: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(_finite(result), indent=2, sort_keys=True))
    tmp.replace(path)


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--json", type=Path, required=True)
    ap.add_argument("--scenes", default="cylinder,bolt")
    ap.add_argument("--scene-size", choices=("small", "full"), default="small")
    ap.add_argument("--atlas", type=int, default=32)
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--ref-spp", type=int, default=1024)
    ap.add_argument("--ref-parts", type=int, default=2,
                    help="the reference as the mean of this many independent renders (2: "
                         "their mutual PSNR measures the reference's own noise)")
    ap.add_argument("--spp", type=int, default=16,
                    help="eye rays per pixel of every mode (module docstring: why 16)")
    ap.add_argument("--seeds", type=int, default=6, help="renders per mode (seeds 0..n-1)")
    ap.add_argument("--warp", action="append", default=None,
                    help=f"a warp spec (repeatable; default: {' '.join(WARPS)})")
    ap.add_argument("--btf", action="store_true",
                    help="bake with settings.btf and render btf (through L) and btf-naive too")
    ap.add_argument("--work", type=Path, default=Path("bench_out/deform"))
    ap.add_argument("--merge", type=Path, nargs="+", default=None,
                    help="render nothing: join the cases of these JSON files (runs of one "
                         "setting, e.g. one scene each), recompute the claims, write --json")
    args = ap.parse_args(argv)
    if args.merge:
        parts = [json.loads(f.read_text()) for f in args.merge]
        result = {"settings": {**parts[0]["settings"],
                               "scenes": ",".join(p["settings"]["scenes"] for p in parts),
                               "scene_size": ",".join(sorted({
                                   p["settings"].get("scene_size", "small") for p in parts})),
                               "merged_from": [f.name for f in args.merge]},
                  "cases": [{"scene_size": p["settings"].get("scene_size", "small"), **c}
                            for p in parts for c in p["cases"]]}
        result.update(claims=_claims(result["cases"]), pairs=_pairs(result["cases"]),
                      lookup_comparisons=_lookup_comparisons(result["cases"]), complete=all(
                          p.get("complete", True) for p in parts))
        _report(result)
        _write(args.json, result)
        return result
    warps = args.warp or list(WARPS)
    settings = {"scenes": args.scenes, "scene_size": args.scene_size, "atlas": args.atlas,
                "size": args.size, "ref_spp": args.ref_spp, "ref_parts": args.ref_parts,
                "spp": args.spp, "seeds": args.seeds, "btf": args.btf,
                "camera": "lod view of the deformed object",
                "psnr": "mean over the seeds, spread the seeds' sample standard deviation; "
                        "'beats': a paired t-test over the seeds at 5 % (the modes share each "
                        "seed's sub-pixel positions); 'pairs' also give the conservative "
                        "rule (difference above the sum of the two spreads)"}
    cases: list[dict] = []

    m1: dict | None = None

    def done(case: dict) -> None:  # the JSON after every case: a cut-short run keeps its cases
        case["m1"] = m1
        case["scene_size"] = args.scene_size
        cases.append(case)
        print(f"{case['scene']} {case['warp']}: done", flush=True)
        _write(args.json, {"settings": settings, "cases": cases, "complete": False,
                           "claims": _claims(cases)})

    kw = {"seeds": args.seeds, "ref_parts": args.ref_parts,
          "modes": MODES + (BTF_MODES if args.btf else ())}
    for scene_name in [s.strip() for s in args.scenes.split(",") if s.strip()]:
        baked = bake_scene(scene_name, args.work, args.atlas, args.scene_size, args.btf)
        scene = load_scene(baked)
        m1 = _m1(baked)
        # the undeformed frame, and the rigid motion seen with the camera and lights moving
        # along (the same relative view)
        cam0 = lod_camera(scene, args.size, args.size)
        # (through the deformed renderer with Ψ = identity, where cpm-naive is cpm)
        ident = AffineWarp(np.eye(3), np.zeros(3))
        rest = _case(scene_name, deform_scene(scene, ident), cam0, args.spp, args.ref_spp,
                     render_deformed, **kw,
                     d_tri=deform_scene(scene, ident, jacobian_field="triangle"))
        done({**rest, "warp": "none"})
        rig = parse_warp(RIGID, scene.asset.bounds)
        d = deform_scene(_moved_with(scene, rig), rig)
        cam_r = PinholeCamera(rig.matrix @ cam0.position + rig.offset,
                              rig.matrix @ cam0.rotation, cam0.tan_half_x, cam0.width,
                              cam0.height)
        done({**_case(scene_name, d, cam_r, args.spp, args.ref_spp, render_deformed, **kw,
                      d_tri=deform_scene(_moved_with(scene, rig), rig,
                                         jacobian_field="triangle")), "warp": RIGID})
        specs = ARM_TIMES if scene_name == "arm" else warps
        for spec in specs:
            psi = (warp_at_time(scene.asset, float(spec.split(":")[1]))
                   if spec.startswith("time:") else parse_warp(spec, scene.asset.bounds))
            d = deform_scene(scene, psi)
            cam = lod_camera(d, args.size, args.size)
            done({**_case(scene_name, d, cam, args.spp, args.ref_spp, render_deformed, **kw,
                          d_tri=deform_scene(scene, psi, jacobian_field="triangle")),
                  "warp": spec})
    result = {"settings": settings, "cases": cases, "complete": True,
              "claims": _claims(cases), "pairs": _pairs(cases),
              "lookup_comparisons": _lookup_comparisons(cases)}
    _report(result)
    _write(args.json, result)
    return result


def _finite(obj):
    """NaN / inf -> None (JSON has no NaN)."""
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_finite(v) for v in obj]
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


if __name__ == "__main__":
    main()
