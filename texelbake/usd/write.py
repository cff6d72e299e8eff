"""Writing the baked folder: maps, the payload layer (crate) and the root layer with its LOD
variants (`texelbake.usd.baked` describes the folder)."""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from pxr import Gf, Kind, Sdf, Usd, UsdGeom, UsdShade, UsdSkel, Vt

from schemas.settings import BakeSettings
from texelbake.errors import AssetError, ShapeError
from texelbake.io.atomic import replace
from texelbake.usd import lodschema, variants
from texelbake.usd.baked import ARRAY_NS, USD_ARRAY_TYPES, BakedAsset
from texelbake.usd.fallback import author_preview_material, fallback_material_path
from texelbake.usd.lodmesh import author_mesh, extent_of
from texelbake.usd.shaderdefs import write_definitions


def author_array(prim: Usd.Prim, name: str, arr: np.ndarray) -> None:
    arr = np.asarray(arr)
    key = arr.dtype.name
    if key not in USD_ARRAY_TYPES:
        raise ShapeError(f"payload array {name!r}: unsupported dtype {arr.dtype}")
    vtype, vt = USD_ARRAY_TYPES[key]
    flat = np.ascontiguousarray(arr.reshape(-1))
    if not flat.flags.aligned:
        # an array mapped from an artifact (`store.read_npz(mmap=True)`) lies where its zip
        # member does: unaligned, numpy exports it with the format '=d', which Vt.FromNumpy
        # refuses ("Unsupported format"); an aligned copy is what it reads
        flat = flat.copy()
    value = vt(flat.tolist()) if key in ("bool", "uint8") else vt.FromNumpy(flat)
    prim.CreateAttribute(f"{ARRAY_NS}{name}", vtype, custom=True).Set(value)
    prim.CreateAttribute(f"{ARRAY_NS}{name}:shape", Sdf.ValueTypeNames.IntArray, custom=True).Set(
        Vt.IntArray([int(x) for x in arr.shape])
    )


def _author_arrays(prim: Usd.Prim, arrays: dict[str, np.ndarray]) -> None:
    for name in sorted(arrays):
        author_array(prim, name, arrays[name])


def _write_maps(out_dir: Path, baked: BakedAsset) -> dict[str, Any]:
    """Write every map file of the bundle; returns the file names the materials use."""
    from texelbake.baselines.filtered_maps import CHANNELS
    from texelbake.io.images import write_pixels

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
        files["fallback_normals"] = []
        if fb.get("normal") is not None:  # the fallback's own, finer than the baseline's
            files["fallback_normal"] = f"{name}_fallback_normal.png"
            _write_png(out_dir / files["fallback_normal"], 0.5 * (np.asarray(fb["normal"]) + 1.0),
                       srgb=False)
            # each LOD after LOD1 its own, in its own tangent frames
            for i, img in enumerate(fb.get("lod_normals", [])[1:], start=2):
                files["fallback_normals"].append(f"{name}_fallback_normal_lod{i}.png")
                _write_png(out_dir / files["fallback_normals"][-1],
                           0.5 * (np.asarray(img) + 1.0), srgb=False)
        if fb.get("metallic") is not None:  # metals beside dielectrics: per texel
            files["metallic"] = f"{name}_metallic.png"
            _write_png(out_dir / files["metallic"], np.asarray(fb["metallic"])[..., None],
                       srgb=False)
        if fb.get("opacity") is not None:  # cut-outs: what is left of each texel
            files["opacity"] = f"{name}_opacity.png"
            _write_png(out_dir / files["opacity"], np.asarray(fb["opacity"])[..., None],
                       srgb=False)
        for i, r in enumerate(fb["roughness"], start=1):
            files["roughness"].append(f"{name}_roughness_lod{i}.png")
            _write_png(out_dir / files["roughness"][-1], np.asarray(r)[..., None], srgb=False)
        # fitted: each LOD its own diffuse and specular colour (specular workflow)
        for key in ("diffuse", "specular"):
            files[key] = []
            for i, img in enumerate(fb.get(key) or [], start=1):
                files[key].append(f"{name}_{key}_lod{i}.png")
                _write_png(out_dir / files[key][-1], np.asarray(img), srgb=True)
        # fitted: what the fit could not reproduce, per texel of the level its gain is fitted
        # on (relative residual; NaN where no sample had a target), for a person to look at
        for i, img in enumerate(fb.get("residual") or [], start=1):
            write_pixels(out_dir / f"{name}_fit_residual_lod{i}.exr",
                         np.asarray(img, np.float32)[..., None], "float", channel_names=("Y",))
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
    from texelbake.io.images import write_png

    write_png(path, rgb, srgb=srgb)


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
    write_definitions(out_dir)  # the CPM and BTF shaders name it (texelbake.usd.shaderdefs)

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
    place = np.asarray(baked.meshes[0].skin.get("xform", np.eye(4)) if skinned else np.eye(4),
                       dtype=np.float64)
    if not np.array_equal(place, np.eye(4)):  # model.SkinData.placement
        UsdGeom.Xformable(baked_root).AddTransformOp().Set(Gf.Matrix4d(place.tolist()))
    cpm_scope = UsdGeom.Scope.Define(pstage, "/Baked/CPM")
    _author_arrays(cpm_scope.GetPrim(), baked.arrays)
    for lvl, arrays in enumerate(baked.levels):
        scope = UsdGeom.Scope.Define(pstage, f"/Baked/CPM/L{lvl:02d}")
        _author_arrays(scope.GetPrim(), arrays)
    UsdGeom.Scope.Define(pstage, "/Baked/Looks")
    for i, mesh in enumerate(baked.meshes, start=1):
        if baked.fallback:  # one fallback per LOD: its roughness is widened for that LOD
            fitted = bool(files["diffuse"])
            mat = author_preview_material(
                pstage, fallback_material_path(i),
                f"./{files['diffuse'][i - 1]}" if fitted else f"./{files['base']}",
                f"./{files['fallback_normal']}" if i < 2 or not files["fallback_normals"]
                else f"./{files['fallback_normals'][i - 2]}",
                "/Baked/CPM", f"./{files['roughness'][i - 1]}", f"./{files['occlusion']}",
                baked.fallback.get("constants"),
                specular_file=(f"./{files['specular'][i - 1]}" if files["specular"]
                               else None),
                opacity_file=f"./{files['opacity']}" if "opacity" in files else None,
                metallic_file=f"./{files['metallic']}" if "metallic" in files else None)
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
            if n_lod:  # the LOD schema's default item follows the selection
                lodschema.author_variant_index(stage, baked_prim.GetPath(), v)
    # the asset as authored by default: a client without a variant picker (Blender's
    # importer) shows the original, not a LOD it did not ask for
    vset.SetVariantSelection("LOD0")
    # (texelbake.usd.variants): a proxy outside the payload, the asset variant
    # selections the bake was made for, and other asset variants shown as authored
    selections = variants.source_variant_selections(source_copy)
    if n_lod:
        last = baked.meshes[-1]
        motion = variants.proxy_motion(stage, f"/{root_name}/Baked/LOD{n_lod}",
                                            last.time_codes, last.points_over_time,
                                            bool(last.skin))
        variants.author_proxy(stage, root_name, last.vertices, last.faces, motion)
        variants.author_variant_guard(
            stage, root.GetPrim(), selections.get(str(default_root), {}),
            variants.variant_names(source_copy, str(default_root)),
            [Sdf.Path(f"/{root_name}").AppendPath(Sdf.Path(mp).MakeRelativePath(default_root))
             for mp in original_mesh_paths])
    stage.GetRootLayer().customLayerData = {"texelbake": _plain_json(
        {**baked.metadata, "variantSelections": selections})}
    if n_lod:  # with payloads unloaded, clients size the asset by this: every LOD inside it,
        # and the proxy at every time code (an animated asset moves beyond its rest bounds)
        lo, hi = _lod_extent(stage, root.GetPrim(), vset, n_lod)
        hint = extent_of(np.concatenate([np.stack([lo, hi])] + [pts for _, pts in motion]))
        UsdGeom.ModelAPI(root.GetPrim()).SetExtentsHint(hint)
        vset.SetVariantSelection("LOD0")
        # the USD LOD schema beside the variant set (texelbake.usd.lodschema)
        lodschema.author_lod_root(stage, root.GetPrim(), n_lod,
                                  baked.metadata.get("settings", {}).get("lod_switch_px")
                                  or BakeSettings().lod_switch_px, np.asarray(hint))
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
