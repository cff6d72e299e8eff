"""The baked USD: writer and reader (DESIGN.md "The baked USD").

A baked asset is a folder:

    <name>_baked.usda        root layer: references the source, adds the payload, LOD variants
    <name>_payload.usdc      the baked data (crate): LOD meshes M1..Mn with atlas uvs, one Scope
                             per CPM level holding its arrays, the preview material
    source/...               a copy of the source asset and the files it references
    <name>_albedo.png, <name>_normal.png
                             the baseline's albedo and normal maps baked onto M1
    <name>_filtered_L<ll>.exr
                             the filtered maps of each mip level (`texelbake.filtered_maps`:
                             mean normal, LEADR moments, AO, albedo, base colour, α²)
    <name>_basecolor.png, <name>_occlusion.png, <name>_roughness_lod<i>.png
    [<name>_fallback_normal.png]
                             the UsdPreviewSurface fallback of each LOD i (with the normal map,
                             the fallback's own when its textures are finer than the atlas):
                             material /Baked/Looks/BakedPreview for LOD1, BakedPreview_LOD<i>
                             for the others
    report.json              what the bake measured

Array attributes live in the `texelbake:` namespace, flattened, each with an int[] companion
`<name>:shape`; the dtype maps one-to-one onto a USD value type (float16 -> half[],
float32 -> float[], float64 -> double[], int32 -> int[], int64 -> int64[], uint8 -> uchar[], bool -> bool[]), so `read_baked`
returns arrays identical to what was written. `read_baked` is the only way the renderer gets
baked data.
"""

from __future__ import annotations

import json
import os
import shutil
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from pxr import Kind, Sdf, Usd, UsdGeom, UsdShade, UsdSkel, Vt

from texelbake import bakedvariants
from texelbake.atomic import atomic_write_bytes, replace
from texelbake.errors import AssetError, ShapeError
from texelbake.lodmesh import (
    LodMesh,
    author_mesh,
    extent_of,
    read_animation,
    read_impostor,
)
from texelbake.preview_material import (
    author_preview_material,
    fallback_material_path,
    read_preview_material,
)
from texelbake.shaderdefs import write_definitions

_NS = "texelbake:"

_DTYPES: dict[str, tuple[Any, Any]] = {
    # numpy dtype name -> (Sdf value type, Vt array class)
    "float16": (Sdf.ValueTypeNames.HalfArray, Vt.HalfArray),
    "float32": (Sdf.ValueTypeNames.FloatArray, Vt.FloatArray),
    "float64": (Sdf.ValueTypeNames.DoubleArray, Vt.DoubleArray),
    "int32": (Sdf.ValueTypeNames.IntArray, Vt.IntArray),
    "int64": (Sdf.ValueTypeNames.Int64Array, Vt.Int64Array),
    "uint32": (Sdf.ValueTypeNames.UIntArray, Vt.UIntArray),
    "uint8": (Sdf.ValueTypeNames.UCharArray, Vt.UCharArray),
    "bool": (Sdf.ValueTypeNames.BoolArray, Vt.BoolArray),
}
_FROM_USD = {
    "half[]": np.float16, "float[]": np.float32, "double[]": np.float64, "int[]": np.int32,
    "int64[]": np.int64, "uint[]": np.uint32,
    "uchar[]": np.uint8, "bool[]": np.bool_,
}


@dataclass
class BakedAsset:
    """Everything a bake writes, as arrays.

    levels : one dict of named arrays per CPM level (level 0 finest), as `texelbake.stages`
        assembles them (CSR texel offsets, characteristic points, weights, a_vis tables)
    arrays : bake-wide arrays (direction grids, material table, ...)
    meshes : M1..Mn
    albedo, normal : (N, N, 3) float32 preview maps over M1's atlas (normal in [-1, 1])
    metadata : JSON-able dict written to customLayerData["texelbake"]
    filtered : per level an (N_l, N_l, C) float32 filtered map (`filtered_maps.CHANNELS`)
    fallback : the UsdPreviewSurface fallback: "base" (R, R, 3) diffuseColor, "occlusion"
        (R, R), "roughness" a list of (n_i, n_i) maps, one per LOD, "constants" (inputs
        carried from the source material) and, when R > N, "normal" (R, R, 3) its own normal
        map (else it shares `normal`); R = `stages.filtered.fallback_resolution`; empty: the albedo/normal material of old bakes.
        `read_baked` returns each LOD's material as authored, under "materials".
    """

    name: str
    levels: list[dict[str, np.ndarray]]
    arrays: dict[str, np.ndarray]
    meshes: list[LodMesh]
    albedo: np.ndarray
    normal: np.ndarray
    metadata: dict[str, Any] = field(default_factory=dict)
    source_layer: str = ""
    root_layer: str = ""
    filtered: list[np.ndarray] = field(default_factory=list)
    fallback: dict[str, Any] = field(default_factory=dict)
    #: the UsdSkel.Skeleton the LOD meshes are bound to (source namespace; "" when unskinned)
    skeleton: str = ""


# --------------------------------------------------------------------------- writing


def _author_array(prim: Usd.Prim, name: str, arr: np.ndarray) -> None:
    arr = np.asarray(arr)
    key = arr.dtype.name
    if key not in _DTYPES:
        raise ShapeError(f"payload array {name!r}: unsupported dtype {arr.dtype}")
    vtype, vt = _DTYPES[key]
    flat = np.ascontiguousarray(arr.reshape(-1))
    if not flat.flags.aligned:
        # an array mapped from an artifact (`store.read_npz(mmap=True)`) lies where its zip
        # member does: unaligned, numpy exports it with the format '=d', which Vt.FromNumpy
        # refuses ("Unsupported format"); an aligned copy is what it reads
        flat = flat.copy()
    value = vt(flat.tolist()) if key in ("bool", "uint8") else vt.FromNumpy(flat)
    prim.CreateAttribute(f"{_NS}{name}", vtype, custom=True).Set(value)
    prim.CreateAttribute(f"{_NS}{name}:shape", Sdf.ValueTypeNames.IntArray, custom=True).Set(
        Vt.IntArray([int(x) for x in arr.shape])
    )


def _author_arrays(prim: Usd.Prim, arrays: dict[str, np.ndarray]) -> None:
    for name in sorted(arrays):
        _author_array(prim, name, arrays[name])


def _write_maps(out_dir: Path, baked: BakedAsset) -> dict[str, Any]:
    """Write every map file of the bundle; returns the file names the materials use."""
    from texelbake.filtered_maps import CHANNELS
    from texelbake.imageio import write_pixels

    name = baked.name
    files: dict[str, Any] = {"albedo": f"{name}_albedo.png", "normal": f"{name}_normal.png"}
    _write_png(out_dir / files["albedo"], baked.albedo, srgb=True)
    _write_png(out_dir / files["normal"], 0.5 * (baked.normal + 1.0), srgb=False)
    for lvl, img in enumerate(baked.filtered):
        if img.ndim != 3 or img.shape[2] != len(CHANNELS):
            raise ShapeError(f"filtered map of level {lvl}: expected (n, n, {len(CHANNELS)}), "
                             f"got {img.shape}")
        write_pixels(out_dir / f"{name}_filtered_L{lvl:02d}.exr", img.astype(np.float32),
                     "float", channel_names=CHANNELS)
    fb = baked.fallback
    if fb:
        files["base"] = f"{name}_basecolor.png"
        files["occlusion"] = f"{name}_occlusion.png"
        _write_png(out_dir / files["base"], fb["base"], srgb=True)
        _write_png(out_dir / files["occlusion"], np.asarray(fb["occlusion"])[..., None],
                   srgb=False)
        files["roughness"] = []
        files["fallback_normal"] = files["normal"]
        if fb.get("normal") is not None:  # the fallback's own, finer than the baseline's
            files["fallback_normal"] = f"{name}_fallback_normal.png"
            _write_png(out_dir / files["fallback_normal"], 0.5 * (np.asarray(fb["normal"]) + 1.0),
                       srgb=False)
        for i, r in enumerate(fb["roughness"], start=1):
            files["roughness"].append(f"{name}_roughness_lod{i}.png")
            _write_png(out_dir / files["roughness"][-1], np.asarray(r)[..., None], srgb=False)
    return files


def _new_stage(path: Path) -> Usd.Stage:
    """A new stage on a temporary file beside `path` (so relative asset paths resolve while
    authoring); `_commit_stage` saves it and renames it onto `path`."""
    tmp = path.with_name(f".{path.stem}.tmp{path.suffix}")
    if tmp.exists():
        tmp.unlink()
    stage = Usd.Stage.CreateNew(str(tmp))
    if stage is None:
        raise AssetError("could not create USD layer", path=str(tmp))
    return stage


def _commit_stage(stage: Usd.Stage, path: Path) -> None:
    layer = stage.GetRootLayer()
    tmp = layer.realPath
    if not layer.Save():
        raise AssetError("could not write USD layer", path=str(path))
    replace(tmp, path)


def _write_png(path: Path, rgb: np.ndarray, srgb: bool) -> None:
    from texelbake.imageio import write_png

    write_png(path, rgb, srgb=srgb)


def copy_source(source_layer: Path, dependencies: list[str], dest: Path) -> Path:
    """Copy the source layer and the files it references (paths relative to its folder) into
    `dest`; returns the copied root layer."""
    src_root = Path(source_layer).resolve().parent
    for dep in sorted({str(Path(d).resolve()) for d in dependencies} | {str(source_layer)}):
        rel = Path(dep).resolve().relative_to(src_root)
        target = dest / rel
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(dep, target)
    return dest / Path(source_layer).resolve().relative_to(src_root)


def pack_usdz(root_layer: Path) -> Path:
    """The baked result with everything it references (the source where it lies, payload,
    maps, shader definitions) in one `<root stem>.usdz` beside it (UsdUtils' packager,
    which rewrites the asset paths into the package). Returns the package path."""
    from pxr import UsdUtils

    root_layer = Path(root_layer)
    out = root_layer.with_suffix(".usdz")
    tmp = out.with_name(f".{out.stem}.tmp.usdz")
    if not UsdUtils.CreateNewUsdzPackage(Sdf.AssetPath(str(root_layer)), str(tmp)):
        raise AssetError("could not pack the baked result into a .usdz", path=str(out))
    replace(tmp, out)
    return out


def write_baked_asset(out_dir: Path, source_copy: Path, baked: BakedAsset,
                      original_mesh_paths: list[str], *,
                      author_extra: Callable[[Usd.Stage], None] | None = None) -> Path:
    """Write the baked folder (see module docstring). `source_copy` is the source root layer
    already copied under out_dir; `author_extra(payload_stage)` may add to the payload layer
    (the BTF shader). Returns the root layer path."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    name = baked.name
    src_stage = Usd.Stage.Open(str(source_copy), Usd.Stage.LoadNone)
    if src_stage is None:
        raise AssetError("cannot reopen the copied source", path=str(source_copy))
    default = src_stage.GetDefaultPrim()
    root_name = default.GetName() if default else "Asset"
    up_axis = UsdGeom.GetStageUpAxis(src_stage)
    mpu = UsdGeom.GetStageMetersPerUnit(src_stage)

    files = _write_maps(out_dir, baked)
    write_definitions(out_dir)  # the CPM and BTF shaders name it (texelbake.shaderdefs)

    # ---- payload layer (crate)
    payload_file = f"{name}_payload.usdc"
    pstage = _new_stage(out_dir / payload_file)
    UsdGeom.SetStageUpAxis(pstage, up_axis)
    UsdGeom.SetStageMetersPerUnit(pstage, mpu)
    # (no Sdf.ChangeBlock here: Usd-level Define/CreateAttribute are not safe inside one)
    skinned = any(m.skin for m in baked.meshes)
    if skinned and not baked.skeleton:
        raise AssetError("skinned LOD meshes but no skeleton path (BakedAsset.skeleton)",
                         path=str(out_dir))
    # a skinned asset's LODs live under their own SkelRoot (UsdSkel skins only prims below one);
    # the skeleton they bind to stays the source's, in its SkelRoot
    baked_root = (UsdSkel.Root if skinned else UsdGeom.Scope).Define(pstage, "/Baked")
    pstage.SetDefaultPrim(baked_root.GetPrim())
    cpm_scope = UsdGeom.Scope.Define(pstage, "/Baked/CPM")
    _author_arrays(cpm_scope.GetPrim(), baked.arrays)
    for lvl, arrays in enumerate(baked.levels):
        scope = UsdGeom.Scope.Define(pstage, f"/Baked/CPM/L{lvl:02d}")
        _author_arrays(scope.GetPrim(), arrays)
    UsdGeom.Scope.Define(pstage, "/Baked/Looks")
    for i, mesh in enumerate(baked.meshes, start=1):
        if baked.fallback:  # one fallback per LOD: its roughness is widened for that LOD
            mat = author_preview_material(
                pstage, fallback_material_path(i), f"./{files['base']}",
                f"./{files['fallback_normal']}",
                "/Baked/CPM", f"./{files['roughness'][i - 1]}", f"./{files['occlusion']}",
                baked.fallback.get("constants"))
        elif i == 1:
            mat = author_preview_material(
                pstage, fallback_material_path(1), f"./{files['albedo']}",
                f"./{files['normal']}", "/Baked/CPM")
        geom = author_mesh(pstage, f"/Baked/LOD{i}", mesh)
        UsdShade.MaterialBindingAPI.Apply(geom.GetPrim()).Bind(mat)
    if author_extra is not None:
        author_extra(pstage)
    _commit_stage(pstage, out_dir / payload_file)

    # ---- root layer
    root_file = out_dir / f"{name}_baked.usda"
    stage = _new_stage(root_file)
    UsdGeom.SetStageUpAxis(stage, up_axis)
    UsdGeom.SetStageMetersPerUnit(stage, mpu)
    rel_source = os.path.relpath(source_copy, out_dir)
    root = UsdGeom.Xform.Define(stage, f"/{root_name}")
    stage.SetDefaultPrim(root.GetPrim())
    Usd.ModelAPI(root.GetPrim()).SetKind(Kind.Tokens.component)
    root.GetPrim().GetReferences().AddReference(f"./{rel_source}")
    baked_prim = (UsdSkel.Root if skinned else UsdGeom.Scope).Define(
        stage, f"/{root_name}/Baked").GetPrim()
    baked_prim.GetPayloads().AddPayload(f"./{payload_file}")
    default_root = Sdf.Path(default.GetPath()) if default else Sdf.Path(f"/{root_name}")
    if skinned:  # the skeleton relationship, in the root layer's namespace
        skel = Sdf.Path(f"/{root_name}").AppendPath(
            Sdf.Path(baked.skeleton).MakeRelativePath(default_root))
        for i, m in enumerate(baked.meshes, start=1):
            if m.skin:
                over = stage.OverridePrim(f"/{root_name}/Baked/LOD{i}")
                UsdSkel.BindingAPI.Apply(over).CreateSkeletonRel().SetTargets([skel])
    if src_stage.HasAuthoredTimeCodeRange():  # a viewer plays the animation over the same range
        stage.SetStartTimeCode(src_stage.GetStartTimeCode())
        stage.SetEndTimeCode(src_stage.GetEndTimeCode())
        stage.SetTimeCodesPerSecond(src_stage.GetTimeCodesPerSecond())

    vset = root.GetPrim().GetVariantSets().AddVariantSet("LOD")
    n_lod = len(baked.meshes)
    for v in range(n_lod + 1):
        vname = f"LOD{v}"
        vset.AddVariant(vname)
        vset.SetVariantSelection(vname)
        with vset.GetVariantEditContext():
            for i in range(1, n_lod + 1):
                img = UsdGeom.Imageable(stage.OverridePrim(f"/{root_name}/Baked/LOD{i}"))
                img.CreateVisibilityAttr(
                    UsdGeom.Tokens.inherited if i == v else UsdGeom.Tokens.invisible
                )
            for mp in original_mesh_paths:
                rel = Sdf.Path(mp).MakeRelativePath(default_root)
                target = Sdf.Path(f"/{root_name}").AppendPath(rel)
                img = UsdGeom.Imageable(stage.OverridePrim(target))
                img.CreateVisibilityAttr(
                    UsdGeom.Tokens.inherited if v == 0 else UsdGeom.Tokens.invisible
                )
    # the asset as authored by default: a client without a variant picker (Blender's
    # importer) shows the original, not a LOD it did not ask for
    vset.SetVariantSelection("LOD0")
    # issue 22 (texelbake.bakedvariants): a proxy outside the payload, the asset variant
    # selections the bake was made for, and other asset variants shown as authored
    selections = bakedvariants.source_variant_selections(source_copy)
    if n_lod:
        last = baked.meshes[-1]
        motion = bakedvariants.proxy_motion(stage, f"/{root_name}/Baked/LOD{n_lod}",
                                            last.time_codes, last.points_over_time,
                                            bool(last.skin))
        bakedvariants.author_proxy(stage, root_name, last.vertices, last.faces, motion)
        bakedvariants.author_variant_guard(
            stage, root.GetPrim(), selections.get(str(default_root), {}),
            bakedvariants.variant_names(source_copy, str(default_root)),
            [Sdf.Path(f"/{root_name}").AppendPath(Sdf.Path(mp).MakeRelativePath(default_root))
             for mp in original_mesh_paths])
    stage.GetRootLayer().customLayerData = {"texelbake": _plain_json(
        {**baked.metadata, "variantSelections": selections})}
    if n_lod:  # with payloads unloaded, clients size the asset by this: every LOD inside it,
        # and the proxy at every time code (an animated asset moves beyond its rest bounds)
        lo, hi = _lod_extent(stage, root.GetPrim(), vset, n_lod)
        UsdGeom.ModelAPI(root.GetPrim()).SetExtentsHint(
            extent_of(np.concatenate([np.stack([lo, hi])] + [pts for _, pts in motion])))
        vset.SetVariantSelection("LOD0")
    _commit_stage(stage, root_file)
    return root_file


def _lod_extent(stage: Usd.Stage, prim: Usd.Prim, vset: Usd.VariantSet, n_lod: int
                ) -> tuple[np.ndarray, np.ndarray]:
    """The union of `prim`'s untransformed bounds under every LOD variant (the original and
    each M_i), default purpose: what `extentsHint` must cover whichever LOD is selected."""
    cache = UsdGeom.BBoxCache(Usd.TimeCode.Default(), [UsdGeom.Tokens.default_],
                              useExtentsHint=False)
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    for v in range(n_lod + 1):  # a loop over the few LODs
        vset.SetVariantSelection(f"LOD{v}")
        cache.Clear()
        box = cache.ComputeUntransformedBound(prim).ComputeAlignedRange()
        if not box.IsEmpty():
            lo = np.minimum(lo, np.asarray(box.GetMin(), dtype=np.float64))
            hi = np.maximum(hi, np.asarray(box.GetMax(), dtype=np.float64))
    if not np.all(np.isfinite(lo) & np.isfinite(hi)):
        raise AssetError("the baked asset has no bounds under any LOD (empty meshes?)",
                         path=str(prim.GetPath()))
    return lo, hi


def _plain_json(obj: Any) -> Any:
    """customLayerData takes dicts, strings, numbers and typed arrays: round trip through JSON
    (NaN/inf written as strings), lists become Vt string / double arrays."""
    plain = json.loads(
        json.dumps(obj, default=lambda o: o.item() if hasattr(o, "item") else str(o)),
        parse_constant=lambda c: c,
    )

    def convert(x: Any) -> Any:
        if isinstance(x, dict):
            return {k: convert(v) for k, v in x.items() if v is not None}
        if isinstance(x, list):
            if all(isinstance(v, str) for v in x):
                return Vt.StringArray(x)
            if all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in x):
                return Vt.DoubleArray([float(v) for v in x])
            return Vt.StringArray([json.dumps(v) for v in x])
        return x

    return convert(plain)


# --------------------------------------------------------------------------- reading


def _read_arrays(prim: Usd.Prim) -> dict[str, np.ndarray]:
    out: dict[str, np.ndarray] = {}
    for attr in prim.GetAttributes():
        full = attr.GetName()
        if not full.startswith(_NS) or full.endswith(":shape"):
            continue
        name = full[len(_NS):]
        tname = str(attr.GetTypeName())
        if tname not in _FROM_USD:
            continue
        shape_attr = prim.GetAttribute(f"{full}:shape")
        shape = tuple(int(x) for x in shape_attr.Get()) if shape_attr else None
        value = attr.Get()
        arr: np.ndarray = np.array(value, dtype=_FROM_USD[tname]) if value is not None \
            else np.zeros(0, _FROM_USD[tname])
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
    wrote none: bakes before issue 21). AssetError naming the file when its channels are not
    `filtered_maps.CHANNELS`."""
    from texelbake.filtered_maps import CHANNELS
    from texelbake.imageio import read_pixels

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
    from texelbake.imageio import read_pixels, srgb_to_linear

    if not path.is_file():
        return np.zeros((0, 0, 3), np.float32)
    px = read_pixels(path)[0][..., :3].astype(np.float64)
    if srgb:
        px = srgb_to_linear(px.astype(np.float32)).astype(np.float64)
    return px


def atomic_json(path: Path, obj: Any) -> None:
    atomic_write_bytes(path, json.dumps(obj, indent=2, sort_keys=True,
                                        default=lambda o: o.item() if hasattr(o, "item")
                                        else str(o)).encode())
