"""f_r(x_j, w_i, w_o) on a product of direction sets for many samples at once (issue 15): the
BRDF evaluation that builds R (seed 000 Eq. 9) for a whole chunk of texels.

`texelbake.cpm.level.brdf_grid` evaluates only the entries whose visibility-cosine product is
nonzero, gathering them with np.nonzero and scattering the result back: for a hemisphere of
directions about the texel normal nearly every entry is live, so the gathers cost more than
they save (profile: 21-23 % of a bake). Here, per material (a loop over the few present):

- Lambert: f = rho / pi wherever both local directions are above the horizon, a function of
  the sample alone: rho per sample from one evaluation at normal incidence (textures sampled
  once per sample), then broadcast over (w_i, w_o): A + B + p work instead of A B p;
- any other model: `brdf.evaluate` on every (w_i, w_o, sample) entry of the material's samples
  (dense, no gather), textures once per sample through sample_index; when fewer than
  DENSE_FRACTION of the entries are live (occluded samples, e.g. a bolt's threads) only the
  live ones, gathered.

Entries that are not live are multiplied by a zero visibility-cosine product afterwards; a
non-finite value at a live entry is an error (NumericalError naming the material), a non-finite
value at a dead entry is set to 0.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from texelbake import brdf as brdf_mod
from texelbake.errors import NumericalError
from texelbake.frames import tangent_frames
from texelbake.tol import TOL

#: below this fraction of live entries a material's samples are evaluated on the live entries
#: only (gathered, as `level.brdf_grid`); above it densely (no gather / scatter)
DENSE_FRACTION = 0.6


def _check_finite(f: np.ndarray, material) -> None:
    if not np.all(np.isfinite(f)):
        raise NumericalError(
            f"material {material.path!r}: BRDF not finite at a visible direction pair"
        )


def brdf_product(
    geo: Mapping[str, np.ndarray],
    materials,
    sample: np.ndarray,
    wi_world: np.ndarray,
    wo_world: np.ndarray,
    live: np.ndarray,
) -> np.ndarray:
    """f_r in each sample's shading frame on a product of direction sets.

    sample : (p,) int64; wi_world : (p, A, 3); wo_world : (p, B, 3); live : (A, B, p) bool
    returns : (3, p, A, B) float64 (channel-major: a sample's rows are contiguous), equal to
        `level.brdf_grid` (A, B, p, 3) on live entries (0 elsewhere up to the caller's
        visibility product)
    """
    p = len(sample)
    A, B = wi_world.shape[1], wo_world.shape[1]
    out = np.zeros((3, p, A, B))
    if p == 0 or A == 0 or B == 0:
        return out
    frames = tangent_frames(geo["sample_nrm"][sample])  # (p, 3, 3)
    wi_loc = np.einsum("pkl,pal->apk", frames, wi_world)  # (A, p, 3)
    wo_loc = np.einsum("pkl,pbl->bpk", frames, wo_world)  # (B, p, 3)
    mat = geo["sample_mat"][sample]
    uv = geo["sample_uv"][sample]
    eps = TOL.grazing_cos
    present = np.flatnonzero(np.bincount(mat))
    for m_i in present:  # a loop over the few materials
        material = materials[int(m_i)]
        sel = np.flatnonzero(mat == m_i)
        n_s = sel.size
        if material.model == "lambert":
            up = np.zeros((n_s, 3))
            up[:, 2] = 1.0
            rho_pi = brdf_mod.evaluate(material, up, up, uv[sel], sample_index=np.arange(n_s))
            mi = wi_loc[:, sel, 2] > eps  # (A, n_s)
            mo = wo_loc[:, sel, 2] > eps  # (B, n_s)
            ok = (mi.T[:, :, None] & mo.T[:, None, :]).astype(np.float64)  # (n_s, A, B)
            for c in range(3):  # loop over colour channels
                out[c, sel] = ok * rho_pi[:, c, None, None]
            continue
        lv = live[:, :, sel].transpose(2, 0, 1)  # (n_s, A, B)
        if float(lv.mean()) < DENSE_FRACTION:  # mostly dead (occluded): gather the live ones
            j, ia, ib = np.nonzero(lv)
            f_live = brdf_mod.evaluate(material, wi_loc[ia, sel[j]], wo_loc[ib, sel[j]],
                                       uv[sel], sample_index=j)
            _check_finite(f_live, material)
            for c in range(3):  # loop over colour channels
                out[c, sel[j], ia, ib] = f_live[:, c]
            continue
        wi = np.broadcast_to(wi_loc[:, sel, :].transpose(1, 0, 2)[:, :, None, :],
                             (n_s, A, B, 3)).reshape(-1, 3)
        wo = np.broadcast_to(wo_loc[:, sel, :].transpose(1, 0, 2)[:, None, :, :],
                             (n_s, A, B, 3)).reshape(-1, 3)
        idx = np.repeat(np.arange(n_s), A * B)
        f = brdf_mod.evaluate(material, wi, wo, uv[sel], sample_index=idx).reshape(n_s, A, B, 3)
        bad = ~np.isfinite(f)
        if bad.any():
            _check_finite(np.where(lv[..., None], f, 0.0), material)
            f[bad] = 0.0
        out[:, sel] = f.transpose(3, 0, 1, 2)
    return out
