"""Visible projected area a_vis per texel on a cube map of directions (seed 000, §3.4).

Definition (seed 000, Eq. 3 summed over the texel's samples g(p), the denominator of Eq. 7):

    a_vis(p, w) = sum_{j in g(p)} V(x_j, w) (n_j . w)^+ dA_j

n_j is the sample's *geometric* normal (the normal of the M_org triangle it lies on), not an
interpolated shading normal: a flat triangle of area A seen from w has projected area
A (n_f . w)^+ exactly, so with geometric normals a_vis is the projected area of the sampled
surface (what the acceptance test (c) checks), and the closed form below is exact. The
characteristic-point stage must use the same n_j in R's (n_j . w_o)^+ factor so that a flat
Lambertian texel reproduces its BRDF exactly (on a flat texel shading and geometric normals agree).

Decisions (the numbers are in benchmarks/avis_methods.py and the report to the lead):

* Direction map: a cube map with res x res texels per face over *world* directions, all six faces
  stored, per texel. World (not texel-frame) directions because a_vis is additive over children
  only in a shared frame: a parent's map is exactly the sum of its 2 x 2 children's maps
  (`coarsen_maps`, `coarsen_level`), whereas the parent's texel frame differs from its
  children's. The texel-frame rotation happens at look-up (`AvisTable.evaluate` takes
  directions in the texel frame (t, b, n) and rotates them with the texel's frame). Directions
  below a texel's horizon are *not* zero in general (a curved or bumpy texel has facets that
  face below its mean plane), so the six faces are kept as the seed does. `avis_cube_maps`
  can also tabulate in the texel frame (`frames=`) for comparison; AvisTable uses world maps.
* Computation: from the samples, with one visibility ray per (sample, direction) with
  n_j . w > 0 (`avis_cube_maps`), i.e. the same samples and the same visibility as R, rather
  than the seed's orthographic renderings (`avis_ortho_grids`: G^2 parallel rays per world
  direction, shared by all texels and levels, each front-facing hit credited to a texel).
  Measured (benchmarks/avis_methods.py, 64 texels, per-texel relative L2 error over
  directions against a reference, one run, 2 shared cores):
      height field  samples  1/tri: 0.22 M rays, 0.13 s, 0.41 %   ortho G=128:  1.2 M, 1.0 s, 3.05 %
                    samples  4/tri: 0.88 M rays, 0.40 s, 0.15 %   ortho G=512: 19.8 M, 7.2 s, 0.38 %
      bumpy sphere  samples 16/tri: 1.70 M rays, 1.0 s,  0.20 %   ortho G=512: 19.8 M, 24 s,  0.27 %
  i.e. 20-90x fewer rays at equal per-texel error. Both get the *total* over texels right
  (< 0.06 %); the ortho grid's per-texel error is pixel quantization at texel borders, so its
  cost grows with the number of texels per level (pixels per texel must stay constant), while
  the sample method's cost is ~m/2 rays per direction with m the samples R needs anyway. Its
  sharing across levels buys nothing here because a_vis is additive: coarser levels are sums
  of the finest one (`coarsen_level`), no rays at all.
* Closed form: `unoccluded_texels` detects, exactly, the texels whose samples are unoccluded in
  every direction of their hemisphere; their a_vis(w) = sum_k A_k (n_k . w)^+ over the distinct
  geometric normals n_k of the texel (areas A_k merged), evaluated at any w without rays and
  without a cube map (`ClosedForm`). When n_k . w >= 0 for all k this is the single 3-vector
  (sum_k A_k n_k) . w; the general form is kept because it is exact at every w. The same
  test per sample (`unoccluded_samples`) spares the rays of the free samples of the other
  texels: their terms are counted as the rays would count them.
* Compression: per cube face, full-depth Haar (texelbake.haar), largest coefficients kept;
  a single direction is reconstructed from O(log res) coefficients (eval_haar_point). For ray
  texels with a stored unoccluded bound U (see below) the Haar maps hold the visible fraction
  F = a_vis / U in [0, 1]; a look-up forms U F at the bilinear taps (U exact at each tap) and
  interpolates: a lossless table interpolates a_vis itself, compression only touches the
  smoother masking fraction, and the look-up is linear in the tap values, so sums over texels
  survive it (the height-field identity: 0.16 % at res 32 on V-grooves and a bumpy field).
  Measured on height-field maps, relative L2 error at the seed's ~5.5 % of coefficients kept:
  res 64: 0.38 % via F vs 1.49 % compressing a_vis directly (3.3 % kept: 0.65 % vs 2.0 %);
  res 32: 0.86 % vs 3.0 %; end to end (AvisTable.evaluate, bilinear, res 16, random
  directions against rays cast at those directions, per texel): 1.8 % vs 5.6 % (lossless:
  0.65 % both), at about half the look-up rate of direct storage (more closed-form work).
* The a_vis -> 0 limit (grazing or fully masked directions): the filtered reflectance of Eq. 7 is
  (sum_j f_j dA_j) / a_vis, a 0/0 there. `AvisTable.evaluate` returns (a, valid) with
  valid = a > TOL.avis_floor * texel_area; where not valid a = 0 and the renderer must use zero
  radiance for the texel (its visible projected area, hence its contribution to the pixel, is
  zero), never divide. A cube map only resolves the horizon to one cube texel: ray-based texels
  keep (when they have at most `max_terms` distinct normals) their unoccluded projected area
  U = sum_k A_k (n_k . w)^+, exact at every tap, so a_vis is 0 from one cube pixel below a flat
  texel's horizon on; within that pixel the bilinear look-up overshoots the true 0 by what it
  undershoots the walls uncovered there (no clamp to U(w) at w: it kept the overshoot's
  texel exact but biased every sum over texels, 1.4 % at res 32 on V-grooves). Haar truncation
  can produce slightly negative values; a_vis >= 0 by definition, so reconstructions are
  clamped at 0.

Cube map convention (OpenGL's): faces +X, -X, +Y, -Y, +Z, -Z; texel (iv, iu) of face f has the
direction normalize(major_f + sc U_f + tc V_f) with sc = 2 (iu + 1/2) / res - 1,
tc = 2 (iv + 1/2) / res - 1; maps are indexed [face, iv, iu].
"""

from __future__ import annotations

from texelbake.cpm.avis.closed_form import (
    ClosedForm,
    closed_form_maps,
    closed_form_terms,
    eval_closed_form,
    unoccluded_samples,
    unoccluded_texels,
)
from texelbake.cpm.avis.compress import compress_level
from texelbake.cpm.avis.cube import cube_directions, cube_solid_angles, dirs_to_cube
from texelbake.cpm.avis.levels import (
    AvisLevel,
    avis_level,
    coarsen_level,
    coarsen_maps,
    level_from_arrays,
    level_to_arrays,
    stack_tiles,
    tile_layout,
)
from texelbake.cpm.avis.maps import (
    avis_cube_maps,
    avis_from_visibility,
    avis_ortho_grids,
    default_eps,
    geometric_normals,
)
from texelbake.cpm.avis.table import AvisTable, visible_fraction

__all__ = [
    "AvisLevel", "AvisTable", "ClosedForm", "avis_cube_maps", "avis_from_visibility", "avis_level",
    "avis_ortho_grids", "closed_form_maps", "closed_form_terms", "coarsen_level", "coarsen_maps",
    "compress_level", "cube_directions", "cube_solid_angles", "default_eps", "dirs_to_cube",
    "eval_closed_form", "geometric_normals", "level_from_arrays", "level_to_arrays",
    "stack_tiles", "tile_layout", "unoccluded_samples",
    "unoccluded_texels", "visible_fraction",
]

