"""BRDF evaluation throughput of `texelbake.brdf`, with the accuracy each path buys.

The CPM bake evaluates 1e8-1e9 BRDF values, so evaluations per second matter. For n direction
pairs (uniform over the upper hemisphere, seeded) the benchmark reports, median of repeats:

- every model (lambert, phong, preview, ggx_conductor, cellular, merl nearest / trilinear):
  seconds and million evaluations per second; for MERL beside its mean relative error against
  the analytic BRDF the table was tabulated from (speed against error);
- the preview kernel's block size (`brdf.analytic.CHUNK`) sweep, which justifies the default;
- numpy against the same UsdPreviewSurface formulas in torch (CPU, whole arrays), with the
  largest absolute difference between the two.

    python benchmarks/brdf_throughput.py --json out.json [--n 1048576] [--repeats 3]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time

import numpy as np

from texelbake import brdf
from texelbake.brdf import analytic as brdf_analytic


def _pairs(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)

    def dirs() -> np.ndarray:
        z = rng.random(n)
        phi = 2.0 * np.pi * rng.random(n)
        r = np.sqrt(1.0 - z * z)
        return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)

    return dirs(), dirs()


def _time(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def _torch_preview(wi, wo, diffuse, metallic, alpha, r2):
    import torch

    zi = wi[:, 2].clamp(min=0.0)
    zo = wo[:, 2].clamp(min=0.0)
    c = ((wi * wo).sum(1) + 1.0).clamp(min=1e-12)
    nh2 = ((zi + zo) ** 2 / (2.0 * c)).clamp(max=1.0)
    w = (1.0 - (0.5 * c).sqrt().clamp(max=1.0)).clamp(min=0.0) ** 5
    f0 = r2 * (1.0 - metallic) + diffuse * metallic
    f90 = (1.0 - metallic) + diffuse * metallic
    fr = f0 + (f90 - f0) * w[:, None]
    a2 = alpha * alpha
    d = nh2 * (a2 - 1.0) + 1.0
    k = alpha / 2.0
    dv = a2 / (np.pi * d * d * 4.0 * (zi * (1 - k) + k) * (zo * (1 - k) + k))
    out = fr * dv[:, None] + diffuse * (1.0 - metallic) / np.pi * (1.0 - fr)
    ok = (wi[:, 2] > 1e-6) & (wo[:, 2] > 1e-6)
    return torch.where(ok[:, None], out, torch.zeros((), dtype=out.dtype))


def run(n: int, repeats: int) -> dict:
    wi, wo = _pairs(n, seed=1)
    uv = np.random.default_rng(2).random((n, 2))
    preview = {"diffuseColor": (0.5, 0.4, 0.3), "metallic": 0.3, "roughness": 0.4}

    def analytic(a, b):
        return brdf.preview_surface(preview, a, b)

    table = brdf.tabulate_merl(analytic)
    truth = analytic(wi, wo)
    keep = (wi[:, 2] > 0.2) & (wo[:, 2] > 0.2)

    def rel_err(f):
        return float(np.abs(f[keep] - truth[keep]).mean() / truth[keep].mean())

    models = {
        "lambert": (lambda: brdf.lambert((0.5, 0.4, 0.3), wi, wo), None),
        "phong": (lambda: brdf.phong((0.3,) * 3, (0.5,) * 3, 20.0, wi, wo), None),
        "preview": (lambda: brdf.preview_surface(preview, wi, wo), None),
        "ggx_conductor": (lambda: brdf.ggx_conductor((1.0, 0.8, 0.3), 0.3, wi, wo), None),
        "cellular": (lambda: brdf.cellular({}, uv, wi, wo), None),
        "merl_nearest": (
            lambda: brdf.merl_lookup(table, wi, wo),
            lambda: rel_err(brdf.merl_lookup(table, wi, wo)),
        ),
        "merl_trilinear": (
            lambda: brdf.merl_lookup(table, wi, wo, interpolate=True),
            lambda: rel_err(brdf.merl_lookup(table, wi, wo, interpolate=True)),
        ),
    }
    result: dict = {"n": n, "repeats": repeats, "models": {}}
    print(f"{'model':16s} {'seconds':>9s} {'M evals/s':>10s} {'mean rel err':>13s}")
    for name, (fn, err) in models.items():
        sec = _time(fn, repeats)
        e = None if err is None else err()
        result["models"][name] = {"seconds": sec, "evals_per_second": n / sec, "rel_err": e}
        es = "" if e is None else f"{e:13.2e}"
        print(f"{name:16s} {sec:9.3f} {n / sec / 1e6:10.2f} {es}")

    print("\npreview block size sweep")
    sweep = {}
    default = brdf_analytic.CHUNK
    try:
        for chunk in (1 << 12, 1 << 14, 1 << 15, 1 << 16, 1 << 18, 1 << 22):
            brdf_analytic.CHUNK = chunk
            sec = _time(lambda: brdf.preview_surface(preview, wi, wo), repeats)
            sweep[str(chunk)] = sec
            print(f"  chunk {chunk:8d}: {sec:.3f} s")
    finally:
        brdf_analytic.CHUNK = default
    result["preview_chunk_seconds"] = sweep

    try:
        import torch
    except ImportError:  # pragma: no cover - torch is a project dependency
        return result
    tw, to = torch.from_numpy(wi), torch.from_numpy(wo)
    dcol = torch.tensor(preview["diffuseColor"], dtype=torch.float64)
    r2 = ((1.0 - 1.5) / (1.0 + 1.5)) ** 2
    t_sec = _time(lambda: _torch_preview(tw, to, dcol, 0.3, 0.16, r2), repeats)
    diff = float(np.abs(_torch_preview(tw, to, dcol, 0.3, 0.16, r2).numpy() - truth).max())
    np_sec = result["models"]["preview"]["seconds"]
    result["preview_torch"] = {
        "seconds": t_sec, "numpy_seconds": np_sec, "max_abs_diff": diff,
        "threads": torch.get_num_threads(),
    }
    print(f"\npreview numpy {np_sec:.3f} s, torch {t_sec:.3f} s "
          f"({torch.get_num_threads()} threads), max |diff| {diff:.1e}")
    return result


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=1 << 20)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--json", type=str, default=None)
    args = ap.parse_args(argv)
    result = run(args.n, args.repeats)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(result, f, indent=2)
    return 0


if __name__ == "__main__":
    sys.exit(main())
