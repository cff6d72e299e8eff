"""The filtered-maps step of the export (issue 21): the filtered normal, LEADR moment, AO,
albedo and base maps of every mip level, from the geometry stage's samples and texel
assignment (`texelbake.filtered_maps`), kept in the artifact store under a content key (the
AO rays are the cost, so a rerun of the export does not cast them again)."""

from __future__ import annotations

import numpy as np

from texelbake.cpm.level import texel_ids
from texelbake.filtered_maps import (
    FILTER_TOL,
    ambient_occlusion,
    bake_filtered_levels,
    material_base,
)
from texelbake.normalmap import face_tangent_space
from texelbake.stages.context import GEOMETRY_FIELDS, StageContext
from texelbake.tol import TOL


def filtered_key(ctx: StageContext) -> str:
    return ctx.key("filtered", f"maps-ao{FILTER_TOL.ao_rays}.npz", GEOMETRY_FIELDS)


def run_filtered(ctx: StageContext, shard: int = 0) -> str:
    """Every level's filtered map (`filtered_maps.bake_filtered_levels`); returns the key."""
    key = filtered_key(ctx)
    if ctx.store.exists(key):
        return key
    s = ctx.settings
    geo = ctx.geometry()
    asset = ctx.asset()
    caster = ctx.caster()
    frames, prim = lod1_frames(geo)
    local = np.einsum("mij,mj->mi", frames[prim], geo["sample_nrm"])
    ao = ambient_occlusion(geo["sample_pos"], geo["sample_gnrm"], caster.occluded,
                           seed=s.seed, ray_eps=TOL.ray_offset * caster.bbox_diag)
    albedo, base, alpha2 = material_base(asset.materials, geo["sample_mat"], geo["sample_uv"])
    texels = [texel_ids(geo, s.atlas_resolution, lvl) for lvl in range(ctx.n_levels)]
    maps = bake_filtered_levels(s.atlas_resolution, ctx.n_levels, texels, geo["sample_area"],
                                local, ao, albedo, base, alpha2)
    return ctx.store.write_arrays(key, {f"L{lvl:02d}": m for lvl, m in enumerate(maps)})


def lod1_frames(geo: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """The tangent frames of LOD1's faces (from its atlas uvs) and each sample's LOD1 face:
    the maps a viewer applies to LOD1 are in LOD1's frames. LOD1 is the atlas mesh M_T (the
    samples' `sample_m1_prim`) unless it was too fine for the atlas (issue 22): then each
    sample takes its closest LOD1 face."""
    from texelbake.geometry.build import lod_meshes
    from texelbake.geometry.raycast import RayCaster

    v, f, uv = lod_meshes(geo)[0]
    if bool(geo["lod_exact"]):
        prim = geo["sample_m1_prim"]
    else:
        _, prim, _ = RayCaster(v, f).closest_points(geo["sample_pos"])
    return face_tangent_space(v, f, uv), prim


def filtered_levels(ctx: StageContext) -> list[np.ndarray]:
    """The maps `run_filtered` wrote (running it when absent), finest level first."""
    data = ctx.store.read_arrays(run_filtered(ctx))
    return [data[f"L{lvl:02d}"] for lvl in range(ctx.n_levels)]


def fallback_maps(ctx: StageContext, maps: list[np.ndarray]) -> dict:
    """The UsdPreviewSurface fallback of every LOD (`payload.BakedAsset.fallback`): base
    colour and occlusion of level 0 (a viewer mip-maps them itself), and per LOD the roughness
    widened by the slope variance of the level where that LOD is shown
    (`filtered_maps.lod_levels`; a viewer filters textures but widens no lobe)."""
    from texelbake.filtered_maps import (
        FIELDS,
        dominant_constants,
        fallback_roughness,
        lod_levels,
        slope_covariance,
    )
    from texelbake.geometry.build import lod_meshes
    from texelbake.geometry.raycast import RayCaster

    geo = ctx.geometry()
    asset = ctx.asset()
    n = ctx.settings.atlas_resolution
    v1, f1, c1 = geo["m1_vertices"], geo["m1_faces"], geo["m1_corner_uvs"]
    tri, uvt = v1[f1], c1
    a_w = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    d1, d2 = uvt[:, 1] - uvt[:, 0], uvt[:, 2] - uvt[:, 0]
    a_uv = 0.5 * np.abs(d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0])
    ok = (a_w > 0) & (a_uv > 0)
    ratio = float(np.median(a_uv[ok] / a_w[ok])) if ok.any() else 1.0
    texel = 1.0 / (n * np.sqrt(ratio))  # world size of a finest texel on M1
    errors = [0.0]
    for v, f, _ in lod_meshes(geo)[1:]:  # a loop over the few LODs (issue 22's lod{i} keys)
        lod = RayCaster(v, f)
        a, _, _ = ctx.caster().closest_points(v)
        b, _, _ = lod.closest_points(asset.points)
        errors.append(float(max(np.linalg.norm(a - v, axis=1).max(),
                                np.linalg.norm(b - asset.points, axis=1).max())))
    rough = []
    for lvl in lod_levels(errors, texel, len(maps)):
        m = maps[lvl].reshape(-1, maps[lvl].shape[2]).astype(np.float64)
        cov = slope_covariance(m[:, FIELDS["m1"]], m[:, FIELDS["m2"]])
        r = fallback_roughness(m[:, FIELDS["alpha2"]][:, 0], cov)
        rough.append(r.reshape(maps[lvl].shape[:2]).astype(np.float32))
    top = maps[0]
    return {"base": top[..., FIELDS["base"]], "occlusion": top[..., FIELDS["ao"]][..., 0],
            "roughness": rough, "levels": lod_levels(errors, texel, len(maps)),
            "constants": dominant_constants(asset.materials, geo["sample_mat"],
                                            geo["sample_area"])}
