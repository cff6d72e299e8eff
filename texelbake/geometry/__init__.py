"""Geometry stage: mesh hierarchy, UV atlas, surface samples, texel assignment, ray casting.

Modules: `mesh` (Mesh, checks, welding), `hierarchy` (QEM levels M1..Mn), `atlas` (UV atlas
on M1, composite map of M_i), `sampling` (samples X on M_org with ΔA), `texels` (g(p) per
mip level, texel frames, uv ↔ texel), `raycast` (batched Embree queries), `closest`
(float64 point-triangle projection).
"""

from texelbake.geometry.atlas import (
    Atlas,
    atlas_uv_of_points,
    build_atlas,
    map_into_atlas,
    rasterize_atlas,
)
from texelbake.geometry.hierarchy import simplify_hierarchy
from texelbake.geometry.mesh import Mesh, compact, weld
from texelbake.geometry.raycast import RayCaster, RayHits, offset_origins
from texelbake.geometry.sampling import Samples, sample_surface
from texelbake.geometry.texel_frames import texel_frames
from texelbake.geometry.texels import (
    TexelAssignment,
    assign_texels,
    bilinear_texels,
    texel_centers_uv,
    texel_surface_points,
    uv_to_texel,
)

__all__ = [
    "Atlas",
    "Mesh",
    "RayCaster",
    "RayHits",
    "Samples",
    "TexelAssignment",
    "assign_texels",
    "atlas_uv_of_points",
    "bilinear_texels",
    "build_atlas",
    "compact",
    "map_into_atlas",
    "offset_origins",
    "rasterize_atlas",
    "sample_surface",
    "simplify_hierarchy",
    "texel_centers_uv",
    "texel_frames",
    "texel_surface_points",
    "uv_to_texel",
    "weld",
]
