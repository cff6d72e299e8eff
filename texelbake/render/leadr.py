"""``leadr`` (and ``leadr+ao``): LEAN/LEADR mapping (Olano & Baker 2010; Dupuy et al. 2013)
from the baked slope moments.

Per eye ray the moments E[x̃], E[ỹ], E[x̃²], E[ỹ²], E[x̃ỹ] are filtered trilinearly at the
pixel footprint (`render.filtered.lookup_filtered`, the level chosen as ``cpm`` chooses it;
linear filtering of moments is exact, LEAN's point), giving the mean slope x̄ and the
covariance Σ = M − x̄x̄ᵀ (LEAN; LEADR), projected onto the PSD cone with
eigenvalues in [0, `FILTER_TOL.max_var`] (`filtered_maps.slope_covariance`: float32 maps and
filtering can leave it indefinite). The mean-slope normal n_μ ∝ (−x̄, −ȳ, 1) is the shading
normal of the diffuse term, whose cosine is that of the mean normal before renormalisation,
E[n·ωi] = n̄·ωi (a stated alternative to LEADR's diffuse treatment: exact for a normal-mapped
Lambertian texel where no normal faces away from the light, and for a displaced one seen from
above). What each BRDF family maps to is the table of `brdf.widened`:
UsdPreviewSurface keeps its GGX lobe, sheared to x̄ and widened to A = α² I + 2Σ, with Smith
masking along the projected roughness (`brdf.widened.preview_leadr`), weighted by the
macro-surface cosine (the microfacet BRDF of the M1 surface, the microfacet model LEADR renders); its diffuse term
and every other family are evaluated at n_μ (Phong widened to α'² = 2/(s+2) + tr Σ), weighted
by n_μ·ωi. The material's Lambertian part is replaced by the albedo map as in ``normalmap``;
``+ao`` multiplies the albedo term by the baked AO. With x̄ = 0 and Σ = 0 the mode is
``normalmap`` exactly.
"""

from __future__ import annotations

import numpy as np

from texelbake import brdf as brdf_mod
from texelbake.baselines.filtered_maps import slope_covariance
from texelbake.brdf.evaluate import PREVIEW_BRDF_INPUTS, material_inputs
from texelbake.brdf.widened import preview_leadr, widen_material
from texelbake.geometry.basis import tangent_frames
from texelbake.render.albedo import baseline_albedo
from texelbake.render.filtered import RadianceFn, field, shade_filtered
from texelbake.render.normalmap import _normalmap_tables
from texelbake.render.scene import RenderScene
from texelbake.tol import TOL
from texelbake.trace.camera import PinholeCamera
from texelbake.trace.tracer import accumulate


def leadr_radiance(scene: RenderScene, values: np.ndarray, texel: np.ndarray, hits: dict,
                   *, ao: bool = False) -> RadianceFn:
    """The shading of the hits (module docstring); values (k, C) looked-up filtered maps,
    texel (k,) finest texel under each hit (its material, as ``normalmap``)."""
    nm = _normalmap_tables(scene)
    mat, uvm, kd = nm["material"][texel], nm["uv"][texel], nm["kd"][texel]
    mean = field(values, "m1")
    cov = slope_covariance(mean, field(values, "m2"))
    n_mu = np.column_stack([-mean, np.ones(mean.shape[0])])
    n_mu /= np.linalg.norm(n_mu, axis=1, keepdims=True)
    var_axis = 0.5 * (cov[:, 0, 0] + cov[:, 1, 1])
    nbar = field(values, "nbar")
    fine = baseline_albedo(scene, hits["uv"], hits["lam"])  # the texture's page, if finer
    albedo = (field(values, "albedo") if fine is None else fine) * (
        field(values, "ao") if ao else 1.0)

    def radiance(sel: np.ndarray, wi_t: np.ndarray, wo_t: np.ndarray) -> np.ndarray:
        frames = tangent_frames(n_mu[sel])
        wi_l = np.einsum("nij,nj->ni", frames, wi_t)
        wo_l = np.einsum("nij,nj->ni", frames, wo_t)
        spec = np.zeros((sel.size, 3))
        diffuse = np.zeros((sel.size, 3))
        ms = mat[sel]
        for m in np.unique(ms):  # a loop over the few materials
            rows = np.flatnonzero(ms == m)
            material = scene.materials[int(m)]
            s = sel[rows]
            if material.model == "preview":
                params = material_inputs(material, PREVIEW_BRDF_INPUTS, uvm[s], None)
                spec[rows], diffuse[rows] = preview_leadr(params, wi_t[rows], wo_t[rows],
                                                          mean[s], cov[s])
            else:
                wm = widen_material(material, var_axis[s])
                diffuse[rows] = brdf_mod.evaluate(wm, wi_l[rows], wo_l[rows], uvm[s])
        g = TOL.grazing_cos
        lam = (wi_l[:, 2] > g) & (wo_l[:, 2] > g)
        diffuse += lam[:, None] * (albedo[sel] - kd[sel]) / np.pi
        # the diffuse cosine integrated over the texel's normals: E[n·ωi] = n̄·ωi (exact where
        # no normal of the texel faces away from the light; n̄ = n_μ on a flat texel)
        cos_d = np.maximum(np.einsum("ij,ij->i", nbar[sel], wi_t), 0.0) * (wi_l[:, 2] > g)
        return (spec * np.maximum(wi_t[:, 2], 0.0)[:, None]
                + np.maximum(diffuse, 0.0) * cos_d[:, None])

    return radiance


def render_leadr(scene: RenderScene, cam: PinholeCamera, spp: int, seed: int, *,
                 ao: bool = False):
    def make(sc, values, texel, hits):
        return leadr_radiance(sc, values, texel, hits, ao=ao)

    return accumulate(cam, spp, seed, lambda o, d: shade_filtered(scene, cam, o, d, spp, make),
                      scene.eye_box)
