"""Eq. 12 of seed 000 for every texel of a level in one frame: the characteristic points' shadow
and view rays, the segment sum over the CSR and one a_vis look-up per texel."""

from __future__ import annotations

import numpy as np

from texelbake import brdf as brdf_mod
from texelbake.render.scene import RenderScene
from texelbake.tol import TOL
from texelbake.trace.shade import direct_radiance


def texel_points(offsets: np.ndarray, texels: object
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The characteristic points of some texels of a level, from its CSR `offsets` (t + 1,):
    (texels (n,) int64, exists (n,) bool: the texel has points, tex (P,) int64: each point's
    index into `texels`, pt (P,) int64: each point's row in the level's point arrays), every
    texel's range concatenated in order."""
    texels = np.asarray(texels, dtype=np.int64)
    counts = offsets[texels + 1] - offsets[texels]
    n_pts = int(counts.sum())
    tex = np.repeat(np.arange(texels.shape[0]), counts)  # (P,) local texel of each point
    first = np.cumsum(counts) - counts
    pt = offsets[texels][tex] + (np.arange(n_pts) - first[tex])
    return texels, counts > 0, tex, pt


def texel_radiance(scene: RenderScene, level: int, cam_pos: np.ndarray,
                   texels: np.ndarray | None = None
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Eq. 12 for the texels of one level (all, or the ids in `texels`), for this frame
    (module docstring). Each texel's value depends only on its own points, so computing a
    subset gives the same values as computing all.

    cam_pos : (3,) float64; texels : (t,) int64 distinct texel ids, None = every texel
    returns : (radiance (t, 3) float64, a_vis (t,) float64 toward the camera (0 where
        invalid: the a_vis -> 0 limit), exists (t,) bool — the texel has characteristic
        points, rays cast)
    """
    lv = scene.baked.levels[level]
    offsets = lv["texel_offsets"]
    if texels is None:
        texels = np.arange(offsets.shape[0] - 1)
    texels, exists, tex, pt = texel_points(offsets, texels)
    n_tex, n_pts = texels.shape[0], pt.shape[0]
    radiance = np.zeros((n_tex, 3))
    avis = np.zeros(n_tex)
    if n_pts == 0:
        return radiance, avis, exists, 0
    cp = scene.points(level)
    pos, ng, ns, w = cp["position"][pt], cp["geom_normal"][pt], cp["normal"][pt], cp["weight"][pt]
    # one view direction per texel: weighted centroid -> camera
    ws = np.abs(w).sum(axis=1)
    ws = np.where(np.bincount(tex, ws, n_tex)[tex] > 0, ws, 1.0)
    wsum = np.bincount(tex, ws, n_tex)
    cen = np.stack([np.bincount(tex, ws * pos[:, c], n_tex) for c in range(3)], axis=1)
    cen = np.divide(cen, wsum[:, None], out=np.zeros_like(cen), where=wsum[:, None] > 0)
    wo_tex = np.asarray(cam_pos[None, :] - cen, dtype=np.float64)
    wo_tex = wo_tex / np.maximum(np.linalg.norm(wo_tex, axis=1, keepdims=True), 1e-300)
    wo = wo_tex[tex]
    g = TOL.grazing_cos
    cos_go = np.einsum("ij,ij->i", ng, wo)
    view = (cos_go > g) & (np.einsum("ij,ij->i", ns, wo) > g)
    rays = 0
    vi = np.flatnonzero(view)
    if vi.size:  # V(x̂k, ωo): a ray from the point toward the camera
        tmax = np.linalg.norm(cam_pos[None, :] - pos[vi], axis=1)
        occ = scene.org.occluded(pos[vi] + scene.ray_eps * ng[vi], wo[vi], tmax=tmax)
        rays += vi.size
        view[vi[occ]] = False
    mat, uv = cp["material"][pt], cp["uv"][pt]
    var = None if cp["var"] is None else cp["var"][pt]

    def brdf(sel: np.ndarray, wi_l: np.ndarray, wo_l: np.ndarray) -> np.ndarray:
        return brdf_mod.evaluate_by_face(scene.materials, mat[sel], wi_l, wo_l, uv[sel],
                                         var=None if var is None else var[sel])

    # Σ_l E_l V_i f_r cos_i (the shading of `direct_radiance`, at the points, toward ωo),
    # for the points that see the camera (the others add nothing)
    lit = np.zeros((n_pts, 3))
    seen = np.flatnonzero(view)
    if seen.size:
        lit[seen], r = direct_radiance(pos[seen], ng[seen], ns[seen], wo[seen], scene.lights,
                                       lambda sel, wi_l, wo_l: brdf(seen[sel], wi_l, wo_l),
                                       scene.org, scene.ray_eps)
        rays += r
    contrib = np.where(view[:, None], lit * w * cos_go[:, None], 0.0)  # (P, 3)
    num = np.stack([np.bincount(tex, contrib[:, c], n_tex) for c in range(3)], axis=1)
    live = np.flatnonzero(exists)
    frames = lv["frames"][texels[live]]
    wo_local = np.einsum("nij,nj->ni", frames, wo_tex[live])
    a, valid = scene.avis_table(level).evaluate(texels[live], wo_local)
    radiance[live] = np.where(valid[:, None], num[live] / np.where(valid, a, 1.0)[:, None], 0.0)
    avis[live] = np.where(valid, a, 0.0)
    return radiance, avis, exists, rays
