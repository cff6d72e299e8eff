"""A MaterialX document (`.mtlx`) that a layer references, read through the `MaterialX` package
into a USD layer texelbake composes in its place.

usd-core's wheel has no `.mtlx` file format (no usdMtlx), so pxr cannot open the document.
`translated_layer` reads it with MaterialX (XIncludes off: an include could name a file outside
the asset) and writes, in memory, the prims usdMtlx would make at the same paths
(`/MaterialX/Materials/<material>`, the layer's default prim `MaterialX`), so an arc such as
`@Rook_mat.mtlx@</MaterialX/Materials/Rook>` finds its material. Each material gets

* `outputs:mtlx:surface`: the document's surface shader as a `ND_<category>_surfaceshader`
  Shader with its constant inputs (what `texelbake.asset.mtlx.preview_params` reads), and
* `outputs:surface`: a UsdPreviewSurface with those constants mapped (`preview_params`) and
  every input an image drives (`image`, `tiledimage`, `UsdUVTexture` nodes, through node
  graphs) as a `UsdUVTexture` + `UsdPrimvarReader_float2`: the file with the document's
  `fileprefix`, relative to the document; `srgb_texture` as sRGB, other colour spaces raw;
  the address modes as wrap modes (periodic -> repeat, constant -> black); the `texcoord`
  index, or the `geompropvalue` / `UsdPrimvarReader` name, as the st primvar; the image's
  `default` (a UsdUVTexture's `fallback`) as the fallback.

What a UsdPreviewSurface cannot hold is warned per input: other nodes between an image and the
shader (math, ramps, normal maps), a tiled image's tiling.
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np

from texelbake.asset.mtlx import MTLX_PREVIEW_SURFACE, STANDARD_SURFACE, preview_params
from texelbake.asset.values import warn
from texelbake.errors import AssetError

#: the translated layer's identifier is the document's path plus this (never written to disk)
TRANSLATED_SUFFIX = ".texelbake.usda"

#: standard_surface input -> (UsdPreviewSurface input, the standard_surface input that scales it)
_STANDARD_TEXTURED = {
    "base_color": ("diffuseColor", "base"), "specular_roughness": ("roughness", None),
    "metalness": ("metallic", None), "coat": ("clearcoat", None),
    "coat_roughness": ("clearcoatRoughness", None), "opacity": ("opacity", None),
    "emission_color": ("emissiveColor", "emission"),
}
_PREVIEW_TEXTURED = ("diffuseColor", "emissiveColor", "specularColor", "metallic", "roughness",
                     "clearcoat", "clearcoatRoughness", "opacity", "occlusion")
_IMAGE_NODES = ("image", "tiledimage", "UsdUVTexture")
_ADDRESS = {"periodic": "repeat", "clamp": "clamp", "mirror": "mirror", "constant": "black"}
_COLOR_TYPES = ("color3", "vector3")


def _value(inp: Any) -> Any:
    """A MaterialX input's constant as float / tuple / bool / int / str (None when unset)."""
    text = inp.getValueString()
    if text == "":
        return None
    kind = inp.getType()
    if kind in ("float",):
        return float(text)
    if kind == "integer":
        return int(text)
    if kind == "boolean":
        return text.strip().lower() == "true"
    if kind.startswith(("color", "vector")):
        return tuple(float(x) for x in text.replace(",", " ").split())
    return text


def _sdf_type(value: Any) -> Any:
    from pxr import Sdf

    if isinstance(value, bool):
        return Sdf.ValueTypeNames.Bool
    if isinstance(value, int):
        return Sdf.ValueTypeNames.Int
    if isinstance(value, float):
        return Sdf.ValueTypeNames.Float
    if isinstance(value, tuple):
        return {2: Sdf.ValueTypeNames.Float2, 3: Sdf.ValueTypeNames.Color3f,
                4: Sdf.ValueTypeNames.Float4}.get(len(value), Sdf.ValueTypeNames.Float3)
    return Sdf.ValueTypeNames.String


def _st_varname(image: Any) -> str:
    tc = image.getInput("st" if image.getCategory() == "UsdUVTexture" else "texcoord")
    node = tc.getConnectedNode() if tc is not None else None
    if node is None:
        return "st"
    if node.getCategory() == "texcoord":
        index = node.getInput("index")
        i = int(_value(index) or 0) if index is not None else 0
        return "st" if i == 0 else f"st{i}"
    for category, name in (("geompropvalue", "geomprop"), ("UsdPrimvarReader", "varname")):
        if node.getCategory() == category:
            prop = node.getInput(name)
            return str(_value(prop) or "st") if prop is not None else "st"
    return "st"


def _author_texture(stage: Any, mat_path: str, image: Any, scale: float, where: str,
                    warns: list[str]) -> tuple[Any, str]:
    """A UsdUVTexture (+ st reader) for a MaterialX image node; returns (shader, output)."""
    from pxr import Sdf, UsdShade

    name = image.getName()
    tex = UsdShade.Shader.Define(stage, f"{mat_path}/{name}")
    tex.CreateIdAttr("UsdUVTexture")
    file_inp = image.getInput("file")
    path = file_inp.getResolvedValueString() if file_inp is not None else ""
    tex.CreateInput("file", Sdf.ValueTypeNames.Asset).Set(path.replace("\\", "/"))
    space = file_inp.getActiveColorSpace() if file_inp is not None else ""
    tex.CreateInput("sourceColorSpace", Sdf.ValueTypeNames.Token).Set(
        "sRGB" if space == "srgb_texture" else ("raw" if space else "auto"))
    category = image.getCategory()
    for axis, (mx_name, usd_name) in enumerate((("uaddressmode", "wrapS"),
                                               ("vaddressmode", "wrapT"))):
        if category == "UsdUVTexture":
            inp = image.getInput(usd_name)
            mode = str(_value(inp)) if inp is not None and _value(inp) else "useMetadata"
        elif category == "tiledimage":
            mode = "repeat"
        else:
            inp = image.getInput(mx_name)
            mode = _ADDRESS.get(str(_value(inp)) if inp is not None else "periodic", "repeat")
        tex.CreateInput(usd_name, Sdf.ValueTypeNames.Token).Set(mode)
        del axis
    if category == "tiledimage":
        tiling = image.getInput("uvtiling")
        if tiling is not None and _value(tiling) not in (None, (1.0, 1.0)):
            warn(warns, f"{where}: tiled image {name} tiles {_value(tiling)} times; "
                        "UsdUVTexture has no tiling, read once per UV unit")
    default = image.getInput("default" if category != "UsdUVTexture" else "fallback")
    if default is not None and _value(default) is not None:
        fb = np.resize(np.asarray(_value(default), np.float64).reshape(-1), 4)
        if image.getType() in _COLOR_TYPES:
            fb[3] = 1.0
        tex.CreateInput("fallback", Sdf.ValueTypeNames.Float4).Set(tuple(float(x) for x in fb))
    if scale != 1.0:
        tex.CreateInput("scale", Sdf.ValueTypeNames.Float4).Set((scale, scale, scale, 1.0))
    reader = UsdShade.Shader.Define(stage, f"{mat_path}/{name}_st")
    reader.CreateIdAttr("UsdPrimvarReader_float2")
    reader.CreateInput("varname", Sdf.ValueTypeNames.Token).Set(_st_varname(image))
    reader.CreateOutput("result", Sdf.ValueTypeNames.Float2)
    tex.CreateInput("st", Sdf.ValueTypeNames.Float2).ConnectToSource(
        reader.ConnectableAPI(), "result")
    out = "rgb" if image.getType() in _COLOR_TYPES else "r"
    tex.CreateOutput(out, Sdf.ValueTypeNames.Float3 if out == "rgb" else Sdf.ValueTypeNames.Float)
    return tex, out


def _author_material(stage: Any, material: Any, warns: list[str], source: str) -> None:
    from pxr import Sdf, UsdShade

    mat_path = f"/MaterialX/Materials/{material.getName()}"
    where = f"MaterialX material {material.getName()} ({source})"
    surf = material.getInput("surfaceshader")
    node = surf.getConnectedNode() if surf is not None else None
    mat = UsdShade.Material.Define(stage, mat_path)
    if node is None:
        warn(warns, f"{where}: no surface shader; UsdPreviewSurface defaults")
        return
    sid = f"ND_{node.getCategory()}_surfaceshader"
    mtlx_shader = UsdShade.Shader.Define(stage, f"{mat_path}/{node.getName()}")
    mtlx_shader.CreateIdAttr(sid)
    mtlx_shader.CreateOutput("surface", Sdf.ValueTypeNames.Token)
    mat.CreateSurfaceOutput("mtlx").ConnectToSource(mtlx_shader.ConnectableAPI(), "surface")
    constants: dict[str, Any] = {}
    images: dict[str, Any] = {}
    other: set[str] = set()
    for inp in node.getInputs():
        upstream = inp.getConnectedNode()
        if upstream is None:
            value = _value(inp)
            if value is not None:
                constants[inp.getName()] = value
                mtlx_shader.CreateInput(inp.getName(), _sdf_type(value)).Set(value)
        elif upstream.getCategory() in _IMAGE_NODES:
            images[inp.getName()] = upstream
        else:
            other.add(inp.getName())
    textured = (_STANDARD_TEXTURED if sid == STANDARD_SURFACE else
                {n: (n, None) for n in _PREVIEW_TEXTURED} if sid == MTLX_PREVIEW_SURFACE else {})
    for name in sorted(set(images) - set(textured)):
        other.add(name)

    def lost(text: str) -> None:
        warn(warns, f"{where}: shader {node.getName()} ({sid}): {text}")

    if sid not in (STANDARD_SURFACE, MTLX_PREVIEW_SURFACE):
        lost("not a standard_surface or UsdPreviewSurface; UsdPreviewSurface defaults")
        return
    params = preview_params(sid, constants.get, lambda n: n in other, lost)
    preview = UsdShade.Shader.Define(stage, f"{mat_path}/PreviewSurface")
    preview.CreateIdAttr("UsdPreviewSurface")
    preview.CreateOutput("surface", Sdf.ValueTypeNames.Token)
    mat.CreateSurfaceOutput().ConnectToSource(preview.ConnectableAPI(), "surface")
    for name, value in sorted(params.items()):
        v = tuple(float(x) for x in value) if isinstance(value, (tuple, np.ndarray)) else value
        preview.CreateInput(name, _sdf_type(v)).Set(v)
    for mx_name, image in sorted(images.items()):
        if mx_name not in textured:
            continue
        usd_name, scaled_by = textured[mx_name]
        scale = float(constants.get(scaled_by, 1.0)) if scaled_by else 1.0
        tex, out = _author_texture(stage, mat_path, image, scale, where, warns)
        kind = (Sdf.ValueTypeNames.Color3f if out == "rgb" else Sdf.ValueTypeNames.Float)
        preview.CreateInput(usd_name, kind).ConnectToSource(tex.ConnectableAPI(), out)


def translated_layer(mtlx_file: str, warns: list[str]) -> Any:
    """The document's materials as an in-memory Sdf layer whose identifier is `mtlx_file` +
    `TRANSLATED_SUFFIX` (so relative paths anchor beside the document); the same layer object
    for the same file while it is alive.

    raises : AssetError naming the file when MaterialX cannot read it
    """
    import MaterialX as mx
    from pxr import Sdf, Usd, UsdGeom

    doc = mx.createDocument()
    options = mx.XmlReadOptions()
    options.readXIncludeFunction = None  # an include could name a file outside the asset
    try:
        mx.readFromXmlFile(doc, mtlx_file, mx.FileSearchPath(), options)
    except Exception as exc:  # MaterialX raises its own exception types from C++
        raise AssetError(f"MaterialX cannot read the document: {' '.join(str(exc).split())}",
                         path=mtlx_file) from exc
    ident = mtlx_file + TRANSLATED_SUFFIX
    layer = Sdf.Layer.Find(ident) or Sdf.Layer.New(Sdf.FileFormat.FindById("usda"), ident)
    layer.Clear()
    stage = Usd.Stage.Open(layer)
    scope = UsdGeom.Scope.Define(stage, "/MaterialX")
    UsdGeom.Scope.Define(stage, "/MaterialX/Materials")
    stage.SetDefaultPrim(scope.GetPrim())
    source = os.path.basename(mtlx_file)
    for material in sorted(doc.getMaterialNodes(), key=lambda m: m.getName()):
        _author_material(stage, material, warns, source)
    return layer
