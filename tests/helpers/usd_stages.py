"""Small builders of USD stages for the ingest tests (tests/asset/test_ingest.py,
tests/asset/test_bad_assets.py). Everything is authored with pxr; nothing here reads texelbake."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import OpenImageIO as oiio
from pxr import Sdf, Usd, UsdGeom, UsdShade, Vt


def new_stage(path: Path) -> Usd.Stage:
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    root = UsdGeom.Xform.Define(stage, "/Root")
    stage.SetDefaultPrim(root.GetPrim())
    return stage


def grid_mesh(stage: Usd.Stage, path: str, nx: int = 2, ny: int = 2,
              z: float = 0.0) -> UsdGeom.Mesh:
    """nx x ny unit quads in the z = const plane, counter-clockwise seen from +z."""
    xs, ys = np.meshgrid(np.arange(nx + 1, dtype=float), np.arange(ny + 1, dtype=float))
    pts = np.stack([xs.ravel(), ys.ravel(), np.full(xs.size, z)], axis=1)
    idx = []
    for j in range(ny):
        for i in range(nx):
            v = j * (nx + 1) + i
            idx += [v, v + 1, v + nx + 2, v + nx + 1]
    mesh = UsdGeom.Mesh.Define(stage, path)
    mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(pts.astype(np.float32)))
    mesh.CreateFaceVertexCountsAttr([4] * (nx * ny))
    mesh.CreateFaceVertexIndicesAttr(idx)
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    return mesh


def triangle_mesh(stage: Usd.Stage, path: str, points, indices) -> UsdGeom.Mesh:
    points = np.asarray(points, dtype=np.float32).reshape(-1, 3)
    indices = [int(i) for i in np.asarray(indices).reshape(-1)]
    mesh = UsdGeom.Mesh.Define(stage, path)
    mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(points))
    mesh.CreateFaceVertexCountsAttr([3] * (len(indices) // 3))
    mesh.CreateFaceVertexIndicesAttr(indices)
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)  # flat (unauthored: catmullClark)
    return mesh


def write_png(path: Path, pixels_u8: np.ndarray) -> None:
    pixels_u8 = np.ascontiguousarray(pixels_u8, dtype=np.uint8)
    h, w, c = pixels_u8.shape
    out = oiio.ImageOutput.create(str(path))
    assert out is not None, oiio.geterror()
    assert out.open(str(path), oiio.ImageSpec(w, h, c, oiio.UINT8)), out.geterror()
    assert out.write_image(pixels_u8)
    out.close()


def preview_material(stage: Usd.Stage, path: str, diffuse=(0.5, 0.5, 0.5),
                     texture: str | None = None, *, color_space: str | None = None,
                     varname: str = "st", output: str = "rgb",
                     connect_to: str = "diffuseColor") -> UsdShade.Material:
    """A UsdPreviewSurface material, optionally with a UsdUVTexture + UsdPrimvarReader_float2."""
    mat = UsdShade.Material.Define(stage, path)
    shader = UsdShade.Shader.Define(stage, f"{path}/Surface")
    shader.CreateIdAttr("UsdPreviewSurface")
    shader.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).Set(tuple(diffuse))
    shader.CreateInput("roughness", Sdf.ValueTypeNames.Float).Set(0.25)
    mat.CreateSurfaceOutput().ConnectToSource(shader.ConnectableAPI(), "surface")
    if texture is not None:
        reader = UsdShade.Shader.Define(stage, f"{path}/StReader")
        reader.CreateIdAttr("UsdPrimvarReader_float2")
        reader.CreateInput("varname", Sdf.ValueTypeNames.Token).Set(varname)
        reader.CreateOutput("result", Sdf.ValueTypeNames.Float2)
        tex = UsdShade.Shader.Define(stage, f"{path}/Texture")
        tex.CreateIdAttr("UsdUVTexture")
        tex.CreateInput("file", Sdf.ValueTypeNames.Asset).Set(texture)
        tex.CreateInput("st", Sdf.ValueTypeNames.Float2).ConnectToSource(
            reader.ConnectableAPI(), "result")
        if color_space is not None:
            tex.CreateInput("sourceColorSpace", Sdf.ValueTypeNames.Token).Set(color_space)
        out_type = Sdf.ValueTypeNames.Float3 if output == "rgb" else Sdf.ValueTypeNames.Float
        tex.CreateOutput(output, out_type)
        in_type = (Sdf.ValueTypeNames.Color3f if connect_to == "diffuseColor"
                   else Sdf.ValueTypeNames.Float)
        shader.CreateInput(connect_to, in_type).ConnectToSource(tex.ConnectableAPI(), output)
    return mat


def bind(prim_or_schema, material: UsdShade.Material) -> None:
    prim = prim_or_schema.GetPrim() if hasattr(prim_or_schema, "GetPrim") else prim_or_schema
    UsdShade.MaterialBindingAPI.Apply(prim).Bind(material)


def uv_texture(stage: Usd.Stage, looks: str, name: str, file: str, output: str,
               color_space: str = "raw", scale=None, bias=None) -> UsdShade.Shader:
    """A UsdUVTexture `<looks>/<name>` reading `file` at the `st` primvar (a
    UsdPrimvarReader_float2 `<looks>/StReader`, made once), with the output `output` ("r" a
    float, "rgb" a float3) and optional scale and bias (4 floats each); connect a surface
    input to it with `.ConnectableAPI()` and `output`."""
    reader_path = f"{looks}/StReader"
    reader = UsdShade.Shader(stage.GetPrimAtPath(reader_path))
    if not reader:
        reader = UsdShade.Shader.Define(stage, reader_path)
        reader.CreateIdAttr("UsdPrimvarReader_float2")
        reader.CreateInput("varname", Sdf.ValueTypeNames.String).Set("st")
        reader.CreateOutput("result", Sdf.ValueTypeNames.Float2)
    tex = UsdShade.Shader.Define(stage, f"{looks}/{name}")
    tex.CreateIdAttr("UsdUVTexture")
    tex.CreateInput("file", Sdf.ValueTypeNames.Asset).Set(file)
    tex.CreateInput("sourceColorSpace", Sdf.ValueTypeNames.Token).Set(color_space)
    if scale is not None:
        tex.CreateInput("scale", Sdf.ValueTypeNames.Float4).Set(tuple(map(float, scale)))
    if bias is not None:
        tex.CreateInput("bias", Sdf.ValueTypeNames.Float4).Set(tuple(map(float, bias)))
    tex.CreateInput("st", Sdf.ValueTypeNames.Float2).ConnectToSource(reader.ConnectableAPI(),
                                                                     "result")
    tex.CreateOutput(output, Sdf.ValueTypeNames.Float if len(output) == 1
                     else Sdf.ValueTypeNames.Float3)
    return tex
