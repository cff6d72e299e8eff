"""The studio cases baked at the defaults: each small asset the tests build for a way studios
ship assets (tests/helpers/studio_assets.py, studio_cases.py, skel_rigs.py) baked by
`texelbake bake` with `BakeSettings()` (the dcc tests bake them with light CPM settings to keep
the suite short), in a child process with 2 processes for the sharded stages.

    python benchmarks/studio_defaults.py [--json PATH] [--cases kit,rig,...]

Printed per case: the exit code (0, or 3 for a quality target missed, with the targets the
report's `quality` names), the seconds, the served size (`cpm_atlas.max_px`), how the LODs
follow the animation (`lod_animation`), the warnings count, and the held-out SNR median of the
finest CPM level (the error beside the time). A case passes when it exits 0, or 3 with its
misses named. Blender's side of each case (gt and LOD1 against Cycles) is in tests/dcc/.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tests.helpers.skel_rigs import write_rig  # noqa: E402
from tests.helpers.studio_assets import (  # noqa: E402
    kit_asset,
    mtlx_asset,
    textured_box,
    wheel_variants_asset,
)
from tests.helpers.studio_cases import (  # noqa: E402
    write_cutout_card,
    write_dome_lit,
    write_subdivision_cube,
)

CASES: dict[str, Callable[[Path], Path]] = {
    "kit (wrapped uvs, no st)": kit_asset,
    "variants (escaping, missing)": lambda d: wheel_variants_asset(d)[0],
    "materialx reference": mtlx_asset,
    "missing texture": lambda d: textured_box(d, "./gone.png", fallback=(0.8, 0.3, 0.2, 1.0)),
    "cut-out": write_cutout_card,
    "dome light": write_dome_lit,
    "subdivision surface": write_subdivision_cube,
    "skinned rig (two meshes)": lambda d: write_rig(d / "rig.usda"),
}


def bake_case(src: Path, out: Path) -> dict:
    cmd = [sys.executable, "-m", "texelbake.cli", "bake", str(src), "-o", str(out), "-q",
           "-j", "2", "--workdir", str(out.parent / "work")]
    t0 = time.perf_counter()
    done = subprocess.run(cmd, env={**os.environ, "PYTHONPATH": str(ROOT)},
                          capture_output=True, text=True, check=False)
    row: dict = {"rc": done.returncode, "seconds": round(time.perf_counter() - t0, 1)}
    rep_path = out / "report.json"
    if rep_path.is_file():
        rep = json.loads(rep_path.read_text())
        quality = rep.get("quality") or {}
        row.update({
            "max_px": (rep.get("cpm_atlas") or {}).get("max_px"),
            "lod_animation": rep.get("lod_animation"),
            "warnings": len(rep.get("warnings") or []),
            "misses": quality.get("missed") or quality.get("misses") or [],
            "heldout_median_db": ((rep.get("levels") or [{}])[0].get("snr_heldout_db")
                                  or {}).get("p50"),
        })
    if done.returncode not in (0, 3):
        row["stderr_tail"] = done.stderr[-1500:]
    row["passes"] = done.returncode == 0 or (done.returncode == 3 and bool(row.get("misses")))
    return row


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--json", type=Path)
    ap.add_argument("--cases", help="comma-separated substrings of the case names")
    args = ap.parse_args(argv)
    names = [n for n in CASES if not args.cases
             or any(c.strip() in n for c in args.cases.split(","))]
    rows = {}
    load0 = os.getloadavg()[0]
    with tempfile.TemporaryDirectory(prefix="texelbake-studio-") as tmp:
        for i, name in enumerate(names):
            folder = Path(tmp) / f"case{i}"
            folder.mkdir()
            src = CASES[name](folder)
            rows[name] = bake_case(Path(src), folder / "out")
    print(f"studio cases at the defaults, 2 processes, load {load0:.1f} -> "
          f"{os.getloadavg()[0]:.1f} (2 cores)")
    print(f"  {'case':30s} exit  seconds  max_px  animation     warn  L0 held-out  misses")
    for name, r in rows.items():
        print(f"  {name:30s} {r['rc']:4d} {r['seconds']:8.1f} {r.get('max_px') or 0:7.1f}  "
              f"{str(r.get('lod_animation')):12s} {r.get('warnings', 0):4d}  "
              f"{r.get('heldout_median_db') or float('nan'):8.1f} dB  {r.get('misses') or ''}")
        if "stderr_tail" in r:
            print(r["stderr_tail"])
    ok = all(r["passes"] for r in rows.values())
    print(f"  every case exits 0 (or 3 naming its misses): {'holds' if ok else 'DOES NOT HOLD'}")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"load_before": load0, "cases": rows}, indent=1,
                                        sort_keys=True))
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
