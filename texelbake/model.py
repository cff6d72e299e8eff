"""The AssetModel: everything the pipeline needs from a USD asset, as immutable arrays.

`texelbake.asset.load_asset` builds it; every later stage reads only this. World space is
the asset's, after flattening transforms; directions are unit vectors.

Shader ids: UsdPreviewSurface is read per its published spec. texelbake's own ids (authored
as `info:id` on a UsdShade.Shader) cover BRDFs UsdPreviewSurface cannot express:

| id                   | model      | inputs (name: type)                                                  |
|----------------------|------------|----------------------------------------------------------------------|
| texelbake:lambert    | lambert    | diffuseColor: color3f                                                |
| texelbake:phong      | phong      | diffuseColor: color3f, specularColor: color3f, exponent: float       |
| texelbake:measured   | merl       | file: asset (MERL .binary), scale: float                              |
| texelbake:cellular   | cellular   | cellScale: float, seed: int, borderWidth: float, borderColor: color3f,|
|                      |            | borderRoughness: float, cellColorA: color3f, cellColorB: color3f      |

A `diffuseColor` (or any color input) connected to a UsdUVTexture lands in
`Material.textures[input_name]`; the constant value stays in `Material.params`.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any

import numpy as np

SHADER_PREVIEW = "UsdPreviewSurface"
SHADER_LAMBERT = "texelbake:lambert"
SHADER_PHONG = "texelbake:phong"
SHADER_MEASURED = "texelbake:measured"
SHADER_CELLULAR = "texelbake:cellular"
#: the baked material's shaders on texelbake's render contexts (texelbake.usd, texelbake.btf)
SHADER_CPM = "texelbake:cpm"
SHADER_BTF = "texelbake:btf_laplacian"

#: shader id -> Material.model
SHADER_MODELS: Mapping[str, str] = MappingProxyType(
    {
        SHADER_PREVIEW: "preview",
        SHADER_LAMBERT: "lambert",
        SHADER_PHONG: "phong",
        SHADER_MEASURED: "merl",
        SHADER_CELLULAR: "cellular",
    }
)

#: the UsdPreviewSurface inputs and their spec defaults (UsdPreviewSurface spec, v2.x)
PREVIEW_DEFAULTS: Mapping[str, Any] = MappingProxyType(
    {
        "diffuseColor": (0.18, 0.18, 0.18),
        "emissiveColor": (0.0, 0.0, 0.0),
        "useSpecularWorkflow": 0,
        "specularColor": (0.0, 0.0, 0.0),
        "metallic": 0.0,
        "roughness": 0.5,
        "clearcoat": 0.0,
        "clearcoatRoughness": 0.01,
        "opacity": 1.0,
        "opacityThreshold": 0.0,
        "ior": 1.5,
        "normal": (0.0, 0.0, 1.0),
        "displacement": 0.0,
        "occlusion": 1.0,
    }
)


def _frozen(a: Any, dtype: Any) -> np.ndarray:
    arr = np.array(a, dtype=dtype, copy=True)
    arr.flags.writeable = False
    return arr


@dataclass(frozen=True, eq=False)
class Texture:
    """An image bound through a UsdUVTexture, loaded as linear float pixels.

    pixels : (h, w, c) float32, row 0 is the *top* of the image (t = 1); sample with
        `texelbake.brdf.sample_texture`, which applies the st transform, wrap, scale and bias.
    st_transform : (a, b, c, d, e, f): st' = (a s + b t + c, d s + e t + f), the
        `UsdTransform2d` between the st primvar and the texture (identity when there is none)
    """

    path: str
    pixels: np.ndarray
    wrap_s: str = "repeat"
    wrap_t: str = "repeat"
    scale: tuple[float, float, float, float] = (1.0, 1.0, 1.0, 1.0)
    bias: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
    source_color_space: str = "auto"
    st_primvar: str = "st"
    st_transform: tuple[float, float, float, float, float, float] = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0)


@dataclass(frozen=True, eq=False)
class Material:
    """One bound material.

    path : prim path of the UsdShade.Material ("" for the fallback default material)
    model : "lambert" | "preview" | "phong" | "merl" | "cellular"
    params : constant inputs by name (floats, ints, strings, (3,) float64 colours; for "merl"
        also "table": (3, 90, 90, 180) float64, the tabulated BRDF in MERL layout)
    textures : input name -> Texture, for inputs driven by a UsdUVTexture
    """

    path: str
    model: str
    params: Mapping[str, Any] = field(default_factory=dict)
    textures: Mapping[str, Texture] = field(default_factory=dict)

    def __post_init__(self) -> None:
        object.__setattr__(self, "params", MappingProxyType(dict(self.params)))
        object.__setattr__(self, "textures", MappingProxyType(dict(self.textures)))


@dataclass(frozen=True, eq=False)
class Light:
    """A UsdLux light, reduced to what direct illumination needs.

    kind : "distant" | "sphere"
    direction : (3,) float64, unit, world space, from the scene *toward* the light (distant)
    position : (3,) float64, world space (sphere)
    radiance_scale : (3,) float64. distant: irradiance at normal incidence (UsdLux: luminance
        color * intensity * 2**exposure, times the solid angle of `inputs:angle` unless
        `inputs:normalize`; `texelbake.asset.lights.distant_irradiance_factor`). sphere: radiant intensity in W/sr
        (color * intensity * 2**exposure * pi * radius**2, or without the area term when
        radius == 0 / treatAsPoint), falling off as 1/d**2.
    """

    path: str
    kind: str
    direction: np.ndarray
    position: np.ndarray
    radius: float
    radiance_scale: np.ndarray


@dataclass(frozen=True, eq=False)
class Camera:
    """A UsdGeom.Camera. The camera looks down its local -Z with +Y up (USD convention).

    world_from_camera : (4, 4) float64, column-vector convention (p_world = M @ p_cam)
    focal_length, horizontal_aperture, vertical_aperture : mm (USD's tenths of a scene unit)
    clipping : (2,) float64 near/far
    """

    path: str
    world_from_camera: np.ndarray
    focal_length: float
    horizontal_aperture: float
    vertical_aperture: float
    clipping: np.ndarray


@dataclass(frozen=True, eq=False)
class SkinData:
    """UsdSkel linear-blend skinning of the whole asset by one skeleton, as a map from the
    rest points (`AssetModel.points`) to the points at each time code (seed 002: the LOD meshes
    get skin bindings transferred from these weights, `texelbake.deform.skinbind`). A point p
    with weights w is at p'(t) = M_t M_r⁻¹ p, M_t = Σ_j w_j transforms[t, j], M_r = Σ_j w_j
    rest[j] (`deform.lbs.skin_blend`): M_r⁻¹ p is its point in the skeleton's bind space.

    skeleton : path of the UsdSkel.Skeleton prim (in the source's namespace)
    joints : joint names, the skeleton's order (joint indices refer to it)
    weights : (n, j) float64 per vertex of `points`, each row sums to 1 (a mesh no skeleton
        skins is bound rigidly to a joint that moves as it does: a one-hot row)
    transforms : (t, j, 4, 4) float64 per time code of `AssetModel.time_codes`, column-vector
        convention, skeleton bind space -> world: (S_j(t) W(t))ᵀ, UsdSkel's skinning
        transform S_j and the skeleton's local-to-world W
    rest : (j, 4, 4) float64 the same at the time the rest points were read
    placement : (4, 4) float64 row-vector convention, the transform of the LODs' SkelRoot
        `Baked` under the asset's root prim, W(rest) R⁻¹ (R the root prim's local-to-world):
        the LODs' points are in the skeleton's bind space (geomBindTransform the identity),
        which UsdSkel skins and places by W(t) whatever the skinned prim's ancestors are, while
        a tool that places a skinned mesh by its parent (Blender's importer: parent · geomBind)
        and one that reads it as a plain mesh see the bind pose where the skeleton stands
    """

    skeleton: str
    joints: tuple[str, ...]
    weights: np.ndarray
    transforms: np.ndarray
    rest: np.ndarray
    placement: np.ndarray


@dataclass(frozen=True, eq=False)
class AssetModel:
    """All meshes of an asset, flattened into one triangle soup with per-face attributes.

    points : (n, 3) float64 world-space vertex positions (at the default time)
    faces : (f, 3) int64 vertex indices, counter-clockwise seen from the front
    corner_normals : (f, 3, 3) float64 unit shading normals per face corner (authored or computed)
    corner_uvs : (f, 3, 2) float64 texture coordinates per face corner (`primvars:st`); zeros
        where `has_uvs` is False
    has_uvs : (f,) bool
    face_material : (f,) int32 index into `materials`
    face_mesh : (f,) int32 index into `mesh_paths`
    time_codes : (t,) float64, empty when the points are not time-sampled
    points_over_time : (t, n, 3) float64, world-space points at each time code
    skin : the UsdSkel skinning that produced `points_over_time`, when one skeleton skins every
        mesh by linear blending (None otherwise: the points are only time samples)
    dropped_faces : number of zero-area / degenerate faces removed at ingest
    warnings : human-readable warnings, each naming a prim path
    unreachable_paths : asset paths only unselected variants name, never read ("'path' (in
        layer L, at spec)"; `texelbake.asset.paths.scan_asset_paths`)
    missing_paths : textures inside the asset that do not exist (their fallbacks are used)
    """

    source: str
    points: np.ndarray
    faces: np.ndarray
    corner_normals: np.ndarray
    corner_uvs: np.ndarray
    has_uvs: np.ndarray
    face_material: np.ndarray
    face_mesh: np.ndarray
    mesh_paths: tuple[str, ...]
    materials: tuple[Material, ...]
    lights: tuple[Light, ...] = ()
    cameras: tuple[Camera, ...] = ()
    up_axis: str = "Y"
    meters_per_unit: float = 1.0
    time_codes: np.ndarray = field(default_factory=lambda: np.zeros(0))
    points_over_time: np.ndarray = field(default_factory=lambda: np.zeros((0, 0, 3)))
    dropped_faces: int = 0
    warnings: tuple[str, ...] = ()
    skin: SkinData | None = None
    unreachable_paths: tuple[str, ...] = ()
    missing_paths: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        for name, dtype in (
            ("points", np.float64),
            ("faces", np.int64),
            ("corner_normals", np.float64),
            ("corner_uvs", np.float64),
            ("has_uvs", bool),
            ("face_material", np.int32),
            ("face_mesh", np.int32),
            ("time_codes", np.float64),
            ("points_over_time", np.float64),
        ):
            object.__setattr__(self, name, _frozen(getattr(self, name), dtype))

    @property
    def num_faces(self) -> int:
        return int(self.faces.shape[0])

    @property
    def bounds(self) -> np.ndarray:
        """(2, 3) float64 min and max corner of the points."""
        if self.points.shape[0] == 0:
            return np.zeros((2, 3))
        return np.stack([self.points.min(axis=0), self.points.max(axis=0)])

    @property
    def bbox_diag(self) -> float:
        lo, hi = self.bounds
        return float(np.linalg.norm(hi - lo))

    @property
    def has_deformation(self) -> bool:
        return self.time_codes.shape[0] > 1
