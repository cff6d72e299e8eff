"""Asset-path safety: every asset path the bake reads resolves inside the asset's folder (or its
`.usdz` package); absolute paths, URLs, `..` escapes and missing layers are rejected, paths only
unselected variants name are listed as unreachable, missing textures as missing."""

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
#: MaterialX documents: composed through their translation (`texelbake.asset.mtlx_document`)
MTLX_EXTENSION = ".mtlx"

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


@dataclass(frozen=True)
class AssetScan:
    """What `scan_asset_paths` found.

    files : sorted absolute paths of the files on disk the asset names (see `check_asset_paths`)
    unreachable : "'asset' (in layer L, at spec)" for every path only unselected variants name:
        never read by the bake
    missing : the same for textures (non-layer paths) inside the asset that do not exist
    mtlx : (identifier of the layer holding the arc, the arc's asset path, the document's
        file) per MaterialX document the layers name
    unreachable_only : (layer identifier, asset path) for paths every use of which in that
        layer is unreachable (what the upload check leaves alone)
    """

    files: tuple[str, ...]
    unreachable: tuple[str, ...] = ()
    missing: tuple[str, ...] = ()
    mtlx: tuple[tuple[str, str, str], ...] = ()
    unreachable_only: tuple[tuple[str, str], ...] = ()


@dataclass(frozen=True)
class _Use:
    """One authored asset path: where it is, whether a variant conditions it, its problem."""

    holder: _Loc
    spec: str
    asset: str
    conditional: bool
    layer_like: bool
    error: AssetError | None

    def describe(self) -> str:
        return f"'{self.asset}' (in layer {self.holder.identifier}, at {self.spec})"

    def reached(self, prims: set[tuple[str, str]], layers: set[str]) -> bool:
        """Does the composed stage use the spec holding this path?"""
        from pxr import Sdf

        key = self.holder.identifier
        if self.spec.startswith("<"):  # sublayers, layer metadata: the layer itself
            return key in layers
        return (key, str(Sdf.Path(self.spec).GetPrimPath())) in prims


def _is_layer_name(asset: str) -> bool:
    name = asset.split("[", 1)[0].lower()
    return name.endswith((*USD_EXTENSIONS, MTLX_EXTENSION))


def _anchored(use: _Use) -> str:
    """The identifier composition would open for a layer arc (what muting names)."""
    asset = use.asset
    if _URL_RE.match(asset) or asset.startswith(("/", "\\")) or _DRIVE_RE.match(asset) \
            or use.holder.member is not None:
        return asset
    return os.path.normpath(os.path.join(os.path.dirname(use.holder.file), asset))


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


class MissingPathError(AssetPathError):
    """An asset path that stays inside the asset but names no file (or no UDIM tile)."""


def _path_error(reason: str, asset: str, holder: _Loc, spec: str) -> AssetPathError:
    kind = MissingPathError if reason.startswith(("does not exist", "matches no UDIM")) \
        else AssetPathError
    return kind(
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

    if loc.member is None and loc.file.lower().endswith(MTLX_EXTENSION):
        from texelbake.asset.mtlx_document import translated_layer

        return translated_layer(loc.file, [])

    try:
        layer = Sdf.Layer.FindOrOpen(loc.identifier)
    except Tf.ErrorException as exc:
        raise AssetError(f"pxr cannot open the layer: {first_line(exc)}",
                         path=loc.identifier) from exc
    if layer is None:
        raise AssetError("pxr cannot open the layer", path=loc.identifier)
    return layer


def check_asset_paths(path: str | Path) -> list[str]:
    """The files on disk an asset names, after `scan_asset_paths` accepted it: sorted absolute
    paths, the root included (for a `.usdz`, the package itself: its members live inside it),
    files named only by unselected variants included (the baked root shows them again when a
    client selects that variant).

    raises : as `scan_asset_paths`
    """
    return list(scan_asset_paths(path).files)


def scan_asset_paths(path: str | Path) -> AssetScan:
    """Check every asset path of an asset before it is composed with its selections.

    Walks the root layer, its sublayers, references, payloads, clips, MaterialX documents and
    every asset-valued attribute or metadata value (textures, MERL files), layer by layer with
    `Sdf.Layer` (parsing only). Each path is anchored to the layer holding it and checked
    *before* that layer is opened, so a hostile reference is never read.

    A path authored inside a variant (or in a layer only a variant reaches) is *conditional*:
    whether the bake reads it depends on the variant selections, so its problem waits until
    `texelbake.asset.compose.reached_specs` has composed the stage with every such unsafe target
    muted (never opened). Reached by the selections, its problem is raised as any other;
    otherwise the path is listed in `AssetScan.unreachable` and never read. A texture (any path
    that is not a layer) inside the asset whose file is missing is listed in
    `AssetScan.missing`: ingest warns and uses the texture's fallback.

    path : the root layer (`.usda` / `.usdc` / `.usd` / `.usdz`)
    raises : AssetPathError naming the asset path and the layer / spec holding it, for absolute
        paths, URLs (`scheme:`), paths escaping the root layer's folder (or the package), path
        expressions (refused wherever they are: what they name is known only once composed),
        and layers that do not exist; AssetError for an unreadable layer.
    """
    from texelbake.asset.compose import reached_specs

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
    conditional_of: dict[_Loc, bool] = {}
    uses: list[_Use] = []  # conditional uses, and unconditional missing textures
    plain: set[tuple[str, str]] = set()  # (layer, asset) used outside any variant
    mtlx: list[tuple[str, str, str]] = []
    translated: set[str] = set()  # documents that opened (an unreachable one may not)
    stack: list[tuple[_Loc, _Use | None]] = [(start, None)]
    while stack:
        loc, via = stack.pop()
        cond = via is not None and via.conditional
        if loc in conditional_of and (not conditional_of[loc] or cond):
            continue
        conditional_of[loc] = cond
        if loc.member is None and loc.file.lower().endswith(".usdz"):
            stack.append((_Loc(loc.file, _first_layer_member(loc.file)), via))
            continue
        try:
            layer = _open_layer(loc)
        except AssetError as exc:
            if not cond:
                raise
            uses.append(_Use(via.holder, via.spec, via.asset, True, True, exc))  # type: ignore[union-attr]
            continue
        translated.add(loc.file)
        for asset, spec, is_layer in _layer_asset_paths(layer):
            c = cond or "{" in spec  # inside a variant
            error: AssetPathError | None = None
            targets: list[_Loc] = []
            try:
                targets = _resolve_safe(asset, loc, root_dir, spec)
            except AssetPathError as exc:
                if asset.startswith("`"):
                    raise
                error = exc
            layer_like = is_layer or _is_layer_name(asset)
            use = _Use(loc, spec, asset, c, layer_like, error)
            if error is not None and not c and (layer_like
                                                or not isinstance(error, MissingPathError)):
                raise error
            if c or error is not None:
                uses.append(use)
            if not c:
                plain.add((loc.identifier, asset))
            for target in targets:
                files.add(target.file)
                name = target.member if target.member is not None else target.file
                if name.lower().endswith(MTLX_EXTENSION):
                    if target.member is not None:
                        raise _path_error("is a MaterialX document inside a .usdz package "
                                          "(not supported)", asset, loc, spec)
                    mtlx.append((loc.identifier, asset, target.file))
                    stack.append((target, use))
                elif is_layer or name.lower().endswith(USD_EXTENSIONS):
                    stack.append((target, use))  # checked above, so safe to open as a layer
    mtlx = sorted({m for m in mtlx if m[2] in translated})
    unreachable: list[str] = []
    missing: list[str] = []
    skipped: set[tuple[str, str]] = set()
    conditional = [u for u in uses if u.conditional]
    if conditional:
        mute = sorted({_anchored(u) for u in conditional if u.error is not None and u.layer_like})
        prims, layers = reached_specs(str(root), mtlx, mute)
        for u in sorted(conditional, key=lambda u: u.describe()):
            if not u.reached(prims, layers):
                unreachable.append(u.describe())
                skipped.add((u.holder.identifier, u.asset))
                continue
            plain.add((u.holder.identifier, u.asset))
            if u.error is not None and (u.layer_like
                                          or not isinstance(u.error, MissingPathError)):
                raise u.error
            elif u.error is not None:
                missing.append(u.describe())
    missing += sorted(u.describe() for u in uses if not u.conditional)
    return AssetScan(files=tuple(sorted(files)), unreachable=tuple(unreachable),
                     missing=tuple(sorted(missing)),
                     mtlx=tuple(mtlx),
                     unreachable_only=tuple(sorted(skipped - plain)))
