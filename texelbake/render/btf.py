"""``btf``: the real-time target of seed 001 (§3.4) on M1, the baked BTF maps looked up with
Eq. 7 (continuous LOD) at the pixel footprint.

On a deformed frame (`render.deformed`, seed 002 §4) the eye rays meet the deformed M1 and the
light and view directions reach the rest texel frame through the look-up rotation L at the
hit (Eq. 10 interpolated on M1's triangle, `lookup`); without it (`btf-naive`) the rest table
is read with deformed-world directions."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from texelbake.errors import StageError
from texelbake.render.cpm import footprint_level
from texelbake.render.scene import RenderScene, hit_m1
from texelbake.tol import TOL
from texelbake.trace.camera import PinholeCamera
from texelbake.trace.shade import lit_points
from texelbake.trace.tracer import accumulate


def _btf_files(scene: RenderScene) -> list[Path]:
    return [scene.root.parent / f"btf_{p}.exr" for p in ("eigen", "weights", "lut", "pairs")]


def has_btf_maps(scene: RenderScene) -> bool:
    """Whether the bake wrote BTF maps beside its USD (`BakeSettings.btf`)."""
    return all(f.is_file() for f in _btf_files(scene))


def btf_maps(scene: RenderScene):
    """The bake's BTF maps (texelbake.btf.BTFMaps), read once from beside the baked USD."""
    if scene._btf is None:
        from texelbake.btf import read_btf_maps

        folder = scene.root.parent
        missing = [str(f) for f in _btf_files(scene) if not f.is_file()]
        if missing:
            raise StageError(f"baked asset {scene.root}: mode 'btf' needs the BTF maps "
                             f"(bake with settings.btf on); missing {missing}")
        maps = read_btf_maps(folder, "btf")
        if tuple(maps.shape) != (scene.n0, scene.n0):
            raise StageError(f"{folder}/btf_weights.exr: BTF map is {tuple(maps.shape)}, "
                             f"expected the atlas resolution ({scene.n0}, {scene.n0})")
        scene._btf = maps
    return scene._btf


def shade_btf(scene: RenderScene, cam: PinholeCamera, o: np.ndarray, d: np.ndarray,
              *, lod_bias: float = 0.0, interpolate: bool = False,
              lookup: Callable[[RenderScene, np.ndarray, np.ndarray], np.ndarray] | None = None
              ) -> tuple[np.ndarray, int, np.ndarray]:
    """Radiance along eye rays traced against M1 with the BTF maps (module docstring).

    o, d : (n, 3) float64 eye rays; lookup : (scene, M1 triangles (k,), barycentrics (k, 3))
    -> the rotations (k, 3, 3) from the deformed world to the rest world at the hits (seed
    002 Eq. 10, `render.deformed.vertex_lookup`), or None (directions in the rest world);
    returns (radiance (n, 3) float64, rays cast, hit (n,) bool)
    """
    from texelbake.btf import btf_lookup_texels

    maps = btf_maps(scene)
    caster = scene.lods[0]
    rays = o.shape[0]
    out = np.zeros((o.shape[0], 3))
    hit, idx, prim, p, _, row, col, bary = hit_m1(scene, o, d)
    if idx.size == 0:
        return out, rays, hit
    n = scene.n0
    frames = scene.baked.levels[0]["frames"][row * n + col].astype(np.float64)  # (k, 3, 3)
    if lookup is not None:  # rest texel frame ∘ L: deformed-world directions in, local out
        frames = frames @ lookup(scene, prim, bary)
    ng = scene.lod_face_normals[0][prim]
    wo = -d[idx]
    lam = footprint_level(scene, cam, 0, prim, p, o[idx], d[idx]) + lod_bias
    lam = np.clip(lam, 0.0, float(maps.top_level))
    view_ok = np.einsum("ij,ij->i", ng, wo) > TOL.grazing_cos
    wo_l = np.einsum("nij,nj->ni", frames, wo)
    for light in scene.lights:  # a loop over the few lights
        live, wi, e, r = lit_points(light, p, ng, view_ok, caster, scene.ray_eps)
        rays += r
        if live.size == 0:
            continue
        wi_l = np.einsum("nij,nj->ni", frames[live], wi[live])
        fbar = btf_lookup_texels(maps, row[live], col[live], wi_l, wo_l[live], lam[live],
                                 interpolate)
        # a truncated PCA can undershoot zero where f̄ is near zero (measured: -0.06 in the
        # demo's cylinder at 16²); reflectance is not negative, so neither is the radiance
        fbar = np.maximum(fbar, 0.0)
        out[idx[live]] += e[live] * fbar  # f̄ carries cos_i cos_o already: E_l only
    return out, rays, hit


def render_btf(scene: RenderScene, cam: PinholeCamera, spp: int, seed: int, **kw):
    return accumulate(cam, spp, seed, lambda o, d: shade_btf(scene, cam, o, d, **kw),
                      scene.eye_box)
