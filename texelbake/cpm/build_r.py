"""Eq. 9's matrix R of a chunk's candidates (seed 000 §3.3), channel-major, the BRDF
evaluated on sample batches bounded by the worker's memory; with 1 / a_vis given, F =
diag(1/a_vis) R written in the same pass with each candidate's channel sums
(`texelbake.cpm.level_batched`)."""

from __future__ import annotations

import numpy as np

from texelbake.cpm.brdf_product import brdf_product
from texelbake.cpm.dense import LevelPass
from texelbake.cpm.level import PointSet, texel_dirs, visibility_cos

#: bytes of temporaries per (sample, direction pair) while the BRDF is evaluated (local
#: directions, the model's intermediates, f): a sample batch uses a quarter of the budget
BYTES_PER_EVAL_ENTRY = 8 * 40


def build_R(lp: LevelPass, cset: PointSet, inv_o: np.ndarray | None = None,
             seg: np.ndarray | None = None):
    """Eq. 9's matrix for every candidate of the chunk, channel-major: (3, P, d) with row
    i * n_o + o. The BRDF is evaluated on sample batches whose temporaries fit a quarter of
    the budget (a sample's entries are independent), so only R itself scales with P.

    With inv_o (t, n_o) (1/a_vis(w_o) of each texel of the chunk, 0 on rows under the floor) and
    seg (P,) (each candidate's texel in the chunk), returns F = diag(1/a_vis) R itself, written
    in the same pass as R (no second P x d array, no second sweep), together with each
    candidate's channel sums of R for `channel_correlation`: (F, s1 (P, 3) = sum over rows of R,
    s2 (P, 3, 3) = R_j^T R_j over rows). Every entry and every per-candidate sum depends only on
    that candidate, so neither the chunk nor the sample batch changes a texel's result."""
    src, frames, dirs = lp.src, lp.frames, lp.dirs
    n_i, n_o = len(dirs["dirs_i"]), len(dirs["dirs_o"])
    P = len(cset.sample)
    step = max(lp.budget // 4 // (BYTES_PER_EVAL_ENTRY * n_i * n_o), 1)
    # one batch: R is its f itself (no copy); several: each batch's f copied into R
    Rt = None if step >= P else np.empty((3, P, n_i * n_o))
    fused = inv_o is not None
    s1 = np.zeros((P, 3))
    s2 = np.zeros((P, 3, 3))
    for s0 in range(0, P, step):  # loop over sample batches (memory bound)
        part = cset.take(np.arange(s0, min(s0 + step, P)))
        p = len(part.sample)
        wi_d = texel_dirs(frames, part.texel, dirs["dirs_i"])  # once per texel
        wo_d = texel_dirs(frames, part.texel, dirs["dirs_o"])
        vi = visibility_cos(src, part.sample, wi_d)
        vo = visibility_cos(src, part.sample, wo_d, "geometric")
        wi, wo = wi_d.per_sample, wo_d.per_sample  # (p, n_i, 3), (p, n_o, 3) for the BRDF
        live = (vi.T[:, None, :] > 0) & (vo.T[None, :, :] > 0)  # (n_i, n_o, p)
        f = brdf_product(src.geo, src.materials, part.sample, wi, wo, live,
                         var=part.var)  # (3, p, n_i, n_o)
        f *= (vi[None, :, :] * part.weight.T[:, :, None])[..., None]
        f *= vo[None, :, None, :]
        f2 = f.reshape(3, p, -1)
        if inv_o is not None and seg is not None:
            s1[s0:s0 + p] = f2.sum(axis=2).T
            s2[s0:s0 + p] = np.matmul(f2.transpose(1, 0, 2), f2.transpose(1, 2, 0))
            f *= inv_o[seg[s0:s0 + p]][None, :, None, :]
        if Rt is None:
            Rt = f2
        else:
            Rt[:, s0:s0 + p] = f2
    if Rt is None:  # no candidate
        Rt = np.empty((3, 0, n_i * n_o))
    if fused:
        return Rt, s1, s2
    return Rt


__all__ = ["BYTES_PER_EVAL_ENTRY", "build_R"]
