"""A million-triangle asset at defaults: seconds and peak memory per stage.

    python benchmarks/million.py [--front-cells 62] [--json PATH] [--set KEY=VALUE ...]

The asset is the project's own wall scene scaled up: every block's front is a jittered,
displaced grid of `--front-cells`² quads (62: 1,538,352 triangles; the full wall has 8 and
29,568), with its 1024² colour texture, written by `texelbake.testscenes.write_scene` with a
parameter override. It is baked by `texelbake bake` at the defaults (`BakeSettings()`, plus
any `--set`) in a child process with 2 processes for the sharded stages, in a fresh artifact
store. Printed: triangles, the seconds of every stage (the result's `run.json`), the cost
model's estimate beside the measured total, the peak resident memory of the bake's process
tree (sampled every 0.2 s: the parent and its workers summed) and of its largest single
process, the load average before and after (2 cores shared), the served size and the held-out
SNR per level (the error beside the time), and whether each bar holds: no stage over 10
minutes, peak memory under 4 GiB.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import psutil

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from texelbake.testscenes import write_scene  # noqa: E402

STAGE_BAR_S = 600.0
MEMORY_BAR = 4 * 2**30


def _tree_rss(proc: psutil.Process) -> tuple[int, int]:
    """(summed RSS of proc and its descendants, the largest single RSS)."""
    try:
        procs = [proc, *proc.children(recursive=True)]
    except psutil.NoSuchProcess:
        return 0, 0
    rss = []
    for p in procs:
        try:
            rss.append(p.memory_info().rss)
        except psutil.NoSuchProcess:
            continue
    return sum(rss), max(rss, default=0)


def bake(layer: Path, out: Path, sets: list[str]) -> dict:
    """Run `texelbake bake` on layer; returns wall seconds, exit code, peak memory."""
    cmd = [sys.executable, "-m", "texelbake.cli", "bake", str(layer), "-o", str(out), "-q",
           "-j", "2", "--workdir", str(out.parent / "work"), "--accept-below-target"]
    for s in sets:
        cmd += ["--set", s]
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    t0 = time.perf_counter()
    child = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                             text=True)
    ps = psutil.Process(child.pid)
    peak = {"tree": 0, "single": 0}
    done = threading.Event()

    def sample() -> None:
        while not done.is_set():
            tree, single = _tree_rss(ps)
            peak["tree"] = max(peak["tree"], tree)
            peak["single"] = max(peak["single"], single)
            done.wait(0.2)

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    log, _ = child.communicate()
    done.set()
    sampler.join()
    return {"wall_s": time.perf_counter() - t0, "rc": child.returncode, "log_tail": log[-2000:],
            "peak_tree_bytes": peak["tree"], "peak_single_bytes": peak["single"]}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--front-cells", type=int, default=62)
    ap.add_argument("--json", type=Path)
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    args = ap.parse_args(argv)
    load0 = os.getloadavg()[0]
    with tempfile.TemporaryDirectory(prefix="texelbake-million-") as tmp:
        layer = write_scene("wall", Path(tmp) / "scene" / "wall_million.usdc", "full",
                            {"front_cells": args.front_cells})
        from pxr import Usd, UsdGeom

        stage = Usd.Stage.Open(str(layer))
        triangles = sum(int((np.asarray(UsdGeom.Mesh(p).GetFaceVertexCountsAttr().Get())
                             - 2).sum())
                        for p in stage.Traverse() if p.IsA(UsdGeom.Mesh))
        del stage
        out = Path(tmp) / "out"
        res = bake(layer, out, args.set)
        run = json.loads((out / "run.json").read_text()) if (out / "run.json").exists() else {}
        report = (json.loads((out / "report.json").read_text())
                  if (out / "report.json").exists() else {})
    load1 = os.getloadavg()[0]
    stages = run.get("stage_seconds", {})
    est_d = run.get("estimate") if isinstance(run.get("estimate"), dict) else {}
    est = next((est_d[k] for k in ("total_seconds", "total_s", "seconds") if k in est_d), None)
    result = {
        "triangles": triangles, "front_cells": args.front_cells, "settings_set": args.set,
        "rc": res["rc"], "wall_s": res["wall_s"], "stage_seconds": stages,
        "estimate_total_s": est, "peak_tree_bytes": res["peak_tree_bytes"],
        "peak_single_bytes": res["peak_single_bytes"], "load_before": load0,
        "load_after": load1, "cpm_atlas": report.get("cpm_atlas"),
        "heldout": [{"level": i, "snr_heldout_db": lv.get("snr_heldout_db")}
                    for i, lv in enumerate(report.get("levels", []))],
        "lods": (report.get("lods") or {}).get("levels", []),
    }
    slowest = max(stages.items(), key=lambda kv: kv[1], default=("-", 0.0))
    result["holds"] = {"no_stage_over_10_min": bool(stages) and slowest[1] <= STAGE_BAR_S,
                       "peak_under_4_gib": res["peak_tree_bytes"] < MEMORY_BAR,
                       "exit_0_or_3": res["rc"] in (0, 3)}
    print(f"wall scene, front cells {args.front_cells}: {triangles:,} triangles; "
          f"load {load0:.1f} -> {load1:.1f} (2 cores)")
    print(f"  exit {res['rc']}, wall {res['wall_s']:.1f} s, cost model "
          f"{est if est is None else f'{est:.1f} s'}")
    for name, sec in sorted(stages.items(), key=lambda kv: -kv[1]):
        print(f"  {name:12s} {sec:9.1f} s")
    print(f"  peak RSS: tree {res['peak_tree_bytes'] / 2**30:.2f} GiB, largest process "
          f"{res['peak_single_bytes'] / 2**30:.2f} GiB")
    for lv in result["lods"]:
        print(f"  LOD {lv.get('triangles')} triangles, within bound: {lv.get('within_bound')}")
    for lv in result["heldout"]:
        ho = lv["snr_heldout_db"] or {}
        print(f"  CPM level {lv['level']}: held-out SNR median {ho.get('p50')} dB, "
              f"p5 {ho.get('p5')} dB")
    for k, v in result["holds"].items():
        print(f"  {k}: {'holds' if v else 'DOES NOT HOLD'}")
    if res["rc"] not in (0, 3):
        print(res["log_tail"])
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(result, indent=1, sort_keys=True))
    return 0 if all(result["holds"].values()) else 1


if __name__ == "__main__":
    raise SystemExit(main())
