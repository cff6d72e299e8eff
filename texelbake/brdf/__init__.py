"""BRDF models, vectorized over flat arrays of direction pairs.

Every BRDF here evaluates f_r(x, wi, wo), the SV-BRDF of seed 000, Eq. 1, from which the
apparent reflectance f = V(wi) V(wo) f_r (n.wi)(n.wo) (seed 000, Eq. 4) and the matrix
R[(wi, wo), j] = f(x_j, wi, wo) dA_j (seed 000, Eqs. 7 and 9) are built; the BTF stage filters
the same quantity (seed 001, Eq. 1).

Conventions (shared by every function of this module):

- Directions are unit vectors in the *local shading frame* (z = shading normal):
  ``wi : (n, 3) float64`` toward the light, ``wo : (n, 3) float64`` toward the viewer. They are
  not renormalised (the caller owns that; renormalising would cost a pass over the data).
- The result is ``f_r : (n, 3) float64``, RGB, in 1/sr, *without* the cosine factor.
- Below the horizon (``wi.z <= TOL.grazing_cos`` or ``wo.z <= TOL.grazing_cos``) and for
  non-finite directions the BRDF is exactly 0.
- Per-element parameters are "broadcastable to (n,)": scalars are ``()``, ``(1,)`` or
  ``(n,)``; colours are ``(3,)``, ``(1, 3)`` or ``(n, 3)``.

Models (``Material.model`` -> function): ``lambert`` -> :func:`lambert`, ``phong`` ->
:func:`phong`, ``preview`` -> :func:`preview_surface`, ``merl`` -> :func:`merl_lookup` on a table
from :func:`read_merl`, ``cellular`` -> :func:`cellular`. :func:`evaluate` dispatches on a
:class:`texelbake.model.Material`, resolving textured inputs with :func:`sample_texture`.

Speed: the large kernels run over blocks of ``CHUNK`` rows so that their temporaries stay in
cache and memory stays bounded for 1e7+ rows. torch (CPU) was measured against numpy for the
UsdPreviewSurface kernel (numbers in :func:`preview_surface`) and was ~6x slower on this 2-core
machine, so numpy is used.

Written by hand because no maintained Python library evaluates these BRDFs vectorized over
numpy arrays with the UsdPreviewSurface semantics (the reference implementations are GLSL/OSL
shaders); the MERL reader follows the layout of MERL's own ``BRDFRead.cpp``.
"""

from texelbake.brdf.albedo import cosine_hemisphere, directional_albedo
from texelbake.brdf.analytic import ggx_conductor, lambert, phong, preview_surface
from texelbake.brdf.cellular_shader import (
    cellular,
    cellular_cell_id,
    cellular_color,
    cellular_mask,
    worley,
)
from texelbake.brdf.common import (
    CELLULAR_DEFAULTS,
    INV_PI,
    LAMBERT_DEFAULTS,
    MERL_DEFAULTS,
    PHONG_DEFAULTS,
    PREVIEW_MIN_ROUGHNESS,
)
from texelbake.brdf.evaluate import diffuse_albedo, evaluate, evaluate_by_face, shading_normal
from texelbake.brdf.merl import (
    MERL_SCALE,
    MERL_SHAPE,
    merl_bin_directions,
    merl_lookup,
    read_merl,
    tabulate_merl,
    write_merl,
)
from texelbake.brdf.textures import sample_texture

__all__ = [
    "CELLULAR_DEFAULTS",
    "INV_PI",
    "LAMBERT_DEFAULTS",
    "MERL_DEFAULTS",
    "MERL_SCALE",
    "MERL_SHAPE",
    "PHONG_DEFAULTS",
    "PREVIEW_MIN_ROUGHNESS",
    "cellular",
    "cellular_cell_id",
    "cellular_color",
    "cellular_mask",
    "cosine_hemisphere",
    "diffuse_albedo",
    "directional_albedo",
    "evaluate",
    "evaluate_by_face",
    "ggx_conductor",
    "lambert",
    "merl_bin_directions",
    "merl_lookup",
    "phong",
    "preview_surface",
    "read_merl",
    "sample_texture",
    "shading_normal",
    "tabulate_merl",
    "worley",
    "write_merl",
]

