"""Reading a baked folder back into arrays identical to what was written: the only way the
renderer gets baked data."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from pxr import Usd, UsdGeom

from texelbake.errors import AssetError
from texelbake.usd.baked import ARRAY_NS, NUMPY_FROM_USD, BakedAsset
from texelbake.usd.fallback import read_preview_material
from texelbake.usd.lodmesh import LodMesh, read_animation, read_impostor


def _read_arrays(prim: Usd.Prim) -> dict[str, np.ndarray]:
    out: dict[str, np.ndarray] = {}
    for attr in prim.GetAttributes():
        full = attr.GetName()
        if not full.startswith(ARRAY_NS) or full.endswith(":shape"):
            continue
        name = full[len(ARRAY_NS):]
        tname = str(attr.GetTypeName())
        if tname not in NUMPY_FROM_USD:
            continue
        shape_attr = prim.GetAttribute(f"{full}:shape")
        shape = tuple(int(x) for x in shape_attr.Get()) if shape_attr else None
        value = attr.Get()
        arr: np.ndarray = np.array(value, dtype=NUMPY_FROM_USD[tname]) if value is not None \
            else np.zeros(0, NUMPY_FROM_USD[tname])
        out[name] = arr.reshape(shape) if shape is not None else arr
    return out


def read_baked(path: str | Path) -> BakedAsset:
    """Read a baked asset (root layer path) back into arrays identical to what was written."""
    path = Path(path)
    stage = Usd.Stage.Open(str(path))
    if stage is None:
        raise AssetError("cannot open baked USD", path=str(path))
    root = stage.GetDefaultPrim()
    if not root:
        raise AssetError("baked USD has no defaultPrim", path=str(path))
    baked_path = root.GetPath().AppendChild("Baked")
    cpm = stage.GetPrimAtPath(baked_path.AppendChild("CPM"))
    if not cpm:
        raise AssetError("no texelbake payload (Baked/CPM) found", path=str(path),
                         prim=str(baked_path))
    arrays = _read_arrays(cpm)
    levels = []
    for child in sorted(cpm.GetChildren(), key=lambda p: p.GetName()):
        levels.append(_read_arrays(child))
    meshes = []
    skeleton = ""
    i = 1
    while True:
        prim = stage.GetPrimAtPath(baked_path.AppendChild(f"LOD{i}"))
        if not prim:
            break
        geom = UsdGeom.Mesh(prim)
        v = np.array(geom.GetPointsAttr().Get(), dtype=np.float32).astype(np.float64)
        f = np.array(geom.GetFaceVertexIndicesAttr().Get(), dtype=np.int64).reshape(-1, 3)
        st = UsdGeom.PrimvarsAPI(geom).GetPrimvar("st").Get()
        uv = np.array(st, dtype=np.float32).astype(np.float64).reshape(-1, 3, 2)
        nrm = geom.GetNormalsAttr().Get()
        cn = (np.array(nrm, dtype=np.float32).astype(np.float64).reshape(-1, 3, 3)
              if nrm is not None and len(nrm) == 3 * len(f) else None)
        mesh = LodMesh(v, f, uv, read_impostor(geom, len(v)), cn)
        skeleton = read_animation(geom, mesh, skeleton)
        meshes.append(mesh)
        i += 1
    meta = dict(stage.GetRootLayer().customLayerData.get("texelbake", {}))
    name = path.name.removesuffix("_baked.usda")
    albedo = _read_png(path.parent / f"{name}_albedo.png", srgb=True)
    normal = _read_png(path.parent / f"{name}_normal.png", srgb=False) * 2.0 - 1.0
    source = ""
    refs = root.GetPrimStack()
    for spec in refs:
        items = spec.referenceList.prependedItems or spec.referenceList.explicitItems
        if items:
            source = str((path.parent / items[0].assetPath).resolve())
            break
    filtered = read_filtered_maps(path.parent, name)
    fallback = {"materials": [read_preview_material(stage, baked_path.AppendChild(f"LOD{i}"))
                              for i in range(1, len(meshes) + 1)]}
    return BakedAsset(name, levels, arrays, meshes, albedo.astype(np.float32),
                      normal.astype(np.float32), meta, source, str(path), filtered, fallback,
                      skeleton)


def read_filtered_maps(folder: Path, name: str) -> list[np.ndarray]:
    """The filtered maps `<name>_filtered_L<ll>.exr` of every level (empty list when the bake
    wrote none: older bakes). AssetError naming the file when its channels are not
    `filtered_maps.CHANNELS`."""
    from texelbake.baselines.filtered_maps import CHANNELS
    from texelbake.io.images import read_pixels

    out: list[np.ndarray] = []
    while (f := Path(folder) / f"{name}_filtered_L{len(out):02d}.exr").is_file():
        px, info = read_pixels(f)
        names = list(info.channel_names)  # EXR stores channels sorted by name: reorder
        if sorted(names) != sorted(CHANNELS):
            raise AssetError(f"filtered map channels {names}, expected {list(CHANNELS)}",
                             path=str(f))
        out.append(px[..., [names.index(c) for c in CHANNELS]])
    return out


def _read_png(path: Path, srgb: bool) -> np.ndarray:
    from texelbake.io.images import read_pixels, srgb_to_linear

    if not path.is_file():
        return np.zeros((0, 0, 3), np.float32)
    px = read_pixels(path)[0][..., :3].astype(np.float64)
    if srgb:
        px = srgb_to_linear(px.astype(np.float32)).astype(np.float64)
    return px
