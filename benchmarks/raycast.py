"""Occlusion-query throughput of `texelbake.geometry.RayCaster` (issue 2 acceptance).

Rays are the ones the CPM stage casts: origins on dense surface samples of the mesh (offset
along the normal by TOL.ray_offset x bbox diagonal), directions uniform over the hemisphere
of the sample's normal. For batch sizes 1e4, 1e5 and 1e6 the benchmark times
`RayCaster.occluded` (median of repeats) and reports rays per second; against it, a naive
loop issues 100 of the same rays one call each through open3d (`test_occlusions` on a
(1, 6) tensor) and through the wrapper (`occluded` on (1, 3) arrays), extrapolated to the
same count. The ratio is the figure. Accuracy beside speed: the batched answers must equal
the per-ray answers and must not depend on the batch size (reported as agreement).

    python benchmarks/raycast.py --json out.json            # the full-size bolt
    python benchmarks/raycast.py --mesh bumpy --json out.json

JSON: {"rays_per_second": {"10000": ..., "100000": ..., "1000000": ...},
       "speedup_vs_loop": ..., ...extra context fields}
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import open3d as o3d

from texelbake.geometry.raycast import RayCaster, offset_origins
from texelbake.geometry.sampling import sample_surface

BATCH_SIZES = (10_000, 100_000, 1_000_000)
LOOP_RAYS = 100
LOOP_REPEATS = 5


def load_bolt(size: str) -> tuple[np.ndarray, np.ndarray, str]:
    """The bolt test scene at `size`, through the real USD writer and ingest."""
    from texelbake.asset import load_asset
    from texelbake.testscenes import write_scene

    with tempfile.TemporaryDirectory() as tmp:
        path = write_scene("bolt", Path(tmp) / "bolt.usda", size)
        asset = load_asset(path)
        return asset.points, asset.faces, f"bolt ({size}, {path.name})"


def bumpy_mesh(subdivisions: int = 5) -> tuple[np.ndarray, np.ndarray, str]:
    """Icosphere with radial bumps (20 * 4**subdivisions triangles)."""
    mesh = o3d.geometry.TriangleMesh.create_icosahedron(1.0).subdivide_midpoint(subdivisions)
    v = np.asarray(mesh.vertices, dtype=np.float64)
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    r = 1.0 + 0.08 * np.sin(9 * v[:, 0]) * np.sin(9 * v[:, 1]) * np.sin(9 * v[:, 2])
    faces = np.asarray(mesh.triangles, dtype=np.int64)
    return v * r[:, None], faces, f"bumpy icosphere (subdiv {subdivisions})"


def hemisphere_rays(
    points: np.ndarray, faces: np.ndarray, n: int, seed: int
) -> tuple[np.ndarray, np.ndarray]:
    """n rays from surface samples into the hemisphere of their normal (uniform)."""
    s = sample_surface(points, faces, n, seed=seed)
    rng = np.random.default_rng(seed + 1)
    idx = rng.permutation(len(s))[:n]  # sample_surface may return a few more than n
    nrm = s.normals[idx]
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    d *= np.sign(np.einsum("nd,nd->n", d, nrm))[:, None]
    diag = float(np.linalg.norm(points.max(axis=0) - points.min(axis=0)))
    return offset_origins(s.positions[idx], nrm, bbox_diag=diag), d


def time_batched(
    caster: RayCaster, o: np.ndarray, d: np.ndarray, min_seconds: float, min_reps: int
) -> tuple[float, np.ndarray]:
    """Median seconds of caster.occluded over repeats (at least min_reps, min_seconds)."""
    times = []
    result = caster.occluded(o, d, batch=o.shape[0])  # warm-up
    start = time.perf_counter()
    while len(times) < min_reps or time.perf_counter() - start < min_seconds:
        t0 = time.perf_counter()
        result = caster.occluded(o, d, batch=o.shape[0])
        times.append(time.perf_counter() - t0)
    return statistics.median(times), result


def time_loop_open3d(caster: RayCaster, o: np.ndarray, d: np.ndarray) -> tuple[float, np.ndarray]:
    """Seconds per ray of a per-ray loop straight into open3d (one (1, 6) tensor each)."""
    scene = caster._scene  # the benchmark measures the raw per-ray cost of the same scene
    out = np.zeros(o.shape[0], dtype=bool)
    t0 = time.perf_counter()
    for i in range(o.shape[0]):  # deliberately naive: this is the baseline being measured
        ray = np.concatenate([o[i], d[i]]).astype(np.float32)[None]
        out[i] = scene.test_occlusions(o3d.core.Tensor(ray)).numpy()[0]
    return (time.perf_counter() - t0) / o.shape[0], out


def time_loop_wrapper(caster: RayCaster, o: np.ndarray, d: np.ndarray) -> tuple[float, np.ndarray]:
    """Seconds per ray of a per-ray loop through RayCaster.occluded."""
    out = np.zeros(o.shape[0], dtype=bool)
    t0 = time.perf_counter()
    for i in range(o.shape[0]):  # deliberately naive
        out[i] = caster.occluded(o[i : i + 1], d[i : i + 1])[0]
    return (time.perf_counter() - t0) / o.shape[0], out


def run(
    mesh: str = "bolt",
    size: str = "full",
    seed: int = 0,
    min_seconds: float = 1.0,
    min_reps: int = 3,
    nthreads: int = 0,
) -> dict:
    if mesh == "bolt":
        points, faces, label = load_bolt(size)
    else:
        points, faces, label = bumpy_mesh(5 if size == "full" else 3)
    caster = RayCaster(points, faces, nthreads=nthreads)
    o, d = hemisphere_rays(points, faces, max(BATCH_SIZES), seed)

    rays_per_second: dict[str, float] = {}
    seconds: dict[str, float] = {}
    results = {}
    for b in BATCH_SIZES:
        sec, occ = time_batched(caster, o[:b], d[:b], min_seconds, min_reps)
        seconds[str(b)] = sec
        rays_per_second[str(b)] = b / sec
        results[b] = occ
    # batch-size invariance: the first 1e4 answers are the same in every run
    small = min(BATCH_SIZES)
    same_across_batches = all(np.array_equal(results[b][:small], results[small]) for b in results)

    # the loops are short: median of LOOP_REPEATS runs (the machine is shared)
    runs_o3d = [time_loop_open3d(caster, o[:LOOP_RAYS], d[:LOOP_RAYS]) for _ in range(LOOP_REPEATS)]
    runs_wrap = [
        time_loop_wrapper(caster, o[:LOOP_RAYS], d[:LOOP_RAYS]) for _ in range(LOOP_REPEATS)
    ]
    loop_o3d = statistics.median(r[0] for r in runs_o3d)
    loop_wrap = statistics.median(r[0] for r in runs_wrap)
    occ_loop, occ_wrap = runs_o3d[0][1], runs_wrap[0][1]
    agree = float(np.mean(occ_loop == results[small][:LOOP_RAYS]))
    agree_wrap = float(np.mean(occ_wrap == results[small][:LOOP_RAYS]))
    best = max(BATCH_SIZES)
    loop_rps = 1.0 / loop_o3d
    return {
        "rays_per_second": rays_per_second,
        "speedup_vs_loop": rays_per_second[str(best)] / loop_rps,
        "speedup_vs_wrapper_loop": rays_per_second[str(best)] * loop_wrap,
        "seconds_per_batch": seconds,
        "loop_rays_per_second": loop_rps,
        "wrapper_loop_rays_per_second": 1.0 / loop_wrap,
        "loop_seconds_extrapolated": {str(b): b * loop_o3d for b in BATCH_SIZES},
        "loop_rays": LOOP_RAYS,
        "loop_repeats": LOOP_REPEATS,
        "agreement_with_loop": agree,
        "agreement_with_wrapper_loop": agree_wrap,
        "batch_size_invariant": bool(same_across_batches),
        "occluded_fraction": float(results[best].mean()),
        "mesh": label,
        "triangles": int(faces.shape[0]),
        "nthreads": nthreads,
    }


def print_table(r: dict) -> None:
    print(
        f"mesh: {r['mesh']}, {r['triangles']} triangles; occluded fraction "
        f"{r['occluded_fraction']:.3f}"
    )
    print(f"{'rays':>10} {'seconds':>10} {'rays/s':>14} {'loop s (extrap.)':>17} {'speedup':>9}")
    for b in BATCH_SIZES:
        k = str(b)
        print(
            f"{b:>10} {r['seconds_per_batch'][k]:>10.4f} {r['rays_per_second'][k]:>14,.0f} "
            f"{r['loop_seconds_extrapolated'][k]:>17.2f} "
            f"{r['rays_per_second'][k] / r['loop_rays_per_second']:>9.0f}"
        )
    print(
        f"per-ray loop ({r['loop_rays']} rays): open3d {r['loop_rays_per_second']:,.0f} rays/s, "
        f"through the wrapper {r['wrapper_loop_rays_per_second']:,.0f} rays/s"
    )
    print(
        f"speedup_vs_loop (1e6 batch vs open3d loop): {r['speedup_vs_loop']:.0f}x; "
        f"vs wrapper loop: {r['speedup_vs_wrapper_loop']:.0f}x"
    )
    print(
        f"accuracy: batched == per-ray on {100 * r['agreement_with_loop']:.0f}% "
        f"(wrapper {100 * r['agreement_with_wrapper_loop']:.0f}%); "
        f"batch-size invariant: {r['batch_size_invariant']}"
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", type=Path, help="write the figures here as well")
    ap.add_argument("--mesh", choices=("bolt", "bumpy"), default="bolt")
    ap.add_argument("--size", choices=("small", "full"), default="full")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--min-seconds", type=float, default=1.0, help="timing per batch size")
    ap.add_argument("--threads", type=int, default=0, help="Embree threads (0 = all)")
    args = ap.parse_args(argv)
    r = run(args.mesh, args.size, args.seed, args.min_seconds, nthreads=args.threads)
    print_table(r)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        tmp = args.json.with_suffix(args.json.suffix + ".tmp")
        tmp.write_text(json.dumps(r, indent=2, sort_keys=True))
        tmp.replace(args.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
