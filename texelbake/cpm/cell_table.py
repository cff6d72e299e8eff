"""f̄ averaged over each direction pair's cell, for the BTF's tables (`BakeSettings.btf_table`).

The BTF stage tabulates Eq. 7 of seed 000 on the training grid's d = N_i x N_o pairs and the
renderer reads it at the nearest pair (seed 001 §3.4's look-up table). A table of point values
(`btf_table="point"`, what `fit_level` computes anyway: the row sums of R / a_vis) hands a lobe
narrower than a cell to every direction of the cell: on the bolt's polished facets (GGX, α ≈
0.02, a lobe ~2° wide; the 64-direction cells reach 16° from their centre) the pair nearest each
facet's mirror configuration holds the lobe's peak, and the `btf` image came out 5-7x gt's
light (docs/decisions.md). `btf_table="cell"` stores instead, per pair (j, k),
the mean of f̄ over the cell C_j x C_k of directions nearer to (l_j, v_k) than to any other
pair — what a nearest look-up should return so that its expected value over a cell is right.

What is averaged: the BRDF alone, over the pair itself and k uniform draws (l_a, v_a) of its
cell (`directions.cell_directions`, draw a of light cell j with draw a of view cell k:
independent uniform draws, so each product is uniform on C_j x C_k); a draw below a sample's
shading or geometric horizon is left out of that sample's mean. Visibility, both cosines and
a_vis stay at the pair (Eq. 7's factors that vary across a cell slowly next to a specular
lobe; casting k x more rays would cost more than the fit this follows). A texel whose BRDF is
constant (Lambertian) so keeps the point table exactly: the flat plane's hard case.
"""

from __future__ import annotations

import numpy as np

from texelbake.cpm.brdf_product import brdf_product
from texelbake.cpm.level import FitInputs, PointSet, segment_sum, visibility_cos, world_dirs
from texelbake.geometry import directions
from texelbake.tol import TOL

_TAG_CELL_I, _TAG_CELL_O = 0x55, 0x66
#: bytes of temporaries per (sample, direction pair) entry of one draw (brdf_product's own
#: temporaries and the running sum), as `build_r.BYTES_PER_EVAL_ENTRY` budgets R
BYTES_PER_ENTRY = 8 * 48


def _above(sn: np.ndarray, gn: np.ndarray, w: np.ndarray) -> np.ndarray:
    """(p, D) bool: world directions w (p, D, 3) above both horizons of each sample."""
    return (np.einsum("pk,pdk->pd", sn, w) > TOL.grazing_cos) \
        & (np.einsum("pk,pdk->pd", gn, w) > TOL.grazing_cos)


def direction_cells(settings, dirs: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """(cells_i (k, n_i, 3), cells_o (k, n_o, 3)): `settings.btf_cell_draws` draws in the cell
    of every light and view direction of the training grid."""
    k, seed = settings.btf_cell_draws, settings.seed * 1000
    return (directions.cell_directions(dirs["dirs_i"], k, seed=seed + _TAG_CELL_I),
            directions.cell_directions(dirs["dirs_o"], k, seed=seed + _TAG_CELL_O))


def cell_fbar(src: FitInputs, frames: np.ndarray, cset: PointSet, seg: np.ndarray, n_t: int,
              dirs: dict[str, np.ndarray], cells_i: np.ndarray, cells_o: np.ndarray,
              inv_o: np.ndarray, budget: int) -> np.ndarray:
    """Cell-averaged f̄ of n_t texels from their candidates (module docstring).

    cset : the texels' candidates (weights per channel), grouped by texel: seg (p,) ascending
        position of each candidate's texel in 0..n_t-1
    dirs : `level.direction_sets` (dirs_i (n_i, 3), dirs_o (n_o, 3)); cells_i (k, n_i, 3),
        cells_o (k, n_o, 3) : `directions.cell_directions` of each
    inv_o : (n_t, n_o) 1 / a_vis(v_o), 0 where a_vis is under the texel's floor
    budget : bytes the temporaries may take
    returns : (n_t, n_i * n_o, 3) float32, row i * n_o + o; 0 on rows under the a_vis floor
    """
    n_i, n_o = len(dirs["dirs_i"]), len(dirs["dirs_o"])
    k = cells_i.shape[0]
    P = len(cset.sample)
    out = np.zeros((n_t, 3, n_i * n_o))
    sn_all = src.geo["sample_nrm"]
    gn_all = src.geo["sample_gnrm"]
    step = max(budget // (BYTES_PER_ENTRY * n_i * n_o), 1)
    for s0 in range(0, P, step):  # loop over sample batches (memory bound)
        part = cset.take(np.arange(s0, min(s0 + step, P)))
        wi0 = world_dirs(frames, part.texel, dirs["dirs_i"])
        wo0 = world_dirs(frames, part.texel, dirs["dirs_o"])
        vi = visibility_cos(src, part.sample, wi0)  # (p, n_i) V (n_s . l)+ at the centre
        vo = visibility_cos(src, part.sample, wo0, "geometric")
        live0 = (vi.T[:, None, :] > 0) & (vo.T[None, :, :] > 0)  # (n_i, n_o, p), R's
        sn, gn = sn_all[part.sample], gn_all[part.sample]
        # the pair itself is a draw too: a cell keeps at least the point table's value
        acc = brdf_product(src.geo, src.materials, part.sample, wi0, wo0, live0)
        count = live0.astype(np.float64)
        for a in range(k):  # loop over the k draws of every cell (k is small)
            wi = world_dirs(frames, part.texel, cells_i[a])  # (p, n_i, 3)
            wo = world_dirs(frames, part.texel, cells_o[a])
            live = live0 & _above(sn, gn, wi).T[:, None, :] & _above(sn, gn, wo).T[None, :, :]
            acc += brdf_product(src.geo, src.materials, part.sample, wi, wo, live)
            count += live
        acc /= np.maximum(count, 1.0).transpose(2, 0, 1)[None]
        acc *= vi[None, :, :, None]
        acc *= part.weight.T[:, :, None, None]
        acc *= vo[None, :, None, :]
        # (3, p, n_i, n_o) -> per texel, 1 / a_vis(v_o) applied after the sum
        out += segment_sum(acc.reshape(3, acc.shape[1], -1), seg[s0:s0 + step], n_t, 1
                           ).transpose(1, 0, 2)
    out = out.reshape(n_t, 3, n_i, n_o) * inv_o[:, None, None, :]
    return np.ascontiguousarray(out.reshape(n_t, 3, -1).transpose(0, 2, 1)).astype(np.float32)
