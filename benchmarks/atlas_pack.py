"""The atlas's use of its page under xatlas's packing options: the fraction of the N x N page
that charts cover (the uv area of M1's triangles) and the seconds `build_atlas` takes, for the
packer as it is and each option changed alone.

    python benchmarks/atlas_pack.py --res 512 --json benchmarks/results/atlas_pack.json

M1 is approximated by the asset's own mesh where the asset is small (the cylinder's LOD1 is
its M_org) and by a QEM simplification to --faces triangles otherwise (what the geometry
stage's LOD1 is at 256 px is asset-dependent; the packing's behaviour is what is compared)."""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np
import xatlas

from texelbake.geometry import atlas as atlas_mod
from texelbake.geometry.hierarchy import simplify_hierarchy
from texelbake.geometry.mesh import Mesh
from texelbake.stages.context import asset_of
from texelbake.testscenes import write_scene

#: option name -> PackOptions attributes changed from the packer's own
VARIANTS = {
    "as is": {},
    "bruteForce": {"bruteForce": True},
    "blockAlign": {"blockAlign": True},
    "no rotate_charts_to_axis": {"rotate_charts_to_axis": False},
}


def _pack_with(changes: dict):
    def pack(vertices, faces, resolution, padding, tpu):
        atlas = xatlas.Atlas()
        atlas.add_mesh(np.ascontiguousarray(vertices, dtype=np.float32),
                       np.ascontiguousarray(faces, dtype=np.uint32))
        opts = xatlas.PackOptions()
        opts.resolution, opts.padding = int(resolution), int(padding)
        opts.bilinear, opts.texels_per_unit = True, float(tpu)
        for k, v in changes.items():
            setattr(opts, k, v)
        atlas.generate(pack_options=opts)
        return atlas
    return pack


def meshes(work: Path, faces: int) -> dict[str, Mesh]:
    out = {}
    for name in ("cylinder", "bolt"):
        a = asset_of(write_scene(name, work / f"{name}.usda", "full"))
        out[name] = Mesh(a.points, a.faces)
    teapot = Path("/work/shared/assets/Teapot/Teapot.usd")
    if teapot.is_file():
        a = asset_of(teapot)
        out["Teapot"] = Mesh(a.points, a.faces)
    for k, m in list(out.items()):
        if m.num_faces > faces:
            out[k] = simplify_hierarchy(m.vertices, m.faces, 1, target_faces=faces)[0]
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--res", type=int, default=512)
    ap.add_argument("--faces", type=int, default=4000)
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    work = Path(tempfile.mkdtemp(prefix="atlas-pack-"))
    rows = []
    orig = atlas_mod._xatlas_pack
    try:
        for name, mesh in meshes(work, args.faces).items():  # loop over assets
            for label, changes in VARIANTS.items():  # loop over packing options
                atlas_mod._xatlas_pack = _pack_with(changes)
                t0 = time.perf_counter()
                at = atlas_mod.build_atlas(mesh, args.res)
                sec = time.perf_counter() - t0
                use = float(np.abs(at.uv_areas()).sum())
                rows.append({"asset": name, "faces": mesh.num_faces, "option": label,
                             "page_use": use, "charts": at.num_charts, "seconds": sec})
                print(f"{name:9s} {mesh.num_faces:6d} f  {label:26s} page use {use:6.1%}  "
                      f"charts {at.num_charts:5d}  {sec:6.2f} s", flush=True)
    finally:
        atlas_mod._xatlas_pack = orig
    if args.json:
        args.json.write_text(json.dumps({"res": args.res, "rows": rows}, indent=2))


if __name__ == "__main__":
    main()
