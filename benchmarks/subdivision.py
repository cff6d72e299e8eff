"""Subdivision surfaces baked from their limit surface: the shared Teapot (a catmullClark cage
of 1236 quads) baked as it is read now (two Catmull–Clark levels with limit positions) and as
its control cage (the same asset with `subdivisionScheme = "none"` over it: what texelbake
baked before), each LOD1 exported (.usdz) and rendered in Blender 5.0.1 beside the original
(tests/blender/import_render.py: Cycles CPU, 160 px, 32 samples, deterministic).

First a table per refinement level (0: the cage) of the Teapot's triangles and its largest
distance from the limit surface (level 4's points) over the diagonal: LOD1's default error
bound is 1/256 = 0.0039. Blender's USD importer does not subdivide at its defaults (`import_subdivision` off: it shows
the cage shaded smooth); with `import_subdivision` on it adds a Subdivision Surface modifier
at render level 2 with limit positions. Both originals are rendered; `MAD` is the mean absolute
difference over the object's pixels (8-bit sRGB, [0, 1]), `IoU` the silhouettes' overlap.

    python benchmarks/subdivision.py --json benchmarks/results/subdivision.json

The bakes use a light CPM (8 samples per texel, 8 x 8 directions, c_max 8): the LOD chain, the
fallback material and its textures, which is what Blender shows, follow the geometry fields,
left at their defaults.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))
TEAPOT = ROOT.parent / "shared" / "assets" / "Teapot" / "Teapot.usd"
LIGHT = {"samples_per_texel": 8, "n_light_dirs": 8, "n_view_dirs": 8, "n_heldout": 16,
         "c_max": 8}


def cage_copy(src: Path, folder: Path) -> Path:
    """A copy of `src`'s folder with a layer over `src` that sets every mesh's
    subdivisionScheme to none (the cage); the asset's paths stay inside its folder."""
    from pxr import Sdf, Usd, UsdGeom

    if not folder.exists():
        shutil.copytree(src.parent, folder)
    out = folder / f"{src.stem}_cage.usda"
    stage = Usd.Stage.Open(str(src))
    meshes = [p.GetPath() for p in stage.Traverse() if p.IsA(UsdGeom.Mesh)]
    layer = Sdf.Layer.CreateNew(str(out))
    over = Usd.Stage.Open(layer)
    over.GetRootLayer().subLayerPaths.append(f"./{src.name}")
    for path in meshes:
        UsdGeom.Mesh(over.OverridePrim(path)).CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    over.SetDefaultPrim(over.GetPrimAtPath(stage.GetDefaultPrim().GetPath()))
    UsdGeom.SetStageUpAxis(over, UsdGeom.GetStageUpAxis(stage))
    UsdGeom.SetStageMetersPerUnit(over, UsdGeom.GetStageMetersPerUnit(stage))
    layer.Save()
    return out


def level_deviation(src: Path, levels=(0, 1, 2, 3), reference: int = 4) -> list[dict]:
    """Per refinement level of every catmullClark mesh of `src` (with limit positions; 0: the
    cage): triangles and the largest distance from the points of level `reference` (on the
    limit surface to ~1e-5 of the diagonal) to that mesh, over the bounding-box diagonal."""
    import numpy as np
    from pxr import Usd, UsdGeom

    from texelbake.asset.meshes import fan_triangles
    from texelbake.geometry.mesh import bbox_diagonal
    from texelbake.geometry.raycast import RayCaster
    from texelbake.geometry.subdivision import catmull_clark

    rows = []
    stage = Usd.Stage.Open(str(src))
    for prim in stage.Traverse():
        if not prim.IsA(UsdGeom.Mesh):
            continue
        m = UsdGeom.Mesh(prim)
        if str(m.GetSubdivisionSchemeAttr().Get()) != "catmullClark":
            continue
        pts = np.asarray(m.GetPointsAttr().Get(), dtype=np.float64)
        counts = np.asarray(m.GetFaceVertexCountsAttr().Get(), dtype=np.int64)
        idx = np.asarray(m.GetFaceVertexIndicesAttr().Get(), dtype=np.int64)
        ref = catmull_clark(counts, idx, len(pts), reference).vertex_matrix @ pts
        diag = bbox_diagonal(ref)
        for k in levels:
            if k == 0:
                v, c, i = pts, counts, idx
            else:
                r = catmull_clark(counts, idx, len(pts), k)
                v, c, i = r.vertex_matrix @ pts, r.counts, r.indices
            tris = fan_triangles(c, i)
            cp, _, _ = RayCaster(v, tris).closest_points(ref)
            rows.append({"mesh": str(prim.GetPath()), "level": k, "triangles": int(len(tris)),
                         "max_dev_rel": float(np.linalg.norm(cp - ref, axis=1).max() / diag)})
    return rows


def bake_one(src: Path, out: Path) -> dict:
    from schemas.settings import BakeSettings
    from texelbake.asset import load_asset
    from texelbake.pipeline.run import bake
    from texelbake.usd.export import export_lod

    done = out / "bake.json"
    if done.is_file():  # a rerun over the same --work folder keeps its bakes
        return json.loads(done.read_text())
    t0 = time.perf_counter()
    asset = load_asset(src)
    load_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    root = bake(src, out / "baked", BakeSettings(**LIGHT), progress=False,
                workdir=out / "work")
    bake_s = time.perf_counter() - t0
    report = json.loads((root.parent / "report.json").read_text())
    lod1 = report["lods"]["levels"][0]
    row = {"m_org_triangles": int(asset.num_faces), "load_s": round(load_s, 2),
            "bake_s": round(bake_s, 1), "lod1_triangles": lod1["triangles"],
            "lod1_hausdorff_rel": lod1["hausdorff_rel"], "lod1_bound_rel": lod1["bound_rel"],
            "lod1": str(export_lod(root, 1, out / "lod1.usdz")),
            "geometry_s": report["stage_seconds"].get("geometry")}
    done.write_text(json.dumps(row))
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--json", type=Path, help="write the results here")
    ap.add_argument("--work", type=Path, help="work folder (default: a temporary one)")
    args = ap.parse_args()
    from tests.helpers.dcc import compare_renders, import_and_render, side_by_side

    work = args.work or Path(tempfile.mkdtemp(prefix="tb_subdiv_"))
    work.mkdir(parents=True, exist_ok=True)
    levels = level_deviation(TEAPOT)
    print(f"{'mesh':20} {'level':>5} {'triangles':>9} {'max dev/diag':>12}")
    for r in levels:
        print(f"{r['mesh']:20} {r['level']:>5} {r['triangles']:>9} {r['max_dev_rel']:>12.6f}")
    print()
    bakes = {"limit": bake_one(TEAPOT, work / "limit"),
             "cage": bake_one(cage_copy(TEAPOT, work / "teapot_cage"), work / "cage")}
    files = {"original": TEAPOT, "original_subdiv": TEAPOT,
             "lod1_limit": Path(bakes["limit"]["lod1"]), "lod1_cage": Path(bakes["cage"]["lod1"])}
    renders = work / "renders"
    got = import_and_render(files, renders, resolution=160, samples=32,
                            options={"original_subdiv": {"import_subdivision": True}})
    png = {k: got["files"][k]["png"] for k in files}
    side_by_side([Path(png[k]) for k in files], renders / "row.png")
    rows = []
    for ref in ("original", "original_subdiv"):
        for lod in ("lod1_limit", "lod1_cage"):
            c = compare_renders(png[ref], png[lod])
            rows.append({"reference": ref, "render": lod, "mad": round(c["mad"], 4),
                         "iou": round(c["iou"], 4), "object_pixels": c["object_pixels"]})
    c = compare_renders(png["original"], png["original_subdiv"])
    rows.append({"reference": "original", "render": "original_subdiv",
                 "mad": round(c["mad"], 4), "iou": round(c["iou"], 4),
                 "object_pixels": c["object_pixels"]})
    print(f"{'bake':6} {'M_org tris':>10} {'load s':>7} {'bake s':>7} {'LOD1 tris':>9} "
          f"{'H/diag':>7} {'bound':>7}")
    for k, b in bakes.items():
        print(f"{k:6} {b['m_org_triangles']:>10} {b['load_s']:>7.2f} {b['bake_s']:>7.1f} "
              f"{b['lod1_triangles']:>9} {b['lod1_hausdorff_rel']:>7.4f} "
              f"{b['lod1_bound_rel']:>7.4f}")
    print(f"\n{'reference':16} {'render':16} {'MAD':>7} {'IoU':>7}")
    for r in rows:
        print(f"{r['reference']:16} {r['render']:16} {r['mad']:>7.4f} {r['iou']:>7.4f}")
    print(f"\nrenders: {renders}")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"levels": levels, "bakes": bakes, "blender": rows,
                                         "renders": str(renders)}, indent=1))


if __name__ == "__main__":
    main()
