"""The filtered-maps step of the export: the filtered normal, LEADR moment, AO,
albedo and base maps of every mip level, from the geometry stage's samples and texel
assignment (`texelbake.baselines.filtered_maps`), kept in the artifact store under a content key (the
AO rays are the cost, so a rerun of the export does not cast them again)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from texelbake.baselines.filtered_maps import (
    FILTER_TOL,
    FilteredSums,
    ambient_occlusion,
    bake_filtered_levels,
    material_base,
)
from texelbake.baselines.normal_maps import face_tangent_space
from texelbake.cpm.level import texel_ids
from texelbake.geometry.build import geometry_chunk
from texelbake.io.chunks import chunk_ranges, sample_rows
from texelbake.stages.context import GEOMETRY_FIELDS, StageContext
from texelbake.tol import TOL


def filtered_key(ctx: StageContext) -> str:
    return ctx.key("filtered", f"maps-v2-ao{FILTER_TOL.ao_rays}.npz", GEOMETRY_FIELDS)


def run_filtered(ctx: StageContext, shard: int = 0) -> str:
    """Every level's filtered map (`filtered_maps.bake_filtered_levels`); returns the key."""
    key = filtered_key(ctx)
    if ctx.store.exists(key):
        return key
    s = ctx.settings
    geo = ctx.geometry()
    materials = ctx.asset().materials
    caster = ctx.caster()
    frames, prim_of = lod1_frames(geo)
    m = len(geo["sample_area"])
    sums = FilteredSums(s.atlas_resolution, ctx.n_levels)
    # a chunk of samples at a time (one pass held ~500 bytes a sample, 8.4 GB at
    # 512²); the sums continue across chunks and AO's draws are the one-pass draws, so the
    # maps are the one-pass maps bit for bit
    for a, b in chunk_ranges(m, geometry_chunk(s)):  # loop over chunks (memory bound)
        r = sample_rows(geo, ("sample_pos", "sample_nrm", "sample_gnrm", "sample_mat",
                              "sample_uv", "sample_area", "sample_row", "sample_col"), a, b)
        local = np.einsum("mij,mj->mi", frames[prim_of(a, b)], r["sample_nrm"])
        ao = ambient_occlusion(r["sample_pos"], r["sample_gnrm"], caster.occluded,
                               seed=s.seed, ray_eps=TOL.ray_offset * caster.bbox_diag,
                               first=a, total=m)
        albedo, base, alpha2 = material_base(materials, r["sample_mat"], r["sample_uv"])
        texels = [texel_ids(r, s.atlas_resolution, lvl) for lvl in range(ctx.n_levels)]
        sums.add(texels, r["sample_area"], local, ao, albedo, base, alpha2)
    maps = sums.maps()
    return ctx.store.write_arrays(key, {f"L{lvl:02d}": m for lvl, m in enumerate(maps)})


def lod1_frames(geo: dict[str, np.ndarray]
                ) -> tuple[np.ndarray, Callable[[int, int], np.ndarray]]:
    """The tangent frames of LOD1's faces (from its atlas uvs) and, for samples a..b, their
    LOD1 face: the maps a viewer applies to LOD1 are in LOD1's frames. LOD1 is the atlas mesh
    M_T (the samples' `sample_m1_prim`) unless it was too fine for the atlas: then
    each sample takes its closest LOD1 face (each sample's on its own: any chunking)."""
    from texelbake.geometry.build import lod_meshes
    from texelbake.geometry.raycast import RayCaster

    v, f, uv = lod_meshes(geo)[0]
    if bool(geo["lod_exact"]):
        def prim_of(a: int, b: int) -> np.ndarray:
            return sample_rows(geo, ("sample_m1_prim",), a, b)["sample_m1_prim"]
    else:
        lod1 = RayCaster(v, f)

        def prim_of(a: int, b: int) -> np.ndarray:
            return lod1.closest_points(sample_rows(geo, ("sample_pos",), a, b)["sample_pos"])[1]
    return face_tangent_space(v, f, uv), prim_of


def filtered_levels(ctx: StageContext) -> list[np.ndarray]:
    """The maps `run_filtered` wrote (running it when absent), finest level first."""
    data = ctx.store.read_arrays(run_filtered(ctx))
    return [data[f"L{lvl:02d}"] for lvl in range(ctx.n_levels)]


#: the fallback textures' largest side (texels): 512² RGB is what studios ship for a prop's
#: LOD1; above it the samples and AO rays of the dense bake cost more than the CPM stage at
#: the defaults (docs/decisions.md)
FALLBACK_MAX_RESOLUTION = 512
#: dense samples per texel of the fallback page (~2.5 per covered texel at 40 % coverage)
FALLBACK_SAMPLES_PER_TEXEL = 1
#: AO rays per dense sample (the texel averages ~2.5 samples: ~20 rays per texel)
FALLBACK_AO_RAYS = 8
_TAG_FALLBACK = 0x5F
#: the dense fallback maps' artifact version (what the fitted gain is computed from too)
FALLBACK_VERSION = "fallback-v7"


def _texel_size(geo: dict[str, np.ndarray], n: int) -> float:
    """World size of one texel of an n x n page on the atlas mesh M_T (its median uv scale)."""
    v1, f1, c1 = geo["m1_vertices"], geo["m1_faces"], geo["m1_corner_uvs"]
    tri = v1[f1]
    a_w = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    d1, d2 = c1[:, 1] - c1[:, 0], c1[:, 2] - c1[:, 0]
    a_uv = 0.5 * np.abs(d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0])
    ok = (a_w > 0) & (a_uv > 0)
    ratio = float(np.median(a_uv[ok] / a_w[ok])) if ok.any() else 1.0
    return 1.0 / (n * np.sqrt(ratio))


def fallback_resolution(ctx: StageContext) -> int:
    """The fallback textures' side: a texel at most one pixel where LOD1 switches in (its
    bounding-box diagonal covers lod_switch_px[0] pixels), measured on the atlas layout the
    LODs' uvs map into, rounded up to a power of two and clamped to [atlas_resolution,
    FALLBACK_MAX_RESOLUTION]. The LODs share the layout, so LOD1's need (the finest) sizes the
    page; a viewer's mip-maps serve the coarser LODs. 'atlas' mode: the atlas resolution."""
    from texelbake.geometry.mesh import bbox_diagonal

    s = ctx.settings
    n = s.atlas_resolution
    if s.lod_mode != "error" or not s.lod_switch_px:
        return n
    geo = ctx.geometry()
    pixel = bbox_diagonal(ctx.asset().points) / float(s.lod_switch_px[0])
    need = n * _texel_size(geo, n) / pixel  # texels per side for a texel of one pixel
    side = int(2 ** int(np.ceil(np.log2(max(need, 1.0)))))
    return int(min(max(side, n), max(FALLBACK_MAX_RESOLUTION, n)))


def nearest_fill(img: np.ndarray, filled: np.ndarray) -> np.ndarray:
    """Empty texels take the value of the nearest filled one (one Euclidean distance
    transform: the chart padding and the page between charts, so a viewer's bilinear and mip
    look-ups never blend in empty texels)."""
    from scipy.ndimage import distance_transform_edt

    if filled.all() or not filled.any():
        return img
    idx = distance_transform_edt(~filled, return_distances=False, return_indices=True)
    return img[idx[0], idx[1]]


#: the last fallback page's samples drawn in this process (`fallback_samples`)
_FALLBACK_SAMPLES: dict[tuple[str, str, int], dict] = {}


def fallback_samples(ctx: StageContext, res: int) -> dict:
    """The fallback page's dense samples: FALLBACK_SAMPLES_PER_TEXEL x res² fresh samples on
    M_org (seeded), placed on M_T like the geometry stage's (`assign_texels`, the bent-normal
    rule on wraps): {"smp" (geometry.sampling samples), "gnrm" (m, 3) their triangles'
    normals, "row", "col" (m,) their texel on the res² page, "prim" (m,) the LOD1 face they
    show on, "seen" (m,) bool whether a ray from it along that face's normal leaves M_org,
    "frames" (f, 3, 3) LOD1's tangent frames, "lod1_vertices", "lod1_faces"}.
    Drawn once per page in a process (the export's maps, opacity, metallic and fitted gain
    all read them); the arrays are read-only."""
    key = (str(ctx.store.root), ctx.geometry_key(), int(res))
    if key not in _FALLBACK_SAMPLES:
        _FALLBACK_SAMPLES.clear()
        fs = _draw_fallback_samples(ctx, res)
        for arr in [*vars(fs["smp"]).values(), *(v for k, v in fs.items() if k != "smp")]:
            arr.flags.writeable = False
        _FALLBACK_SAMPLES[key] = fs
    return _FALLBACK_SAMPLES[key]


def _draw_fallback_samples(ctx: StageContext, res: int) -> dict:
    """`fallback_samples`' draw."""
    from texelbake.baselines.normal_maps import face_tangent_space
    from texelbake.geometry.atlas import Atlas
    from texelbake.geometry.build import lod_meshes
    from texelbake.geometry.lodnormals import lod_corner_normals
    from texelbake.geometry.mesh import Mesh, face_normals, plane_bary
    from texelbake.geometry.mikktspace import frames_at, mikk_tangents
    from texelbake.geometry.raycast import RayCaster
    from texelbake.geometry.sampling import sample_surface
    from texelbake.geometry.texels import assign_texels

    s = ctx.settings
    geo = ctx.geometry()
    asset = ctx.asset()
    caster = ctx.caster()
    smp = sample_surface(asset.points, asset.faces, res * res * FALLBACK_SAMPLES_PER_TEXEL,
                         s.seed * 1000 + _TAG_FALLBACK, corner_normals=asset.corner_normals,
                         corner_uvs=asset.corner_uvs, face_material=asset.face_material,
                         normal_input=ctx.normal_input())
    gnrm = face_normals(asset.points, asset.faces)[smp.face]
    m_t = Mesh(geo["m1_vertices"], geo["m1_faces"])
    atlas = Atlas(m_t, geo["m1_corner_uvs"], res, np.arange(m_t.num_vertices),
                  np.zeros(m_t.num_faces, np.int64), 1)
    wrapped = float(geo["m1_wrap_offset"]) > 0.0
    asg = assign_texels(smp.positions, m_t, atlas, 1, normals=gnrm,
                        occluder=caster if wrapped else None)
    v, f, uv = lod_meshes(geo)[0]
    _, near, bary = RayCaster(v, f).closest_points(smp.positions)
    if bool(geo["lod_exact"]):  # the texel's face; the point projected on its plane
        near = asg.prim
        bary = plane_bary(v[f[near]], smp.positions)
    cnrm = lod_corner_normals(v, f, asset.corner_normals, caster)
    tangent, sign = mikk_tangents(v, f, cnrm, uv)
    # seen from outside: a ray from the sample along the normal of the LOD1 face it shows on
    # leaves M_org (`_seen_means`)
    lod_n = np.cross(v[f][:, 1] - v[f][:, 0], v[f][:, 2] - v[f][:, 0])
    d = (lod_n / np.maximum(np.linalg.norm(lod_n, axis=1, keepdims=True), 1e-300))[near]
    seen = ~caster.occluded(smp.positions + TOL.ray_offset * caster.bbox_diag * d, d)
    return {"smp": smp, "gnrm": gnrm, "row": asg.row, "col": asg.col, "prim": near,
            "seen": seen, "frames": face_tangent_space(v, f, uv), "lod1_vertices": v,
            "lod1_faces": f,
            "mikk": frames_at(tangent, sign, cnrm, near, np.column_stack(
                [1.0 - bary[:, 0] - bary[:, 1], bary]))}


def fallback_opacity(ctx: StageContext, res: int) -> np.ndarray | None:
    """(res, res) float32 the fraction of each fallback texel's area that is not cut out
    (M_org's cut-outs, `brdf.opacity`), or None when nothing can be cut. The fallback cuts
    where it is below one half (its opacityThreshold), as a viewer's alpha test would. Texels
    no sample reaches are 1."""
    cutout = ctx.caster().cutout
    if cutout is None:
        return None
    fs = fallback_samples(ctx, res)
    smp = fs["smp"]
    kept = ~cutout.cut_uv(smp.face, smp.uv)
    t0 = fs["row"] * res + fs["col"]
    area = np.bincount(t0, weights=smp.area, minlength=res * res)
    solid = np.bincount(t0, weights=smp.area * kept, minlength=res * res)
    out = np.divide(solid, area, out=np.ones(res * res), where=area > 0)
    return out.reshape(res, res).astype(np.float32)


def dense_fallback_levels(ctx: StageContext, res: int) -> tuple[list[np.ndarray], np.ndarray]:
    """The filtered maps (CHANNELS) of every level of a res x res page on the atlas layout,
    from FALLBACK_SAMPLES_PER_TEXEL x res² fresh samples on M_org placed on M_T like the
    geometry stage's (`assign_texels`, the bent-normal rule on wraps), and the level-0 tangent-
    space normal map (unit). Level 0's base colour is weighted by AO (below). Kept in the
    artifact store."""
    from texelbake.baselines.filtered_maps import CHANNELS, FIELDS
    from texelbake.geometry.mikktspace import encode

    n_levels = int(np.log2(res)) + 1
    key = ctx.key("filtered", f"{FALLBACK_VERSION}-{res}-s{FALLBACK_SAMPLES_PER_TEXEL}"
                  f"-ao{FALLBACK_AO_RAYS}.npz", GEOMETRY_FIELDS)
    if ctx.store.exists(key):
        data = ctx.store.read_arrays(key)
        return [data[f"L{lvl:02d}"] for lvl in range(n_levels)], data["normal"]
    s = ctx.settings
    asset = ctx.asset()
    caster = ctx.caster()
    fs = fallback_samples(ctx, res)
    smp, gnrm, prim = fs["smp"], fs["gnrm"], fs["prim"]
    asg_row, asg_col = fs["row"], fs["col"]
    # the slope statistics (roughness widening) in the flat frame of the LOD1 face, where
    # z is the face's normal; the normal map in MikkTSpace frames (what other tools decode),
    # whose interpolated normal a transferred corner normal may tilt far from the face's
    local = np.einsum("mij,mj->mi", fs["frames"][prim], smp.normals)
    mikk = encode(fs["mikk"], smp.normals) * smp.area[:, None]
    ao = ambient_occlusion(smp.positions, gnrm, caster.occluded, n_rays=FALLBACK_AO_RAYS,
                           seed=s.seed, ray_eps=TOL.ray_offset * caster.bbox_diag)
    albedo, base, alpha2 = material_base(asset.materials, smp.material.astype(np.int32), smp.uv)
    texels = [(asg_row >> lvl) * (res >> lvl) + (asg_col >> lvl) for lvl in range(n_levels)]
    # bake_filtered_levels fills empty texels by repeated 4-neighbour passes (fine at 16²);
    # here one nearest-texel fill per level, so the filled flags are recomputed
    maps = []
    for lvl in range(n_levels):  # a loop over the few levels
        n_l = res >> lvl
        img = bake_filtered_levels(n_l, 1, [texels[lvl]], smp.area, local, ao, albedo, base,
                                   alpha2, fill=False)[0]
        filled = np.bincount(texels[lvl], weights=smp.area, minlength=n_l * n_l) > 0
        maps.append(nearest_fill(img, filled.reshape(n_l, n_l)).astype(np.float32))
    # the base colour as seen from outside: a sample counts only when a ray from it along the
    # normal of the LOD1 face it shows on leaves M_org (so a part enclosed by another, like
    # BoxAnimated's inner box whose samples project onto the outer walls, does not tint what
    # covers it); texels none of whose samples is seen keep the area mean
    t0 = texels[0]
    seen, base_seen = _seen_means(fs, res, base)
    filled0 = np.bincount(t0, weights=smp.area, minlength=res * res) > 0
    top = maps[0].reshape(res * res, -1)
    top[seen, FIELDS["base"]] = base_seen[seen]
    maps[0] = nearest_fill(np.where(filled0[:, None], top, 0.0).reshape(res, res, -1),
                            filled0.reshape(res, res)).astype(np.float32)
    nbar = np.stack([np.bincount(t0, weights=mikk[:, c], minlength=res * res)
                     for c in range(3)], axis=1)
    length = np.linalg.norm(nbar, axis=1, keepdims=True)
    nbar = np.where(length > 0, nbar / np.maximum(length, 1e-300), [0.0, 0.0, 1.0])
    normal = nearest_fill(nbar.reshape(res, res, 3), filled0.reshape(res, res))
    assert maps[0].shape[2] == len(CHANNELS)
    ctx.store.write_arrays(key, {**{f"L{lvl:02d}": m for lvl, m in enumerate(maps)},
                                 "normal": normal.astype(np.float32)})
    return maps, normal.astype(np.float32)


def _page_texel(fs: dict, res: int) -> np.ndarray:  # each fallback sample's texel, (m,)
    return fs["row"].astype(np.int64) * res + fs["col"]


def _seen_means(fs: dict, res: int, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per texel of the res² fallback page (`fallback_samples` fs) the mean of `values` (m, c)
    over the samples seen from outside: (seen (res²,) bool, means (res², c) where seen)."""
    smp = fs["smp"]
    t0 = _page_texel(fs, res)
    w = smp.area * fs["seen"]
    wsum = np.bincount(t0, weights=w, minlength=res * res)
    seen = wsum > 1e-6 * np.bincount(t0, weights=smp.area, minlength=res * res).clip(1e-300)
    means = np.stack([np.bincount(t0, weights=w * v, minlength=res * res) for v in values.T],
                     axis=1) / np.where(seen, wsum, 1.0)[:, None]
    return seen, means


def fallback_metallic(ctx: StageContext, res: int) -> np.ndarray | None:
    """(res, res) float32 each fallback texel's metallic (`filtered_maps.material_metallic`,
    averaged like the base colour: over the samples seen from outside, else over all), the
    page between charts filled from the nearest covered texel; None when every sample's
    metallic is the same (the constant then says it). A texel where a metal and a dielectric
    meet takes their area mix, which UsdPreviewSurface's metallic input interpolates (its
    diffuse scaled by 1 − metallic, F0 between 0.04 and the base colour). Kept in the artifact
    store."""
    from texelbake.baselines.filtered_maps import material_metallic, metallic_workflow

    mats = ctx.asset().materials
    if not any(metallic_workflow(m) and ("metallic" in m.textures
                                         or float(m.params.get("metallic", 0.0)) > 0.0)
               for m in mats):
        return None  # no sample can be metallic
    key = ctx.key("filtered", f"fallback-metallic-v1-{res}-s{FALLBACK_SAMPLES_PER_TEXEL}.npz",
                  GEOMETRY_FIELDS)
    if not ctx.store.exists(key):
        fs = fallback_samples(ctx, res)
        smp = fs["smp"]
        met = material_metallic(mats, smp.material.astype(np.int32), smp.uv)
        arrays = {"varies": np.array(float(np.ptp(met)) > 1e-6)}
        if bool(arrays["varies"]):
            t0 = _page_texel(fs, res)
            area = np.bincount(t0, weights=smp.area, minlength=res * res)
            mean = np.bincount(t0, weights=smp.area * met, minlength=res * res) / np.where(
                area > 0, area, 1.0)
            seen, seen_mean = _seen_means(fs, res, met[:, None])
            mean[seen] = seen_mean[seen, 0]
            arrays["metallic"] = nearest_fill(mean.reshape(res, res), (area > 0).reshape(
                res, res)).astype(np.float32)
        ctx.store.write_arrays(key, arrays)
    d = ctx.store.read_arrays(key)
    return d["metallic"] if bool(d["varies"]) else None


def lod_normal_maps(ctx: StageContext, res: int) -> list[np.ndarray]:
    """The fallback's tangent-space normal map of each LOD after LOD1 (res, res, 3) float32
    unit: the dense samples' normals (`fallback_samples`, on the shared layout) encoded in the
    MikkTSpace frame of that LOD's own surface (its authored corner normals and uvs: what a
    viewer decodes it with) at the centre of the sample's texel there, area means per texel,
    empty texels filled from the nearest covered one. A map baked in LOD1's frames does not decode on a
    coarser LOD: its normals there are not LOD1's. Kept in the artifact store."""
    from texelbake.geometry.atlas import rasterize_atlas
    from texelbake.geometry.build import lod_meshes
    from texelbake.geometry.lodnormals import lod_corner_normals
    from texelbake.geometry.mikktspace import encode, frames_at, mikk_tangents
    from texelbake.geometry.raycast import RayCaster

    geo = ctx.geometry()
    lods = lod_meshes(geo)[1:]
    key = ctx.key("filtered", f"fallback-normals-v3-{res}-s{FALLBACK_SAMPLES_PER_TEXEL}.npz",
                  GEOMETRY_FIELDS)
    if ctx.store.exists(key):
        d = ctx.store.read_arrays(key)
        return [d[f"lod{i}"] for i in range(len(lods))]
    fs = fallback_samples(ctx, res)
    smp = fs["smp"]
    t0 = _page_texel(fs, res)
    filled = (np.bincount(t0, weights=smp.area, minlength=res * res) > 0).reshape(res, res)
    out = {}
    for i, (v, f, uv) in enumerate(lods):  # a loop over the few LODs
        cnrm = lod_corner_normals(v, f, ctx.asset().corner_normals, ctx.caster())
        tangent, sign = mikk_tangents(v, f, cnrm, uv)
        # the frame where a viewer decodes the sample's texel: at the texel's centre on
        # this LOD (its uvs); texels this LOD's charts miss: at the sample's closest point
        face, bary3, _ = rasterize_atlas(uv, res)
        on = face[t0] >= 0
        fr = frames_at(tangent, sign, cnrm, np.maximum(face[t0], 0), bary3[t0])
        if not on.all():
            _, prim, bary = RayCaster(v, f).closest_points(smp.positions[~on])
            fr[~on] = frames_at(tangent, sign, cnrm, prim, np.column_stack(
                [1.0 - bary[:, 0] - bary[:, 1], bary]))
        local = encode(fr, smp.normals) * smp.area[:, None]
        acc = np.stack([np.bincount(t0, weights=local[:, c], minlength=res * res)
                        for c in range(3)], axis=1)
        length = np.linalg.norm(acc, axis=1, keepdims=True)
        nrm = np.where(length > 0, acc / np.maximum(length, 1e-300), [0.0, 0.0, 1.0])
        out[f"lod{i}"] = nearest_fill(nrm.reshape(res, res, 3), filled).astype(np.float32)
    ctx.store.write_arrays(key, out)
    return [out[f"lod{i}"] for i in range(len(lods))]


def fallback_maps(ctx: StageContext, maps: list[np.ndarray]) -> dict:
    """The UsdPreviewSurface fallback of every LOD (`usd.baked.BakedAsset.fallback`): base
    colour and occlusion of level 0 (a viewer mip-maps them itself), a metallic map in the
    metallic workflow where the samples' metallic differs (`fallback_metallic`; else the
    dominant material's constants), and per LOD the roughness
    widened by the slope variance of the level where that LOD is shown
    (`filtered_maps.lod_levels`; a viewer filters textures but widens no lobe).

    The textures' side is `fallback_resolution`: when it is above the
    atlas resolution the maps are baked from their own dense samples on the same layout
    (`dense_fallback_levels`) and the fallback gets its own normal map ("normal"); else
    they are the filtered levels `maps` and the normal map is the baseline's."""
    from texelbake.baselines.filtered_maps import (
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
    res = fallback_resolution(ctx)
    normal = None
    if res > ctx.settings.atlas_resolution:
        maps, normal = dense_fallback_levels(ctx, res)
    texel = _texel_size(geo, res)  # world size of a texel of the fallback page on M1
    errors = [0.0]
    for v, f, _ in lod_meshes(geo)[1:]:  # a loop over the few LODs (the lod{i} keys)
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
    constants = dominant_constants(asset.materials, geo["sample_mat"], geo["sample_area"])
    metallic = fallback_metallic(ctx, res)
    if metallic is not None:  # metals and dielectrics (or a metallic texture): a map
        constants = {**{k: v for k, v in constants.items()
                        if k not in ("metallic", "specularColor")}, "useSpecularWorkflow": 0}
    out = {"base": top[..., FIELDS["base"]], "occlusion": top[..., FIELDS["ao"]][..., 0],
           "roughness": rough, "levels": lod_levels(errors, texel, len(maps)),
           "constants": constants, "resolution": int(res)}
    if normal is not None:
        out["normal"] = normal
        out["lod_normals"] = [normal, *lod_normal_maps(ctx, res)]
    opacity = fallback_opacity(ctx, res)
    if opacity is not None:
        out["opacity"] = opacity
    if metallic is not None:
        out["metallic"] = metallic
    return out
