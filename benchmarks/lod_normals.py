"""The LODs' corner normals (docs/decisions.md "The LOD meshes carry their own shading normals"):
per asset and LOD, the dihedral angles between the LOD's faces and how far each corner's normal
lies from its face's, for M_org's normal at the corner (`lodnormals.org_corner_normals`, the
rule before) and for `lodnormals.lod_corner_normals` at crease angles of 45, 60 and 80 degrees.

    python benchmarks/lod_normals.py --json benchmarks/results/lod_normals.json
        [--assets bolt wall ...] [--size full]

Assets and LODs as benchmarks/fallback.py bakes them (its `BAKE` settings; only the ingest and
geometry stages run): the four generated scenes at `--size` (full), the Teapot and
BoxAnimated.usdz from ../shared/assets. Dihedral angles are between the two faces of each edge
(vertices at one position are one), counted in the bins `BINS` (degrees).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

from schemas.settings import BakeSettings
from texelbake import stages
from texelbake.geometry.build import lod_meshes
from texelbake.geometry.lodnormals import lod_corner_normals, org_corner_normals
from texelbake.pipeline.plan import resolve_settings

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))
from benchmarks.fallback import BAKE, asset_cases  # noqa: E402  (the same bakes)

BINS = (0, 5, 10, 20, 30, 40, 50, 60, 70, 80, 95, 120, 180)
CREASES = (45.0, 60.0, 80.0)


def dihedrals(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    """(e,) float64 degrees between the normals of the two faces of each interior edge."""
    tri = v[f]
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    fn /= np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-300)
    _, wid = np.unique(v, axis=0, return_inverse=True)
    fw = wid.reshape(-1)[f]
    edge = np.sort(np.stack([fw, np.roll(fw, -1, axis=1)], axis=2).reshape(-1, 2), axis=1)
    key = edge[:, 0] * (int(fw.max()) + 1) + edge[:, 1]
    face = np.repeat(np.arange(len(f)), 3)
    order = np.argsort(key, kind="stable")
    pair = key[order][1:] == key[order][:-1]
    a, b = face[order][:-1][pair], face[order][1:][pair]
    return np.degrees(np.arccos(np.clip(np.einsum("pd,pd->p", fn[a], fn[b]), -1.0, 1.0)))


def off_face(n: np.ndarray, v: np.ndarray, f: np.ndarray) -> dict[str, float]:
    """Percentiles of the corners' angles (degrees) off their face's normal."""
    tri = v[f]
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    fn /= np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-300)
    deg = np.degrees(np.arccos(np.clip(np.einsum("fkd,fd->fk", n, fn), -1.0, 1.0))).ravel()
    return {"p50": round(float(np.median(deg)), 2), "p90": round(float(np.percentile(deg, 90)), 2),
            "max": round(float(deg.max()), 2)}


def measure(name: str, src: Path, work: Path) -> list[dict]:
    settings = resolve_settings(src, BakeSettings(**BAKE))
    ctx = stages.StageContext.create(work / f"{name}_work", src, settings)
    stages.run_ingest(ctx, 0)
    stages.run_geometry(ctx, 0)
    asset, caster = ctx.asset(), ctx.caster()
    rows = []
    for i, (v, f, _) in enumerate(lod_meshes(ctx.geometry()), start=1):
        dih = dihedrals(v, f)
        row = {"asset": name, "lod": i, "triangles": int(len(f)),
               "dihedral_hist": {"bins": list(BINS),
                                 "counts": np.histogram(dih, bins=BINS)[0].tolist()},
               "dihedral_p50_p90_p99": [round(float(np.percentile(dih, q)), 2)
                                        for q in (50, 90, 99)],
               "off_face": {"org": off_face(org_corner_normals(v, f, asset.corner_normals,
                                                               caster), v, f)}}
        for c in CREASES:  # a loop over the few crease angles
            row["off_face"][f"lod_crease{c:g}"] = off_face(lod_corner_normals(
                v, f, asset.corner_normals, caster, crease_deg=c), v, f)
        rows.append(row)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--json", type=Path, help="write the rows here")
    ap.add_argument("--size", default="full")
    ap.add_argument("--assets", nargs="*", help="subset of the asset names")
    args = ap.parse_args()
    work = Path(tempfile.mkdtemp(prefix="lod_normals_"))
    cases = asset_cases(work, args.size, args.assets)
    rows: list[dict] = []
    for name in args.assets or list(cases):
        src = cases.get(name)
        if src is None or not src.is_file():
            print(f"{name}: {src} is missing, skipped")
            continue
        for r in measure(name, src, work):
            rows.append(r)
            offs = "  ".join(f"{k} {o['p50']:.1f}/{o['p90']:.1f}/{o['max']:.1f}"
                             for k, o in r["off_face"].items())
            print(f"{name:<13} LOD{r['lod']} {r['triangles']:>6} tris  dihedral p50/p90/p99 "
                  f"{r['dihedral_p50_p90_p99']}  counts {r['dihedral_hist']['counts']}\n"
                  f"{'':<14}off face p50/p90/max: {offs}", flush=True)
    print(f"dihedral bins (degrees): {list(BINS)}")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"size": args.size, "bake": BAKE,
                                         "rows": rows}, indent=1, sort_keys=True) + "\n")


if __name__ == "__main__":
    sys.exit(main())
