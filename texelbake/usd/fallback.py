"""The baked asset's UsdPreviewSurface fallback material (what any USD viewer shows): its
authoring per LOD, with the baked maps and the constants carried from the source material and
texelbake's CPM shader on the `texelbake` render context, and reading one back as authored.
`texelbake.usd.write` and `texelbake.usd.read` write and read the bundle through these."""

from __future__ import annotations

from typing import Any

import numpy as np
from pxr import Gf, Sdf, Usd, UsdShade

from texelbake.errors import AssetError
from texelbake.model import SHADER_CPM
from texelbake.usd.shaderdefs import author_shader


def author_preview_material(
    stage: Usd.Stage, path: str, albedo_file: str, normal_file: str, cpm_scope: str,
    roughness_file: str | None = None, occlusion_file: str | None = None,
    constants: dict[str, Any] | None = None, specular_file: str | None = None, *,
    opacity_file: str | None = None, metallic_file: str | None = None,
) -> UsdShade.Material:
    """UsdPreviewSurface with the baked maps (what any viewer shows): diffuseColor and normal,
    and when given roughness and occlusion (single-channel) textures and constant inputs
    carried from the source material, and a specularColor texture (sRGB, for the specular
    workflow) when given; texelbake's CPM shader on the `texelbake` render context. With
    `opacity_file` (single-channel) the surface is a cut-out: opacity from it,
    opacityThreshold 0.5; with `metallic_file` (single-channel) metallic is read from it."""
    mat = UsdShade.Material.Define(stage, path)
    reader = UsdShade.Shader.Define(stage, f"{path}/stReader")
    reader.CreateIdAttr("UsdPrimvarReader_float2")
    reader.CreateInput("varname", Sdf.ValueTypeNames.String).Set("st")
    st_out = reader.CreateOutput("result", Sdf.ValueTypeNames.Float2)
    surf = UsdShade.Shader.Define(stage, f"{path}/PreviewSurface")
    surf.CreateIdAttr("UsdPreviewSurface")
    if roughness_file is None:
        surf.CreateInput("roughness", Sdf.ValueTypeNames.Float).Set(0.6)
    for name, value in sorted((constants or {}).items()):
        if name in _COLOR3_INPUTS:
            surf.CreateInput(name, Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(*map(float, value)))
        elif name == "useSpecularWorkflow":
            surf.CreateInput(name, Sdf.ValueTypeNames.Int).Set(int(value))
        else:
            surf.CreateInput(name, Sdf.ValueTypeNames.Float).Set(float(value))
    textures = [
        ("diffuseColor", albedo_file, "sRGB", "rgb", Sdf.ValueTypeNames.Float3,
         Sdf.ValueTypeNames.Color3f, None, None),
        ("normal", normal_file, "raw", "rgb", Sdf.ValueTypeNames.Float3,
         Sdf.ValueTypeNames.Normal3f, (2.0, 2.0, 2.0, 1.0), (-1.0, -1.0, -1.0, 0.0)),
    ]
    if specular_file is not None:
        textures.append(("specularColor", specular_file, "sRGB", "rgb", Sdf.ValueTypeNames.Float3,
                         Sdf.ValueTypeNames.Color3f, None, None))
    if opacity_file is not None:
        surf.CreateInput("opacityThreshold", Sdf.ValueTypeNames.Float).Set(0.5)
    for name, file in (("roughness", roughness_file), ("metallic", metallic_file),
                       ("occlusion", occlusion_file), ("opacity", opacity_file)):
        if file is not None:
            textures.append((name, file, "raw", "r", Sdf.ValueTypeNames.Float,
                             Sdf.ValueTypeNames.Float, None, None))
    for name, file, cs, out_name, out_type, in_type, scale, bias in textures:
        tex = UsdShade.Shader.Define(stage, f"{path}/{name}Texture")
        tex.CreateIdAttr("UsdUVTexture")
        tex.CreateInput("file", Sdf.ValueTypeNames.Asset).Set(Sdf.AssetPath(file))
        tex.CreateInput("sourceColorSpace", Sdf.ValueTypeNames.Token).Set(cs)
        tex.CreateInput("wrapS", Sdf.ValueTypeNames.Token).Set("clamp")
        tex.CreateInput("wrapT", Sdf.ValueTypeNames.Token).Set("clamp")
        if scale is not None and bias is not None:
            tex.CreateInput("scale", Sdf.ValueTypeNames.Float4).Set(Gf.Vec4f(*scale))
            tex.CreateInput("bias", Sdf.ValueTypeNames.Float4).Set(Gf.Vec4f(*bias))
        tex.CreateInput("st", Sdf.ValueTypeNames.Float2).ConnectToSource(st_out)
        out = tex.CreateOutput(out_name, out_type)
        surf.CreateInput(name, in_type).ConnectToSource(out)
    mat.CreateSurfaceOutput().ConnectToSource(surf.CreateOutput("surface", Sdf.ValueTypeNames.Token))
    cpm = author_shader(stage, f"{path}/CPM", SHADER_CPM)
    cpm.GetPrim().CreateRelationship("texelbake:levels", custom=True).SetTargets([Sdf.Path(cpm_scope)])
    mat.CreateSurfaceOutput("texelbake").ConnectToSource(
        cpm.CreateOutput("surface", Sdf.ValueTypeNames.Token)
    )
    return mat


_COLOR3_INPUTS = ("diffuseColor", "specularColor", "emissiveColor")


def fallback_material_path(lod: int) -> str:
    """The payload path of LOD `lod`'s (1-based) UsdPreviewSurface fallback material."""
    return "/Baked/Looks/BakedPreview" if lod == 1 else f"/Baked/Looks/BakedPreview_LOD{lod}"


def read_preview_material(stage: Usd.Stage, mesh_path: Sdf.Path) -> dict[str, Any]:
    """The UsdPreviewSurface bound to a LOD mesh, as authored: {"path", "constants": input ->
    value, "textures": input -> (h, w, c) float64 texel values after the UsdUVTexture's colour
    space, scale and bias, the component its output names}. Empty dict when none is bound."""
    from texelbake.io.images import read_pixels, srgb_to_linear

    prim = stage.GetPrimAtPath(mesh_path)
    if not prim:
        return {}
    mat, _ = UsdShade.MaterialBindingAPI(prim).ComputeBoundMaterial()
    if not mat:
        return {}
    surf = mat.ComputeSurfaceSource()[0]
    if not surf or surf.GetIdAttr().Get() != "UsdPreviewSurface":
        return {}
    consts: dict[str, Any] = {}
    texs: dict[str, np.ndarray] = {}
    for inp in surf.GetInputs():
        name = inp.GetBaseName()
        src = inp.GetConnectedSources()[0]
        if not src:
            v = inp.Get()
            consts[name] = np.asarray(v, dtype=np.float64) if v is not None else None
            continue
        tex = UsdShade.Shader(src[0].source.GetPrim())
        if tex.GetIdAttr().Get() != "UsdUVTexture":
            raise AssetError(f"input {name} is connected to {tex.GetIdAttr().Get()}, not a "
                             "UsdUVTexture", prim=str(tex.GetPath()))
        file = tex.GetInput("file").Get()
        fpath = file.resolvedPath if file is not None else ""
        if not fpath:
            raise AssetError("texture file does not resolve", prim=str(tex.GetPath()))
        px = read_pixels(fpath, prim=str(tex.GetPath()))[0].astype(np.float64)
        cs = tex.GetInput("sourceColorSpace")
        if cs and cs.Get() == "sRGB":
            px[..., :3] = srgb_to_linear(px[..., :3].astype(np.float32)).astype(np.float64)
        c = px.shape[2]
        for key, default in (("scale", 1.0), ("bias", 0.0)):
            attr = tex.GetInput(key)
            vec = np.asarray(attr.Get(), dtype=np.float64)[:c] if attr and attr.Get() is not None \
                else np.full(c, default)
            px = px * vec if key == "scale" else px + vec
        comp = {"r": [0], "g": [1], "b": [2], "a": [3], "rgb": [0, 1, 2]}[src[0].sourceName]
        texs[name] = px[..., comp]
    return {"path": str(mat.GetPath()), "constants": consts, "textures": texs}
