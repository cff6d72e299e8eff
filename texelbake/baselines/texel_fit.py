"""Per-texel least-squares fit of UsdPreviewSurface inputs (roughness and diffuseColor in the
averaged fallback's workflow) to a texel's filtered reflectance, over many light and view
directions drawn per sample by projected solid angle.

The data are rows, one per (sample, light, view) pair of a texel: the light wi and view wo in
the texel's shading frame (z its mean normal), the target y = f_s(l, v) V_s(l) (n_s·l)⁺ (the
sample's radiance toward v under unit irradiance from l) and the weight w = A_s V_s(v)
(n_g,s·v)⁺ / (n_face·v) (its visible projected area; the views are cosine distributed about
the LOD face, so the weighted sum over rows estimates the image's squared error over lights
and views weighted by projected solid angle). Per pair the weighted least-squares optimum is
the filtered reflectance T(l, v) = Σ w y / Σ w, shadowing and masking included.

The model is the preview surface L(l, v) = f_ps(l, v) (n·l)⁺ on the shading normal. With the
workflow, metallic and the other constants fixed, f_ps is affine in diffuseColor per channel,
f = A + d B (exact for the specular workflow and for metallic 0 or 1; between, the metallic
workflow's d² term is left out and A, B are the chord from d = 0 to d = 1). Per texel the fit
minimises over roughness r (a grid, and the averaged roughness r0) and d, per channel,

    E(r, d) = Σ w (A_r + d B_r − y)²
              + λ [Σ w (A_r + d0 B_r − L0)² + Σ w B_r² (d − d0)²]

with L0 the averaged inputs' (r0, d0) radiance per row: a prior toward the averaged fallback
measured in radiance (λ = 0: least squares; λ = ∞: the averaged inputs). Given r, d is closed
form, d = (Σ w B (y − A) + λ d0 Σ w B²) / ((1 + λ) Σ w B²), clipped to [0, 1]. λ is chosen on
held-out rows (`choose_lambda`). Everything is sums over rows, vectorised over texels; no
randomness here, no iteration.
"""

from __future__ import annotations

import numpy as np

from texelbake.brdf.analytic import preview_surface
from texelbake.errors import ShapeError

#: the roughness candidates of the search besides each texel's averaged roughness
ROUGHNESS_GRID = (0.05, 0.08, 0.12, 0.17, 0.24, 0.33, 0.45, 0.6, 0.8, 1.0)
#: the prior's weights toward the averaged inputs, chosen per LOD on held-out rows
FIT_LAMBDAS = (0.0, 0.1, 0.3, 1.0, 3.0, float("inf"))
#: the sharpest candidate a texel may take, as a fraction of its averaged roughness
SHARPEN = 0.8
#: the pairs a lobe must hold to be fitted (`resolvable_roughness`)
MIN_LOBE_HITS = 8.0
#: a texel whose Σ w B² is below this fraction of the largest keeps d0 (no light reaches it)
_B_FLOOR = 1e-12


def lattice(n: int) -> np.ndarray:
    """A fixed Fibonacci lattice of n points in [0, 1)²: (n, 2) float64."""
    i = np.arange(n, dtype=np.float64)
    return np.column_stack([(i + 0.5) / n, np.mod(i * 0.6180339887498949, 1.0)])


def cosine_dirs(u: np.ndarray) -> np.ndarray:
    """Cosine-distributed directions about +z (Malley): u (..., 2) in [0, 1)² -> (..., 3) unit,
    density cos θ / π."""
    u = np.asarray(u, dtype=np.float64)
    r = np.sqrt(u[..., 0])
    phi = 2.0 * np.pi * u[..., 1]
    return np.stack([r * np.cos(phi), r * np.sin(phi),
                     np.sqrt(np.maximum(1.0 - u[..., 0], 0.0))], axis=-1)


def shifted_dirs(shift: np.ndarray, n: int) -> np.ndarray:
    """Each sample's n directions: the lattice shifted by the sample's shift (m, 2) in
    [0, 1)² (Cranley–Patterson), cosine distributed about +z: (m, n, 3) float64."""
    shift = np.asarray(shift, dtype=np.float64)
    if shift.ndim != 2 or shift.shape[1] != 2:
        raise ShapeError(f"shifted_dirs: shift must be (m, 2), got {shift.shape}")
    return cosine_dirs(np.mod(lattice(n)[None] + shift[:, None], 1.0))


def affine_terms(const: dict, rough: np.ndarray, wi: np.ndarray, wo: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
    """(A, B) (n, 3) float64: the preview surface's radiance f_ps (n·wi)⁺ at diffuseColor 0 and
    its growth to diffuseColor 1, L(d) = A + d B, for constants `const`, roughness (n,) and
    wi, wo (n, 3) in the shading frame."""
    wi = np.asarray(wi, dtype=np.float64)
    wo = np.asarray(wo, dtype=np.float64)
    n = wi.shape[0]
    rough = np.broadcast_to(np.asarray(rough, dtype=np.float64), (n,))
    cos = np.maximum(wi[:, 2:3], 0.0)
    a = preview_surface({**const, "diffuseColor": np.zeros((n, 3)), "roughness": rough},
                        wi, wo) * cos
    b = preview_surface({**const, "diffuseColor": np.ones((n, 3)), "roughness": rough},
                        wi, wo) * cos - a
    return a, b


def row_sums(a: np.ndarray, b: np.ndarray, y: np.ndarray, w: np.ndarray, l0: np.ndarray,
             d0: np.ndarray, group: np.ndarray, n_groups: int) -> np.ndarray:
    """Per group and channel the sums of E: (g, 4, 3) float64 [Σ w (y − A)², Σ w B (y − A),
    Σ w B², Σ w (A + d0 B − L0)²]. a, b, y, l0 (n, 3); w (n,); d0 (n, 3) each row's texel's;
    group (n,) int in [0, n_groups)."""
    r = y - a
    wb = w[:, None] * b
    prior = a + d0 * b - l0
    terms = (w[:, None] * r * r, wb * r, wb * b, w[:, None] * prior * prior)
    return np.stack([np.stack([np.bincount(group, weights=x[:, c], minlength=n_groups)
                               for c in range(3)], axis=-1) for x in terms], axis=1)


def solve(sums: np.ndarray, d0: np.ndarray, lam: float) -> tuple[np.ndarray, np.ndarray]:
    """Per candidate roughness and texel the optimal d and its E: sums (c, t, 4, 3) of
    `row_sums`, d0 (t, 3) -> (d (c, t, 3), E (c, t)) float64. λ = ∞ gives d0 and E of d0 with
    no prior term (the caller keeps r0)."""
    s0, s1, s2, p2 = (sums[..., j, :] for j in range(4))
    big = np.maximum(s2.max(initial=0.0), 1e-300)
    ok = s2 > _B_FLOOR * big
    if np.isfinite(lam):
        d = np.where(ok, (s1 + lam * d0 * s2) / np.where(ok, (1.0 + lam) * s2, 1.0), d0)
    else:
        d = np.broadcast_to(d0, s1.shape).copy()
    d = np.clip(d, 0.0, 1.0)
    data = s0 - 2.0 * d * s1 + d * d * s2
    if np.isfinite(lam):
        data = data + lam * (p2 + s2 * (d - d0) ** 2)
    return d, data.sum(axis=-1)


def resolvable_roughness(n_pairs: np.ndarray, min_hits: float = MIN_LOBE_HITS) -> np.ndarray:
    """(t,) the narrowest roughness whose lobe n_pairs cosine-distributed (light, view) pairs
    resolve: a GGX lobe of width α holds about the fraction 4α² of such pairs (a cone of
    half-angle 2α about the mirror direction, by projected solid angle), so it holds min_hits
    of them when α = sqrt(min_hits / (4 n)); roughness = sqrt(α). A narrower lobe's least
    squares over the pairs is ruled by whether a pair hits its peak (noise), not by its
    energy."""
    n = np.maximum(np.asarray(n_pairs, dtype=np.float64), 1.0)
    return np.sqrt(np.minimum(np.sqrt(min_hits / (4.0 * n)), 1.0))


def pick(sums: np.ndarray, d0: np.ndarray, r0: np.ndarray, grid: np.ndarray, lam: float,
         n_pairs: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The fit of each texel at λ: sums (c, t, 4, 3) over candidates [r0, *grid]
    (candidate 0 each texel's averaged roughness r0 (t,)) -> (roughness (t,), d (t, 3),
    candidate index (t,) int). With n_pairs (t,) (the texel's rows), a texel whose averaged
    lobe is narrower than its pairs resolve (`resolvable_roughness`) keeps the averaged
    inputs, and no texel takes a grid roughness below that, nor below SHARPEN x r0 (filtering
    widens a lobe, never sharpens it)."""
    t = d0.shape[0]
    if not np.isfinite(lam):
        return r0.copy(), d0.copy(), np.zeros(t, np.int64)
    d, e = solve(sums, d0, lam)
    floor = SHARPEN * r0
    keep = np.zeros(t, bool)
    if n_pairs is not None:
        r_res = resolvable_roughness(n_pairs)
        floor = np.maximum(floor, r_res)
        keep = r0 < r_res
    e = np.where(np.concatenate([keep[None], grid[:, None] < floor[None]]), np.inf, e)
    best = np.argmin(e, axis=0)  # (t,) ties: the first, r0
    best[keep] = 0
    d[0, keep] = d0[keep]
    rough = np.concatenate([r0[None], np.broadcast_to(grid[:, None], (grid.size, t))])
    return rough[best, np.arange(t)], d[best, np.arange(t)], best


def residual(sums: np.ndarray, d: np.ndarray, best: np.ndarray) -> np.ndarray:
    """Σ w (A + d B − y)² of each texel's chosen candidate (t,): sums (c, t, 4, 3)."""
    s = sums[best, np.arange(best.size)]  # (t, 4, 3)
    return (s[:, 0] - 2.0 * d * s[:, 1] + d * d * s[:, 2]).sum(axis=-1)


def choose_lambda(sums_half: np.ndarray, d0: np.ndarray, r0: np.ndarray, grid: np.ndarray,
                  n_pairs: np.ndarray | None = None, lambdas=FIT_LAMBDAS) -> np.ndarray:
    """Held-out error of each λ (len(lambdas),): the fit on one half of the rows judged on the
    other's data term, both ways. sums_half (2, c, t, 4, 3); n_pairs (2, t) or None."""
    out = np.zeros(len(lambdas))
    for i, lam in enumerate(lambdas):  # the few λ
        for h in (0, 1):
            _, d, best = pick(sums_half[h], d0, r0, grid, lam,
                              None if n_pairs is None else n_pairs[h])
            out[i] += float(residual(sums_half[1 - h], d, best).sum())
    return out
