"""The continuous level of detail of seed 001 (Eq. 7: λ from distance, weights w_k) and a
BTF reconstructed from its maps at a level."""

from __future__ import annotations

import numpy as np

from texelbake.btf.compress import BTFMaps, mean_on_pairs
from texelbake.btf.laplacian import expand


def lod_weights(lod: np.ndarray, top_level: int) -> np.ndarray:
    """Eq. 7 level weights w_k = clamp(1 - lambda + k, 0, 1), lambda clamped to [0, top].

    lod : (n,) float64 -> (n, top_level + 1) float64
    """
    lam = np.clip(np.asarray(lod, dtype=np.float64), 0.0, float(top_level))
    k = np.arange(top_level + 1, dtype=np.float64)
    return np.clip(1.0 - lam[:, None] + k[None, :], 0.0, 1.0)


def lod_from_distance(distance: np.ndarray, top_level: int) -> np.ndarray:
    """The seed's range-based LOD: lambda = min(lambda_max, max(log2 d, 0)). (n,) -> (n,)."""
    dist = np.asarray(distance, dtype=np.float64)
    with np.errstate(divide="ignore"):
        return np.minimum(float(top_level), np.maximum(np.log2(np.maximum(dist, 0.0)), 0.0))


def reconstruct_channel(maps: BTFMaps, channel: int, lod: float = 0.0) -> np.ndarray:
    """One YCbCr channel of the whole BTF from the maps, Eq. 7 on the sampled pairs.

    channel : 0 (Y), 1 (Cb), 2 (Cr); lod : one lambda for every texel
    returns : (h, w, d) float32
    """
    sl = maps.channel_slices()[channel]
    wk = lod_weights(np.array([lod]), maps.top_level)[0]  # (L,)
    wi, wo = maps.dirs_i.astype(np.float64), maps.dirs_o.astype(np.float64)
    mean = mean_on_pairs(maps.mean_models, maps.mean_params, maps.mean_table, wi, wo)[:, channel]
    top = maps.top_level
    out = maps.weights[top][:, :, sl] @ maps.eigen[top][:, sl].T  # (h_top, w_top, d)
    out += mean.astype(np.float32)
    for k in range(top - 1, -1, -1):
        term = maps.weights[k][:, :, sl] @ maps.eigen[k][:, sl].T  # (h_k, w_k, d)
        if wk[k] != 1.0:
            term *= np.float32(wk[k])
        out = term + expand(out, term.shape[:2])
    return out


def reconstruct_btf(maps: BTFMaps, lod: float = 0.0) -> np.ndarray:
    """The whole BTF in RGB from the maps (Eq. 7 on the sampled pairs, then YCbCr -> RGB).

    returns : (d, h, w, 3) float32
    """
    from texelbake.btf.color import RGB_FROM_YCBCR

    planes = [np.moveaxis(reconstruct_channel(maps, c, lod), -1, 0) for c in range(3)]
    m = RGB_FROM_YCBCR.astype(np.float32)
    return (
        m[:, 0] * planes[0][..., None] + m[:, 1] * planes[1][..., None]
        + m[:, 2] * planes[2][..., None]
    ).astype(np.float32)
