"""Small assets shaped like the ones studios ship, built with pxr (and plain XML for MaterialX)
for the ingest, upload and Blender tests: a kit whose textures tile UVs far outside 0..1 under
a non-`st` primvar, variants naming files outside the asset or missing from it, a material in a
referenced MaterialX document, a texture missing from the download. Nothing here reads
texelbake."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from pxr import Sdf, Usd, UsdGeom, UsdShade, Vt

from tests.helpers.usd_stages import bind, new_stage, preview_material, uv_texture, write_png

#: the kit's swatches (8-bit sRGB) and the faces of the box each covers (GeomSubsets)
KIT_SWATCHES = {"Red": (200, 30, 25), "Grey": (128, 128, 128), "Blue": (30, 60, 210)}
KIT_FACES = {"Red": [0, 1], "Grey": [2, 3], "Blue": [4, 5]}
#: the kit's UVs span this range on every face (the public kit's were -37.8..37.8)
KIT_UV = 37.8

_BOX_POINTS = np.array([[x, y, z] for z in (-0.5, 0.5) for y in (-0.5, 0.5) for x in (-0.5, 0.5)],
                       dtype=np.float32)
_BOX_QUADS = [[0, 2, 3, 1], [4, 5, 7, 6], [0, 1, 5, 4], [2, 6, 7, 3], [0, 4, 6, 2],
              [1, 3, 7, 5]]  # -z, +z, -y, +y, -x, +x, counter-clockwise from outside


def box_mesh(stage: Usd.Stage, path: str, uv_name: str = "st",
             uv_span: tuple[float, float] = (0.0, 1.0)) -> UsdGeom.Mesh:
    """A unit cube (6 quads) with faceVarying UVs `uv_name` spanning `uv_span` on every face."""
    mesh = UsdGeom.Mesh.Define(stage, path)
    mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(_BOX_POINTS))
    mesh.CreateFaceVertexCountsAttr([4] * 6)
    mesh.CreateFaceVertexIndicesAttr([int(i) for q in _BOX_QUADS for i in q])
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    mesh.CreateExtentAttr([(-0.5, -0.5, -0.5), (0.5, 0.5, 0.5)])
    lo, hi = uv_span
    corner = np.array([[lo, lo], [hi, lo], [hi, hi], [lo, hi]], dtype=np.float32)
    UsdGeom.PrimvarsAPI(mesh).CreatePrimvar(
        uv_name, Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.faceVarying).Set(
        Vt.Vec2fArray.FromNumpy(np.tile(corner, (6, 1))))
    return mesh


def texture_material(stage: Usd.Stage, path: str, texture: str, *, st_varname: str | None,
                     diffuse=(0.5, 0.5, 0.5), fallback=None) -> UsdShade.Material:
    """UsdPreviewSurface whose diffuseColor reads `texture`; `st_varname` None: no st input
    (and no wrap modes authored), as the kit ships."""
    mat = UsdShade.Material.Define(stage, path)
    surface = UsdShade.Shader.Define(stage, f"{path}/Surface")
    surface.CreateIdAttr("UsdPreviewSurface")
    surface.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).Set(tuple(diffuse))
    surface.CreateInput("roughness", Sdf.ValueTypeNames.Float).Set(0.6)
    mat.CreateSurfaceOutput().ConnectToSource(surface.ConnectableAPI(), "surface")
    tex = UsdShade.Shader.Define(stage, f"{path}/Texture")
    tex.CreateIdAttr("UsdUVTexture")
    tex.CreateInput("file", Sdf.ValueTypeNames.Asset).Set(texture)
    tex.CreateOutput("rgb", Sdf.ValueTypeNames.Float3)
    if fallback is not None:
        tex.CreateInput("fallback", Sdf.ValueTypeNames.Float4).Set(tuple(fallback))
    if st_varname is not None:
        reader = UsdShade.Shader.Define(stage, f"{path}/StReader")
        reader.CreateIdAttr("UsdPrimvarReader_float2")
        reader.CreateInput("varname", Sdf.ValueTypeNames.Token).Set(st_varname)
        reader.CreateOutput("result", Sdf.ValueTypeNames.Float2)
        tex.CreateInput("st", Sdf.ValueTypeNames.Float2).ConnectToSource(
            reader.ConnectableAPI(), "result")
    surface.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).ConnectToSource(
        tex.ConnectableAPI(), "rgb")
    return mat


def kit_asset(folder: Path) -> Path:
    """A box whose three materials read 32x32 colour swatches through UsdUVTexture nodes with
    no st input and no wrap modes, its UVs in -KIT_UV..KIT_UV under `primvars:map1`."""
    folder.mkdir(parents=True, exist_ok=True)
    stage = new_stage(folder / "kit.usda")
    mesh = box_mesh(stage, "/Root/Box", "map1", (-KIT_UV, KIT_UV))
    binding = UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim())
    for name, rgb in KIT_SWATCHES.items():
        write_png(folder / f"{name.lower()}.png", np.broadcast_to(
            np.array(rgb, np.uint8), (32, 32, 3)))
        mat = texture_material(stage, f"/Root/Looks/{name}", f"./{name.lower()}.png",
                               st_varname=None)
        subset = binding.CreateMaterialBindSubset(name, Vt.IntArray(KIT_FACES[name]))
        UsdShade.MaterialBindingAPI.Apply(subset.GetPrim()).Bind(mat)
    stage.Save()
    return folder / "kit.usda"


def textured_box(folder: Path, texture: str = "./print.png", *, fallback=None) -> Path:
    """A box with a printed texture (a 16x16 two-colour checker of 4x4 cells, st 0..1); the
    texture file is written unless `texture` names a file that is not there on purpose."""
    folder.mkdir(parents=True, exist_ok=True)
    cells = (np.indices((16, 16)) // 4).sum(axis=0) % 2
    pixels = np.where(cells[..., None] == 1, np.array([220, 180, 40], np.uint8),
                      np.array([40, 90, 160], np.uint8)).astype(np.uint8)
    if texture == "./print.png":
        write_png(folder / "print.png", pixels)
    stage = new_stage(folder / "box.usda")
    mesh = box_mesh(stage, "/Root/Box")
    bind(mesh, texture_material(stage, "/Root/Looks/Print", texture, st_varname="st",
                                diffuse=(0.8, 0.2, 0.2), fallback=fallback))
    stage.Save()
    return folder / "box.usda"


def normal_mapped_box(folder: Path, with_map: bool = True) -> Path:
    """A grey flat-shaded box whose UsdPreviewSurface reads a tangent-space normal map (raw,
    scale 2, bias -1: 16x16 texels of vertical stripes tilted 35° toward +u and -u, 4 texels
    wide) on every face; `with_map` False: the same box without the normal input."""
    folder.mkdir(parents=True, exist_ok=True)
    t = np.radians(35.0)
    cols = (np.arange(16) // 4) % 2
    nrm = np.stack([np.where(cols == 0, np.sin(t), -np.sin(t)), np.zeros(16),
                    np.full(16, np.cos(t))], axis=1)
    write_png(folder / "bumps.png", np.broadcast_to(
        np.round((nrm * 0.5 + 0.5) * 255).astype(np.uint8), (16, 16, 3)))
    stage = new_stage(folder / "box.usda")
    mesh = box_mesh(stage, "/Root/Box")
    # flat faces (faceVarying normals): without the map both renderers shade each face flat
    quads = _BOX_POINTS[np.asarray(_BOX_QUADS)]  # (6, 4, 3)
    fn = np.cross(quads[:, 1] - quads[:, 0], quads[:, 2] - quads[:, 0])
    fn /= np.linalg.norm(fn, axis=1, keepdims=True)
    mesh.CreateNormalsAttr(Vt.Vec3fArray.FromNumpy(np.repeat(fn, 4, axis=0).astype(np.float32)))
    mesh.SetNormalsInterpolation(UsdGeom.Tokens.faceVarying)
    mat = preview_material(stage, "/Root/Looks/Bumps", diffuse=(0.6, 0.6, 0.6))
    if with_map:
        surface = UsdShade.Shader(stage.GetPrimAtPath("/Root/Looks/Bumps/Surface"))
        tex = uv_texture(stage, "/Root/Looks/Bumps", "NormalMap", "./bumps.png", "rgb",
                         scale=(2, 2, 2, 1), bias=(-1, -1, -1, 0))
        surface.CreateInput("normal", Sdf.ValueTypeNames.Normal3f).ConnectToSource(
            tex.ConnectableAPI(), "rgb")
    bind(mesh, mat)
    stage.Save()
    return folder / "box.usda"


def fallback_colour_box(folder: Path, fallback) -> Path:
    """The textured box with `fallback` (rgb) as its constant diffuseColor and no texture:
    what a renderer shows of `textured_box(..., "./gone.png", fallback=...)` (Blender paints a
    missing image magenta, so this is the reference its render is compared with)."""
    ref = textured_box(folder, "./print.png")
    stage = Usd.Stage.Open(str(ref))
    surface = UsdShade.Shader(stage.GetPrimAtPath("/Root/Looks/Print/Surface"))
    surface.GetInput("diffuseColor").GetAttr().Clear()
    surface.GetInput("diffuseColor").GetAttr().Set(tuple(fallback))
    stage.RemovePrim("/Root/Looks/Print/Texture")
    stage.Save()
    return ref


def wheel_variants_asset(folder: Path) -> tuple[Path, Path]:
    """`folder/car/root.usda`: a body and a `wheels` variant set whose selected variant
    `stock` is local; `sport` references `../../../wheels/wheelVariants.usda` (a real file
    outside the asset), `racing` a file missing from the download. Returns (root, outside)."""
    asset = folder / "a" / "b" / "car"
    asset.mkdir(parents=True, exist_ok=True)
    outside = folder / "wheels" / "wheelVariants.usda"
    outside.parent.mkdir(parents=True, exist_ok=True)
    other = new_stage(outside)
    box_mesh(other, "/Root/Wheel")
    other.Save()
    stage = new_stage(asset / "root.usda")
    box_mesh(stage, "/Root/Body")
    vset = stage.GetPrimAtPath("/Root").GetVariantSets().AddVariantSet("wheels")
    for name in ("stock", "sport", "racing"):
        vset.AddVariant(name)
        vset.SetVariantSelection(name)
        with vset.GetVariantEditContext():
            wheel = stage.DefinePrim("/Root/Wheels")
            if name == "stock":
                UsdGeom.Xformable(box_mesh(stage, "/Root/Wheels/W")).AddTranslateOp().Set(
                    (1.5, 0.0, 0.0))
            elif name == "sport":
                wheel.GetReferences().AddReference("../../../wheels/wheelVariants.usda")
            else:
                wheel.GetReferences().AddReference("./parts/racing_wheels.usda")
    vset.SetVariantSelection("stock")
    paint = preview_material(stage, "/Root/Looks/Paint", (0.6, 0.45, 0.3))
    bind(stage.GetPrimAtPath("/Root"), paint)  # inherited by the body and every wheel
    stage.Save()
    return asset / "root.usda", outside


MTLX_DOC = """<?xml version="1.0"?>
<materialx version="1.38" fileprefix="./textures/">
  <nodegraph name="NG_rook">
    <image name="rook_color" type="color3">
      <input name="file" type="filename" value="{texture}" colorspace="srgb_texture" />
    </image>
    <output name="out_color" type="color3" nodename="rook_color" />
  </nodegraph>
  <standard_surface name="SR_rook" type="surfaceshader">
    <input name="base" type="float" value="1.0" />
    <input name="base_color" type="color3" nodegraph="NG_rook" output="out_color" />
    <input name="specular_roughness" type="float" value="0.6" />
    <input name="metalness" type="float" value="0.0" />
  </standard_surface>
  <surfacematerial name="Rook" type="material">
    <input name="surfaceshader" type="surfaceshader" nodename="SR_rook" />
  </surfacematerial>
</materialx>
"""


def mtlx_asset(folder: Path, texture: str = "rook_color.png") -> Path:
    """A box bound to `/Root/Looks/Rook`, which references `@./Rook_mat.mtlx@</MaterialX/
    Materials/Rook>`: a standard_surface whose base_color is an image (the checker of
    `textured_box`, under the document's fileprefix `./textures/`)."""
    (folder / "textures").mkdir(parents=True, exist_ok=True)
    cells = (np.indices((16, 16)) // 4).sum(axis=0) % 2
    write_png(folder / "textures" / "rook_color.png",
              np.where(cells[..., None] == 1, np.array([220, 180, 40], np.uint8),
                       np.array([40, 90, 160], np.uint8)).astype(np.uint8))
    (folder / "Rook_mat.mtlx").write_text(MTLX_DOC.format(texture=texture))
    stage = new_stage(folder / "rook.usda")
    mesh = box_mesh(stage, "/Root/Box")
    looks = stage.DefinePrim("/Root/Looks/Rook")
    looks.GetReferences().AddReference("./Rook_mat.mtlx", "/MaterialX/Materials/Rook")
    UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim()).GetDirectBindingRel().SetTargets(
        [looks.GetPath()])
    stage.Save()
    return folder / "rook.usda"
