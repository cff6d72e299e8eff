"""a_vis from visibility: the sample method (one ray per sample and direction, as R) and the
seed's orthographic renderings, on cube maps."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from texelbake.cpm.avis.cube import OccludedFn, check_res, cube_directions
from texelbake.errors import NumericalError, SettingsError, ShapeError
from texelbake.geometry.basis import grid_to_world, tangent_frames
from texelbake.geometry.mesh import face_normals
from texelbake.tol import TOL

# --------------------------------------------------------------------------------------------
# inputs


def coerce_samples(normals, areas, texel_of_sample, n_texels, positions=None):
    nrm = np.asarray(normals, dtype=np.float64)
    if nrm.ndim != 2 or nrm.shape[1] != 3:
        raise ShapeError(f"normals must be (m, 3), got {nrm.shape}")
    m = nrm.shape[0]
    ar = np.asarray(areas, dtype=np.float64)
    if ar.shape != (m,):
        raise ShapeError(f"areas must be ({m},), got {ar.shape}")
    tex = np.asarray(texel_of_sample)
    if tex.shape != (m,) or (m and not np.issubdtype(tex.dtype, np.integer)):
        raise ShapeError(f"texel_of_sample must be ({m},) int, got {tex.shape} {tex.dtype}")
    tex = tex.astype(np.int64)
    n_texels = int(n_texels)
    if n_texels < 0:
        raise SettingsError(f"n_texels must be >= 0, got {n_texels}")
    if m and (tex.min() < 0 or tex.max() >= n_texels):
        raise ShapeError(f"texel_of_sample must be in [0, {n_texels}), got "
                         f"[{tex.min()}, {tex.max()}]")
    for name, arr in (("normals", nrm), ("areas", ar)):
        fin = np.isfinite(arr)
        bad = ~(fin if fin.ndim == 1 else fin.all(axis=1))
        if bad.any():
            raise NumericalError(f"{name} is NaN or Inf at sample {int(np.flatnonzero(bad)[0])}")
    if m and ar.min() < 0:
        raise NumericalError(f"areas must be >= 0, got {ar.min()} at sample {int(ar.argmin())}")
    # Make unit (zero stays zero). Only lengths off 1 by more than round-off are touched, so
    # coercing twice is the identity and equal normals stay bit-identical (closed-form merging).
    length = np.linalg.norm(nrm, axis=1, keepdims=True)
    fix = (np.abs(length - 1.0) > 8 * np.finfo(np.float64).eps) & (length > 0)
    nrm = np.where(fix, nrm / np.where(length > 0, length, 1.0), np.where(length > 0, nrm, 0.0))
    out = [nrm, ar, tex, n_texels]
    if positions is not None:
        pos = np.asarray(positions, dtype=np.float64)
        if pos.shape != (m, 3):
            raise ShapeError(f"positions must be ({m}, 3), got {pos.shape}")
        bad = ~np.isfinite(pos).all(axis=1)
        if bad.any():
            raise NumericalError(f"positions is NaN or Inf at sample {int(np.flatnonzero(bad)[0])}")
        out.insert(0, pos)
    return out


def _bbox_diag(points: np.ndarray) -> float:
    if points.shape[0] == 0:
        return 0.0
    return float(np.linalg.norm(points.max(axis=0) - points.min(axis=0)))


def default_eps(positions: np.ndarray) -> float:
    """The ray-origin offset used here and by unoccluded_texels: TOL.ray_offset * bbox diagonal
    of the sample positions (scalar float)."""
    return TOL.ray_offset * _bbox_diag(np.asarray(positions, dtype=np.float64).reshape(-1, 3))


def geometric_normals(points: np.ndarray, faces: np.ndarray,
                      face_of_sample: np.ndarray) -> np.ndarray:
    """The geometric normal of the M_org triangle of every sample (what a_vis needs; the
    samples' shading normals are for the BRDF).

    points : (v, 3) float64; faces : (f, 3) int; face_of_sample : (m,) int in [0, f)
    returns : (m, 3) float64 unit (zero for degenerate triangles)
    """
    pts = np.asarray(points, dtype=np.float64)
    fcs = np.asarray(faces, dtype=np.int64)
    fid = np.asarray(face_of_sample, dtype=np.int64)
    if pts.ndim != 2 or pts.shape[1] != 3 or fcs.ndim != 2 or fcs.shape[1] != 3:
        raise ShapeError(f"points (v, 3) and faces (f, 3) expected, got {pts.shape}, {fcs.shape}")
    if fid.size and (fid.min() < 0 or fid.max() >= fcs.shape[0]):
        raise ShapeError(f"face_of_sample must be in [0, {fcs.shape[0]})")
    return face_normals(pts, fcs[fid])


def _area_matrix(tex: np.ndarray, areas: np.ndarray, n_texels: int) -> sp.csr_matrix:
    """(n_texels, m) sparse: row t holds dA_j of the samples of texel t."""
    m = tex.shape[0]
    return sp.csr_matrix((areas, (tex, np.arange(m))), shape=(n_texels, m))


# --------------------------------------------------------------------------------------------
# a_vis from visibility


def avis_from_visibility(visible: np.ndarray, normals: np.ndarray, areas: np.ndarray,
                         texel_of_sample: np.ndarray, n_texels: int,
                         dirs: np.ndarray) -> np.ndarray:
    """a_vis of every texel at d directions from per-sample visibility (seed 000, Eq. 3 / Eq. 7).

    Use this with the visibility already computed for R (the view directions of the CPM grid)
    so that the denominator of Eq. 7 uses exactly R's samples and rays.

    visible : (m, d) bool, V(x_j, w)
    normals : (m, 3) float64 geometric normals; areas : (m,) float64 dA_j
    texel_of_sample : (m,) int in [0, n_texels)
    dirs : (d, 3) float64 unit directions shared by all samples, or (m, d, 3) per sample
        (e.g. texel-frame directions rotated to world by each sample's texel frame)
    returns : (n_texels, d) float64
    """
    nrm, ar, tex, n_texels = coerce_samples(normals, areas, texel_of_sample, n_texels)
    vis = np.asarray(visible, dtype=bool)
    w = np.asarray(dirs, dtype=np.float64)
    m = nrm.shape[0]
    if vis.ndim != 2 or vis.shape[0] != m:
        raise ShapeError(f"visible must be ({m}, d), got {vis.shape}")
    d = vis.shape[1]
    if w.shape == (d, 3):
        cos = nrm @ w.T  # (m, d)
    elif w.shape == (m, d, 3):
        cos = np.einsum("jk,jdk->jd", nrm, w)
    else:
        raise ShapeError(f"dirs must be ({d}, 3) or ({m}, {d}, 3), got {w.shape}")
    contrib = np.where(vis & (cos > TOL.grazing_cos), cos, 0.0)  # (m, d)
    return np.asarray(_area_matrix(tex, ar, n_texels) @ contrib)


PairsFn = Callable[[np.ndarray, np.ndarray, np.ndarray, np.ndarray], np.ndarray]


def never_occluded(origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """An occluded_fn under which nothing is occluded: `avis_cube_maps` with it is the
    unoccluded projected area sum_j (n_j . w)^+ dA_j, and casts (and gathers) no ray."""
    return np.zeros(len(origins), dtype=bool)


def pairs_fn(occluded_fn: OccludedFn) -> PairsFn:
    """(origins (a, 3), dirs (b, 3), jj (k,), dd (k,)) -> (k,) bool: occlusion of the rays
    origins[jj] along dirs[dd]. A `RayCaster.occluded` is replaced by the caster's
    `occluded_pairs`, which builds Embree's float32 rays from the pairs directly (the same rays,
    no float64 gathers); any other function gets the gathered rays."""
    owner = getattr(occluded_fn, "__self__", None)
    fast = getattr(owner, "occluded_pairs", None)
    if fast is not None and getattr(occluded_fn, "__name__", "") == "occluded":
        return fast

    def gathered(org: np.ndarray, dirs: np.ndarray, jj: np.ndarray, dd: np.ndarray
                 ) -> np.ndarray:
        occ = np.asarray(occluded_fn(org[jj], dirs[dd]), dtype=bool)
        if occ.shape != jj.shape:
            raise ShapeError(f"occluded_fn returned {occ.shape}, expected {jj.shape}")
        return occ
    return gathered


def avis_cube_maps(positions: np.ndarray, normals: np.ndarray, areas: np.ndarray,
                   texel_of_sample: np.ndarray, n_texels: int, frames: np.ndarray | None,
                   res: int, occluded_fn: OccludedFn, *, skip_texels: np.ndarray | None = None,
                   free_samples: np.ndarray | None = None, ray_eps: float | None = None,
                   max_rays: int = 1 << 21, dtype: type = np.float32) -> np.ndarray:
    """a_vis of every texel at every cube-map direction, by one visibility ray per
    (sample, direction) pair that faces the direction (n_j . w > TOL.grazing_cos).

    positions : (m, 3) float64 sample positions on M_org
    normals : (m, 3) float64 geometric normals (made unit here; zero normals contribute 0)
    areas : (m,) float64 dA_j
    texel_of_sample : (m,) int in [0, n_texels)
    frames : None for a world-direction cube map (what AvisTable uses: additive over texels),
        or (n_texels, 3, 3) texel frames (rows t, b, n) to tabulate in each texel's frame
    res : cube face side
    occluded_fn : (origins (k, 3), dirs (k, 3)) -> (k,) bool, e.g. RayCaster(...).occluded;
        origins are already offset by ray_eps along the normal
    skip_texels : (n_texels,) bool, texels to leave at zero (closed-form texels: no rays cast)
    free_samples : (m,) bool, samples proven unoccluded in every facing direction
        (`closed_form.unoccluded_samples`, same ray_eps): they count (n_j . w)^+ dA_j as the
        ray path would and cast no ray (world directions only, frames None)
    ray_eps : origin offset; default `default_eps(positions)`
    max_rays : bound on the candidate (sample, direction) pairs held in memory at once
    returns : (n_texels, 6, res, res) `dtype` (float32 by default; accumulated in float64)
    """
    pos, nrm, ar, tex, n_texels = coerce_samples(normals, areas, texel_of_sample, n_texels,
                                                  positions)
    res = check_res(res)
    dirs_cube = cube_directions(res).reshape(-1, 3)  # (nd, 3)
    nd = dirs_cube.shape[0]
    out = np.zeros((n_texels, nd), dtype=np.float64)
    if frames is not None:
        frames = np.asarray(frames, dtype=np.float64)
        if frames.shape != (n_texels, 3, 3):
            raise ShapeError(f"frames must be ({n_texels}, 3, 3), got {frames.shape}")
    sel = np.ones(tex.shape[0], dtype=bool)
    if skip_texels is not None:
        skip = np.asarray(skip_texels, dtype=bool)
        if skip.shape != (n_texels,):
            raise ShapeError(f"skip_texels must be ({n_texels},), got {skip.shape}")
        sel = ~skip[tex]
    sel &= (ar > 0) & np.any(nrm != 0, axis=1)
    idx = np.flatnonzero(sel)
    free = np.zeros(tex.shape[0], dtype=bool)
    if free_samples is not None:
        if frames is not None:
            raise SettingsError("free_samples needs world directions (frames None)")
        free = np.asarray(free_samples, dtype=bool)
        if free.shape != tex.shape:
            raise ShapeError(f"free_samples must be ({tex.shape[0]},), got {free.shape}")
    if idx.size == 0 or n_texels == 0:
        return out.reshape(n_texels, 6, res, res).astype(dtype)
    eps = default_eps(pos) if ray_eps is None else float(ray_eps)
    origins = pos + eps * nrm
    occluded_pairs = None if occluded_fn is never_occluded else pairs_fn(occluded_fn)
    max_rays = max(int(max_rays), 1)
    mb = min(idx.size, max_rays)
    db = max(1, min(nd, max_rays // mb))
    for s0 in range(0, idx.size, mb):  # loop over memory-bounded batches, not rays
        js = idx[s0:s0 + mb]
        amat = _area_matrix(tex[js], ar[js], n_texels)  # (n_texels, mb)
        nrm_js, org_js = nrm[js], origins[js]  # gathered once per batch, not per direction block
        cast_js = ~free[js][:, None]
        for d0 in range(0, nd, db):
            dl = dirs_cube[d0:d0 + db]  # (db, 3)
            if frames is None:
                cos = nrm_js @ dl.T  # (mb, db)
                face = cos > TOL.grazing_cos
                if occluded_pairs is not None:
                    # the facing pairs of samples not proven free, as flat (j, d) indices
                    flat = np.flatnonzero(face & cast_js)
                    occ = occluded_pairs(org_js, dl, *np.divmod(flat, dl.shape[0]))
            else:
                dw = grid_to_world(frames[tex[js]], dl)  # (mb, db, 3) world
                cos = np.einsum("jl,jdl->jd", nrm_js, dw)
                face = cos > TOL.grazing_cos
                if occluded_pairs is not None:
                    flat = np.flatnonzero(face)  # also the row of each pair's direction in dw
                    occ = occluded_pairs(org_js, dw.reshape(-1, 3), flat // dl.shape[0], flat)
            # cos where the sample faces w and its ray escapes, else 0: the facing entries
            # kept whole and only the occluded ones scattered (most rays escape)
            contrib = np.where(face, cos, 0.0)
            if occluded_pairs is not None:
                contrib.ravel()[flat[occ]] = 0.0
            out[:, d0:d0 + db] += amat @ contrib
    return out.reshape(n_texels, 6, res, res).astype(dtype)


def avis_ortho_grids(caster, sample_positions: np.ndarray, texel_of_sample: np.ndarray,
                     n_texels: int, res: int, *, grid_res: int = 256, max_rays: int = 1 << 21,
                     seed: int = 0, texel_of_points: Callable | None = None,
                     dtype: type = np.float32) -> np.ndarray:
    """a_vis on a world-direction cube map by orthographic ray grids (the seed's method, §3.4,
    with rays instead of GPU renderings), shared by all texels and all levels.

    For every cube direction w a grid of grid_res^2 parallel rays (direction -w, one jittered
    ray per pixel of side h over the projected bounding sphere) is cast; a first hit on a
    triangle facing w (n . w > 0) credits h^2 to the texel of the nearest sample (the seed marks
    texels with a high-resolution texture; nearest sample is the point-set version of that).
    Back-facing first hits occlude and credit nothing, as (n . w)^+ = 0.

    caster : object with `cast(origins (k, 3), dirs (k, 3))` returning hits with `.t` (k,)
        (inf when missed) and `.normal` (k, 3) geometric normals, and `.points` (v, 3) the mesh
        vertices (texelbake.geometry.raycast.RayCaster)
    sample_positions : (m, 3) float64; texel_of_sample : (m,) int in [0, n_texels)
    res : cube face side; grid_res : rays per side of each orthographic grid
    seed : jitter seed (the same jitter pattern is used for every direction)
    texel_of_points : optional (k, 3) float64 -> (k,) int texel of surface points (e.g. closest
        point on M1 -> atlas texel, -1 for none); default: texel of the nearest sample
    returns : (n_texels, 6, res, res) `dtype`, world-direction cube maps
    """
    pos = np.asarray(sample_positions, dtype=np.float64)
    tex = np.asarray(texel_of_sample, dtype=np.int64)
    if pos.ndim != 2 or pos.shape[1] != 3 or tex.shape != (pos.shape[0],):
        raise ShapeError(f"sample_positions (m, 3) and texel_of_sample (m,) expected, got "
                         f"{pos.shape} and {tex.shape}")
    res = check_res(res)
    grid_res = int(grid_res)
    if grid_res < 1:
        raise SettingsError(f"grid_res must be >= 1, got {grid_res}")
    n_texels = int(n_texels)
    dirs_cube = cube_directions(res).reshape(-1, 3)
    nd = dirs_cube.shape[0]
    out = np.zeros(n_texels * nd, dtype=np.float64)
    if pos.shape[0] == 0 or n_texels == 0:
        return out.reshape(n_texels, 6, res, res).astype(dtype)
    verts = np.asarray(caster.points, dtype=np.float64)
    lo, hi = verts.min(axis=0), verts.max(axis=0)
    centre = 0.5 * (lo + hi)
    radius = 0.5 * float(np.linalg.norm(hi - lo)) * (1.0 + 1e-6)
    h = 2.0 * radius / grid_res
    rng = np.random.default_rng(seed)
    jit = rng.random((grid_res, grid_res, 2))
    gy, gx = np.meshgrid(np.arange(grid_res), np.arange(grid_res), indexing="ij")
    px = (-radius + (gx + jit[..., 0]) * h).ravel()  # (G^2,)
    py = (-radius + (gy + jit[..., 1]) * h).ravel()
    inside = px * px + py * py <= radius * radius  # rays outside the disc cannot hit
    px, py = px[inside], py[inside]
    n_pix = px.shape[0]
    basis = tangent_frames(dirs_cube)  # (nd, 3, 3): rows (U, V, w)
    tree = cKDTree(pos) if texel_of_points is None else None
    db = max(1, min(nd, max(int(max_rays), 1) // n_pix))
    for d0 in range(0, nd, db):  # loop over batches of directions
        fr = basis[d0:d0 + db]  # (b, 3, 3)
        w = fr[:, 2]  # (b, 3)
        o = (centre + 2.0 * radius * w[:, None, :] + px[None, :, None] * fr[:, None, 0]
             + py[None, :, None] * fr[:, None, 1]).reshape(-1, 3)
        ray_d = np.repeat(-w, n_pix, axis=0)
        hits = caster.cast(o, ray_d)
        did = np.repeat(np.arange(d0, d0 + fr.shape[0]), n_pix)
        front = np.isfinite(hits.t) & (np.einsum("ki,ki->k", hits.normal, -ray_d) > 0)
        p = o[front] + hits.t[front, None] * ray_d[front]
        if texel_of_points is not None:
            hit_tex = np.asarray(texel_of_points(p), dtype=np.int64)
        elif tree is not None:
            hit_tex = tex[tree.query(p)[1]]
        ok = (hit_tex >= 0) & (hit_tex < n_texels)
        key = hit_tex[ok] * nd + did[front][ok]
        out += np.bincount(key, minlength=n_texels * nd) * (h * h)
    return out.reshape(n_texels, 6, res, res).astype(dtype)
