"""Asset-path safety: every asset path of every layer resolves inside the asset's folder (or its
`.usdz` package); absolute paths, URLs, `..` escapes and missing files are rejected."""

from __future__ import annotations

import os
import posixpath
import re
import zipfile
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from texelbake.asset.values import first_line
from texelbake.errors import AssetError, AssetPathError

# "scheme:" with a scheme of >= 2 characters is a URL ("C:" alone is a Windows drive).
USD_EXTENSIONS = (".usd", ".usda", ".usdc", ".usdz")

_URL_RE = re.compile(r"^[A-Za-z][A-Za-z0-9+.\-]+:")
_DRIVE_RE = re.compile(r"^[A-Za-z]:")


@dataclass(frozen=True)
class _Loc:
    """Where a layer or file lives: on disk (`member` None) or inside a `.usdz` package."""

    file: str  # absolute real path of the file on disk (the package for package members)
    member: str | None = None  # posix path inside the package

    @property
    def identifier(self) -> str:
        return self.file if self.member is None else f"{self.file}[{self.member}]"


def _zip_members(package: str) -> list[str]:
    try:
        with zipfile.ZipFile(package) as zf:
            return [n for n in zf.namelist() if not n.endswith("/")]
    except (OSError, zipfile.BadZipFile) as exc:
        raise AssetError(f"cannot read the .usdz package: {exc}", path=package) from exc


def _first_layer_member(package: str) -> str:
    members = _zip_members(package)
    for name in members:  # the usdz spec: the first file is the root layer
        if name.lower().endswith(USD_EXTENSIONS[:3]):
            return name
    raise AssetError("the .usdz package holds no USD layer", path=package)


def _iter_asset_values(value: Any) -> Iterator[tuple[str, bool]]:
    """(asset path, is a composition arc) for every asset path inside a metadata or attribute
    value (nested dicts, lists; reference / payload list ops are arcs)."""
    from pxr import Sdf

    if isinstance(value, Sdf.AssetPath):
        yield value.path, False
    elif isinstance(value, Sdf.AssetPathArray):
        for v in value:
            yield v.path, False
    elif isinstance(value, (Sdf.ReferenceListOp, Sdf.PayloadListOp)):
        seen: list[str] = []
        for items in (
            value.explicitItems,
            value.addedItems,
            value.prependedItems,
            value.appendedItems,
            value.orderedItems,
            value.deletedItems,
        ):
            for item in items:
                if item.assetPath and item.assetPath not in seen:
                    seen.append(item.assetPath)
        for asset in seen:
            yield asset, True
    elif isinstance(value, dict):
        for k in sorted(value, key=str):
            yield from _iter_asset_values(value[k])
    elif isinstance(value, (list, tuple)):
        for v in value:
            yield from _iter_asset_values(v)


#: spec metadata whose asset paths are layers USD composes (value clips)
_CLIP_KEYS = ("clips", "clipAssetPaths", "clipManifestAssetPath")


def _layer_asset_paths(layer: Any) -> list[tuple[str, str, bool]]:
    """(authored asset path, spec path holding it, is a layer USD composes) for every asset
    path in one Sdf layer: sublayers, references, payloads, clips, asset-valued attributes
    (defaults and time samples) and asset-valued metadata, variants included."""
    from pxr import Sdf

    found: list[tuple[str, str, bool]] = [(p, "<subLayers>", True) for p in layer.subLayerPaths]
    spec_paths: list[Any] = []
    layer.Traverse(Sdf.Path.absoluteRootPath, spec_paths.append)
    for spec_path in sorted(spec_paths, key=str):
        spec = layer.GetObjectAtPath(spec_path)
        if spec is None:
            continue
        if isinstance(spec, Sdf.VariantSpec):
            spec = spec.primSpec
        where = "<layer metadata>" if spec_path == Sdf.Path.absoluteRootPath else str(spec_path)
        for key in spec.ListInfoKeys():
            if key in ("subLayers", "subLayerOffsets"):
                continue
            try:
                value = spec.GetInfo(key)
            except (TypeError, RuntimeError):  # values pxr cannot convert hold no asset paths
                continue
            found.extend((p, where, arc or key in _CLIP_KEYS)
                         for p, arc in _iter_asset_values(value))
    return found


def _path_error(reason: str, asset: str, holder: _Loc, spec: str) -> AssetPathError:
    return AssetPathError(
        f"asset path '{asset}' {reason} (in layer {holder.identifier}, at {spec})",
        path=asset,
        prim=spec,
    )


def _resolve_safe(asset: str, holder: _Loc, root_dir: str, spec: str) -> list[_Loc]:
    """Anchor `asset` to the layer `holder`; raise AssetPathError unless it stays inside.

    Returns the location of the file (every tile for a `<UDIM>` pattern; none for "").
    """
    from pxr import Ar

    if asset == "":
        return []
    if asset.startswith("`"):
        raise _path_error("is an expression; expressions are not allowed", asset, holder, spec)
    if _URL_RE.match(asset):
        raise _path_error("is a URL; only relative paths inside the asset are allowed",
                          asset, holder, spec)
    if asset.startswith(("/", "\\")) or _DRIVE_RE.match(asset):
        raise _path_error("is absolute; only relative paths inside the asset are allowed",
                          asset, holder, spec)
    inner: str | None = None
    outer = asset
    if Ar.IsPackageRelativePath(asset):
        outer, inner = Ar.SplitPackageRelativePathOuter(asset)
    if holder.member is not None:
        # inside a package: anchored to the holding member, must stay inside the package
        member = posixpath.normpath(posixpath.join(posixpath.dirname(holder.member), outer))
        if member == ".." or member.startswith("../"):
            raise _path_error("escapes the .usdz package", asset, holder, spec)
        members = _zip_members(holder.file)
        if "<UDIM>" in member:
            pattern = re.compile(re.escape(member).replace("<UDIM>", r"\d{4}") + "$")
            tiles = [_Loc(holder.file, m) for m in sorted(members) if pattern.match(m)]
            if not tiles:
                raise _path_error("matches no UDIM tile in the package", asset, holder, spec)
            return tiles
        if member not in members:
            raise _path_error("does not exist in the package", asset, holder, spec)
        if inner is not None or member.lower().endswith(".usdz"):
            raise _path_error("nests a .usdz package inside a package (not supported)",
                              asset, holder, spec)
        return [_Loc(holder.file, member)]
    target = os.path.realpath(os.path.join(os.path.dirname(holder.file), outer))
    if os.path.commonpath([target, root_dir]) != root_dir:
        raise _path_error(f"escapes the asset's folder {root_dir}", asset, holder, spec)
    if "<UDIM>" in target:
        folder, name = os.path.split(target)
        pattern = re.compile(re.escape(name).replace("<UDIM>", r"\d{4}") + "$")
        names = sorted(os.listdir(folder)) if os.path.isdir(folder) else []
        tiles = [_Loc(os.path.join(folder, n)) for n in names if pattern.match(n)]
        if not tiles:
            raise _path_error("matches no UDIM tile", asset, holder, spec)
        return tiles
    if not os.path.isfile(target):
        raise _path_error("does not exist", asset, holder, spec)
    if inner is not None:
        if inner not in _zip_members(target):
            raise _path_error("does not exist in the package", asset, holder, spec)
        return [_Loc(target, inner)]
    return [_Loc(target)]


def _open_layer(loc: _Loc) -> Any:
    from pxr import Sdf, Tf

    try:
        layer = Sdf.Layer.FindOrOpen(loc.identifier)
    except Tf.ErrorException as exc:
        raise AssetError(f"pxr cannot open the layer: {first_line(exc)}",
                         path=loc.identifier) from exc
    if layer is None:
        raise AssetError("pxr cannot open the layer", path=loc.identifier)
    return layer


def check_asset_paths(path: str | Path) -> list[str]:
    """Check every asset path of an asset before it is composed; return the bundle's files.

    Walks the root layer, its sublayers, references, payloads, clips and every asset-valued
    attribute or metadata value (textures, MERL files), layer by layer with `Sdf.Layer` (parsing
    only: no composition, no resolver). Each path is anchored to the layer holding it and
    checked *before* that layer is opened, so a hostile reference is never read.

    path : the root layer (`.usda` / `.usdc` / `.usd` / `.usdz`)
    returns : sorted absolute paths of the files on disk the asset uses, the root included
        (for a `.usdz`, the package itself: its members live inside it)
    raises : AssetPathError naming the asset path and the layer / spec holding it, for absolute
        paths, URLs (`scheme:`), paths escaping the root layer's folder (or the package),
        path expressions, and files that do not exist; AssetError for an unreadable layer.
    """
    root = Path(path)
    if not root.is_file():
        raise AssetPathError("asset file does not exist", path=str(path))
    root_real = os.path.realpath(root)
    root_dir = os.path.dirname(root_real)
    start = (
        _Loc(root_real, _first_layer_member(root_real))
        if root_real.lower().endswith(".usdz")
        else _Loc(root_real)
    )
    files: set[str] = {root_real}
    visited: set[_Loc] = set()
    stack = [start]
    while stack:
        loc = stack.pop()
        if loc in visited:
            continue
        visited.add(loc)
        if loc.member is None and loc.file.lower().endswith(".usdz"):
            stack.append(_Loc(loc.file, _first_layer_member(loc.file)))
            continue
        layer = _open_layer(loc)
        for asset, spec, is_layer in _layer_asset_paths(layer):
            for target in _resolve_safe(asset, loc, root_dir, spec):
                files.add(target.file)
                name = target.member if target.member is not None else target.file
                if is_layer or name.lower().endswith(USD_EXTENSIONS):
                    stack.append(target)  # checked above, so safe to open as a layer
    return sorted(files)
