"""Numerical tolerances in one place (after trimesh's `tol`). Modules import `TOL` and pass
values on as `eps=` keyword arguments; no literal tolerances scattered through the code."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Tolerances:
    # geometry
    zero_area: float = 1e-14          # relative to bbox_diag**2: faces below are degenerate
    merge: float = 1e-10              # relative to bbox_diag: vertex welding
    ray_offset: float = 1e-5          # relative to bbox_diag: origin offset along the normal
    # linear algebra
    svd_rcond: float = 1e-12          # relative singular value cut-off for pseudo-inverses
    energy_floor: float = 1e-300      # ||R||_F^2 below this is treated as an all-zero matrix
    gram_subspace: float = 1e-6       # Gram-route span(V_k) error bound above this: full SVD
    residual_rounding: float = 32.0   # x (k+1) eps ||R_j||^2: residual column energy is rounding
    const_channel_var: float = 1e-10  # variance / sum x^2 below this: a constant colour channel
    # visible projected area
    avis_floor: float = 1e-9          # relative to texel area: a_vis below is "fully masked"
    exact_fit_db: float = 100.0       # a fit this close to the grid's Eq. 7 is exact (rank 1)
    # one-point texels (texelbake.cpm.classify): normals within 1e-6 rad (1 - cos) change each
    # cosine of Eq. 7 by at most 1e-6 relative, 20 dB under exact_fit_db's 1e-5 amplitude
    exact_normal: float = 5e-13
    exact_brdf: float = 1e-6          # relative residual of f_r(x_j) - s_j f_r(x_ref): 120 dB
    # directions
    grazing_cos: float = 1e-6         # n.w below this counts as below the horizon
    # brdf
    brdf_eps: float = 1e-12
    # btf (seed 001)
    pca_eig_rcond: float = 1e-12      # Gram eigenvalue / largest below this: component dropped
    phong_alpha_min: float = 1e-3     # Phong exponent outside [min, max]: fit diverged
    phong_alpha_max: float = 1e4
    dir_match: float = 1e-6           # directions closer than this (chord) are the same sample
    # skinning: a point's blended rest transform with sigma_min / sigma_max below this is
    # near-singular; its bind-space point M_r^-1 p would carry its rounding and weight-transfer
    # error amplified by more than 1 / 0.05 = 20 (two joints 50/50 at 174 degrees apart)
    skin_blend_cond: float = 0.05
    # skinning: a joint's motion matches an unskinned mesh's within this (matrix entries,
    # translations relative to the asset's size): the bar the skinned points are checked to,
    # 100x the ~1e-7 float32 joint transforms carry
    skin_match: float = 1e-5


TOL = Tolerances()
