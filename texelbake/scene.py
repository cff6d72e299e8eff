"""USD ingest: a USD asset (`.usda` / `.usdc` / `.usd` / `.usdz`) -> one immutable AssetModel.

Public entry points:

- `check_asset_paths(path) -> list[str]`: walks every layer of the asset *as Sdf layers*, before
  any stage is composed, and rejects asset paths that are absolute, URLs, escape the asset's
  folder (or its `.usdz` package) or name files that do not exist. Also used by the upload
  service.
- `load_asset(path, *, time_code=None) -> AssetModel`: flattens transforms, fan-triangulates
  n-gons, reads normals (authored or computed), UVs, material bindings (GeomSubsets included),
  UsdPreviewSurface and texelbake shader networks with their textures, UsdLux distant and
  sphere lights, cameras and time-sampled points.
- `describe(asset) -> str`: the report `texelbake inspect FILE` prints.

The AssetModel fields are documented in `texelbake.model`. This module is pure I/O: nothing
here is from the seeds' equations; the reflectance it hands on is what seed 000 Eq. 1 calls
f_r(x, wi, wo) per sample (a material per face, textures per corner UV).

USD conventions used throughout: USD matrices act on *row* vectors (`p_world = p @ M`,
`M = XformCache.GetLocalToWorldTransform(prim)`); AssetModel stores points in that world space
and cameras as column-vector matrices (`M.T`).
"""

from __future__ import annotations

import os
import posixpath
import re
import tempfile
import warnings
import zipfile
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from texelbake.errors import AssetError, AssetPathError
from texelbake.model import (
    PREVIEW_DEFAULTS,
    SHADER_MEASURED,
    SHADER_MODELS,
    SHADER_PREVIEW,
    AssetModel,
    Camera,
    Light,
    Material,
    Texture,
)
from texelbake.shaderdefs import SHADER_INPUTS
from texelbake.tol import TOL

__all__ = [
    "AssetWarning",
    "DEFAULT_MATERIAL",
    "TEXELBAKE_DEFAULTS",
    "check_asset_paths",
    "describe",
    "load_asset",
    "srgb_to_linear",
]

USD_EXTENSIONS = (".usd", ".usda", ".usdc", ".usdz")

#: defaults for unauthored inputs of texelbake's own shader ids: the Sdr definitions'
#: defaults (texelbake.shaderdefs.SHADER_INPUTS), colours as tuples
TEXELBAKE_DEFAULTS: dict[str, dict[str, Any]] = {
    sid: {name: ("" if type_name == "asset" else default)
          for name, type_name, default in inputs}
    for sid, inputs in SHADER_INPUTS.items()
}

#: the fallback for faces with no bound material: grey Lambert, path ""
def _readonly(params: dict[str, Any]) -> dict[str, Any]:
    """Arrays in material params made read-only (Materials are shared, immutable values)."""
    for value in params.values():
        if isinstance(value, np.ndarray):
            value.flags.writeable = False
    return params


DEFAULT_MATERIAL = Material(path="", model="lambert",
                            params=_readonly({"diffuseColor": np.full(3, 0.18)}))

# UsdUVTexture output name -> channels of the canonical RGBA image
_TEXTURE_OUTPUT_CHANNELS = {
    "rgb": (0, 1, 2),
    "rgba": (0, 1, 2, 3),
    "r": (0,),
    "g": (1,),
    "b": (2,),
    "a": (3,),
}
_WRAP_MODES = ("black", "clamp", "repeat", "mirror")

# "scheme:" with a scheme of >= 2 characters is a URL ("C:" alone is a Windows drive).
_URL_RE = re.compile(r"^[A-Za-z][A-Za-z0-9+.\-]+:")
_DRIVE_RE = re.compile(r"^[A-Za-z]:")


class AssetWarning(UserWarning):
    """A recoverable problem in an asset (dropped faces, unsupported shader network, ...)."""


# --------------------------------------------------------------------------------------------
# asset path safety
# --------------------------------------------------------------------------------------------


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
        raise AssetError(f"pxr cannot open the layer: {_first_line(exc)}",
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


# --------------------------------------------------------------------------------------------
# small helpers
# --------------------------------------------------------------------------------------------


def _first_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split())
    return text[:300]


def _warn(warns: list[str], message: str) -> None:
    warns.append(message)
    warnings.warn(message, AssetWarning, stacklevel=3)


def _matrix(gf_matrix: Any) -> np.ndarray:
    """Gf.Matrix4d -> (4, 4) float64, USD row-vector convention."""
    return np.array(gf_matrix, dtype=np.float64).reshape(4, 4)


def _to_python(value: Any) -> Any:
    """A USD attribute value -> float / int / str / bool / (k,) float64 array."""
    from pxr import Sdf

    if value is None:
        return None
    if isinstance(value, Sdf.AssetPath):
        return value.resolvedPath or value.path
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return float(value)
    if isinstance(value, str):
        return str(value)
    try:
        arr = np.array(value, dtype=np.float64)
    except (TypeError, ValueError):
        return str(value)
    return arr


def _coerce_like(value: Any, default: Any) -> Any:
    """Shape an authored value like its default (colours as (3,) float64 arrays)."""
    value = _to_python(value)
    if isinstance(default, tuple):
        arr = np.asarray(value, dtype=np.float64).reshape(-1)
        if arr.shape[0] == 1:
            arr = np.repeat(arr, len(default))
        return arr
    if isinstance(default, bool):
        return bool(value)
    if isinstance(default, int) and not isinstance(value, str):
        return int(np.asarray(value).reshape(-1)[0])
    if isinstance(default, float) and not isinstance(value, str):
        return float(np.asarray(value).reshape(-1)[0])
    return value


def _default_param(default: Any) -> Any:
    return np.asarray(default, dtype=np.float64) if isinstance(default, tuple) else default


def srgb_to_linear(values: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1 sRGB decoding, elementwise.

    values : (...) float32 encoded in [0, 1]
    returns : (...) float32 linear

    Hand-written rather than OpenImageIO's colorconvert: the exact piecewise formula does not
    depend on which OCIO config OIIO finds, and it is three lines.
    """
    v = np.asarray(values, dtype=np.float32)
    return np.where(
        v <= np.float32(0.04045),
        v / np.float32(12.92),
        np.power((np.maximum(v, 0.0) + np.float32(0.055)) / np.float32(1.055), np.float32(2.4)),
    ).astype(np.float32)


# --------------------------------------------------------------------------------------------
# file access (plain files and .usdz members)
# --------------------------------------------------------------------------------------------


def _read_resolved_bytes(resolved: str, prim: str) -> bytes:
    from pxr import Ar

    try:
        if Ar.IsPackageRelativePath(resolved):
            package, member = Ar.SplitPackageRelativePathOuter(resolved)
            with zipfile.ZipFile(package) as zf:
                return zf.read(member)
        return Path(resolved).read_bytes()
    except (OSError, KeyError, zipfile.BadZipFile) as exc:
        raise AssetPathError(f"cannot read '{resolved}': {exc}", path=resolved, prim=prim) from exc


def _load_image(resolved: str, prim: str) -> tuple[np.ndarray, bool, str]:
    """Pixels of an image through OpenImageIO.

    returns : pixels (h, w, c) float32 (row 0 = top), whether the file stores 8-bit channels,
        the file's "wrapmodes" metadata ("" when absent)
    """
    import OpenImageIO as oiio
    from pxr import Ar

    def read(filename: str) -> tuple[np.ndarray, bool, str]:
        inp = oiio.ImageInput.open(filename)
        if inp is None:
            raise AssetError(f"cannot read texture '{resolved}': {oiio.geterror()}",
                             path=resolved, prim=prim)
        try:
            spec = inp.spec()
            is_8bit = spec.format.basetype in (oiio.UINT8, oiio.INT8)
            wrapmodes = str(spec.get_string_attribute("wrapmodes", ""))
            pixels = inp.read_image(0, 0, 0, spec.nchannels, oiio.FLOAT)
        finally:
            inp.close()
        if pixels is None:
            raise AssetError(f"cannot decode texture '{resolved}': {oiio.geterror()}",
                             path=resolved, prim=prim)
        pixels = np.asarray(pixels, dtype=np.float32).reshape(spec.height, spec.width,
                                                              spec.nchannels)
        return pixels, is_8bit, wrapmodes

    if Ar.IsPackageRelativePath(resolved):
        data = _read_resolved_bytes(resolved, prim)
        suffix = Path(Ar.SplitPackageRelativePathInner(resolved)[1]).suffix
        with tempfile.TemporaryDirectory() as tmp:
            local = os.path.join(tmp, "texture" + suffix)
            Path(local).write_bytes(data)
            return read(local)
    if not os.path.isfile(resolved):
        raise AssetPathError(f"texture '{resolved}' does not exist", path=resolved, prim=prim)
    return read(resolved)


def _load_merl(resolved: str, prim: str) -> np.ndarray:
    """A MERL .binary BRDF -> (3, n_th, n_td, n_pd) float64 via `texelbake.brdf.read_merl`
    (channel scales (1, 1.15, 1.66) / 1500 applied; standard files are (3, 90, 90, 180)).

    A file inside a `.usdz` is copied to a temporary file first (the reader takes a path).
    """
    from pxr import Ar

    from texelbake.brdf import read_merl

    def read(filename: str) -> np.ndarray:
        try:
            return np.asarray(read_merl(filename), dtype=np.float64)
        except AssetError as exc:  # re-raised naming the shader prim as well
            raise AssetError(f"{exc} (measured BRDF '{resolved}')", path=resolved,
                             prim=prim) from exc

    if Ar.IsPackageRelativePath(resolved):
        data = _read_resolved_bytes(resolved, prim)
        with tempfile.TemporaryDirectory() as tmp:
            local = os.path.join(tmp, "brdf.binary")
            Path(local).write_bytes(data)
            return read(local)
    if not os.path.isfile(resolved):
        raise AssetPathError(f"measured BRDF '{resolved}' does not exist", path=resolved,
                             prim=prim)
    return read(resolved)


# --------------------------------------------------------------------------------------------
# materials
# --------------------------------------------------------------------------------------------


class _MaterialReader:
    """Reads UsdShade materials into model.Material, caching textures per load."""

    def __init__(self, time: Any, warns: list[str]):
        self.time = time
        self.warns = warns
        self._images: dict[str, tuple[np.ndarray, bool, str]] = {}

    # ---- network helpers -------------------------------------------------------------------
    @staticmethod
    def _source(inp_or_out: Any) -> Any:
        """The attribute that produces this input's / output's value (through node graphs)."""
        attrs = inp_or_out.GetValueProducingAttributes()
        return attrs[0] if attrs else None

    @staticmethod
    def _shader_id(prim: Any) -> str | None:
        from pxr import UsdShade

        shader = UsdShade.Shader(prim)
        if not shader:
            return None
        sid = shader.GetShaderId()
        return str(sid) if sid else None

    def _surface(self, material: Any, context: str) -> tuple[Any, str | None] | None:
        """(shader prim, shader id) feeding the material's surface output for a context."""
        out = material.GetSurfaceOutput(context) if context else material.GetSurfaceOutput()
        if not out or not out.HasConnectedSource():
            return None
        src = self._source(out)
        if src is None:
            return None
        prim = src.GetPrim()
        return prim, self._shader_id(prim)

    # ---- entry -----------------------------------------------------------------------------
    def read(self, material: Any) -> Material:
        mat_path = str(material.GetPath())
        found = self._surface(material, "texelbake")
        if found is not None:
            prim, sid = found
            if sid is not None and sid in SHADER_MODELS:
                return self._read_shader(mat_path, prim, sid)
            _warn(self.warns,
                  f"material {mat_path}: unsupported shader id {sid!r} on "
                  f"outputs:texelbake:surface (shader {prim.GetPath()}); using outputs:surface")
        found = self._surface(material, "")
        if found is None:
            _warn(self.warns, f"material {mat_path}: no surface shader connected; "
                              "using UsdPreviewSurface defaults")
            return self._constant_preview(mat_path, None)
        prim, sid = found
        if sid is not None and sid in SHADER_MODELS:
            return self._read_shader(mat_path, prim, sid)
        _warn(self.warns,
              f"material {mat_path}: unsupported shader network (shader {prim.GetPath()}, id "
              f"{sid!r}); falling back to its constant values")
        return self._constant_preview(mat_path, prim)

    def _constant_preview(self, mat_path: str, prim: Any) -> Material:
        """UsdPreviewSurface defaults overlaid by a foreign shader's constant preview inputs."""
        from pxr import UsdShade

        params = {k: _default_param(v) for k, v in PREVIEW_DEFAULTS.items()}
        if prim is not None:
            shader = UsdShade.Shader(prim)
            for name, default in PREVIEW_DEFAULTS.items():
                inp = shader.GetInput(name) if shader else None
                if inp and inp.GetAttr().HasAuthoredValue():
                    value = inp.GetAttr().Get(self.time)
                    if value is not None:
                        params[name] = _coerce_like(value, default)
        return Material(path=mat_path, model="preview", params=_readonly(params))

    def _read_shader(self, mat_path: str, prim: Any, sid: str) -> Material:
        from pxr import UsdShade

        shader = UsdShade.Shader(prim)
        defaults = PREVIEW_DEFAULTS if sid == SHADER_PREVIEW else TEXELBAKE_DEFAULTS[sid]
        params: dict[str, Any] = {}
        textures: dict[str, Texture] = {}
        for name, default in defaults.items():
            params[name] = _default_param(default)
            inp = shader.GetInput(name)
            if not inp:
                continue
            own = inp.GetAttr().Get(self.time) if inp.GetAttr().HasAuthoredValue() else None
            if own is not None:
                params[name] = _coerce_like(own, default)
            src = self._source(inp)
            if src is None:
                continue
            if UsdShade.Output.IsOutput(src):
                src_prim = src.GetPrim()
                src_id = self._shader_id(src_prim)
                if src_id == "UsdUVTexture":
                    out_name = UsdShade.Output(src).GetBaseName()
                    texture = self._read_texture(src_prim, out_name, mat_path)
                    if texture is not None:
                        textures[name] = texture
                else:
                    _warn(self.warns,
                          f"material {mat_path}: input {name} of shader {prim.GetPath()} is "
                          f"driven by an unsupported node {src_prim.GetPath()} (id {src_id!r}); "
                          "using its constant value")
            else:  # a value from an interface input (material or node graph)
                value = src.Get(self.time)
                if value is not None:
                    params[name] = _coerce_like(value, default)
        if sid == SHADER_MEASURED:
            file_inp = shader.GetInput("file")
            src = self._source(file_inp) if file_inp else None
            asset = src.Get(self.time) if src is not None and not src.GetName().startswith(
                "outputs:") else None
            resolved = asset.resolvedPath if asset is not None else ""
            if not resolved:
                shown = asset.path if asset is not None else ""
                raise AssetPathError(
                    f"measured BRDF file '{shown}' of material {mat_path} does not resolve",
                    path=shown, prim=str(prim.GetPath()))
            params["file"] = resolved
            params["table"] = _load_merl(resolved, str(prim.GetPath()))
        return Material(path=mat_path, model=SHADER_MODELS[sid], params=_readonly(params),
                        textures=textures)

    def _input_value(self, shader: Any, name: str, default: Any) -> Any:
        inp = shader.GetInput(name)
        if not inp:
            return default
        src = self._source(inp)
        if src is None or src.GetName().startswith("outputs:"):
            return default
        value = src.Get(self.time)
        return default if value is None else value

    def _read_texture(self, prim: Any, out_name: str, mat_path: str) -> Texture | None:
        """The Texture a UsdUVTexture output provides; None (with a warning) for UDIM sets."""
        from pxr import UsdShade

        shader = UsdShade.Shader(prim)
        prim_path = str(prim.GetPath())
        asset = self._input_value(shader, "file", None)
        if asset is None or not asset.path:
            raise AssetPathError(f"UsdUVTexture of material {mat_path} has no file",
                                 path="", prim=prim_path)
        if "<UDIM>" in asset.path:
            _warn(self.warns, f"material {mat_path}: UDIM texture '{asset.path}' of {prim_path} "
                              "is not supported; using the input's constant value")
            return None
        resolved = asset.resolvedPath
        if not resolved:
            raise AssetPathError(
                f"texture '{asset.path}' of material {mat_path} does not resolve (missing file)",
                path=asset.path, prim=prim_path)
        if resolved not in self._images:
            self._images[resolved] = _load_image(resolved, prim_path)
        pixels, is_8bit, wrapmodes = self._images[resolved]
        h, w, c = pixels.shape
        # canonical RGBA per the UsdUVTexture spec: grey -> (g, g, g, 1), grey+alpha -> (g, g, g, a)
        if c == 1:
            rgba = np.concatenate([np.repeat(pixels, 3, axis=2), np.ones((h, w, 1), np.float32)], 2)
        elif c == 2:
            rgba = np.concatenate([np.repeat(pixels[..., :1], 3, axis=2), pixels[..., 1:2]], 2)
        elif c == 3:
            rgba = np.concatenate([pixels, np.ones((h, w, 1), np.float32)], 2)
        else:
            rgba = pixels[..., :4]
        color_space = str(self._input_value(shader, "sourceColorSpace", "auto"))
        if color_space == "sRGB" or (color_space == "auto" and is_8bit):
            rgba = np.concatenate([srgb_to_linear(rgba[..., :3]), rgba[..., 3:]], axis=2)
        channels = _TEXTURE_OUTPUT_CHANNELS.get(out_name)
        if channels is None:
            _warn(self.warns, f"material {mat_path}: unknown UsdUVTexture output "
                              f"'{out_name}' of {prim_path}; using rgb")
            channels = _TEXTURE_OUTPUT_CHANNELS["rgb"]
        sel = list(channels)
        scale4 = np.asarray(self._input_value(shader, "scale", (1.0, 1.0, 1.0, 1.0)), np.float64)
        bias4 = np.asarray(self._input_value(shader, "bias", (0.0, 0.0, 0.0, 0.0)), np.float64)
        # scale/bias follow the selected channels, padded with identity values to 4
        scale = tuple(float(x) for x in np.concatenate([scale4[sel], np.ones(4 - len(sel))]))
        bias = tuple(float(x) for x in np.concatenate([bias4[sel], np.zeros(4 - len(sel))]))
        meta_wraps = [m.strip() for m in wrapmodes.split(",")] if wrapmodes else []
        wraps = []
        for axis, key in enumerate(("wrapS", "wrapT")):
            mode = str(self._input_value(shader, key, "useMetadata"))
            if mode == "useMetadata":
                # the file's own wrap metadata when present; otherwise "black" (spec fallback)
                mode = meta_wraps[axis] if axis < len(meta_wraps) else "black"
                mode = {"periodic": "repeat"}.get(mode, mode)
            if mode not in _WRAP_MODES:
                _warn(self.warns, f"material {mat_path}: unknown {key} '{mode}' on {prim_path}; "
                                  "using repeat")
                mode = "repeat"
            wraps.append(mode)
        st_primvar = "st"
        st_inp = shader.GetInput("st")
        src = self._source(st_inp) if st_inp else None
        if src is not None and UsdShade.Output.IsOutput(src):
            reader = UsdShade.Shader(src.GetPrim())
            rid = self._shader_id(src.GetPrim())
            if rid is not None and rid.startswith("UsdPrimvarReader"):
                st_primvar = str(self._input_value(reader, "varname", "st")) or "st"
            else:
                _warn(self.warns, f"material {mat_path}: st of {prim_path} is driven by an "
                                  f"unsupported node {src.GetPrim().GetPath()} (id {rid!r}); "
                                  "using primvar st")
        pixels_out = np.ascontiguousarray(rgba[..., sel], dtype=np.float32)  # (h, w, len(sel))
        pixels_out.flags.writeable = False
        return Texture(
            path=resolved,
            pixels=pixels_out,
            wrap_s=wraps[0],
            wrap_t=wraps[1],
            scale=scale,  # type: ignore[arg-type]
            bias=bias,  # type: ignore[arg-type]
            source_color_space=color_space,
            st_primvar=st_primvar,
        )


# --------------------------------------------------------------------------------------------
# meshes
# --------------------------------------------------------------------------------------------


@dataclass
class _MeshData:
    path: str
    points: np.ndarray  # (n, 3) float64 world
    tris: np.ndarray  # (t, 3) int64 local vertex ids, counter-clockwise
    tri_face: np.ndarray  # (t,) int64 source polygon
    corner_normals: np.ndarray | None  # (t, 3, 3) float64 world unit, None = compute
    corner_uvs: np.ndarray  # (t, 3, 2) float64
    has_uvs: bool
    tri_material: np.ndarray  # (t,) int32
    bad_polygons: int  # polygons with < 3 vertices


def _fan(counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Fan triangulation of polygons given their vertex counts, without a loop per face.

    counts : (F,) int64 faceVertexCounts
    returns : tri_fv (T, 3) int64 face-varying corner indices (into faceVertexIndices),
        tri_face (T,) int64 the polygon of each triangle; polygon i with c_i >= 3 corners yields
        (s, s + k, s + k + 1) for k = 1 .. c_i - 2, s its first corner.
    """
    counts = np.asarray(counts, dtype=np.int64)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
    n_tri = np.maximum(counts - 2, 0)  # (F,)
    tri_face = np.repeat(np.arange(counts.shape[0], dtype=np.int64), n_tri)  # (T,)
    first_tri = np.concatenate([[0], np.cumsum(n_tri)[:-1]]).astype(np.int64)
    k = np.arange(tri_face.shape[0], dtype=np.int64) - first_tri[tri_face] + 1  # (T,)
    s = starts[tri_face]
    return np.stack([s, s + k, s + k + 1], axis=1), tri_face


def _expand(values: np.ndarray, interp: str, tri_fv: np.ndarray, tri_vid: np.ndarray,
            tri_face: np.ndarray, n_points: int, n_faces: int, n_fv: int) -> np.ndarray | None:
    """Primvar values of any interpolation -> (T, 3, k) per triangle corner; None on mismatch."""
    n = values.shape[0]
    if interp == "constant":
        if n < 1:
            return None
        return np.broadcast_to(values[0], (tri_fv.shape[0], 3, values.shape[1])).copy()
    if interp == "uniform":
        return np.repeat(values[tri_face][:, None, :], 3, axis=1) if n == n_faces else None
    if interp in ("vertex", "varying"):
        return values[tri_vid] if n == n_points else None
    if interp == "faceVarying":
        return values[tri_fv] if n == n_fv else None
    return None


def _primvar_values(primvar: Any, time: Any, width: int) -> np.ndarray | None:
    """(k, width) float64 primvar values with indices applied; None when not authored / bad."""
    raw = primvar.Get(time)
    if raw is None:
        return None
    values = np.asarray(raw, dtype=np.float64)
    if values.ndim != 2 or values.shape[1] != width:
        return None
    if primvar.IsIndexed():
        idx = np.asarray(primvar.GetIndices(time), dtype=np.int64)
        if idx.size and (idx.min() < 0 or idx.max() >= values.shape[0]):
            return None
        values = values[idx]
    return values


def _tri_cross(points: np.ndarray, tris: np.ndarray) -> np.ndarray:
    """(t, 3) float64 cross products (p1 - p0) x (p2 - p0): twice the area times the unit
    normal. Written per component: several times faster than np.cross on (t, 3) arrays."""
    p0, p1, p2 = points[tris[:, 0]], points[tris[:, 1]], points[tris[:, 2]]
    e1, e2 = p1 - p0, p2 - p0
    return np.stack([e1[:, 1] * e2[:, 2] - e1[:, 2] * e2[:, 1],
                     e1[:, 2] * e2[:, 0] - e1[:, 0] * e2[:, 2],
                     e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]], axis=1)


def _row_norm(v: np.ndarray) -> np.ndarray:
    return np.sqrt(np.einsum("...j,...j->...", v, v))


def _area_weighted_normals(points: np.ndarray, tris: np.ndarray,
                           cross: np.ndarray | None = None) -> np.ndarray:
    """(t, 3, 3) corner normals: per vertex, the sum of incident triangle cross products.

    points : (n, 3) float64; tris : (t, 3) int64; cross : (t, 3) float64 `_tri_cross` if known
    The cross product is twice the area times the unit normal, so the sum is area-weighted.
    A vertex whose sum vanishes (an isolated degenerate fan, opposite faces) takes the normal
    of each triangle it is a corner of (zero for a degenerate triangle).
    """
    if cross is None:
        cross = _tri_cross(points, tris)
    n = points.shape[0]
    flat = tris.reshape(-1)  # (3t,) every corner adds its triangle's cross product
    acc = np.stack([np.bincount(flat, weights=np.repeat(cross[:, k], 3), minlength=n)
                    for k in range(3)], axis=1)  # (n, 3)
    length = _row_norm(acc)  # (n,)
    ok = length > 0
    vertex_unit = np.zeros_like(acc)
    vertex_unit[ok] = acc[ok] / length[ok, None]
    corner = vertex_unit[tris]  # (t, 3, 3)
    bad_t, bad_c = np.nonzero(~ok[tris])
    if bad_t.size:
        face = cross[bad_t]
        face_len = _row_norm(face)[:, None]
        corner[bad_t, bad_c] = np.divide(face, face_len, out=np.zeros_like(face),
                                         where=face_len > 0)
    return corner


def _skinning_queries(stage: Any, warns: list[str]) -> dict[str, tuple[Any, Any]]:
    """mesh prim path -> (UsdSkel.SkinningQuery, UsdSkel.SkeletonQuery) for skinned meshes.

    Linear-blend (and dual-quaternion) skinning of points is evaluated by UsdSkel itself
    (`SkinningQuery.ComputeSkinnedPoints`); blend shapes are not applied (warning).
    """
    from pxr import Usd, UsdSkel

    out: dict[str, tuple[Any, Any]] = {}
    roots = [p for p in stage.Traverse(Usd.TraverseInstanceProxies(Usd.PrimDefaultPredicate))
             if p.IsA(UsdSkel.Root)]
    if not roots:
        return out
    cache = UsdSkel.Cache()
    for prim in roots:
        root = UsdSkel.Root(prim)
        cache.Populate(root, Usd.PrimDefaultPredicate)
        for binding in cache.ComputeSkelBindings(root, Usd.PrimDefaultPredicate):
            skel_query = cache.GetSkelQuery(binding.GetSkeleton())
            if not skel_query:
                _warn(warns, f"skeleton {binding.GetSkeleton().GetPath()}: invalid; its "
                             "meshes are read unskinned")
                continue
            for sq in binding.GetSkinningTargets():
                path = str(sq.GetPrim().GetPath())
                if not sq.HasJointInfluences():
                    continue
                if sq.HasBlendShapes():
                    _warn(warns, f"mesh {path}: UsdSkel blend shapes are not applied")
                out[path] = (sq, skel_query)
    return out


def _world_points(prim: Any, points: np.ndarray, time: Any, xcache: Any,
                  skin: tuple[Any, Any] | None, source: str) -> tuple[np.ndarray, np.ndarray]:
    """Mesh points (n, 3) float64 in local space -> world (n, 3) float64, and the (3, 3) linear
    part of the frame that took them there.

    Unskinned: the prim's local-to-world transform. Skinned: UsdSkel's skinned points (skel
    space) times the Skeleton's local-to-world (the mesh's own transform does not apply).
    """
    from pxr import Vt

    if skin is None:
        world = _matrix(xcache.GetLocalToWorldTransform(prim))
    else:
        sq, skel_query = skin
        xforms = skel_query.ComputeSkinningTransforms(time)
        skinned = Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(points, dtype=np.float32))
        if xforms is None or not sq.ComputeSkinnedPoints(xforms, skinned, time):
            raise AssetError(f"mesh {prim.GetPath()}: UsdSkel could not skin its points "
                             f"with skeleton {skel_query.GetPrim().GetPath()}",
                             path=source, prim=str(prim.GetPath()))
        points = np.array(skinned, dtype=np.float64).reshape(-1, 3)
        world = _matrix(xcache.GetLocalToWorldTransform(skel_query.GetPrim()))
    return points @ world[:3, :3] + world[3, :3], world[:3, :3]


def _read_mesh(prim: Any, time: Any, xcache: Any, face_materials: np.ndarray | None,
               uv_names: list[str], warns: list[str], source: str,
               skin: tuple[Any, Any] | None = None) -> _MeshData:
    from pxr import UsdGeom

    mesh = UsdGeom.Mesh(prim)
    path = str(prim.GetPath())
    pts_raw = mesh.GetPointsAttr().Get(time)
    points = np.asarray(pts_raw if pts_raw is not None else [], dtype=np.float64).reshape(-1, 3)
    bad = ~np.isfinite(points).all(axis=1)
    if bad.any():
        first = int(np.flatnonzero(bad)[0])
        raise AssetError(f"mesh {path} has NaN/Inf points ({int(bad.sum())} bad, first at "
                         f"index {first}: {points[first].tolist()})", path=source, prim=path)
    counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get(time) or [], dtype=np.int64)
    fvi = np.asarray(mesh.GetFaceVertexIndicesAttr().Get(time) or [], dtype=np.int64)
    if (counts < 0).any():
        raise AssetError(f"mesh {path} has negative faceVertexCounts", path=source, prim=path)
    if int(counts.sum()) != fvi.shape[0]:
        raise AssetError(f"mesh {path}: faceVertexCounts sum to {int(counts.sum())} but there are "
                         f"{fvi.shape[0]} faceVertexIndices", path=source, prim=path)
    n_points = points.shape[0]
    out_of_range = (fvi < 0) | (fvi >= n_points)
    if out_of_range.any():
        first = int(np.flatnonzero(out_of_range)[0])
        raise AssetError(
            f"mesh {path}: faceVertexIndices[{first}] = {int(fvi[first])} is out of range for "
            f"{n_points} points", path=source, prim=path)
    n_faces = counts.shape[0]
    bad_polygons = int((counts < 3).sum())
    if bad_polygons:
        _warn(warns, f"mesh {path}: dropped {bad_polygons} polygon(s) with fewer than 3 vertices")
    tri_fv, tri_face = _fan(counts)  # (T, 3), (T,)
    holes = np.asarray(mesh.GetHoleIndicesAttr().Get(time) or [], dtype=np.int64)
    if holes.size:
        keep = ~np.isin(tri_face, holes)
        tri_fv, tri_face = tri_fv[keep], tri_face[keep]

    points_w, lin = _world_points(prim, points, time, xcache, skin, source)  # (n, 3), (3, 3)
    det = float(np.linalg.det(lin))
    left = mesh.GetOrientationAttr().Get(time) == UsdGeom.Tokens.leftHanded
    if left != (det < 0):  # either flips the winding; both cancel
        tri_fv = tri_fv[:, [0, 2, 1]]
    tri_vid = fvi[tri_fv]  # (T, 3)

    # normals: primvars:normals wins over the normals attribute (UsdGeomPointBased docs)
    corner_normals = None
    pv_api = UsdGeom.PrimvarsAPI(prim)
    nrm_pv = pv_api.GetPrimvar("normals")
    if skin is not None:
        # UsdSkel in Python skins points only: normals are computed from the skinned surface
        if (nrm_pv and nrm_pv.HasAuthoredValue()) or mesh.GetNormalsAttr().HasAuthoredValue():
            _warn(warns, f"mesh {path}: skinned by UsdSkel; its authored (rest-pose) normals are "
                         "replaced by normals computed from the skinned points")
        values, interp, label = None, "", ""
    elif nrm_pv and nrm_pv.HasAuthoredValue():
        values, interp, label = _primvar_values(nrm_pv, time, 3), nrm_pv.GetInterpolation(), \
            "primvars:normals"
    elif mesh.GetNormalsAttr().HasAuthoredValue():
        raw = mesh.GetNormalsAttr().Get(time)
        values = None if raw is None else np.asarray(raw, dtype=np.float64).reshape(-1, 3)
        interp, label = mesh.GetNormalsInterpolation(), "normals"
    else:
        values, interp, label = None, "", ""
    if label:
        expanded = None if values is None else _expand(
            values, interp, tri_fv, tri_vid, tri_face, n_points, n_faces, fvi.shape[0])
        if expanded is None:
            n_vals = -1 if values is None else values.shape[0]
            _warn(warns, f"mesh {path}: {label} ({interp}, {n_vals} values) does not match the "
                         f"topology ({n_points} points, {n_faces} faces, {fvi.shape[0]} corners); "
                         "computing normals")
        else:
            normal_xf = np.linalg.inv(lin).T  # row vectors: n' = n @ inv(A).T
            nw = expanded @ normal_xf
            length = np.linalg.norm(nw, axis=2, keepdims=True)
            ok = np.isfinite(length) & (length > 0)
            corner_normals = np.divide(nw, length, out=np.zeros_like(nw), where=ok)
            if not ok.all():
                _warn(warns, f"mesh {path}: {int((~ok).sum())} authored normal(s) are zero or "
                             "not finite; those corners use computed normals")
                computed = _area_weighted_normals(points_w, tri_vid)  # (T, 3, 3)
                corner_normals = np.where(ok, corner_normals, computed)

    # UVs: primvars:st, else the primvar the material's textures read, else any texCoord2f
    names = ["st", *[n for n in uv_names if n != "st"]]
    candidates = [pv_api.GetPrimvar(n) for n in names]
    chosen = next((pv for pv in candidates if pv and pv.HasAuthoredValue()), None)
    if chosen is None:
        tex_coords = sorted(
            (pv for pv in pv_api.GetPrimvarsWithAuthoredValues()
             if pv.GetTypeName().role == "TextureCoordinate"),
            key=lambda pv: pv.GetPrimvarName())
        chosen = tex_coords[0] if tex_coords else None
    corner_uvs = np.zeros((tri_fv.shape[0], 3, 2))
    has_uvs = False
    if chosen is not None:
        values = _primvar_values(chosen, time, 2)
        interp = chosen.GetInterpolation()
        expanded = None if values is None else _expand(
            values, interp, tri_fv, tri_vid, tri_face, n_points, n_faces, fvi.shape[0])
        if expanded is None:
            n_vals = -1 if values is None else values.shape[0]
            _warn(warns, f"mesh {path}: primvars:{chosen.GetPrimvarName()} ({interp}, {n_vals} "
                         f"values) does not match the topology; ignoring UVs")
        else:
            corner_uvs, has_uvs = expanded, True
            if chosen.GetPrimvarName() != "st":
                _warn(warns, f"mesh {path}: no primvars:st; using primvars:"
                             f"{chosen.GetPrimvarName()} as UVs")

    tri_material = (np.zeros(tri_face.shape[0], np.int32) if face_materials is None
                    else face_materials[tri_face].astype(np.int32))
    return _MeshData(path, points_w, tri_vid, tri_face, corner_normals, corner_uvs, has_uvs,
                     tri_material, bad_polygons)


def _is_rendered(prim: Any, time: Any) -> bool:
    from pxr import UsdGeom

    img = UsdGeom.Imageable(prim)
    if img.ComputeVisibility(time) == UsdGeom.Tokens.invisible:
        return False
    return img.ComputePurpose() != UsdGeom.Tokens.guide


# --------------------------------------------------------------------------------------------
# lights and cameras
# --------------------------------------------------------------------------------------------


def _read_light(prim: Any, time: Any, xcache: Any, warns: list[str]) -> Light | None:
    from pxr import UsdLux

    path = str(prim.GetPath())
    if prim.IsA(UsdLux.DistantLight):
        light: Any = UsdLux.DistantLight(prim)
        kind = "distant"
    elif prim.IsA(UsdLux.SphereLight):
        light = UsdLux.SphereLight(prim)
        kind = "sphere"
    else:
        _warn(warns, f"light {path}: unsupported light type {prim.GetTypeName()}; ignored")
        return None
    api = UsdLux.LightAPI(prim)
    intensity = float(api.GetIntensityAttr().Get(time))
    exposure = float(api.GetExposureAttr().Get(time))
    color = np.asarray(api.GetColorAttr().Get(time), dtype=np.float64)
    if api.GetEnableColorTemperatureAttr().Get(time):
        temp = float(api.GetColorTemperatureAttr().Get(time))
        color = color * np.asarray(UsdLux.BlackbodyTemperatureAsRgb(temp), dtype=np.float64)
    scale = color * intensity * 2.0 ** exposure
    world = _matrix(xcache.GetLocalToWorldTransform(prim))
    lin = world[:3, :3]
    position = world[3, :3].copy()
    if kind == "distant":
        toward = np.array([0.0, 0.0, 1.0]) @ lin  # the light shines along its local -Z
        norm = float(np.linalg.norm(toward))
        if not np.isfinite(norm) or norm == 0.0:
            raise AssetError(f"distant light {path} has a singular transform", prim=path)
        return Light(path=path, kind=kind, direction=toward / norm, position=position,
                     radius=0.0, radiance_scale=scale)
    radius = float(light.GetRadiusAttr().Get(time)) * float(abs(np.linalg.det(lin))) ** (1 / 3)
    treat_as_point = bool(light.GetTreatAsPointAttr().Get(time))
    if treat_as_point or radius == 0.0:
        radiance = scale
    elif api.GetNormalizeAttr().Get(time):
        # normalize divides the radiance by the surface area 4 pi r^2: pi r^2 / (4 pi r^2)
        radiance = scale * 0.25
    else:
        radiance = scale * np.pi * radius ** 2
    return Light(path=path, kind=kind, direction=np.zeros(3), position=position,
                 radius=0.0 if treat_as_point else radius, radiance_scale=radiance)


def _read_camera(prim: Any, time: Any, xcache: Any, warns: list[str]) -> Camera:
    from pxr import UsdGeom

    cam = UsdGeom.Camera(prim)
    if cam.GetProjectionAttr().Get(time) != UsdGeom.Tokens.perspective:
        _warn(warns, f"camera {prim.GetPath()}: projection is "
                     f"{cam.GetProjectionAttr().Get(time)}; read as perspective")
    world = _matrix(xcache.GetLocalToWorldTransform(prim))
    return Camera(
        path=str(prim.GetPath()),
        world_from_camera=world.T,
        focal_length=float(cam.GetFocalLengthAttr().Get(time)),
        horizontal_aperture=float(cam.GetHorizontalApertureAttr().Get(time)),
        vertical_aperture=float(cam.GetVerticalApertureAttr().Get(time)),
        clipping=np.asarray(cam.GetClippingRangeAttr().Get(time), dtype=np.float64),
    )


# --------------------------------------------------------------------------------------------
# bindings
# --------------------------------------------------------------------------------------------


def _bound(prim: Any, warns: list[str]) -> Any:
    from pxr import UsdShade

    material, _ = UsdShade.MaterialBindingAPI(prim).ComputeBoundMaterial()
    if material:
        return material
    rel = prim.GetRelationship("material:binding")
    if rel and rel.GetTargets() and not prim.HasAPI(UsdShade.MaterialBindingAPI):
        _warn(warns, f"prim {prim.GetPath()}: material:binding is authored but "
                     "MaterialBindingAPI is not applied, so USD ignores it")
    return None


def _face_materials(prim: Any, n_faces: int, time: Any, index_of: Any, warns: list[str],
                    source: str) -> np.ndarray:
    """(F,) int32 material index per source polygon: GeomSubsets (familyName materialBind),
    then the mesh's own binding (or the default material) for faces no subset covers."""
    from pxr import UsdGeom, UsdShade

    path = str(prim.GetPath())
    face_mat = np.full(n_faces, -1, dtype=np.int32)  # -1: not (yet) bound by a subset
    for subset in UsdShade.MaterialBindingAPI(prim).GetMaterialBindSubsets():
        sub_path = str(subset.GetPath())
        if subset.GetElementTypeAttr().Get() != UsdGeom.Tokens.face:
            _warn(warns, f"subset {sub_path}: elementType is not face; ignored")
            continue
        idx = np.asarray(subset.GetIndicesAttr().Get(time) or [], dtype=np.int64)
        bad = (idx < 0) | (idx >= n_faces)
        if bad.any():
            first = int(idx[np.flatnonzero(bad)[0]])
            raise AssetError(f"GeomSubset {sub_path}: face index {first} is out of range for "
                             f"{n_faces} faces of mesh {path}", path=source, prim=sub_path)
        if idx.size:
            face_mat[idx] = index_of(_bound(subset.GetPrim(), warns))
    rest = face_mat < 0
    if rest.any():  # only materials some face uses enter the list
        face_mat[rest] = index_of(_bound(prim, warns))
    return face_mat


# --------------------------------------------------------------------------------------------
# load_asset
# --------------------------------------------------------------------------------------------


def _ancestors(prim: Any) -> Iterable[Any]:
    while prim and not prim.IsPseudoRoot():
        yield prim
        prim = prim.GetParent()


def load_asset(path: str | Path, *, time_code: float | None = None) -> AssetModel:
    """Read a USD asset into one AssetModel (see `texelbake.model.AssetModel` for every field).

    path : `.usda` / `.usdc` / `.usd` / `.usdz`. `check_asset_paths` runs first, before the stage
        is composed.
    time_code : the time at which points, transforms, lights and cameras are read. None reads
        each attribute at its earliest time sample, or its default value when it has none
        (`Usd.TimeCode.EarliestTime()`).

    Meshes (visible, non-guide `UsdGeom.Mesh` prims, instance proxies included) are flattened to
    world space (normals by the inverse-transpose), fan-triangulated, and counter-clockwise
    (winding flipped for `orientation = "leftHanded"` and for mirroring transforms). Triangles
    with area below `TOL.zero_area * bbox_diag**2` are dropped and counted, with a warning.
    Time-sampled points or transforms (on the mesh or an ancestor) give `time_codes` and
    `points_over_time` (every mesh, same vertex order as `points`).

    Texture contract: `Texture.pixels` holds exactly the channels of the UsdUVTexture output
    that drives the input (`rgb` -> 3, `r`/`g`/`b`/`a` -> 1), linear (sRGB decoded for RGB when
    `sourceColorSpace` is sRGB, or auto with an 8-bit file); `scale`/`bias` are reordered to
    follow those channels. `wrapS/T = useMetadata` takes the file's wrap metadata, else "black".
    A "merl" material holds the file's resolved path in params["file"], the table in
    params["table"] (`texelbake.brdf.read_merl`: MERL RGB scale applied, invalid entries 0)
    and the shader's `scale` input unapplied.

    raises : AssetPathError (unsafe / missing asset paths), AssetError (unreadable file, no mesh,
        NaN/Inf points, out-of-range indices, every face degenerate), each naming the prim/file.
    """
    from pxr import Tf, Usd, UsdGeom

    src = Path(path)
    source = str(src)
    if not src.is_file():
        raise AssetError("asset file does not exist", path=source)
    check_asset_paths(src)
    try:
        stage = Usd.Stage.Open(source)
    except Tf.ErrorException as exc:
        raise AssetError(f"pxr cannot open the file: {_first_line(exc)}", path=source) from exc
    if stage is None:
        raise AssetError("pxr cannot open the file", path=source)

    time = Usd.TimeCode.EarliestTime() if time_code is None else Usd.TimeCode(float(time_code))
    xcache = UsdGeom.XformCache(time)
    warns: list[str] = []
    reader = _MaterialReader(time, warns)

    materials: list[Material] = []
    index_by_path: dict[str, int] = {}

    def index_of(material: Any) -> int:
        key = str(material.GetPath()) if material else ""
        if key not in index_by_path:
            index_by_path[key] = len(materials)
            materials.append(reader.read(material) if material else DEFAULT_MATERIAL)
        return index_by_path[key]

    mesh_prims: list[Any] = []
    lights: list[Light] = []
    cameras: list[Camera] = []
    prims = iter(Usd.PrimRange(stage.GetPseudoRoot(),
                               Usd.TraverseInstanceProxies(Usd.PrimDefaultPredicate)))
    for prim in prims:
        if prim.IsA(UsdGeom.PointInstancer):
            _warn(warns, f"point instancer {prim.GetPath()}: not supported; its prototypes "
                         "and instances are skipped")
            prims.PruneChildren()
        elif prim.IsA(UsdGeom.Mesh):
            if _is_rendered(prim, time):
                mesh_prims.append(prim)
            else:
                _warn(warns, f"mesh {prim.GetPath()}: invisible or guide purpose; skipped")
        elif prim.IsA(UsdGeom.Camera):
            cameras.append(_read_camera(prim, time, xcache, warns))
        elif _is_light(prim):
            light = _read_light(prim, time, xcache, warns)
            if light is not None:
                lights.append(light)
        elif prim.IsA(UsdGeom.Gprim) and _is_rendered(prim, time):
            _warn(warns, f"prim {prim.GetPath()}: {prim.GetTypeName()} is not a UsdGeom.Mesh; "
                         "ignored")
    if not mesh_prims:
        raise AssetError("the asset has no UsdGeom.Mesh prim (nothing to bake)", path=source,
                         prim=str(stage.GetDefaultPrim().GetPath()) if stage.GetDefaultPrim()
                         else "/")

    skins = _skinning_queries(stage, warns)
    meshes: list[_MeshData] = []
    for prim in mesh_prims:
        n_faces = len(UsdGeom.Mesh(prim).GetFaceVertexCountsAttr().Get(time) or [])
        face_mat = _face_materials(prim, n_faces, time, index_of, warns, source)
        uv_names = sorted({
            tex.st_primvar for i in np.unique(face_mat).tolist()
            for tex in materials[i].textures.values()})
        meshes.append(_read_mesh(prim, time, xcache, face_mat, uv_names, warns, source,
                                 skins.get(str(prim.GetPath()))))

    # ---- assemble, computing missing normals, dropping degenerate triangles ----------------
    all_points = np.concatenate([m.points for m in meshes], axis=0)  # (n, 3)
    diag = float(np.linalg.norm(all_points.max(0) - all_points.min(0))) if len(all_points) else 0.0
    min_area = TOL.zero_area * diag ** 2
    offsets = np.concatenate([[0], np.cumsum([m.points.shape[0] for m in meshes])[:-1]])
    parts: dict[str, list[np.ndarray]] = {k: [] for k in
                                          ("faces", "normals", "uvs", "has", "mat", "mesh")}
    dropped = sum(m.bad_polygons for m in meshes)
    for mi, m in enumerate(meshes):
        cross = _tri_cross(m.points, m.tris)  # (t, 3)
        keep = 0.5 * _row_norm(cross) > min_area
        n_drop = int((~keep).sum())
        if n_drop:
            dropped += n_drop
            _warn(warns, f"mesh {m.path}: dropped {n_drop} zero-area / degenerate triangle(s) "
                         f"(area <= {min_area:.3g})")
        normals = (m.corner_normals if m.corner_normals is not None
                   else _area_weighted_normals(m.points, m.tris, cross))
        sel = slice(None) if n_drop == 0 else keep  # no masked copies for clean meshes
        parts["faces"].append(m.tris[sel] + offsets[mi])
        parts["normals"].append(normals[sel])
        parts["uvs"].append(m.corner_uvs[sel])
        parts["has"].append(np.full(int(keep.sum()), m.has_uvs))
        parts["mat"].append(m.tri_material[sel])
        parts["mesh"].append(np.full(int(keep.sum()), mi, dtype=np.int32))
    faces = np.concatenate(parts["faces"]).astype(np.int64).reshape(-1, 3)
    if faces.shape[0] == 0 and dropped == 0:
        raise AssetError(
            f"the mesh(es) {', '.join(m.path for m in meshes)} have no faces", path=source,
            prim=meshes[0].path)
    if faces.shape[0] == 0:
        raise AssetError(
            f"every face is degenerate (zero area or fewer than 3 vertices; {dropped} dropped) in "
            f"mesh(es) {', '.join(m.path for m in meshes)}", path=source, prim=meshes[0].path)

    # materials used only by dropped faces stay in the list: indices are stable per binding
    time_codes, points_over_time = _time_samples(mesh_prims, meshes, skins, source)
    return AssetModel(
        source=source,
        points=all_points,
        faces=faces,
        corner_normals=np.concatenate(parts["normals"]).reshape(-1, 3, 3),
        corner_uvs=np.concatenate(parts["uvs"]).reshape(-1, 3, 2),
        has_uvs=np.concatenate(parts["has"]).astype(bool),
        face_material=np.concatenate(parts["mat"]).astype(np.int32),
        face_mesh=np.concatenate(parts["mesh"]).astype(np.int32),
        mesh_paths=tuple(m.path for m in meshes),
        materials=tuple(materials),
        lights=tuple(lights),
        cameras=tuple(cameras),
        up_axis=str(UsdGeom.GetStageUpAxis(stage)),
        meters_per_unit=float(UsdGeom.GetStageMetersPerUnit(stage)),
        time_codes=time_codes,
        points_over_time=points_over_time,
        dropped_faces=int(dropped),
        warnings=tuple(warns),
    )


def _is_light(prim: Any) -> bool:
    from pxr import UsdLux

    return bool(prim.HasAPI(UsdLux.LightAPI))


def _time_samples(mesh_prims: list[Any], meshes: list[_MeshData],
                  skins: dict[str, tuple[Any, Any]], source: str) -> tuple[np.ndarray, np.ndarray]:
    """Union of the time samples of every mesh's points, of its (ancestors') transforms and,
    for skinned meshes, of the skeleton's animation, skinning primvars and transforms.

    returns : time_codes (t,) float64, points_over_time (t, n, 3) float64 (world, flattened,
        the vertex order of `points`)
    """
    from pxr import Usd, UsdGeom

    times: set[float] = set()

    def xform_samples(prim: Any) -> list[float]:
        found: list[float] = []
        for anc in _ancestors(prim):
            xf = UsdGeom.Xformable(anc)
            if xf:
                found.extend(xf.GetTimeSamples())
        return found

    varying: list[bool] = []  # per mesh: do its world points change at all?
    for prim in mesh_prims:
        mesh_times = list(UsdGeom.Mesh(prim).GetPointsAttr().GetTimeSamples())
        skin = skins.get(str(prim.GetPath()))
        if skin is None:
            mesh_times += xform_samples(prim)
        else:
            sq, skel_query = skin
            mesh_times += list(sq.GetTimeSamples()) + xform_samples(skel_query.GetPrim())
            anim = skel_query.GetAnimQuery()
            if anim:
                mesh_times += list(anim.GetJointTransformTimeSamples())
        times.update(mesh_times)
        varying.append(len(set(mesh_times)) > 1)
    if not times:
        return np.zeros(0), np.zeros((0, sum(m.points.shape[0] for m in meshes), 3))
    codes = np.array(sorted(times), dtype=np.float64)
    frames = []
    for t in codes.tolist():  # a loop over time codes, each a whole-array evaluation
        tc = Usd.TimeCode(t)
        xcache = UsdGeom.XformCache(tc)
        per_mesh = []
        for prim, m, moves in zip(mesh_prims, meshes, varying, strict=True):
            if not moves:  # at most one sample: the same points at every time
                per_mesh.append(m.points)
                continue
            raw = UsdGeom.Mesh(prim).GetPointsAttr().Get(tc)
            pts = np.asarray(raw if raw is not None else [], dtype=np.float64).reshape(-1, 3)
            if pts.shape[0] != m.points.shape[0]:
                raise AssetError(
                    f"mesh {m.path}: {pts.shape[0]} points at time {t:g}, expected "
                    f"{m.points.shape[0]} (changing topology is not supported)",
                    path=source, prim=m.path)
            bad = ~np.isfinite(pts).all(axis=1)
            if bad.any():
                raise AssetError(
                    f"mesh {m.path} has NaN/Inf points at time {t:g} (first at index "
                    f"{int(np.flatnonzero(bad)[0])})", path=source, prim=m.path)
            world_pts, _ = _world_points(prim, pts, tc, xcache, skins.get(m.path), source)
            per_mesh.append(world_pts)
        frames.append(np.concatenate(per_mesh, axis=0))
    return codes, np.stack(frames)


# --------------------------------------------------------------------------------------------
# describe
# --------------------------------------------------------------------------------------------


def _fmt_vec(v: Any) -> str:
    return "(" + ", ".join(f"{float(x):.4g}" for x in np.asarray(v).reshape(-1)) + ")"


def _param_summary(mat: Material) -> str:
    """`name=value` for a material's constants (for "preview", only those off the spec
    defaults; never the MERL table or file, shown separately)."""
    parts = []
    for key in sorted(mat.params):
        if key in ("table", "file"):
            continue
        value = mat.params[key]
        if mat.model == "preview" and key in PREVIEW_DEFAULTS and np.allclose(
                np.asarray(value, dtype=np.float64), np.asarray(PREVIEW_DEFAULTS[key], np.float64)):
            continue
        text = (_fmt_vec(value) if isinstance(value, np.ndarray)
                else f"{value:.4g}" if isinstance(value, float) else str(value))
        parts.append(f"{key}={text}")
    return ", ".join(parts)


def describe(asset: AssetModel) -> str:
    """The human-readable summary `texelbake inspect FILE` prints.

    asset : an AssetModel from `load_asset`
    returns : multi-line text: meshes with face counts, materials with model and textures,
        lights, cameras, bounds and bbox diagonal, deformation, dropped faces, warnings.
    """
    lines = [f"asset: {asset.source}",
             f"up axis: {asset.up_axis}, meters per unit: {asset.meters_per_unit:g}"]
    counts = np.bincount(asset.face_mesh, minlength=len(asset.mesh_paths))
    lines.append(f"meshes: {len(asset.mesh_paths)} ({asset.num_faces} triangles, "
                 f"{asset.points.shape[0]} points)")
    for path, n in zip(asset.mesh_paths, counts.tolist(), strict=True):
        lines.append(f"  {path}: {n} triangles")
    n_tex = len({t.path for m in asset.materials for t in m.textures.values()})
    lines.append(f"materials: {len(asset.materials)}")
    used = np.bincount(asset.face_material, minlength=len(asset.materials))
    for i, mat in enumerate(asset.materials):
        name = mat.path or "<default grey lambert>"
        lines.append(f"  {name}: {mat.model}, {int(used[i])} triangles")
        shown = _param_summary(mat)
        if shown:
            lines.append(f"    {shown}")
        for inp, tex in sorted(mat.textures.items()):
            h, w, c = tex.pixels.shape
            lines.append(f"    {inp} <- texture {tex.path} ({w}x{h}, {c} ch, "
                         f"{tex.source_color_space}, st={tex.st_primvar})")
        if mat.model == "merl":
            lines.append(f"    measured BRDF {mat.params.get('file', '')}")
    lines.append(f"textures: {n_tex}")
    lines.append(f"lights: {len(asset.lights)}")
    for light in asset.lights:
        where = (f"toward {_fmt_vec(light.direction)}" if light.kind == "distant"
                 else f"at {_fmt_vec(light.position)}, radius {light.radius:.4g}")
        lines.append(f"  {light.path}: {light.kind} {where}, "
                     f"scale {_fmt_vec(light.radiance_scale)}")
    lines.append(f"cameras: {len(asset.cameras)}")
    for cam in asset.cameras:
        lines.append(f"  {cam.path}: at {_fmt_vec(cam.world_from_camera[:3, 3])}, focal "
                     f"{cam.focal_length:.4g} mm")
    lo, hi = asset.bounds
    lines.append(f"bounds: min {_fmt_vec(lo)} max {_fmt_vec(hi)}")
    lines.append(f"bbox diagonal: {asset.bbox_diag:.6g}")
    uv_faces = int(asset.has_uvs.sum())
    lines.append(f"uvs: {uv_faces} of {asset.num_faces} triangles")
    if asset.has_deformation:
        lines.append(f"deformation: yes ({asset.time_codes.shape[0]} time codes, "
                     f"{asset.time_codes[0]:g} .. {asset.time_codes[-1]:g})")
    else:
        lines.append(f"deformation: no ({asset.time_codes.shape[0]} time codes)")
    lines.append(f"dropped faces: {asset.dropped_faces}")
    lines.append(f"warnings: {len(asset.warnings)}")
    lines.extend(f"  - {w}" for w in asset.warnings)
    return "\n".join(lines)
