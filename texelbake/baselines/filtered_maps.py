"""The filtered normal maps studios ship: per mip level of M1's atlas, from the
geometry stage's samples and their texel assignment (the same `texel_ids` as the CPM levels),

- the mean tangent-space normal *before* renormalisation, n̄ = Σ ΔA n / Σ ΔA, whose length
  gives Toksvig's factor (Toksvig 2005, "Mipmapping normal maps", §"Estimating Normal Variation": for a Gaussian
  spread of normals of angular variance σ², |n̄| = 1 / (1 + σ²), so σ² = (1 − |n̄|) / |n̄|);
- the first and second moments of the slopes (x̃, ỹ) = (−n_x / n_z, −n_y / n_z), E[x̃], E[ỹ],
  E[x̃²], E[ỹ²], E[x̃ỹ] (Olano & Baker 2010, LEAN mapping: the "B" and "M" maps; Dupuy et al.
  2013, LEADR mapping: the same five moments of the displaced surface). Moments are linear, so the
  coarser levels are exact area-weighted means of the same samples, and trilinear filtering
  at render time stays exact;
- ambient occlusion, AO = (1/π) ∫ V(x, ω) (n·ω) dω, by cosine-weighted hemisphere rays
  against M_org (what Blender, Substance and xNormal bake), per sample, then area-averaged;
- the albedo (as `normalmap.bake_preview_maps`), the base colour UsdPreviewSurface's
  ``diffuseColor`` needs (for metals the albedo is 0 but the colour is F0), and the base
  microfacet variance α² of the sample's material (the roughness a fallback widens).

The tangent space is the normal map's (`normalmap.face_tangent_space`: the M1 triangle under
the sample), so the moments describe the same normals the `normalmap` mode decodes.

Hard cases (each tested in tests/baselines/test_filtered_maps.py):
- slopes at grazing normals: n_z is clamped to `FILTER_TOL.min_cos` before dividing (a normal
  at or below the M1 tangent plane gets slope |n_xy| / min_cos ≤ ~10 along its own
  azimuth), so no moment is infinite;
- empty texels (no sample): filled from their neighbours like the preview maps (`dilate`),
  a convex combination, so moments stay consistent (E[x̃²] ≥ E[x̃]²);
- AO with nothing above the surface: every ray escapes, AO = 1 exactly.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from texelbake import brdf
from texelbake.baselines.normal_maps import dilate
from texelbake.brdf.common import as_scalar
from texelbake.brdf.evaluate import material_inputs
from texelbake.errors import ShapeError
from texelbake.io.chunks import bincount_continued
from texelbake.model import Material

#: channel layout of one level's filtered map (EXR channel names, in order)
CHANNELS = ("nbar.x", "nbar.y", "nbar.z", "m1.x", "m1.y", "m2.xx", "m2.yy", "m2.xy", "ao",
            "albedo.R", "albedo.G", "albedo.B", "base.R", "base.G", "base.B", "alpha2")
#: slices of CHANNELS by quantity
FIELDS = {"nbar": slice(0, 3), "m1": slice(3, 5), "m2": slice(5, 8), "ao": slice(8, 9),
          "albedo": slice(9, 12), "base": slice(12, 15), "alpha2": slice(15, 16)}


@dataclass(frozen=True)
class FilterTol:
    """Named tolerances of the filtered maps (one place, as `texelbake.tol`)."""

    #: n_z below this is clamped in the slope transform (slope magnitude <= ~1 / min_cos)
    min_cos: float = 0.1
    #: |n̄| below this counts as "normals cancel": Toksvig variance capped there
    min_nbar: float = 1e-3
    #: largest slope variance per axis a filtered lobe may take (= max slope²)
    max_var: float = 100.0
    #: AO rays per sample (cosine-weighted, stratified, rotated per sample)
    ao_rays: int = 32


FILTER_TOL = FilterTol()


def slopes(local_normals: np.ndarray, *, min_cos: float = FILTER_TOL.min_cos) -> np.ndarray:
    """Slopes (x̃, ỹ) = (−n_x, −n_y) / max(n_z, min_cos) of tangent-space normals (LEAN;
    a height field h has n ∝ (−h_x, −h_y, 1), so these are its slopes).

    local_normals : (m, 3) float64 (need not be unit); returns (m, 2) float64
    """
    n = np.asarray(local_normals, dtype=np.float64)
    if n.ndim != 2 or n.shape[1] != 3:
        raise ShapeError(f"local_normals must be (m, 3), got {n.shape}")
    length = np.linalg.norm(n, axis=1, keepdims=True)
    u = np.divide(n, length, out=np.tile([0.0, 0.0, 1.0], (n.shape[0], 1)), where=length > 0)
    return -u[:, :2] / np.maximum(u[:, 2:3], min_cos)


def _radical_inverse(j: np.ndarray) -> np.ndarray:
    """Van der Corput radical inverse in base 2 of non-negative integers j, (n,) float64."""
    j = np.asarray(j, dtype=np.uint64)
    out = np.zeros(j.shape)
    scale = 0.5
    for _ in range(32):  # bits of a 32-bit index
        out += (j & np.uint64(1)) * scale
        j = j >> np.uint64(1)
        scale *= 0.5
    return out


def ambient_occlusion(points: np.ndarray, normals: np.ndarray,
                      occluded: Callable[[np.ndarray, np.ndarray], np.ndarray], *,
                      n_rays: int = FILTER_TOL.ao_rays, seed: int = 0, ray_eps: float = 0.0,
                      batch: int = 1 << 20, first: int = 0, total: int | None = None
                      ) -> np.ndarray:
    """AO = (1/π) ∫ V (n·ω) dω per point, the cosine-weighted Monte Carlo estimate
    1 − (occluded rays) / n_rays. Directions: a Hammersley set (u₀ = (j + ξ) / n_rays
    stratified, u₁ the radical inverse of j), with a seeded random offset ξ of the strata and
    a random rotation about the normal per point (Cranley–Patterson: unbiased, no structured
    banding across points), mapped to the cosine-weighted hemisphere (r = √u₀, φ = 2π u₁).

    points, normals : (m, 3) float64 (normals unit, the side the rays leave from)
    occluded : the ray caster's any-hit test, (k, 3) origins, (k, 3) dirs -> (k,) bool
    first, total : these points are points first.. of `total` (default: all of them): the
        offsets ξ and rotations are the draws of those points in the one-pass streams (ξ of
        every point, then every rotation), so a chunked pass gives the one-pass AO bit for bit
    returns : (m,) float64 in [0, 1]; exactly 1 where no ray hits anything
    """
    p = np.asarray(points, dtype=np.float64)
    nrm = np.asarray(normals, dtype=np.float64)
    if p.shape != nrm.shape or p.ndim != 2 or p.shape[1] != 3:
        raise ShapeError(f"points and normals must both be (m, 3), got {p.shape}, {nrm.shape}")
    m = p.shape[0]
    if m == 0:
        return np.zeros(0)
    from texelbake.geometry.basis import tangent_frames

    j = np.arange(n_rays)
    u1 = _radical_inverse(j)  # (r,)
    total = m if total is None else int(total)
    # np.random.default_rng(seed)'s streams, entered where these points' draws are (a
    # uniform double is one 64-bit step of PCG64)
    xi = np.asarray(np.random.Generator(np.random.PCG64(seed).advance(int(first)))
                    .uniform(0.0, 1.0, size=m))
    rot = np.asarray(np.random.Generator(np.random.PCG64(seed).advance(total + int(first)))
                     .uniform(0.0, 2.0 * np.pi, size=m))
    frames = tangent_frames(nrm)  # (m, 3, 3) rows t, b, n
    hits = np.zeros(m)
    per = max(1, batch // n_rays)
    for lo in range(0, m, per):  # a loop over big batches of points (n_rays each)
        hi = min(lo + per, m)
        u0 = (j[None, :] + xi[lo:hi, None]) / n_rays  # (b, r)
        r = np.sqrt(u0)
        phi = 2.0 * np.pi * u1[None, :] + rot[lo:hi, None]
        lx, ly, lz = r * np.cos(phi), r * np.sin(phi), np.sqrt(np.maximum(1.0 - u0, 0.0))
        fr = frames[lo:hi]
        d = (lx[..., None] * fr[:, None, 0] + ly[..., None] * fr[:, None, 1]
             + lz[..., None] * fr[:, None, 2])  # (b, r, 3)
        o = np.repeat(p[lo:hi] + ray_eps * nrm[lo:hi], n_rays, axis=0)
        occ = occluded(o, d.reshape(-1, 3)).reshape(hi - lo, n_rays)
        hits[lo:hi] = occ.sum(axis=1)
    return 1.0 - hits / n_rays


def material_base(materials: Sequence[Material], sample_material: np.ndarray,
                  sample_uv: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per sample: the diffuse albedo (`brdf.diffuse_albedo`), the base colour a
    UsdPreviewSurface fallback takes as ``diffuseColor`` (preview: diffuseColor; others: their
    albedo) and the material's microfacet variance α² (preview: roughness⁴, UsdPreviewSurface's
    α = roughness²; phong: 2 / (s + 2), the Beckmann α of Phong exponent s (Walter et al. 2007,
    §5.2); cellular: its borders' roughness⁴; lambert and measured: 1, the widest lobe), a
    textured roughness or exponent read at the sample's uv.

    returns : (albedo (m, 3), base (m, 3), alpha2 (m,)) float64
    """
    m = sample_material.shape[0]
    albedo, base, alpha2 = np.zeros((m, 3)), np.zeros((m, 3)), np.ones(m)
    for mi in np.unique(sample_material):  # a loop over the few materials
        sel = sample_material == mi
        mat = materials[int(mi)]
        albedo[sel] = brdf.diffuse_albedo(mat, sample_uv[sel])
        base[sel] = albedo[sel]
        alpha2[sel] = base_alpha2(mat)
        lobe = {"preview": "roughness", "phong": "exponent"}.get(mat.model)
        if lobe is not None and lobe in mat.textures:  # a textured lobe: per sample
            v = material_inputs(mat, (lobe,), sample_uv[sel], None)[lobe].astype(np.float64)
            alpha2[sel] = (np.clip(v, 1e-3, 1.0) ** 4 if lobe == "roughness"
                           else 2.0 / (np.maximum(v, 0.0) + 2.0))
        if mat.model == "preview":
            d = mat.params.get("diffuseColor", (0.18, 0.18, 0.18))
            if "diffuseColor" in mat.textures:
                from texelbake.brdf.textures import sample_texture

                base[sel] = sample_texture(mat.textures["diffuseColor"], sample_uv[sel])[:, :3]
            else:
                base[sel] = np.asarray(d, dtype=np.float64).reshape(1, 3)
    return albedo, base, alpha2


def metallic_workflow(material: Material) -> bool:
    """A UsdPreviewSurface in the metallic workflow (its metallic input applies)."""
    return material.model == "preview" and not int(material.params.get("useSpecularWorkflow", 0))


def material_metallic(materials: Sequence[Material], sample_material: np.ndarray,
                      sample_uv: np.ndarray) -> np.ndarray:
    """Per sample the UsdPreviewSurface metallic a fallback in the metallic workflow takes:
    a metallic-workflow preview material's metallic (its texture sampled at uv, or its
    constant), clipped to [0, 1]; 0 for every other material (a dielectric: the specular
    workflow, Phong, Lambert, cellular, measured). returns (m,) float64."""
    out = np.zeros(sample_material.shape[0])
    for mi in np.unique(sample_material):  # a loop over the few materials
        mat = materials[int(mi)]
        if not metallic_workflow(mat):
            continue
        sel = sample_material == mi
        v = material_inputs(mat, ("metallic",), sample_uv[sel], None)["metallic"]
        out[sel] = np.clip(as_scalar(v, int(sel.sum()), "metallic"), 0.0, 1.0)
    return out


def base_alpha2(material: Material) -> float:
    """The material's microfacet variance α² (see `material_base`), a constant per material."""
    p = material.params
    if material.model == "preview":
        return float(np.clip(float(p.get("roughness", 0.5)), 1e-3, 1.0) ** 4)
    if material.model == "phong":
        return 2.0 / (float(p.get("exponent", 32.0)) + 2.0)
    if material.model == "cellular":
        return float(np.clip(float(p.get("borderRoughness", 0.25)), 1e-3, 1.0) ** 4)
    return 1.0


def bake_filtered_levels(resolution: int, n_levels: int, texels: Sequence[np.ndarray],
                         area: np.ndarray, local_normals: np.ndarray, ao: np.ndarray,
                         albedo: np.ndarray, base: np.ndarray, alpha2: np.ndarray,
                         *, fill: bool = True) -> list[np.ndarray]:
    """Every level's filtered map (module docstring), area-weighted over the samples of
    each texel, batched with `np.bincount` (no loop over texels or samples); `FilteredSums`
    takes the samples a chunk at a time with the same result.

    texels : per level, (m,) int64 flat texel id of every sample (`cpm.level.texel_ids`)
    area : (m,) ΔA; local_normals : (m, 3) tangent-space normals; ao : (m,); albedo, base :
        (m, 3); alpha2 : (m,)
    fill : dilate into empty texels (`normalmap.dilate`); False leaves them at the empty
        values (nbar (0, 0, 1), AO 1, α² 1, the rest 0) for the caller to fill
    returns : per level ℓ an (N_ℓ, N_ℓ, len(CHANNELS)) float32 map
    """
    sums = FilteredSums(resolution, n_levels)
    sums.add(texels, area, local_normals, ao, albedo, base, alpha2)
    return sums.maps(fill=fill)


class FilteredSums:
    """`bake_filtered_levels` over chunks of samples given in order: the area-weighted sums
    per texel are continued across chunks (`chunks.bincount_continued`), so the maps equal
    the one-pass maps bit for bit (the export's pass over a 512² bake's 16.8 M samples)."""

    def __init__(self, resolution: int, n_levels: int) -> None:
        self.resolution, self.n_levels = int(resolution), int(n_levels)
        sizes = [max(self.resolution >> level, 1) ** 2 for level in range(self.n_levels)]
        self.wsum = [np.zeros(n) for n in sizes]
        self.acc = [np.zeros((len(CHANNELS), n)) for n in sizes]

    def add(self, texels: Sequence[np.ndarray], area: np.ndarray, local_normals: np.ndarray,
            ao: np.ndarray, albedo: np.ndarray, base: np.ndarray, alpha2: np.ndarray) -> None:
        """The next chunk of samples (arguments as `bake_filtered_levels`')."""
        a = np.asarray(area, dtype=np.float64)
        nrm = np.asarray(local_normals, dtype=np.float64)
        length = np.linalg.norm(nrm, axis=1, keepdims=True)
        unit = np.divide(nrm, length, out=np.tile([0.0, 0.0, 1.0], (nrm.shape[0], 1)),
                         where=length > 0)
        s = slopes(unit)
        per_sample = np.column_stack([
            unit, s, s[:, 0] ** 2, s[:, 1] ** 2, s[:, 0] * s[:, 1], ao, albedo, base, alpha2,
        ])  # (m, C)
        if per_sample.shape[1] != len(CHANNELS):
            raise ShapeError(f"per-sample channels {per_sample.shape[1]} != {len(CHANNELS)}")
        for level in range(self.n_levels):  # a loop over the few levels
            t = np.asarray(texels[level], dtype=np.int64)
            self.wsum[level] = bincount_continued(self.wsum[level], t, a)
            for c in range(len(CHANNELS)):  # a loop over the channels
                self.acc[level][c] = bincount_continued(self.acc[level][c], t,
                                                        a * per_sample[:, c])

    def maps(self, *, fill: bool = True) -> list[np.ndarray]:
        empty = np.zeros(len(CHANNELS))
        empty[FIELDS["nbar"]] = (0.0, 0.0, 1.0)
        empty[FIELDS["ao"]] = 1.0
        empty[FIELDS["alpha2"]] = 1.0
        out = []
        for level in range(self.n_levels):  # a loop over the few levels
            n_l = max(self.resolution >> level, 1)
            wsum, acc = self.wsum[level], np.ascontiguousarray(self.acc[level].T)
            filled = wsum > 0
            mean = np.where(filled[:, None], acc / np.where(filled, wsum, 1.0)[:, None],
                            empty[None, :])
            img = mean.reshape(n_l, n_l, -1)
            if fill:
                img = dilate(img, filled.reshape(n_l, n_l), iterations=max(8, n_l))
            out.append(img.astype(np.float32))
        return out


def slope_covariance(m1: np.ndarray, m2: np.ndarray, *, max_var: float = FILTER_TOL.max_var
                     ) -> np.ndarray:
    """Σ = M − E[s] E[s]ᵀ from filtered moments (LEAN and LEADR: Σ = M − B Bᵀ), projected onto the
    positive semi-definite cone with eigenvalues at most `max_var`: filtering in float16 or
    float32 (and the EXR round trip) can leave E[x̃²] − E[x̃]² slightly negative or the 2×2
    determinant below 0; clamping the eigenvalues of the symmetric 2×2 (closed form) to
    [0, max_var] is the nearest valid covariance in the Frobenius norm.

    m1 : (n, 2) E[x̃], E[ỹ]; m2 : (n, 3) E[x̃²], E[ỹ²], E[x̃ỹ]
    returns : (n, 2, 2) float64 symmetric, PSD, finite (non-finite input -> 0)
    """
    m1 = np.asarray(m1, dtype=np.float64)
    m2 = np.asarray(m2, dtype=np.float64)
    a = m2[:, 0] - m1[:, 0] ** 2
    c = m2[:, 1] - m1[:, 1] ** 2
    b = m2[:, 2] - m1[:, 0] * m1[:, 1]
    half_tr = 0.5 * (a + c)
    disc = np.sqrt(np.maximum(0.25 * (a - c) ** 2 + b * b, 0.0))
    l1, l2 = half_tr + disc, half_tr - disc  # eigenvalues, l1 >= l2
    # eigenvector of l1: (b, l1 - a), or (1, 0) / (0, 1) when b = 0
    vx = np.where(np.abs(b) > 0, b, np.where(a >= c, 1.0, 0.0))
    vy = np.where(np.abs(b) > 0, l1 - a, np.where(a >= c, 0.0, 1.0))
    norm = np.hypot(vx, vy)
    norm = np.where(norm > 0, norm, 1.0)
    vx, vy = vx / norm, vy / norm
    l1 = np.clip(np.nan_to_num(l1, nan=0.0), 0.0, max_var)
    l2 = np.clip(np.nan_to_num(l2, nan=0.0), 0.0, max_var)
    cov = np.empty((m1.shape[0], 2, 2))
    cov[:, 0, 0] = l1 * vx * vx + l2 * vy * vy
    cov[:, 1, 1] = l1 * vy * vy + l2 * vx * vx
    cov[:, 0, 1] = cov[:, 1, 0] = (l1 - l2) * vx * vy
    return np.nan_to_num(cov, nan=0.0, posinf=0.0, neginf=0.0)


def toksvig_variance(nbar_length: np.ndarray, *, min_nbar: float = FILTER_TOL.min_nbar,
                     max_var: float = FILTER_TOL.max_var) -> np.ndarray:
    """σ² = (1 − |n̄|) / |n̄| (Toksvig 2005, |n̄| = 1 / (1 + σ²) inverted), |n̄| clamped to [min_nbar, 1]
    (normals that cancel, |n̄| → 0, give the bounded σ² ≤ max_var, never NaN); (n,) float64."""
    ln = np.clip(np.nan_to_num(np.asarray(nbar_length, dtype=np.float64), nan=0.0),
                 min_nbar, 1.0)
    return np.minimum((1.0 - ln) / ln, max_var)


def fallback_roughness(alpha2: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """UsdPreviewSurface roughness widened by the slope variance: α'² = α² + tr Σ (the
    isotropic lobe whose per-axis slope variance α'²/2 is the material's α²/2 plus the mean of
    the two meso-scale variances; Beckmann/GGX slope variance per axis is α²/2), clamped to
    the spec's [0, 1], roughness = √α' = (α'²)^¼. alpha2 : (n,); cov : (n, 2, 2)."""
    a2 = np.asarray(alpha2, dtype=np.float64) + cov[:, 0, 0] + cov[:, 1, 1]
    return np.clip(a2, 0.0, 1.0) ** 0.25


def lod_levels(lod_errors: Sequence[float], texel_size: float, n_levels: int) -> list[int]:
    """The mip level whose maps a LOD's fallback carries: M_i is shown where its geometric
    error (`lod_errors[i]`, world units) spans at most a pixel (`render.cpm.choose_mesh`), so a
    pixel there covers ≥ that error and the texel level ℓ = round(log2(error / texel_size)),
    clipped to the levels; M1 (index 0) is shown up close and keeps level 0."""
    out = [0]
    for err in list(lod_errors)[1:]:
        lvl = round(float(np.log2(max(float(err), 1e-300) / texel_size)))
        out.append(int(np.clip(lvl, 0, n_levels - 1)))
    return out


def dominant_constants(materials: Sequence[Material], sample_material: np.ndarray,
                       area: np.ndarray) -> dict[str, object]:
    """UsdPreviewSurface inputs carried from the material covering the most area (the
    fallback's base parameters): a preview material's metallic, specular workflow,
    specularColor (only in the specular workflow: the metallic one ignores it, and Blender's
    importer would make it a metal's edge tint), ior, clearcoat; Phong's ks as the specular
    workflow's specularColor; otherwise the specular workflow with specularColor 0 (a diffuse
    material; UsdPreviewSurface keeps its Fresnel edge)."""
    w = np.bincount(sample_material, weights=area, minlength=len(materials))
    mat = materials[int(np.argmax(w))]
    p = mat.params
    if mat.model == "preview":
        keep = ["metallic", "useSpecularWorkflow", "ior", "clearcoat", "clearcoatRoughness"]
        if int(p.get("useSpecularWorkflow", 0)):
            keep.append("specularColor")
        return {k: p[k] for k in keep if k in p and k not in mat.textures}
    if mat.model == "phong":
        return {"useSpecularWorkflow": 1,
                "specularColor": tuple(np.asarray(p.get("specularColor", (0, 0, 0)), float))}
    if mat.model == "cellular":
        return {}
    return {"useSpecularWorkflow": 1, "specularColor": (0.0, 0.0, 0.0)}
