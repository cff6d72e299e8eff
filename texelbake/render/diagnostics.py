"""Diagnostic images of a bake: the mip level each pixel used, colour-coded (seed 000 Fig. 9),
and the characteristic-point density over the atlas and on the model (its Fig. 8)."""

from __future__ import annotations

import math

import numpy as np

from texelbake.render.scene import RenderScene
from texelbake.trace import camera as cam_mod


def level_colours(level: np.ndarray, n_levels: int) -> np.ndarray:
    """Mip level image -> colours (seed 000 Fig. 9): level j gets colour j of a qualitative
    map, fractional levels blend the two neighbours, -1 (M_org fallback) is white, NaN
    (background) black.

    level : (h, w) float; returns (h, w, 3) float64 in [0, 1]
    """
    from matplotlib import colormaps

    lv = np.asarray(level, dtype=np.float64)
    pal = np.asarray(colormaps["tab10"](np.arange(10)))[:, :3]
    out = np.zeros(lv.shape + (3,))
    ok = np.isfinite(lv) & (lv >= 0)
    x = np.clip(np.where(ok, lv, 0.0), 0.0, max(n_levels - 1, 0))
    j0 = np.floor(x).astype(np.int64)
    j1 = np.minimum(j0 + 1, max(n_levels - 1, 0))
    f = (x - j0)[..., None]
    col = (1 - f) * pal[j0 % 10] + f * pal[j1 % 10]
    out[ok] = col[ok]
    out[lv == -1.0] = 1.0
    return out


def density_atlas(scene: RenderScene, level: int = 0) -> np.ndarray:
    """Characteristic points per texel of one level as an (n_l, n_l) int64 image (row 0 is the
    top of the atlas, v = 1)."""
    lv = scene.baked.levels[level]
    counts = np.diff(lv["texel_offsets"])
    n_l = int(round(math.sqrt(counts.shape[0])))
    return counts.reshape(n_l, n_l).astype(np.int64)


def density_colours(counts: np.ndarray, vmax: float | None = None) -> np.ndarray:
    """Counts -> viridis colours, zero counts dark grey. (h, w) -> (h, w, 3) float64."""
    from matplotlib import colormaps

    c = np.asarray(counts, dtype=np.float64)
    vmax = float(c.max()) if vmax is None else float(vmax)
    rgb = colormaps["viridis"](np.clip(c / max(vmax, 1.0), 0.0, 1.0))[..., :3]
    rgb[c <= 0] = 0.15
    return rgb


def density_on_model(scene: RenderScene, cam: cam_mod.PinholeCamera, level: int = 0,
                     seed: int = 0) -> np.ndarray:
    """M1 coloured by the characteristic-point count of the texel under each pixel (nearest
    texel of `level`), shaded by |n·v| so the shape reads (seed 000 Fig. 8).
    returns (h, w, 3) float64 in [0, 1] (background black)"""
    counts = density_atlas(scene, level)
    n_l = counts.shape[0]
    m = scene.baked.meshes[0]
    off = cam_mod.sample_offsets(1, cam.width * cam.height, seed)
    o, d = cam_mod.eye_rays(cam, off)
    hits = scene.lods[0].cast(o, d)
    out = np.zeros((o.shape[0], 3))
    idx = np.flatnonzero(hits.hit)
    if idx.size:
        prim = hits.prim[idx]
        uv = np.einsum("nk,nkj->nj", hits.bary3()[idx], m.corner_uvs[prim])
        x = np.clip(np.floor(uv[:, 0] * n_l), 0, n_l - 1).astype(np.int64)
        y = np.clip(np.floor((1.0 - uv[:, 1]) * n_l), 0, n_l - 1).astype(np.int64)
        col = density_colours(counts, counts.max())[y, x]
        shade = np.abs(np.einsum("ij,ij->i", scene.lod_face_normals[0][prim], d[idx]))
        out[idx] = col * (0.35 + 0.65 * shade[:, None])
    return out.reshape(cam.height, cam.width, 3)
