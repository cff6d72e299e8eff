"""Why cpm through L loses to cpm-naive on the bolt (issue 12; docs/deformation.md, "Why cpm
loses on the bolt"): per warp, the reference gt of the deformed M_org twice (two seeds: its own
noise), cpm (through L, the default per-point look-up), cpm-naive, cpm-texel, cpm-vertex (the seed's
look-up) and gt at `--spp`, each with PSNR over
the object, PSNR after a Gaussian blur of 1 and 2 pixels (a highlight one pixel off is then
not counted twice), and the light it shows against the reference's (flux ratio). Options: the
metal's roughness overridden at render time (`--roughness`: gt and cpm both evaluate the true
BRDF, so a wider lobe asks whether L or the lobe's sharpness decides).

    .venv/bin/python benchmarks/deform_diagnose.py BAKED_ROOT --json out.json
        [--warps "bend:angle=90;twist:angle=90"] [--ref-spp 128] [--spp 4] [--size 512]
        [--roughness R] [--jacobian-field vertex|triangle]

BAKED_ROOT: e.g. the bolt baked by benchmarks/deform.py (`--work DIR`). Camera: the `lod` view
of the deformed object, as the benchmark. Numbers of 2026-11-25 (32² atlas, before the
Jacobian field of 2026-11-27: `--jacobian-field triangle`) are in docs/deformation.md.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np
from scipy.ndimage import gaussian_filter

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from texelbake.deform.warps import parse_warp  # noqa: E402
from texelbake.io.atomic import atomic_json  # noqa: E402
from texelbake.render import metrics  # noqa: E402
from texelbake.render.deformed import deform_scene  # noqa: E402
from texelbake.render.frame import render_deformed  # noqa: E402
from texelbake.render.scene import load_scene, lod_camera  # noqa: E402

MODES = (("cpm", "cpm", {}), ("cpm-naive", "cpm-naive", {}),
         ("cpm-texel", "cpm", {"lookup": "texel"}), ("cpm-vertex", "cpm", {"lookup": "vertex"}),
         ("gt", "gt", {}))


def _psnr(img, ref, mask, blur: float = 0.0) -> float:
    a, b = img.astype(np.float64), ref.astype(np.float64)
    if blur:
        a = np.stack([gaussian_filter(a[..., c], blur) for c in range(3)], -1)
        b = np.stack([gaussian_filter(b[..., c], blur) for c in range(3)], -1)
    return round(float(metrics.psnr_db(a[mask], b[mask], b[mask].max())), 2)


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("baked")
    ap.add_argument("--json", type=Path, required=True)
    ap.add_argument("--warps", default="bend:angle=90;twist:angle=90")
    ap.add_argument("--ref-spp", type=int, default=128)
    ap.add_argument("--spp", type=int, default=4)
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--roughness", type=float, default=None)
    ap.add_argument("--jacobian-field", default="vertex",
                    help="render.deformed.JACOBIAN_FIELDS: 'triangle' reproduces the figures "
                         "of 2026-11-25 (before the fix of 2026-11-27)")
    args = ap.parse_args(argv)
    scene = load_scene(args.baked)
    if args.roughness is not None:
        mats = tuple(dataclasses.replace(m, params={**m.params, "roughness": args.roughness})
                     if "roughness" in m.params else m for m in scene.materials)
        scene.materials = mats
        scene.asset = dataclasses.replace(scene.asset, materials=mats)
    cases = {}
    for spec in [w for w in args.warps.split(";") if w]:
        t0 = time.perf_counter()
        d = deform_scene(scene, parse_warp(spec, scene.asset.bounds),
                         jacobian_field=args.jacobian_field)
        cam = lod_camera(d, args.size, args.size)
        ref = render_deformed(d, "gt", cam, args.ref_spp, 1)
        ref2 = render_deformed(d, "gt", cam, args.ref_spp, 2)
        mask = metrics.object_mask(ref.coverage, ref.coverage)
        lum = np.sort(ref.image.sum(-1)[mask])[::-1]
        case = {"object_pixels": int(mask.sum()), "reference_seconds": round(ref.seconds, 2),
                "reference_vs_reference_db": _psnr(ref2.image, ref.image, mask),
                "reference_top2_share": round(float(lum[:2].sum() / lum.sum()), 3),
                "modes": {}}
        for label, mode, kw in MODES:  # a loop over the few modes
            r = render_deformed(d, mode, cam, args.spp, 0, **kw)
            case["modes"][label] = {
                "seconds": round(r.seconds, 3), "psnr_db": _psnr(r.image, ref.image, mask),
                "psnr_db_blur1": _psnr(r.image, ref.image, mask, 1.0),
                "psnr_db_blur2": _psnr(r.image, ref.image, mask, 2.0),
                "flux_ratio": round(float(r.image[mask].sum() / ref.image[mask].sum()), 3)}
        cases[spec] = case
        print(f"{spec} ({time.perf_counter() - t0:.0f} s): object {case['object_pixels']} px, "
              f"reference vs reference {case['reference_vs_reference_db']} dB, its 2 brightest "
              f"pixels hold {case['reference_top2_share']:.0%} of its light", flush=True)
        print(f"  {'mode':<11}{'s':>7}{'PSNR':>8}{'blur1':>8}{'blur2':>8}{'light':>8}")
        for label, e in case["modes"].items():
            print(f"  {label:<11}{e['seconds']:>7.3f}{e['psnr_db']:>8.2f}"
                  f"{e['psnr_db_blur1']:>8.2f}{e['psnr_db_blur2']:>8.2f}{e['flux_ratio']:>8.3f}")
    out = {"settings": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
           "cases": cases}
    args.json.parent.mkdir(parents=True, exist_ok=True)
    atomic_json(args.json, out)  # sorted, indented, written whole or not at all
    return out


if __name__ == "__main__":
    main()
