"""USD ingest: a USD asset (`.usda` / `.usdc` / `.usd` / `.usdz`) -> one immutable AssetModel.

Public entry points:

- `check_asset_paths(path) -> list[str]`: walks every layer of the asset *as Sdf layers*, before
  any stage is composed, and rejects asset paths the bake would read that are absolute, URLs,
  escape the asset's folder (or its `.usdz` package) or name layers that do not exist; paths
  only unselected variants name are left unread (`paths.scan_asset_paths` lists them, and
  missing textures). Also used by the upload service.
- `load_asset(path, *, time_code=None) -> AssetModel`: flattens transforms, fan-triangulates
  n-gons, refines catmullClark surfaces to their limit surface, reads normals (authored or
  computed), UVs, material bindings (GeomSubsets included), UsdPreviewSurface and texelbake
  shader networks with their textures, UsdLux distant and sphere lights, dome lights (as
  importance-sampled distant lights), cameras and time-sampled points.
- `describe(asset) -> str`: the report `texelbake inspect FILE` prints.

The AssetModel fields are documented in `texelbake.model`. This module is pure I/O: nothing
here is from the seeds' equations; the reflectance it hands on is what seed 000 Eq. 1 calls
f_r(x, wi, wo) per sample (a material per face, textures per corner UV).

Modules: `paths` (asset-path safety), `compose` (the composed stage, MaterialX documents
through `mtlx_document`), `load` (load_asset), `meshes`, `materials`, `uvtexture`, `lights`
(lights and cameras), `dome` (DomeLight), `files` (textures and MERL tables, .usdz members),
`values` (USD value
helpers, the sRGB decode), `describe`.

USD conventions used throughout: USD matrices act on *row* vectors (`p_world = p @ M`,
`M = XformCache.GetLocalToWorldTransform(prim)`); AssetModel stores points in that world space
and cameras as column-vector matrices (`M.T`).
"""


from texelbake.asset.describe import describe
from texelbake.asset.load import load_asset
from texelbake.asset.materials import DEFAULT_MATERIAL, TEXELBAKE_DEFAULTS
from texelbake.asset.paths import USD_EXTENSIONS, check_asset_paths
from texelbake.asset.values import AssetWarning
from texelbake.io.images import srgb_to_linear

__all__ = [
    "DEFAULT_MATERIAL",
    "TEXELBAKE_DEFAULTS",
    "USD_EXTENSIONS",
    "AssetWarning",
    "check_asset_paths",
    "describe",
    "load_asset",
    "srgb_to_linear",
]
