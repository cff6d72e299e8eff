"""``toksvig`` (and ``toksvig+ao``): the mip-mapped normal map with the lobe widened by
Toksvig's factor (Toksvig 2005, "Mipmapping normal maps"), what engines ship as "specular
anti-aliasing" of normal maps.

Per eye ray the filtered maps are looked up trilinearly at the pixel footprint
(`render.filtered.lookup_filtered`, the level chosen as ``cpm`` chooses it): the mean normal
n̄ before renormalisation shades along n̂ = n̄ / |n̄|, and its length gives the variance of
the normals the filter averaged, σ² = (1 − |n̄|) / |n̄| (Toksvig's |n̄| = 1 / (1 + σ²) inverted; |n̄| clamped
to `FILTER_TOL.min_nbar`: normals that cancel give a bounded, widest lobe, never NaN, and n̂
falls back to the macro normal when |n̄| = 0). Per family (`brdf.widened`): Phong's exponent
becomes s f_t, f_t = |n̄| / (|n̄| + s (1 − |n̄|)) (Toksvig, §"Eliminating Aliasing of Specular Highlights"); UsdPreviewSurface's
roughness becomes (α² + 2σ²)^¼ (Toksvig's σ² is Phong's 1/s, α² = 2/s); Lambert, measured and
cellular materials are evaluated at n̂ unwidened. As ``normalmap``, the material's
Lambertian part is replaced by the albedo map, f = max(f_mat − kd/π + albedo/π, 0); with
``+ao`` the albedo term is multiplied by the baked AO (engines multiply AO into the diffuse
and indirect terms; this renderer has direct light only). With zero variance (|n̄| = 1) the
mode is ``normalmap`` exactly.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from texelbake import brdf as brdf_mod
from texelbake.baselines.filtered_maps import toksvig_variance
from texelbake.brdf.widened import toksvig_phong_exponent, widen_material
from texelbake.geometry.basis import tangent_frames
from texelbake.render.albedo import baseline_albedo
from texelbake.render.filtered import RadianceFn, field, shade_filtered
from texelbake.render.normalmap import _normalmap_tables
from texelbake.render.scene import RenderScene
from texelbake.tol import TOL
from texelbake.trace.camera import PinholeCamera
from texelbake.trace.tracer import accumulate


def toksvig_radiance(scene: RenderScene, values: np.ndarray, texel: np.ndarray, hits: dict,
                     *, ao: bool = False) -> RadianceFn:
    """The shading of the hits (module docstring); values (k, C) looked-up filtered maps,
    texel (k,) finest texel under each hit (its material, as ``normalmap``)."""
    nm = _normalmap_tables(scene)
    mat, uvm, kd = nm["material"][texel], nm["uv"][texel], nm["kd"][texel]
    nbar = field(values, "nbar")
    length = np.linalg.norm(nbar, axis=1)
    up = np.tile([0.0, 0.0, 1.0], (nbar.shape[0], 1))
    n_hat = np.divide(nbar, length[:, None], out=up, where=length[:, None] > 0)
    sigma2 = toksvig_variance(length)
    fine = baseline_albedo(scene, hits["uv"], hits["lam"])  # the texture's page, if finer
    albedo = (field(values, "albedo") if fine is None else fine) * (
        field(values, "ao") if ao else 1.0)

    def radiance(sel: np.ndarray, wi_t: np.ndarray, wo_t: np.ndarray) -> np.ndarray:
        frames = tangent_frames(n_hat[sel])
        wi_l = np.einsum("nij,nj->ni", frames, wi_t)
        wo_l = np.einsum("nij,nj->ni", frames, wo_t)
        f = np.zeros((sel.size, 3))
        ms = mat[sel]
        for m in np.unique(ms):  # a loop over the few materials
            rows = np.flatnonzero(ms == m)
            material = scene.materials[int(m)]
            if material.model == "phong":
                s = float(material.params.get("exponent", 32.0))
                wm = replace(material, params={**material.params, "exponent":
                                               toksvig_phong_exponent(s, length[sel][rows])})
            else:
                wm = widen_material(material, sigma2[sel][rows])
            f[rows] = brdf_mod.evaluate(wm, wi_l[rows], wo_l[rows], uvm[sel][rows])
        g = TOL.grazing_cos
        lam = (wi_l[:, 2] > g) & (wo_l[:, 2] > g)
        f += lam[:, None] * (albedo[sel] - kd[sel]) / np.pi
        return np.maximum(f, 0.0) * np.maximum(wi_l[:, 2], 0.0)[:, None]

    return radiance


def render_toksvig(scene: RenderScene, cam: PinholeCamera, spp: int, seed: int, *,
                   ao: bool = False):
    def make(sc, values, texel, hits):
        return toksvig_radiance(sc, values, texel, hits, ao=ao)

    return accumulate(cam, spp, seed, lambda o, d: shade_filtered(scene, cam, o, d, spp, make),
                      scene.eye_box)
