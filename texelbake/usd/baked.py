"""The baked asset as arrays, and how its arrays are typed in USD (DESIGN.md "The baked USD").

A baked asset is a folder:

    <name>_baked.usda        root layer: references the source, adds the payload, LOD variants
    <name>_payload.usdc      the baked data (crate): LOD meshes M1..Mn with atlas uvs, one Scope
                             per CPM level holding its arrays, the preview material
    source/...               a copy of the source asset and the files it references
    <name>_albedo.png, <name>_normal.png
                             the baseline's albedo and normal maps baked onto M1
    <name>_filtered_L<ll>.exr
                             the filtered maps of each mip level (`texelbake.baselines.filtered_maps`:
                             mean normal, LEADR moments, AO, albedo, base colour, α²)
    <name>_basecolor.png, <name>_occlusion.png, <name>_roughness_lod<i>.png
    [<name>_fallback_normal.png, <name>_fallback_normal_lod<i>.png]
                             the UsdPreviewSurface fallback of each LOD i (with the normal map,
                             the fallback's own when its textures are finer than the atlas):
                             material /Baked/Looks/BakedPreview for LOD1, BakedPreview_LOD<i>
                             for the others
    report.json              what the bake computed (a function of source and settings:
                             byte-identical on every run, farm or local)
    run.json                 a local bake's run facts (seconds, estimate, host, date): the
                             one file that differs between runs (the farm keeps it beside
                             the result zip, outside the archive)

Array attributes live in the `texelbake:` namespace, flattened, each with an int[] companion
`<name>:shape`; the dtype maps one-to-one onto a USD value type (float16 -> half[],
float32 -> float[], float64 -> double[], int32 -> int[], int64 -> int64[], uint8 -> uchar[], bool -> bool[]), so `read_baked`
returns arrays identical to what was written. `read_baked` is the only way the renderer gets
baked data.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from pxr import Sdf, Vt

from texelbake.usd.lodmesh import LodMesh

#: the namespace of every baked array attribute
ARRAY_NS = "texelbake:"

#: numpy dtype name -> (Sdf value type, Vt array class)
USD_ARRAY_TYPES: dict[str, tuple[Any, Any]] = {
    "float16": (Sdf.ValueTypeNames.HalfArray, Vt.HalfArray),
    "float32": (Sdf.ValueTypeNames.FloatArray, Vt.FloatArray),
    "float64": (Sdf.ValueTypeNames.DoubleArray, Vt.DoubleArray),
    "int32": (Sdf.ValueTypeNames.IntArray, Vt.IntArray),
    "int64": (Sdf.ValueTypeNames.Int64Array, Vt.Int64Array),
    "uint32": (Sdf.ValueTypeNames.UIntArray, Vt.UIntArray),
    "uint8": (Sdf.ValueTypeNames.UCharArray, Vt.UCharArray),
    "bool": (Sdf.ValueTypeNames.BoolArray, Vt.BoolArray),
}
#: USD value type name -> numpy dtype
NUMPY_FROM_USD = {
    "half[]": np.float16, "float[]": np.float32, "double[]": np.float64, "int[]": np.int32,
    "int64[]": np.int64, "uint[]": np.uint32,
    "uchar[]": np.uint8, "bool[]": np.bool_,
}


@dataclass
class BakedAsset:
    """Everything a bake writes, as arrays.

    levels : one dict of named arrays per CPM level (level 0 finest), as `texelbake.stages`
        assembles them (CSR texel offsets, characteristic points, weights, a_vis tables)
    arrays : bake-wide arrays (direction grids, material table, ...)
    meshes : M1..Mn
    albedo, normal : (N, N, 3) float32 preview maps over M1's atlas (normal in [-1, 1])
    metadata : JSON-able dict written to customLayerData["texelbake"]
    filtered : per level an (N_l, N_l, C) float32 filtered map (`filtered_maps.CHANNELS`)
    fallback : the UsdPreviewSurface fallback: "base" (R, R, 3) diffuseColor (or per LOD
        "diffuse" (R, R, 3) when fitted), "occlusion"
        (R, R), "roughness" a list of (n_i, n_i) maps, one per LOD, "constants" (inputs
        carried from the source material) and, when R > N, "normal" (R, R, 3) its own normal
        map (else it shares `normal`) and "lod_normals" each LOD's (LOD1's is "normal"; the
        others' in their own MikkTSpace frames), and for cut-outs "opacity" (R, R) the uncut fraction
        of each texel; R = `stages.filtered.fallback_resolution`; empty: the albedo/normal material of old bakes.
        `read_baked` returns each LOD's material as authored, under "materials".
    """

    name: str
    levels: list[dict[str, np.ndarray]]
    arrays: dict[str, np.ndarray]
    meshes: list[LodMesh]
    albedo: np.ndarray
    normal: np.ndarray
    metadata: dict[str, Any] = field(default_factory=dict)
    source_layer: str = ""
    root_layer: str = ""
    filtered: list[np.ndarray] = field(default_factory=list)
    fallback: dict[str, Any] = field(default_factory=dict)
    #: the UsdSkel.Skeleton the LOD meshes are bound to (source namespace; "" when unskinned)
    skeleton: str = ""

