"""A `UsdUVTexture` node read as a renderer reads it: its file, channels, colour space, wrap
modes, scale/bias, st primvar, and its `fallback` when the file is not there.

The rules, each where the Sdr definition (usdShaders' `shaderDefs.usda`) leaves a choice, as
Blender's USD importer (the DCC the tests render with) reads them:

* `wrapS` / `wrapT`: black, clamp, repeat, mirror as authored; `useMetadata` (the default)
  takes the file's `wrapmodes` metadata and, when the file has none, **repeat**. Storm's
  UsdUVTexture shader takes black there, but Blender, MaterialX's `ND_UsdUVTexture`
  (`periodic`) and the DCC exporters that leave the input unauthored all tile: a kit whose UVs
  span -37.8..37.8 over 32x32 colour swatches baked black with "black" (its colours with repeat).
* `sourceColorSpace`: sRGB decodes the RGB channels, raw does not; `auto` decodes when the
  file stores 8-bit channels, has 3 or 4 of them and drives a colour input (`COLOR_INPUTS`): a
  single-channel 8-bit roughness map and an 8-bit normal map stay linear, as in Blender.
* `st`: the `varname` of the `UsdPrimvarReader_float2` connected to it (a value or an interface
  input), also through a `UsdTransform2d` (its scale, rotation and translation kept as
  `Texture.st_transform`); unconnected, the mesh's `st`, else its first texCoord2f primvar (the
  mesh reader's rule: `texelbake.asset.meshes.read_mesh`), as Blender takes the mesh's active
  UV map.
* a file that does not resolve (missing from the bundle) or a UDIM set: a warning, and the
  input takes the node's authored `fallback` (the channels of the output it drives), else the
  material's own constant for that input.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np

from texelbake.asset.files import load_image
from texelbake.asset.values import warn
from texelbake.errors import AssetPathError
from texelbake.io.images import srgb_to_linear
from texelbake.model import Texture

#: UsdUVTexture output name -> channels of the canonical RGBA image
OUTPUT_CHANNELS = {
    "rgb": (0, 1, 2),
    "rgba": (0, 1, 2, 3),
    "r": (0,),
    "g": (1,),
    "b": (2,),
    "a": (3,),
}
WRAP_MODES = ("black", "clamp", "repeat", "mirror")
#: the wrap `useMetadata` takes when the file carries no wrap metadata (module docstring)
WRAP_WITHOUT_METADATA = "repeat"
#: inputs that take a colour: `sourceColorSpace = auto` decodes sRGB only for these
COLOR_INPUTS = frozenset({"diffuseColor", "emissiveColor", "specularColor", "borderColor",
                          "cellColorA", "cellColorB"})

InputValue = Callable[[Any, str, Any], Any]


def _canonical_rgba(pixels: np.ndarray) -> np.ndarray:
    """(h, w, c) -> (h, w, 4) per the UsdUVTexture spec: grey -> (g, g, g, 1),
    grey+alpha -> (g, g, g, a), rgb -> (r, g, b, 1)."""
    h, w, c = pixels.shape
    one = np.ones((h, w, 1), np.float32)
    if c == 1:
        return np.concatenate([np.repeat(pixels, 3, axis=2), one], 2)
    if c == 2:
        return np.concatenate([np.repeat(pixels[..., :1], 3, axis=2), pixels[..., 1:2]], 2)
    if c == 3:
        return np.concatenate([pixels, one], 2)
    return pixels[..., :4]


def _fallback(shader: Any, channels: tuple[int, ...], input_value: InputValue) -> Any:
    """The node's authored `fallback` (float4) reduced to the output's channels; None when
    unauthored (then the material's constant stands)."""
    inp = shader.GetInput("fallback")
    if not inp or not inp.GetAttr().HasAuthoredValue():
        return None
    value = input_value(shader, "fallback", None)
    if value is None:
        return None
    fb = np.resize(np.asarray(value, np.float64).reshape(-1), 4)
    picked = fb[list(channels)]
    return picked if picked.shape[0] > 1 else float(picked[0])


def _transform2d(node: Any, input_value: InputValue) -> tuple[float, ...]:
    """A UsdTransform2d's affine map of st: in * scale, rotated (degrees, counter-clockwise),
    plus translation (the Sdr definition's order), as (a, b, c, d, e, f)."""
    sx, sy = (float(x) for x in np.resize(np.asarray(
        input_value(node, "scale", (1.0, 1.0)), np.float64).reshape(-1), 2))
    tx, ty = (float(x) for x in np.resize(np.asarray(
        input_value(node, "translation", (0.0, 0.0)), np.float64).reshape(-1), 2))
    r = math.radians(float(input_value(node, "rotation", 0.0)))
    cos, sin = math.cos(r), math.sin(r)
    return (cos * sx, -sin * sy, tx, sin * sx, cos * sy, ty)


def _st_source(shader: Any, input_value: InputValue, mat_path: str, prim_path: str,
               warns: list[str]) -> tuple[str, tuple[float, ...]]:
    """(st primvar name, st transform) of a UsdUVTexture: through a UsdTransform2d (its `in`)
    to a UsdPrimvarReader's varname; unconnected: "st" (module docstring)."""
    from pxr import UsdShade

    transform: tuple[float, ...] = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0)
    node, input_name = shader, "st"
    for _ in range(2):  # the texture's st, then a UsdTransform2d's in
        inp = node.GetInput(input_name)
        attrs = inp.GetValueProducingAttributes() if inp else []
        src = attrs[0] if attrs else None
        if src is None or not UsdShade.Output.IsOutput(src):
            return "st", transform
        src_prim = src.GetPrim()
        node = UsdShade.Shader(src_prim)
        rid = node.GetShaderId() if node else None
        if rid is not None and rid.startswith("UsdPrimvarReader"):
            return str(input_value(node, "varname", "st") or "st"), transform
        if rid == "UsdTransform2d" and input_name == "st":
            transform, input_name = _transform2d(node, input_value), "in"
            continue
        break
    warn(warns, f"material {mat_path}: st of {prim_path} is driven by an unsupported node "
                f"{src_prim.GetPath()} (id {rid!r}); using primvar st")
    return "st", transform


def read_uv_texture(prim: Any, out_name: str, input_name: str, mat_path: str,
                    input_value: InputValue,
                    images: dict[str, tuple[np.ndarray, bool, str]], warns: list[str]
                    ) -> tuple[Texture | None, Any]:
    """The Texture a UsdUVTexture output gives the input `input_name`, or (None, fallback) when
    its file is missing or a UDIM set (module docstring; fallback None: the material's constant).

    input_value(shader, name, default) : an input's value through connections to interface
        inputs; images : resolved path -> (pixels (h, w, c) float32, is 8-bit, wrapmodes), the
        reader's cache
    raises : AssetPathError when the node has no file at all
    """
    from pxr import UsdShade

    shader = UsdShade.Shader(prim)
    prim_path = str(prim.GetPath())
    channels = OUTPUT_CHANNELS.get(out_name)
    if channels is None:
        warn(warns, f"material {mat_path}: unknown UsdUVTexture output '{out_name}' of "
                    f"{prim_path}; using rgb")
        channels = OUTPUT_CHANNELS["rgb"]
    asset = input_value(shader, "file", None)
    if asset is None or not asset.path:
        raise AssetPathError(f"UsdUVTexture of material {mat_path} has no file",
                             path="", prim=prim_path)
    fallback = _fallback(shader, channels, input_value)
    instead = ("its fallback" if fallback is not None
               else f"the material's constant {input_name}")
    if "<UDIM>" in asset.path:
        warn(warns, f"material {mat_path}: UDIM texture '{asset.path}' of {prim_path} is not "
                    f"supported; using {instead}")
        return None, fallback
    resolved = asset.resolvedPath
    if not resolved:
        warn(warns, f"material {mat_path}: texture '{asset.path}' of {prim_path} does not "
                    f"exist; using {instead}")
        return None, fallback
    if resolved not in images:
        images[resolved] = load_image(resolved, prim_path)
    pixels, is_8bit, wrapmodes = images[resolved]
    rgba = _canonical_rgba(pixels)
    color_space = str(input_value(shader, "sourceColorSpace", "auto"))
    if color_space == "sRGB" or (color_space == "auto" and is_8bit and pixels.shape[2] >= 3
                                 and input_name in COLOR_INPUTS):
        rgba = np.concatenate([srgb_to_linear(rgba[..., :3]), rgba[..., 3:]], axis=2)
    sel = list(channels)
    scale4 = np.resize(np.asarray(input_value(shader, "scale", (1.0, 1.0, 1.0, 1.0)),
                                  np.float64).reshape(-1), 4)
    bias4 = np.resize(np.asarray(input_value(shader, "bias", (0.0, 0.0, 0.0, 0.0)),
                                 np.float64).reshape(-1), 4)
    # scale/bias follow the selected channels, padded with identity values to 4
    scale = tuple(float(x) for x in np.concatenate([scale4[sel], np.ones(4 - len(sel))]))
    bias = tuple(float(x) for x in np.concatenate([bias4[sel], np.zeros(4 - len(sel))]))
    meta_wraps = [m.strip() for m in wrapmodes.split(",")] if wrapmodes else []
    wraps = []
    for axis, key in enumerate(("wrapS", "wrapT")):
        mode = str(input_value(shader, key, "useMetadata"))
        if mode == "useMetadata":
            mode = meta_wraps[axis] if axis < len(meta_wraps) else WRAP_WITHOUT_METADATA
            mode = {"periodic": "repeat"}.get(mode, mode)
        if mode not in WRAP_MODES:
            warn(warns, f"material {mat_path}: unknown {key} '{mode}' on {prim_path}; "
                        "using repeat")
            mode = "repeat"
        wraps.append(mode)
    st_primvar, st_transform = _st_source(shader, input_value, mat_path, prim_path, warns)
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
        st_transform=st_transform,  # type: ignore[arg-type]
    ), None
