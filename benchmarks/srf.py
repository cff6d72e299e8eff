"""Surface reflectance fields (issue 14; seed 002 §3, §5): deferred, cache-sorted shading
against naive order, and the field's error against gt.

    .venv/bin/python benchmarks/srf.py --json out.json [--scene cylinder] [--cameras 24]
        [--lights 12] [--capture-size 48] [--capture-spp 16] [--size 64]
        [--warp twist:angle=60] [--work DIR] [--sweep]

Captures the scene's M_org (texelbake.testscenes, small) with `gt` from `--cameras` cameras on a
sphere × `--lights` directional lights at `--capture-size`² and `--capture-spp` eye rays per
pixel (raw blocks: one `.npy` per image), unless already captured under `--work`. The impostor is the convex hull of M_org (an
enclosing mesh, as a visual hull carved from every direction), sampled into surfels. Then:

1. *sorted vs naive*: one frame of the warped asset (`--warp`) at `--size`² from a view
   between the capture cameras, lit by three point lights (red, green, blue, as the seed's
   Fig. 13). Its shading operations are executed in sorted and in naive order against a
   cache capped at three blocks (the seed's). Per executor: seconds (sort included),
   block reads, peak bytes (tracemalloc over the execution: the cache plus the operation
   arrays, stated as `overhead_bytes`), and whether the images are bit-identical. The bar:
   ≥ 10× fewer block reads and ≥ 5× less time sorted, with an SRF larger than the cap.
2. *error beside time*: the same frame against the deformed M_org's `gt` (PSNR over the
   object's pixels), through L (`srf`) and without it (`srf-naive`);
3. *capture views*: a capture camera under a capture light against its captured image
   (the acceptance: ≥ 40 dB);
4. with `--sweep`: held-out PSNR against the number of cameras and lights — a second
   capture (`--sweep-cameras` × `--sweep-lights` at 32²) is cut into subsets (every k-th
   camera and light of the spirals, `store.subset`) and each renders the undeformed asset
   from a view and under a directional light that no capture has, against `gt`
   (`srf_sweep.png` beside the JSON).

JSON: {"settings", "store": {"blocks", "block_bytes", "store_bytes", "cap_bytes"},
"sorted": {"seconds", "block_reads", "peak_bytes", "identical", "runs"}, "naive": {...},
"operations", "overhead_bytes", "ratios": {"block_reads", "seconds"}, "errors": {...},
"capture_views": [...], "sweep": [{"cameras", "lights", "psnr_db_object", "seconds"}],
"claims": [{"claim", "holds", "why"}]}.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import time
import tracemalloc
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from scipy.spatial import ConvexHull  # noqa: E402

from texelbake.asset import load_asset  # noqa: E402
from texelbake.deform.normals import deform_normals  # noqa: E402
from texelbake.deform.warps import parse_warp  # noqa: E402
from texelbake.geometry.raycast import RayCaster  # noqa: E402
from texelbake.model import Light  # noqa: E402
from texelbake.render import metrics  # noqa: E402
from texelbake.srf.cache import shade  # noqa: E402
from texelbake.srf.capture import capture, unit_light  # noqa: E402
from texelbake.srf.deferred import VIS_OFFSET, frame_ops, render_srf, splat_surfels  # noqa: E402
from texelbake.srf.store import SrfStore, open_store, subset  # noqa: E402
from texelbake.srf.surfels import surfels_from_mesh  # noqa: E402
from texelbake.testscenes import write_scene  # noqa: E402
from texelbake.trace import camera as cam_mod  # noqa: E402
from texelbake.trace.org import render_model  # noqa: E402


def hull_impostor(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The convex hull as an outward-facing triangle mesh."""
    hull = ConvexHull(points)
    v = points[hull.vertices]
    remap = np.full(len(points), -1)
    remap[hull.vertices] = np.arange(len(hull.vertices))
    f = remap[hull.simplices]
    t = v[f]
    n = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    out = np.einsum("ij,ij->i", n, t.mean(axis=1) - v.mean(axis=0)) < 0
    f[out] = f[out][:, ::-1]
    return v, f


def point_lights(bounds: np.ndarray, power: float) -> list[Light]:
    c = bounds.mean(axis=0)
    r = float(np.linalg.norm(bounds[1] - bounds[0]))
    spots = [(1.0, 0.8, 1.2), (-1.2, 0.6, 0.9), (0.2, -0.9, 1.3)]
    cols = [(1.0, 0.2, 0.2), (0.2, 1.0, 0.2), (0.3, 0.3, 1.0)]
    return [Light(path=f"/Bench/Point{i}", kind="sphere", direction=np.zeros(3),
                  position=c + r * np.asarray(s), radius=0.0,
                  radiance_scale=power * r * r * np.asarray(col))
            for i, (s, col) in enumerate(zip(spots, cols, strict=True))]


def sweep(asset, work: Path, n_cams: int, n_lights: int, json_path: Path, spp: int
          ) -> list[dict]:
    """Held-out PSNR against rig size (module docstring, 4)."""
    big_dir = work / f"sweep_{n_cams}x{n_lights}_32_{spp}"
    big = (open_store(big_dir) if (big_dir / "srf.json").is_file() else
           capture(asset, big_dir, n_cameras=n_cams, n_lights=n_lights, size=32, spp=spp))
    hv, hf = hull_impostor(asset.points)
    surf = surfels_from_mesh(hv, hf)
    bounds = asset.bounds
    cam = cam_mod.auto_frame(bounds, 48, 48, view_from=(0.42, 0.31, 0.85))
    ld = np.array([0.45, 0.75, 0.48])
    light = unit_light(ld / np.linalg.norm(ld), 0)
    ref = render_model(dataclasses.replace(asset, lights=(light,)), cam, 16, seed=1)
    rows = []
    for nc in sorted({max(n_cams // 8, 3), n_cams // 4, n_cams // 2, n_cams}):
        for nl in sorted({max(n_lights // 4, 3), n_lights // 2, n_lights}):
            cams = list(range(0, n_cams, n_cams // nc))[:nc]
            lts = list(range(0, n_lights, n_lights // nl))[:nl]
            sub = subset(big, cams, lts, work / f"sub_{nc}x{nl}_{spp}")
            res = render_srf(sub, surf, cam, [light])
            e = metrics.object_errors(res.image, ref.image,
                                      metrics.object_mask(ref.coverage, res.coverage))
            rows.append({"cameras": len(cams), "lights": len(lts), "seconds": res.seconds,
                         "psnr_db_object": e["psnr_db_object"]})
            print(f"sweep {len(cams)} cameras x {len(lts)} lights: "
                  f"{e['psnr_db_object']:.2f} dB, {res.seconds:.2f} s", flush=True)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 3.5))
    for nl in sorted({r["lights"] for r in rows}):
        pts = [(r["cameras"], r["psnr_db_object"]) for r in rows if r["lights"] == nl]
        ax.plot(*zip(*pts, strict=True), marker="o", label=f"{nl} lights")
    ax.set_xscale("log")
    ax.set_xlabel("capture cameras")
    ax.set_ylabel("PSNR over the object (dB)")
    ax.set_title("held-out view and light against gt")
    ax.legend()
    fig.tight_layout()
    fig.savefig(json_path.with_name("srf_sweep.png"), dpi=100)
    plt.close(fig)
    return rows


def _measured(fn):
    tracemalloc.start()
    tracemalloc.reset_peak()
    base = tracemalloc.get_traced_memory()[0]
    out = fn()
    peak = tracemalloc.get_traced_memory()[1] - base
    tracemalloc.stop()
    return out, int(peak)


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--json", type=Path, required=True)
    ap.add_argument("--scene", default="cylinder")
    ap.add_argument("--cameras", type=int, default=24)
    ap.add_argument("--lights", type=int, default=12)
    ap.add_argument("--capture-size", type=int, default=48)
    ap.add_argument("--capture-spp", type=int, default=16)
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--ref-spp", type=int, default=16)
    ap.add_argument("--warp", default="twist:angle=60")
    ap.add_argument("--work", type=Path, default=Path("bench_out/srf_work"))
    ap.add_argument("--sweep", action="store_true")
    ap.add_argument("--sweep-cameras", type=int, default=48)
    ap.add_argument("--sweep-lights", type=int, default=24)
    args = ap.parse_args(argv)
    args.work.mkdir(parents=True, exist_ok=True)
    args.json.parent.mkdir(parents=True, exist_ok=True)
    src = args.work / f"{args.scene}.usda"
    if not src.is_file():
        write_scene(args.scene, src, size="small")
    asset = load_asset(src)
    key = f"{args.scene}_{args.cameras}x{args.lights}_{args.capture_size}_{args.capture_spp}"
    store_dir = args.work / key
    t0 = time.perf_counter()
    store: SrfStore = (open_store(store_dir) if (store_dir / "srf.json").is_file() else
                       capture(asset, store_dir, n_cameras=args.cameras, n_lights=args.lights,
                               size=args.capture_size, spp=args.capture_spp))
    capture_s = time.perf_counter() - t0
    print(f"capture {store.n_cameras} x {store.n_lights} at {store.width}²: {capture_s:.1f} s "
          f"(0 if reused)", flush=True)
    hv, hf = hull_impostor(asset.points)
    surf = surfels_from_mesh(hv, hf)
    bounds = asset.bounds
    warp = parse_warp(args.warp, bounds)
    lights = point_lights(bounds, 0.6)
    cam = cam_mod.auto_frame(bounds, args.size, args.size, view_from=(0.35, 0.55, 1.0))

    # 1. sorted vs naive on one frame's operations
    g = splat_surfels(surf, cam, warp)
    occ = RayCaster(surf.mesh_vertices, surf.mesh_faces)
    vis = VIS_OFFSET * float(np.median(np.maximum(surf.su, surf.sv)))
    pix, ops, _ = frame_ops(store, g, cam, lights, occ, vis)
    runs = {}
    for ex in ("sorted", "naive"):
        shade(store, ops, pix.size, ex)  # warm (imports, page cache)
        (col, st), peak = _measured(lambda ex=ex: shade(store, ops, pix.size, ex))
        runs[ex] = {"seconds": st.seconds, "block_reads": st.block_reads, "peak_bytes": peak,
                    "runs": st.runs, "peak_cache_bytes": st.peak_resident_bytes, "colours": col}
    identical = bool(np.array_equal(runs["sorted"].pop("colours"), runs["naive"].pop("colours")))
    for r in runs.values():
        r["identical"] = identical
    n_ops = len(ops)
    overhead = int(n_ops * (8 * 5 + 24) + n_ops * 24 * 2 + n_ops * 8 * 2 + pix.size * 24)
    blocks = store.n_cameras * store.n_lights
    store_bytes = int(sum(p.stat().st_size for p in (store.path / "blocks").glob("*.npy")))
    cap = 3 * store.block_nbytes()

    # 2. error beside time against the deformed M_org
    pts = warp.positions(asset.points)
    corner = deform_normals(warp.jacobian(asset.points)[asset.faces.reshape(-1)],
                            asset.corner_normals.reshape(-1, 3)).reshape(
                                asset.corner_normals.shape)
    deformed = dataclasses.replace(asset, points=pts, corner_normals=corner,
                                   lights=tuple(lights))
    ref = render_model(deformed, cam, args.ref_spp, seed=1)
    errors = {}
    for name, use_l in (("srf", True), ("srf-naive", False)):
        res = render_srf(store, surf, cam, lights, warp=warp, use_lookup=use_l)
        mask = metrics.object_mask(ref.coverage, res.coverage)
        e = metrics.object_errors(res.image, ref.image, mask)
        errors[name] = {"seconds": res.seconds, "psnr_db_object": e["psnr_db_object"],
                        "delta_e_mean": e["delta_e_mean"]}
    errors["gt_reference"] = {"seconds": ref.seconds, "spp": args.ref_spp}

    # 3. capture views under capture lights
    views = []
    for c, j in ((0, 0), (store.n_cameras // 2, store.n_lights // 3),
                 (store.n_cameras - 1, store.n_lights - 1)):
        res = render_srf(store, surf, store.cameras[c], [unit_light(store.light_dirs[j], 0)])
        views.append({"camera": c, "light": j,
                      "psnr_db": metrics.psnr_db(res.image, store.image(c, j))})

    rows = (sweep(asset, args.work, args.sweep_cameras, args.sweep_lights, args.json,
                  args.capture_spp)
            if args.sweep else [])

    rr = runs["naive"]["block_reads"] / max(runs["sorted"]["block_reads"], 1)
    tr = runs["naive"]["seconds"] / max(runs["sorted"]["seconds"], 1e-12)
    claims = [
        {"claim": "sorted reads >= 10x fewer blocks than naive", "holds": rr >= 10,
         "why": f"{runs['naive']['block_reads']} / {runs['sorted']['block_reads']} = {rr:.1f}x"},
        {"claim": "sorted takes >= 5x less time than naive", "holds": tr >= 5,
         "why": f"{runs['naive']['seconds']:.3f} s / {runs['sorted']['seconds']:.3f} s = "
                f"{tr:.1f}x"},
        {"claim": "sorted and naive images are bit-identical", "holds": identical, "why": ""},
        {"claim": "the SRF is larger than the three-block cap", "holds": store_bytes > cap,
         "why": f"{store_bytes} B on disk against a {cap} B cap"},
        {"claim": "peak memory within the cap plus the operation arrays",
         "holds": runs["sorted"]["peak_bytes"] <= cap + overhead,
         "why": f"sorted peak {runs['sorted']['peak_bytes']} B <= {cap} + {overhead} B"},
        {"claim": "capture views reproduce their images (>= 40 dB)",
         "holds": all(v["psnr_db"] >= 40 for v in views),
         "why": ", ".join(f"{v['psnr_db']:.1f}" for v in views) + " dB"},
        {"claim": "under the warp, srf through L beats srf without L against gt",
         "holds": errors["srf"]["psnr_db_object"] > errors["srf-naive"]["psnr_db_object"],
         "why": f"{errors['srf']['psnr_db_object']:.2f} vs "
                f"{errors['srf-naive']['psnr_db_object']:.2f} dB"},
    ]
    result = {"settings": {k: str(v) for k, v in vars(args).items()},
              "store": {"blocks": blocks, "block_bytes": store.block_nbytes(),
                        "store_bytes": store_bytes, "cap_bytes": cap,
                        "capture_seconds": capture_s},
              "operations": n_ops, "shading_points": int(pix.size), "overhead_bytes": overhead,
              "sorted": runs["sorted"], "naive": runs["naive"],
              "ratios": {"block_reads": rr, "seconds": tr}, "errors": errors,
              "capture_views": views, "sweep": rows, "claims": claims}
    print(f"\nSRF {store.n_cameras} cameras x {store.n_lights} lights = {blocks} blocks of "
          f"{store.block_nbytes()} B ({store_bytes} B on disk); cache 3 blocks = {cap} B; "
          f"{n_ops} shading operations on {pix.size} pixels ({args.warp}, 3 point lights)")
    print(f"{'executor':<10}{'seconds':>9}{'block reads':>13}{'peak bytes':>12}{'identical':>11}")
    for ex in ("sorted", "naive"):
        r = runs[ex]
        print(f"{ex:<10}{r['seconds']:>9.3f}{r['block_reads']:>13}{r['peak_bytes']:>12}"
              f"{str(r['identical']):>11}")
    print(f"\n{'mode':<12}{'seconds':>9}{'PSNR obj':>10}{'dE mean':>9}   (vs gt of the deformed "
          f"M_org at {args.ref_spp} spp, {ref.seconds:.2f} s)")
    for m in ("srf", "srf-naive"):
        e = errors[m]
        print(f"{m:<12}{e['seconds']:>9.3f}{e['psnr_db_object']:>10.2f}{e['delta_e_mean']:>9.2f}")
    print("capture views (camera, light, PSNR vs captured): " + ", ".join(
        f"({v['camera']}, {v['light']}) {v['psnr_db']:.1f} dB" for v in views))
    print()
    for cl in claims:
        print(f"{'HOLDS' if cl['holds'] else 'DOES NOT HOLD'}: {cl['claim']} — {cl['why']}")
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(_finite(result), indent=2, sort_keys=True) + "\n")
    return result


def _finite(obj):
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_finite(v) for v in obj]
    if isinstance(obj, float) and not math.isfinite(obj):
        return str(obj)
    if isinstance(obj, np.generic):
        return obj.item()
    return obj


if __name__ == "__main__":
    main()
