"""Authoring a scene description as USD (materials, meshes, camera, lights) and writing it
with its textures (`write_scene`)."""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path
from types import MappingProxyType
from typing import Any

import numpy as np
from pxr import Gf, Kind, Sdf, Sdr, Usd, UsdGeom, UsdLux, UsdShade, Vt

from texelbake.errors import SettingsError
from texelbake.io.atomic import atomic_path
from texelbake.io.images import write_png
from texelbake.model import SHADER_PREVIEW
from texelbake.testscenes.bolt import build_bolt
from texelbake.testscenes.cloisonne import build_cloisonne
from texelbake.testscenes.cylinder import build_cylinder
from texelbake.testscenes.params import (
    LAYER_SUFFIXES,
    METERS_PER_UNIT,
    SCENE_PARAMS,
    SEEDS,
    check_scene,
)
from texelbake.testscenes.spec import LightSpec, MaterialSpec, MeshSpec, unit
from texelbake.testscenes.wall import build_wall
from texelbake.usd.shaderdefs import (
    ALL_SHADER_INPUTS,
    author_shader,
    input_type,
    write_definitions,
)

#: the angular diameter the scenes' distant lights author (the Sun's, UsdLux's fallback);
#: the renderer treats distant lights as directions (hard shadows)
DISTANT_ANGLE_DEGREES = 0.53

_BUILDERS = MappingProxyType(
    {"cylinder": build_cylinder, "wall": build_wall, "bolt": build_bolt, "cloisonne": build_cloisonne}
)


def _sdf_type(shader_id: str, input_name: str) -> Sdf.ValueTypeName:
    """The Sdf type the shader's definition declares for an input (so the validator's type
    check agrees): texelbake's own definitions for its ids, Sdr's for UsdPreviewSurface."""
    if shader_id in ALL_SHADER_INPUTS:
        return input_type(shader_id, input_name)
    node = Sdr.Registry().GetShaderNodeByIdentifier(shader_id)
    prop = node.GetShaderInput(input_name) if node else None
    if prop is None:
        raise SettingsError(f"shader {shader_id!r} has no input {input_name!r} in Sdr")
    return prop.GetTypeAsSdfType().GetSdfType()


def _set_inputs(shader: UsdShade.Shader, shader_id: str, values: Mapping[str, Any]) -> None:
    for name in sorted(values):
        shader.CreateInput(name, _sdf_type(shader_id, name)).Set(values[name])


def _author_material(stage: Usd.Stage, path: str, spec: MaterialSpec,
                     texture_files: Mapping[str, str]) -> UsdShade.Material:
    material = UsdShade.Material.Define(stage, path)
    preview = UsdShade.Shader.Define(stage, f"{path}/PreviewSurface")
    preview.CreateIdAttr(SHADER_PREVIEW)
    _set_inputs(preview, SHADER_PREVIEW, spec.preview)
    material.CreateSurfaceOutput().ConnectToSource(
        preview.CreateOutput("surface", Sdf.ValueTypeNames.Token))
    if spec.texture is not None:
        input_name, role = spec.texture
        reader = UsdShade.Shader.Define(stage, f"{path}/StReader")
        reader.CreateIdAttr("UsdPrimvarReader_float2")
        _set_inputs(reader, "UsdPrimvarReader_float2", {"varname": "st"})
        tex = UsdShade.Shader.Define(stage, f"{path}/{role.capitalize()}Texture")
        tex.CreateIdAttr("UsdUVTexture")
        _set_inputs(tex, "UsdUVTexture", {
            "file": Sdf.AssetPath(f"./{texture_files[role]}"),
            "wrapS": "repeat", "wrapT": "repeat", "sourceColorSpace": "sRGB",
            "fallback": Gf.Vec4f(0.5, 0.5, 0.5, 1.0),
        })
        tex.CreateInput("st", _sdf_type("UsdUVTexture", "st")).ConnectToSource(
            reader.CreateOutput("result", Sdf.ValueTypeNames.Float2))
        preview.CreateInput(input_name, _sdf_type(SHADER_PREVIEW, input_name)).ConnectToSource(
            tex.CreateOutput("rgb", Sdf.ValueTypeNames.Float3))
    if spec.texelbake_id is not None:
        own = author_shader(stage, f"{path}/TexelbakeSurface", spec.texelbake_id)
        _set_inputs(own, spec.texelbake_id, spec.texelbake_inputs)
        material.CreateSurfaceOutput("texelbake").ConnectToSource(
            own.CreateOutput("surface", Sdf.ValueTypeNames.Token))
    return material


def _bind(prim: Usd.Prim, material: UsdShade.Material) -> None:
    UsdShade.MaterialBindingAPI.Apply(prim).Bind(material)


def _author_mesh(stage: Usd.Stage, path: str, spec: MeshSpec,
                 materials: Mapping[str, UsdShade.Material]) -> UsdGeom.Mesh:
    mesh = UsdGeom.Mesh.Define(stage, path)
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(spec.points, np.float32)))
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.ascontiguousarray(spec.counts)))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(np.ascontiguousarray(spec.indices)))
    mesh.CreateNormalsAttr(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(spec.normals,
                                                                         np.float32)))
    mesh.SetNormalsInterpolation(spec.normals_interp)
    UsdGeom.PrimvarsAPI(mesh).CreatePrimvar(
        "st", Sdf.ValueTypeNames.TexCoord2fArray, spec.st_interp
    ).Set(Vt.Vec2fArray.FromNumpy(np.ascontiguousarray(spec.st, np.float32)))
    mesh.CreateExtentAttr(UsdGeom.Boundable.ComputeExtentFromPlugins(mesh,
                                                                     Usd.TimeCode.Default()))
    if spec.material is not None:
        _bind(mesh.GetPrim(), materials[spec.material])
    if spec.subsets:
        binding = UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim())
        for name, faces, mat in spec.subsets:
            subset = binding.CreateMaterialBindSubset(
                name, Vt.IntArray.FromNumpy(np.ascontiguousarray(faces, np.int32)),
                UsdGeom.Tokens.face)
            _bind(subset.GetPrim(), materials[mat])
        binding.SetMaterialBindSubsetsFamilyType(UsdGeom.Tokens.partition)
    return mesh


def _look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray) -> Gf.Matrix4d:
    """USD (row-vector) transform of a camera or light at `eye` whose local -Z points at
    `target` and whose local +Y leans toward `up`."""
    z = unit(eye - target)
    x = unit(np.cross(up, z))
    y = np.cross(z, x)
    m = np.eye(4)
    m[0, :3], m[1, :3], m[2, :3], m[3, :3] = x, y, z, eye
    m = np.round(m, 12) + 0.0  # no -0.0 or 1e-17 noise in the written layer
    return Gf.Matrix4d(m.tolist())


def _author_camera(stage: Usd.Stage, path: str, centre: np.ndarray, radius: float,
                   view_from: np.ndarray) -> None:
    focal, aperture = 50.0, 24.0  # mm; a 27 degree square field of view
    half_fov = math.atan(0.5 * aperture / focal)
    dist = 1.1 * radius / math.sin(half_fov)
    cam = UsdGeom.Camera.Define(stage, path)
    cam.CreateFocalLengthAttr(focal)
    cam.CreateHorizontalApertureAttr(aperture)
    cam.CreateVerticalApertureAttr(aperture)
    cam.CreateClippingRangeAttr(Gf.Vec2f(max(dist - 2.0 * radius, 0.01 * dist),
                                         dist + 2.0 * radius))
    eye = centre + dist * view_from
    cam.AddTransformOp().Set(_look_at(eye, centre, np.array([0.0, 1.0, 0.0])))


def _author_light(stage: Usd.Stage, path: str, spec: LightSpec, centre: np.ndarray,
                  radius: float) -> None:
    if spec.kind == "distant":
        light = UsdLux.DistantLight.Define(stage, path)
        # a distant light shines down its local -Z: put +Z on `toward`
        up = np.array([0.0, 1.0, 0.0]) if abs(spec.toward[1]) < 0.9 else np.array([1.0, 0, 0])
        eye = centre + 3.0 * radius * spec.toward
        UsdGeom.Xformable(light).AddTransformOp().Set(_look_at(eye, centre, up))
    else:
        light = UsdLux.SphereLight.Define(stage, path)
        light.CreateRadiusAttr(spec.radius)
        light.CreateTreatAsPointAttr(False)
        UsdGeom.Xformable(light).AddTranslateOp().Set(Gf.Vec3d(*spec.position.tolist()))
        light.CreateExtentAttr(UsdGeom.Boundable.ComputeExtentFromPlugins(
            UsdGeom.Boundable(light), Usd.TimeCode.Default()))
    light.CreateIntensityAttr(spec.intensity)
    light.CreateColorAttr(Gf.Vec3f(*spec.color))
    # UsdLux units, authored explicitly (a reader must not depend on fallbacks): a normalized
    # distant light's intensity is its irradiance at normal incidence; a sphere light's is
    # its luminance (not divided by its area)
    light.CreateNormalizeAttr(spec.kind == "distant")
    if spec.kind == "distant":
        light.CreateAngleAttr(DISTANT_ANGLE_DEGREES)


def build_stage(name: str, size: str = "small", params: Mapping[str, int] | None = None
                ) -> tuple[Usd.Stage, dict[str, np.ndarray]]:
    """The scene as an in-memory stage plus its textures {file name: (h, w, 3) uint8}.

    Texture file names are relative to the folder the layer will be written to. `params`
    overrides entries of the size's row of the parameter table (a scaled scene for a
    benchmark; the layer's customLayerData records them). Raises SettingsError for an unknown
    name, size or parameter.
    """
    check_scene(name, size)
    table = dict(SCENE_PARAMS[name][size])
    unknown = sorted(set(params or {}) - set(table))
    if unknown:
        raise SettingsError(f"field 'params': {unknown} are not parameters of scene {name!r}; "
                            f"expected some of {', '.join(sorted(table))}")
    table.update({k: int(v) for k, v in (params or {}).items()})
    spec = _BUILDERS[name](table, np.random.default_rng(SEEDS[name]))
    tex_files = {role: f"{name}_{size}_{role}.png" for role in sorted(spec.textures)}

    stage = Usd.Stage.CreateInMemory(f"{name}_{size}.usda")
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, METERS_PER_UNIT[name])
    layer = stage.GetRootLayer()
    layer.documentation = f"texelbake test scene '{name}' ({size}), written by texelbake.testscenes"
    info: dict[str, object] = {"scene": name, "size": size, "seed": SEEDS[name]}
    if params:
        info["params"] = {k: int(v) for k, v in sorted(params.items())}
    layer.customLayerData = {"texelbake": info}
    root_path = f"/{spec.root}"
    root = UsdGeom.Xform.Define(stage, root_path)
    Usd.ModelAPI(root.GetPrim()).SetKind(Kind.Tokens.component)
    stage.SetDefaultPrim(root.GetPrim())

    UsdGeom.Scope.Define(stage, f"{root_path}/Looks")
    materials = {m.name: _author_material(stage, f"{root_path}/Looks/{m.name}", m, tex_files)
                 for m in spec.materials}
    UsdGeom.Xform.Define(stage, f"{root_path}/Geom")
    for m in spec.meshes:
        _author_mesh(stage, f"{root_path}/Geom/{m.name}", m, materials)

    pts = np.concatenate([m.points for m in spec.meshes])
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    centre = 0.5 * (lo + hi)
    radius = float(np.linalg.norm(pts - centre, axis=1).max())
    UsdGeom.Xform.Define(stage, f"{root_path}/Lights")
    for light in spec.lights:
        _author_light(stage, f"{root_path}/Lights/{light.name}", light, centre, radius)
    _author_camera(stage, f"{root_path}/Camera", centre, radius, spec.view_from)
    hint = UsdGeom.BBoxCache(Usd.TimeCode.Default(), [UsdGeom.Tokens.default_])
    UsdGeom.ModelAPI(root.GetPrim()).SetExtentsHint(
        UsdGeom.ModelAPI(root.GetPrim()).ComputeExtentsHint(hint))
    return stage, {tex_files[role]: spec.textures[role] for role in tex_files}


def write_scene(name: str, path: str | Path, size: str = "small",
                params: Mapping[str, int] | None = None) -> Path:
    """Write test scene `name` at `size` to `path` (.usda, .usdc or .usd) and its PNG
    textures beside it; return the layer's path.

    Deterministic: the same (name, size) gives byte-identical files. Every file is written
    to a temporary name in the target folder and renamed into place; the folder is created
    if missing. Raises SettingsError naming the field for an unknown name, size or suffix.
    """
    check_scene(name, size)
    path = Path(path)
    if path.suffix not in LAYER_SUFFIXES:
        raise SettingsError(
            f"field 'path': {str(path)!r} has suffix {path.suffix!r}; expected one of "
            f"{', '.join(LAYER_SUFFIXES)}"
        )
    stage, textures = build_stage(name, size, params)
    path.parent.mkdir(parents=True, exist_ok=True)
    for file_name in sorted(textures):  # textures first: the layer must resolve them
        write_png(path.parent / file_name, textures[file_name])
    write_definitions(path.parent)  # the texelbake shaders' definitions (texelbake.usd.shaderdefs)
    with atomic_path(path) as tmp:
        if not stage.GetRootLayer().Export(str(tmp)):
            raise OSError(f"cannot write {path}")
    return path
