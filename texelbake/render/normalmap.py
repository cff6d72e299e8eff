"""``normalmap``: the baseline studios bake today, M1 with the baked albedo and tangent-space
normal maps, multi-sampled; the material's Lambertian part replaced by the albedo map."""

from __future__ import annotations

import numpy as np

from texelbake import brdf as brdf_mod
from texelbake.baselines.normal_maps import face_tangent_space
from texelbake.errors import StageError
from texelbake.geometry.texels import bilinear_texels
from texelbake.render.albedo import baseline_albedo
from texelbake.render.scene import RenderScene, hit_m1, m1_arrays
from texelbake.tol import TOL
from texelbake.trace.camera import PinholeCamera
from texelbake.trace.shade import direct_radiance
from texelbake.trace.tracer import accumulate


def _normalmap_tables(scene: RenderScene) -> dict[str, np.ndarray]:
    """Per finest texel: material and texture uv of its heaviest characteristic point (the
    material id map a baker writes beside the albedo and normal maps), filled in empty texels
    from the nearest filled one; the material's own diffuse albedo there."""
    if scene._nm is not None:
        return scene._nm
    from scipy.spatial import cKDTree

    lv = scene.baked.levels[0]
    n = scene.n0
    counts = np.diff(lv["texel_offsets"])
    tex = np.repeat(np.arange(n * n), counts)
    w = lv["point_weight"].astype(np.float64).sum(axis=1)
    # heaviest point per texel: sort by (texel, weight)
    order = np.lexsort((w, tex))
    last = np.flatnonzero(np.r_[tex[order][1:] != tex[order][:-1], True])
    best = order[last]  # one point per filled texel
    filled = tex[best]
    if filled.size == 0:
        raise StageError(f"{scene.root}: the finest CPM level has no points")
    rc = np.stack(np.divmod(np.arange(n * n), n), axis=1)
    _, near = cKDTree(rc[filled]).query(rc)
    src = best[near]
    mat = lv["point_material"][src].astype(np.int64)
    uv = lv["point_uv"][src].astype(np.float64)
    kd = np.zeros((n * n, 3))
    for m in np.unique(mat):  # the few materials
        sel = mat == m
        kd[sel] = brdf_mod.diffuse_albedo(scene.materials[int(m)], uv[sel])
    scene._nm = {"material": mat, "uv": uv, "kd": kd,
                 "frames": face_tangent_space(*m1_arrays(scene))}
    return scene._nm


def _bilinear_map(img: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear look-up of an (N, N, c) atlas map at uv (n, 2) (row = (1 - v) N)."""
    n = img.shape[0]
    idx, w = bilinear_texels(uv, n)
    flat = img.reshape(n * n, -1).astype(np.float64)
    return np.einsum("nk,nkc->nc", w, flat[idx])


def baseline_maps(scene: RenderScene) -> tuple[np.ndarray, np.ndarray]:
    """The albedo and tangent-space normal maps (N, N, 3) the mode reads: the float maps of
    the finest filtered level when the bake wrote them (the renormalised mean normal and the
    albedo, the same area-weighted means as the 8-bit PNGs, without their quantisation: the
    filtered modes read the same floats, so with zero variance they equal this mode exactly),
    else the PNGs of the USD fallback (bakes from before the filtered maps)."""
    if not scene.baked.filtered:
        return scene.baked.albedo, scene.baked.normal
    from texelbake.baselines.filtered_maps import FIELDS

    top = scene.baked.filtered[0].astype(np.float64)
    nbar = top[..., FIELDS["nbar"]]
    length = np.linalg.norm(nbar, axis=2, keepdims=True)
    normal = np.divide(nbar, length, out=np.zeros_like(nbar) + [0.0, 0.0, 1.0],
                       where=length > 0)
    return top[..., FIELDS["albedo"]], normal


def normalmap_brdf(scene: RenderScene, texel: np.ndarray, albedo: np.ndarray):
    """The baseline's BRDF at hits on M1: the texel's material (nearest texel of the material
    map) with its Lambertian part replaced by the albedo map,
    f = max(f_mat − kd_mat/π + albedo/π, 0): what a look-dev artist gets by plugging the baked
    albedo into the material's diffuse colour (exact for Lambertian materials)."""
    nm = _normalmap_tables(scene)
    mat = nm["material"][texel]

    def brdf(sel: np.ndarray, wi: np.ndarray, wo: np.ndarray) -> np.ndarray:
        t = texel[sel]
        f = brdf_mod.evaluate_by_face(scene.materials, mat[sel], wi, wo, nm["uv"],
                                      sample_index=t)
        lam = (wi[:, 2] > TOL.grazing_cos) & (wo[:, 2] > TOL.grazing_cos)
        f += lam[:, None] * (albedo[sel] - nm["kd"][t]) / np.pi
        return np.maximum(f, 0.0)

    return brdf


def shade_normalmap(scene: RenderScene, o: np.ndarray, d: np.ndarray
                    ) -> tuple[np.ndarray, int, np.ndarray]:
    """Radiance along eye rays traced against M1 with the baked normal and albedo maps;
    returns (radiance (n, 3), rays cast, hit (n,) bool)."""
    nm = _normalmap_tables(scene)
    caster = scene.lods[0]
    rays = o.shape[0]
    out = np.zeros((o.shape[0], 3))
    hit, idx, prim, p, uv, row, col, _ = hit_m1(scene, o, d)
    if idx.size == 0:
        return out, rays, hit
    albedo_map, normal_map = baseline_maps(scene)
    fine = baseline_albedo(scene, uv)  # the texture's page where it is finer than the atlas
    albedo = _bilinear_map(albedo_map, uv) if fine is None else fine
    local = _bilinear_map(normal_map, uv)
    ns = np.einsum("nji,nj->ni", nm["frames"][prim], local)  # tangent space -> world
    ns /= np.maximum(np.linalg.norm(ns, axis=1, keepdims=True), 1e-300)
    texel = row * scene.n0 + col
    rad, shadow = direct_radiance(p, scene.lod_face_normals[0][prim], ns, -d[idx], scene.lights,
                                  normalmap_brdf(scene, texel, albedo), caster, scene.ray_eps)
    out[idx] = rad
    return out, rays + shadow, hit


def render_normalmap(scene: RenderScene, cam: PinholeCamera, spp: int, seed: int):
    return accumulate(cam, spp, seed, lambda o, d: shade_normalmap(scene, o, d), scene.eye_box)
