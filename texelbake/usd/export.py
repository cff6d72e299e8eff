"""One LOD of a baked asset as a self-contained file, for tools without variant support
(`texelbake export BAKED --lod N -o FILE`).

The baked root selects a LOD through its `LOD` variant set; many clients (Blender's importer,
glTF converters, game-engine importers) have no variant picker and, importing every prim,
would stack the LODs on each other. The export selects LOD N, flattens the composed stage into
one layer and keeps only what that LOD shows:

- LOD0 is the asset as authored: the `Baked` scope (LOD meshes, CPM arrays) and the `Proxy` are
  dropped (every export drops the proxy).
- LOD N >= 1: every prim the variant hid (the original meshes, the other LODs) is dropped, as
  are the CPM arrays, texelbake's own shaders inside `Baked` (the CPM and BTF render-context
  shaders, which only texelbake reads) with the material outputs that lead to them, and
  materials no remaining prim binds. The UsdPreviewSurface fallback stays.
- The USD LOD schema (`texelbake.usd.lodschema`: the heuristic, `LODRootAPI` on `Baked` and its
  empty `LOD0` item) selects among LODs; with one LOD in the file it is dropped.

Texture files are copied beside the output (`<stem>_maps/`, paths made relative) for `.usda`
and `.usdc`, or packed into the archive for `.usdz` (`UsdUtils.CreateNewUsdzPackage`). Files
are written atomically (`texelbake.io.atomic`).
"""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

from pxr import Sdf, Usd, UsdGeom, UsdUtils

from texelbake.errors import AssetError, SettingsError
from texelbake.io.atomic import atomic_path
from texelbake.usd.lodschema import HEURISTIC_NAME
from texelbake.usd.shaderdefs import SOURCE_TYPE

SUFFIXES = (".usda", ".usdc", ".usdz")


def export_lod(baked_root: str | Path, lod: int, out: str | Path) -> Path:
    """Write LOD `lod` of the baked asset at `baked_root` to `out` (.usda, .usdc or .usdz).
    Raises SettingsError naming the field for a bad LOD index or suffix; AssetError when the
    file is not a baked asset. Returns the written path."""
    baked_root, out = Path(baked_root), Path(out)
    if out.suffix not in SUFFIXES:
        raise SettingsError(f"field 'output': {str(out)!r} must end in one of {SUFFIXES}")
    stage = Usd.Stage.Open(str(baked_root))
    if stage is None:
        raise AssetError("cannot open the baked asset", path=str(baked_root))
    root = stage.GetDefaultPrim()
    if not root or not root.GetVariantSets().HasVariantSet("LOD"):
        raise AssetError("not a baked asset: its default prim has no LOD variant set",
                         path=str(baked_root))
    vset = root.GetVariantSets().GetVariantSet("LOD")
    names = vset.GetVariantNames()
    if not names:
        raise AssetError("not a baked asset: its default prim has no LOD variant set",
                         path=str(baked_root))
    if f"LOD{int(lod)}" not in names:
        raise SettingsError(f"field 'lod': {lod} is not one of the asset's LODs "
                            f"(0..{len(names) - 1})")
    vset.SetVariantSelection(f"LOD{int(lod)}")
    layer = stage.Flatten()
    _prune(layer, root.GetPath(), int(lod))
    with tempfile.TemporaryDirectory(dir=out.parent if out.parent.exists() else None) as tmp:
        work = Path(tmp)
        maps_dir = f"{out.stem}_maps"
        copied = _localize_assets(layer, work / maps_dir, maps_dir)
        if out.suffix == ".usdz":
            flat = work / f"{out.stem}.usdc"
            layer.Export(str(flat))
            with atomic_path(out) as dest:
                if not UsdUtils.CreateNewUsdzPackage(Sdf.AssetPath(str(flat)), str(dest)):
                    raise AssetError("could not write the usdz package", path=str(out))
        else:
            if copied:
                final_maps = out.parent / maps_dir
                final_maps.mkdir(parents=True, exist_ok=True)
                for f in sorted((work / maps_dir).iterdir()):  # a loop over a few maps
                    with atomic_path(final_maps / f.name) as dest:
                        shutil.copyfile(f, dest)
            with atomic_path(out) as dest:
                if not layer.Export(str(dest)):
                    raise AssetError("could not write the exported layer", path=str(out))
    return out


def _prune(layer: Sdf.Layer, root: Sdf.Path, lod: int) -> None:
    """Drop what LOD `lod` does not show (module docstring), in place."""
    baked = root.AppendChild("Baked")
    # the proxy (texelbake.usd.variants) is for a stage with payloads unloaded: one LOD is
    # the whole file here
    drop: list[Sdf.Path] = [root.AppendChild("Proxy")] if layer.GetPrimAtPath(
        root.AppendChild("Proxy")) else []
    # the LOD schema (texelbake.usd.lodschema) selects among LODs: one LOD is the whole file
    heuristic = root.AppendChild(HEURISTIC_NAME)
    if layer.GetPrimAtPath(heuristic):
        drop.append(heuristic)
    if lod == 0:
        drop.append(baked)
    else:
        drop.append(baked.AppendChild("LOD0"))
        _drop_lod_root(layer, baked)
        drop.append(baked.AppendChild("CPM"))

        def visit(spec: Sdf.PrimSpec) -> None:
            vis = spec.attributes.get(UsdGeom.Tokens.visibility)
            if vis is not None and vis.default == UsdGeom.Tokens.invisible:
                drop.append(spec.path)
                return
            if spec.typeName == "Shader" and spec.path.HasPrefix(baked):
                ident = spec.attributes.get("info:id")
                if spec.attributes.get(f"info:{SOURCE_TYPE}:sourceAsset") is not None or (
                        ident is not None and str(ident.default).startswith("texelbake:")):
                    drop.append(spec.path)
                    return
            for child in spec.nameChildren:
                visit(child)

        for top in layer.rootPrims:
            visit(top)
    _remove(layer, drop)
    if lod:
        _drop_texelbake_outputs(layer, baked)
        _drop_unbound_materials(layer)


def _drop_lod_root(layer: Sdf.Layer, baked: Sdf.Path) -> None:
    """`LODRootAPI` and its `lod:` properties off the `Baked` prim spec."""
    spec = layer.GetPrimAtPath(baked)
    if spec is None:
        return
    schemas = spec.GetInfo("apiSchemas") if spec.HasInfo("apiSchemas") else None
    if schemas is not None:
        kept = [n for n in schemas.ApplyOperations([]) if n != "LODRootAPI"]
        if kept:
            spec.SetInfo("apiSchemas", Sdf.TokenListOp.CreateExplicit(kept))
        else:
            spec.ClearInfo("apiSchemas")
    for prop in [p for p in spec.properties if p.name.startswith("lod:")]:
        spec.RemoveProperty(prop)
    if spec.HasInfo("primOrder"):
        spec.ClearInfo("primOrder")


def _remove(layer: Sdf.Layer, paths: list[Sdf.Path]) -> None:
    edit = Sdf.BatchNamespaceEdit()
    for p in sorted(set(paths), key=lambda q: -q.pathElementCount):  # deepest first
        if layer.GetPrimAtPath(p):
            edit.Add(p, Sdf.Path.emptyPath)
    if not layer.Apply(edit):
        raise AssetError("could not prune the flattened layer", path=layer.identifier)


def _walk(layer: Sdf.Layer):
    stack = list(layer.rootPrims)
    while stack:  # a walk over prim specs (tens to thousands), not samples
        spec = stack.pop()
        yield spec
        stack.extend(spec.nameChildren)


def _drop_texelbake_outputs(layer: Sdf.Layer, baked: Sdf.Path) -> None:
    """Material outputs of the `texelbake` render context inside `baked` (their shaders are
    gone)."""
    for spec in _walk(layer):
        if spec.typeName == "Material" and spec.path.HasPrefix(baked):
            for name in [a.name for a in spec.attributes if a.name.startswith("outputs:texelbake:")]:
                spec.RemoveProperty(spec.attributes[name])


def _drop_unbound_materials(layer: Sdf.Layer) -> None:
    bound = set()
    for spec in _walk(layer):
        rel = spec.relationships.get("material:binding")
        if rel is not None:
            bound.update(rel.targetPathList.GetAddedOrExplicitItems())
    unused = [s.path for s in _walk(layer)
              if s.typeName == "Material" and s.path not in bound]
    _remove(layer, unused)


def _localize_assets(layer: Sdf.Layer, maps: Path, rel_dir: str) -> list[Path]:
    """Copy every file an asset-valued attribute names into `maps` and point the attribute at
    `./<rel_dir>/<name>`. Returns the copies."""
    copied: dict[str, Path] = {}
    for spec in _walk(layer):
        for attr in spec.attributes:
            if attr.typeName != Sdf.ValueTypeNames.Asset or not attr.default:
                continue
            src = Path(attr.default.resolvedPath or attr.default.path)
            if not src.is_file():
                raise AssetError(f"{attr.path}: file not found", path=str(src))
            if str(src) not in copied:
                maps.mkdir(parents=True, exist_ok=True)
                dest = maps / src.name
                if dest.exists() and dest.read_bytes() != src.read_bytes():
                    dest = maps / f"{len(copied)}_{src.name}"
                shutil.copyfile(src, dest)
                copied[str(src)] = dest
            attr.default = Sdf.AssetPath(f"./{rel_dir}/{copied[str(src)].name}")
    return list(copied.values())
