"""What the filtered-normal-map modes (`toksvig`, `leadr`, their `+ao` variants) share: the
bake's filtered maps read back through `texelbake.usd.read` (`texelbake.baselines.filtered_maps`
layout), looked up trilinearly at each eye ray's footprint exactly as ``cpm`` picks its level
(`cpm.footprint_level`, each of the spp samples at its 1/spp share of the pixel: λ lower by
½ log2 spp, clipped to the levels — the maps have no M_org fall-back: closer than the finest
level they are magnified, as a texture unit does), and the direct-light loop on M1 with
shadows on M1 (as ``normalmap``).

The shading functions get directions in the M1 tangent frame of the hit (the frame the
normal map and the moments are expressed in: `normalmap.face_tangent_space`) and return the
radiance per unit irradiance, cosines included, so that each mode owns its own cosine terms
(LEADR weighs its specular lobe by the macro-surface cosine and its diffuse term by the mean
normal's).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from texelbake.baselines.filtered_maps import CHANNELS, FIELDS
from texelbake.errors import StageError
from texelbake.geometry.texels import bilinear_texels
from texelbake.render.cpm import footprint_level
from texelbake.render.normalmap import _normalmap_tables
from texelbake.render.scene import RenderScene, hit_m1
from texelbake.tol import TOL
from texelbake.trace.camera import PinholeCamera
from texelbake.trace.shade import lit_points

#: radiance(selection (k,) into the hits, wi (k, 3), wo (k, 3) in the M1 tangent frame)
#: -> (k, 3): f_r times the mode's cosines (per unit irradiance)
RadianceFn = Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]


def filtered_tables(scene: RenderScene) -> list[np.ndarray]:
    """Every level's filtered map as (N_l², C) float64, converted once per scene. StageError
    naming the bake when it wrote none (bakes from before the filtered maps)."""
    cached = getattr(scene, "_filtered_tables", None)
    if cached is not None:
        return cached
    maps = scene.baked.filtered
    if not maps:
        raise StageError(f"baked asset {scene.root}: the filtered-map modes need "
                         f"{scene.baked.name}_filtered_L00.exr ... (rebake with this version)")
    if maps[0].shape[:2] != (scene.n0, scene.n0) or len(maps) != len(scene.baked.levels):
        raise StageError(f"baked asset {scene.root}: filtered maps {[m.shape for m in maps]} "
                         f"do not match the {len(scene.baked.levels)} levels of a "
                         f"{scene.n0}² atlas")
    tables = [m.reshape(-1, len(CHANNELS)).astype(np.float64) for m in maps]
    scene._filtered_tables = tables  # type: ignore[attr-defined]
    return tables


def lookup_filtered(scene: RenderScene, cam: PinholeCamera, spp: int, prim: np.ndarray,
                    p: np.ndarray, o: np.ndarray, d: np.ndarray, uv: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Trilinear look-up of the filtered maps at each hit's footprint (module docstring).

    prim (k,) M1 triangles, p (k, 3) hits, o, d (k, 3) their eye rays, uv (k, 2) atlas uv
    returns : (values (k, C) float64, λ (k,) the footprint's fractional level before it is
        clipped to the levels; below 0 the maps are magnified)"""
    tables = filtered_tables(scene)
    n_lv = len(tables)
    lam_raw = footprint_level(scene, cam, 0, prim, p, o, d) - 0.5 * math.log2(max(int(spp), 1))
    lam = np.clip(lam_raw, 0.0, n_lv - 1.0)
    j0 = np.floor(lam).astype(np.int64)
    fr = lam - j0
    out = np.zeros((prim.shape[0], len(CHANNELS)))
    for j in range(n_lv):  # a loop over the few levels; each hit reads two
        for sel, weight in ((np.flatnonzero(j0 == j), None),
                            (np.flatnonzero((j0 + 1 == j) & (fr > 0)), True)):
            if sel.size:
                tex, w = bilinear_texels(uv[sel], max(scene.n0 >> j, 1))
                wl = fr[sel] if weight else 1.0 - fr[sel]
                out[sel] += wl[:, None] * np.einsum("nk,nkc->nc", w, tables[j][tex])
    return out, lam_raw


def field(values: np.ndarray, name: str) -> np.ndarray:
    """The columns of one quantity (`filtered_maps.FIELDS`) of looked-up values."""
    return values[:, FIELDS[name]]


def shade_filtered(scene: RenderScene, cam: PinholeCamera, o: np.ndarray, d: np.ndarray,
                   spp: int, make_radiance: Callable[..., RadianceFn]
                   ) -> tuple[np.ndarray, int, np.ndarray]:
    """Radiance along eye rays traced against M1 with the filtered maps: `make_radiance(scene,
    values, texel, hits)` builds the mode's shading for the hits (values from
    `lookup_filtered`, texel (k,) the finest texel under each hit, hits a dict with "prim",
    "lam" (the unclipped footprint level) and "uv" (atlas uv));
    returns (radiance (n, 3), rays cast, hit (n,) bool)."""
    nm = _normalmap_tables(scene)
    caster = scene.lods[0]
    rays = o.shape[0]
    out = np.zeros((o.shape[0], 3))
    hit, idx, prim, p, uv, row, col, _ = hit_m1(scene, o, d)
    if idx.size == 0:
        return out, rays, hit
    values, lam = lookup_filtered(scene, cam, spp, prim, p, o[idx], d[idx], uv)
    frames = nm["frames"][prim]  # (k, 3, 3) rows t, b, n of the M1 tangent space
    ng = scene.lod_face_normals[0][prim]
    wo = -d[idx]
    view_ok = np.einsum("ij,ij->i", ng, wo) > TOL.grazing_cos
    radiance = make_radiance(scene, values, row * scene.n0 + col, {"prim": prim, "lam": lam, "uv": uv})
    wo_t = np.einsum("nij,nj->ni", frames, wo)
    for light in scene.lights:  # a loop over the few lights
        live, wi, e, r = lit_points(light, p, ng, view_ok, caster, scene.ray_eps)
        rays += r
        if live.size == 0:
            continue
        wi_t = np.einsum("nij,nj->ni", frames[live], wi[live])
        out[idx[live]] += e[live] * radiance(live, wi_t, wo_t[live])
    return out, rays, hit
