"""The project's own USD test scenes, modelled on the scenes of seed 000 (§1, §5, Table 3).

`write_scene(name, path, size)` writes one scene as a USD layer (and its PNG textures beside
it); `expected_counts(name, size)` says, from the parameter table alone, how many meshes,
triangles, materials, lights, cameras and textures a reader must find in it.

| scene     | geometry                                                  | appearance                     |
|-----------|-----------------------------------------------------------|--------------------------------|
| cylinder  | radius-1 cylinder of sharp ridges along its axis, each a  | facets alternate: a yellow     |
|           | triangular cross-section (seed 000 Fig. 1), closed by caps | Lambertian and a glossy blue   |
|           |                                                           | Phong, bound per face through  |
|           |                                                           | GeomSubsets (materialBind)     |
| wall      | running-bond blocks with chamfered edges and a jittered   | Lambertian UsdPreviewSurface   |
|           | front grid, standing proud of a mortar plane (2 meshes)   | with a PNG colour texture      |
| bolt      | shaft covered in diamond (pyramidal) bumps, a hex head    | metallic, low roughness, with  |
|           | (2 meshes)                                                | a PNG stain texture            |
| cloisonne | bumpy blob (displaced icosphere)                          | `texelbake:cellular`: a        |
|           |                                                           | Lambertian colour per Worley   |
|           |                                                           | cell, sharp metal on borders   |

Every scene has `upAxis = "Y"`, `metersPerUnit`, a `defaultPrim` (an Xform of kind
component), one UsdGeom.Camera framing the object, one UsdLux.DistantLight and, for the bolt
and the cloisonne, a UsdLux.SphereLight. Meshes use `subdivisionScheme = "none"`, authored
`normals` (faceVarying for the faceted cylinder and bolt, vertex for the wall and the
cloisonne) and `primvars:st` (texCoord2f[]); authored extents; MaterialBindingAPI applied
wherever a binding is authored.

Material convention (the ingest reads it this way): a material whose BRDF
UsdPreviewSurface cannot express carries a texelbake shader (`info:id` one of the ids in
`texelbake.model`, with exactly the input names of its table) on the `texelbake` render
context output, `outputs:texelbake:surface`, AND a UsdPreviewSurface approximation on the
universal `outputs:surface`, so any USD viewer shows something. The ingest reads
`outputs:texelbake:surface` first and falls back to `outputs:surface`. Materials that
UsdPreviewSurface expresses exactly (the wall's Lambertian: specular workflow with zero
specular colour; the bolt's metal) have only `outputs:surface`.

Meaning of the `texelbake:cellular` inputs (evaluated by `texelbake.brdf.cellular_shader`): Worley
cells over `st * cellScale` (the cloisonne's st is a spherical map, so 16 gives 16 cells
around and 16 from pole to pole), `seed` the feature-point seed, `borderWidth` in cell
units (a point is on a border where F2 - F1 < borderWidth), `borderRoughness` the roughness
of the border metal, `cellColorA`/`cellColorB` the range of the Lambertian cell colours.

Textures are 8-bit sRGB PNGs named `{scene}_{size}_{role}.png`, written beside the layer and
referenced by a relative path (`./wall_small_albedo.png`), so both sizes of one scene can
share a folder. Everything is seeded (`SEEDS`); rewriting a scene gives identical bytes.
Files are written atomically (temp file in the same folder, then rename).

texelbake's shaders name their definition by source asset: `texelbake_shaders.usda`, written
beside the layer (`texelbake.usd.shaderdefs`), so a stock pxr that never imported texelbake
validates every scene with no error. Lights author `inputs:normalize` and, for distant lights,
`inputs:angle` explicitly (a distant light's intensity is then its irradiance at normal
incidence, the UsdLux rule for a normalized distant light).

Modules: `params` (the parameter table, `expected_counts`), `spec` (scene descriptions as
arrays), one module per scene (`cylinder`, `wall`, `bolt`, `cloisonne`), `author` (USD
authoring, `build_stage`, `write_scene`).
"""

from texelbake.testscenes.author import build_stage, write_scene
from texelbake.testscenes.params import (
    CELLULAR_INPUTS,
    LAYER_SUFFIXES,
    SCENE_NAMES,
    SCENE_PARAMS,
    SIZES,
    expected_counts,
)

__all__ = [
    "CELLULAR_INPUTS", "LAYER_SUFFIXES", "SCENE_NAMES", "SCENE_PARAMS", "SIZES", "build_stage",
    "expected_counts", "write_scene",
]
