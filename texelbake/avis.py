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
  (sum_k A_k n_k) . w; the general form is kept because it is exact at every w.
* Compression: per cube face, full-depth Haar (texelbake.haar), largest coefficients kept;
  a single direction is reconstructed from O(log res) coefficients (eval_haar_point). For ray
  texels with a stored unoccluded bound U (see below) the Haar maps hold the visible fraction
  F = a_vis / U in [0, 1]; a look-up forms U F at the bilinear taps (U exact at each tap),
  interpolates, and clamps by U exact at w: the horizon is exact, a lossless table still
  interpolates a_vis itself, and compression only touches the smoother masking fraction.
  Measured on height-field maps, relative L2 error at the seed's ~5.5 % of coefficients kept:
  res 64: 0.38 % via F vs 1.49 % compressing a_vis directly (3.3 % kept: 0.65 % vs 2.0 %);
  res 32: 0.86 % vs 3.0 %; end to end (AvisTable.evaluate, bilinear, res 16, random
  directions against rays cast at those directions, per texel): 1.8 % vs 5.6 % (lossless:
  0.65 % both), at about half the look-up rate of direct storage (more closed-form work).
* The a_vis -> 0 limit (grazing or fully masked directions): the filtered reflectance of Eq. 7 is
  (sum_j f_j dA_j) / a_vis, a 0/0 there. `AvisTable.evaluate` returns (a, valid) with
  valid = a > TOL.avis_floor * texel_area; where not valid a = 0 and the renderer must use zero
  radiance for the texel (its visible projected area, hence its contribution to the pixel, is
  zero), never divide. A cube map only resolves the horizon to one cube texel, so ray-based
  texels also keep (when they have at most `max_terms` distinct normals) their unoccluded
  projected area sum_k A_k (n_k . w)^+, a hard upper bound applied at look-up: a flat texel's
  a_vis then goes to 0 at grazing exactly like its closed form. Haar truncation can produce
  slightly negative values; a_vis >= 0 by definition, so reconstructions are clamped at 0.

Cube map convention (OpenGL's): faces +X, -X, +Y, -Y, +Z, -Z; texel (iv, iu) of face f has the
direction normalize(major_f + sc U_f + tc V_f) with sc = 2 (iu + 1/2) / res - 1,
tc = 2 (iv + 1/2) / res - 1; maps are indexed [face, iv, iu].
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.spatial import ConvexHull, QhullError, cKDTree

from texelbake.errors import NumericalError, SettingsError, ShapeError
from texelbake.frames import tangent_frames, to_world
from texelbake.haar import HaarCoeffs, compress_haar, eval_haar_point
from texelbake.tol import TOL

# rows: major axis, U (sc), V (tc) per face, OpenGL cube-map convention
_FACE_BASIS = np.array(
    [
        [[1, 0, 0], [0, 0, -1], [0, -1, 0]],   # +X
        [[-1, 0, 0], [0, 0, 1], [0, -1, 0]],   # -X
        [[0, 1, 0], [1, 0, 0], [0, 0, 1]],     # +Y
        [[0, -1, 0], [1, 0, 0], [0, 0, -1]],   # -Y
        [[0, 0, 1], [1, 0, 0], [0, -1, 0]],    # +Z
        [[0, 0, -1], [-1, 0, 0], [0, -1, 0]],  # -Z
    ],
    dtype=np.float64,
)

OccludedFn = Callable[[np.ndarray, np.ndarray], np.ndarray]


# --------------------------------------------------------------------------------------------
# cube map directions


def _check_res(res: int) -> int:
    res_i = int(res)
    if res_i != res or res_i < 1:
        raise SettingsError(f"res (cube face side) must be a positive integer, got {res!r}")
    return res_i


def cube_directions(res: int) -> np.ndarray:
    """Unit directions through the centres of the cube-map texels.

    res : texels per face side
    returns : (6, res, res, 3) float64, indexed [face, iv, iu]
    """
    res = _check_res(res)
    c = (2.0 * (np.arange(res) + 0.5) / res) - 1.0  # (res,)
    tc, sc = np.meshgrid(c, c, indexing="ij")  # (res, res): rows iv, cols iu
    d = (_FACE_BASIS[:, None, None, 0, :] + sc[None, :, :, None] * _FACE_BASIS[:, None, None, 1, :]
         + tc[None, :, :, None] * _FACE_BASIS[:, None, None, 2, :])  # (6, res, res, 3)
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def cube_solid_angles(res: int) -> np.ndarray:
    """Exact solid angle of every cube-map texel (they sum to 4 pi).

    The solid angle of [0, x] x [0, y] on the face plane at distance 1 is
    atan2(x y, sqrt(x^2 + y^2 + 1)); a texel is the signed combination of its four corners.
    returns : (6, res, res) float64
    """
    res = _check_res(res)
    e = np.linspace(-1.0, 1.0, res + 1)
    y, x = np.meshgrid(e, e, indexing="ij")
    area = np.arctan2(x * y, np.sqrt(x * x + y * y + 1.0))  # (res+1, res+1)
    omega = area[1:, 1:] - area[1:, :-1] - area[:-1, 1:] + area[:-1, :-1]
    return np.broadcast_to(np.abs(omega), (6, res, res)).copy()


def dirs_to_cube(dirs: np.ndarray, res: int) -> tuple[np.ndarray, ...]:
    """Cube-map texel of each direction.

    dirs : (n, 3) float, need not be unit; a zero or non-finite direction maps to the centre of
        face 0 (callers flag such directions invalid themselves)
    res : texels per face side
    returns : (face (n,) int64, iu (n,) int64, iv (n,) int64, fu (n,) float64, fv (n,) float64):
        the nearest texel, and continuous coordinates in texel units with texel centres at
        integers (fu = iu exactly at a centre), for bilinear look-ups
    """
    res = _check_res(res)
    d = np.asarray(dirs, dtype=np.float64)
    if d.ndim != 2 or d.shape[1] != 3:
        raise ShapeError(f"dirs must be (n, 3), got {d.shape}")
    d = np.where(np.isfinite(d).all(axis=1, keepdims=True), d, 0.0)
    a = np.abs(d)
    axis = np.argmax(a, axis=1)  # ties -> lowest axis, deterministic
    rows = np.arange(d.shape[0])
    major = a[rows, axis]
    neg = d[rows, axis] < 0
    face = (2 * axis + neg).astype(np.int64)
    basis = _FACE_BASIS[face]  # (n, 3, 3)
    ok = major > 0
    sc = np.divide(np.einsum("ni,ni->n", d, basis[:, 1]), major, out=np.zeros_like(major),
                   where=ok)
    tc = np.divide(np.einsum("ni,ni->n", d, basis[:, 2]), major, out=np.zeros_like(major),
                   where=ok)
    fu = (sc + 1.0) * 0.5 * res - 0.5
    fv = (tc + 1.0) * 0.5 * res - 0.5
    iu = np.clip(np.floor(fu + 0.5), 0, res - 1).astype(np.int64)
    iv = np.clip(np.floor(fv + 0.5), 0, res - 1).astype(np.int64)
    return face, iu, iv, fu, fv


# --------------------------------------------------------------------------------------------
# inputs


def _coerce_samples(normals, areas, texel_of_sample, n_texels, positions=None):
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
    tri = pts[fcs[fid]]  # (m, 3, 3)
    cr = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    length = np.linalg.norm(cr, axis=1, keepdims=True)
    return np.divide(cr, length, out=np.zeros_like(cr), where=length > 0)


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
    nrm, ar, tex, n_texels = _coerce_samples(normals, areas, texel_of_sample, n_texels)
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


def avis_cube_maps(positions: np.ndarray, normals: np.ndarray, areas: np.ndarray,
                   texel_of_sample: np.ndarray, n_texels: int, frames: np.ndarray | None,
                   res: int, occluded_fn: OccludedFn, *, skip_texels: np.ndarray | None = None,
                   ray_eps: float | None = None, max_rays: int = 1 << 21,
                   dtype: type = np.float32) -> np.ndarray:
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
    ray_eps : origin offset; default `default_eps(positions)`
    max_rays : bound on the candidate (sample, direction) pairs held in memory at once
    returns : (n_texels, 6, res, res) `dtype` (float32 by default; accumulated in float64)
    """
    pos, nrm, ar, tex, n_texels = _coerce_samples(normals, areas, texel_of_sample, n_texels,
                                                  positions)
    res = _check_res(res)
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
    if idx.size == 0 or n_texels == 0:
        return out.reshape(n_texels, 6, res, res).astype(dtype)
    eps = default_eps(pos) if ray_eps is None else float(ray_eps)
    origins = pos + eps * nrm
    max_rays = max(int(max_rays), 1)
    mb = min(idx.size, max_rays)
    db = max(1, min(nd, max_rays // mb))
    for s0 in range(0, idx.size, mb):  # loop over memory-bounded batches, not rays
        js = idx[s0:s0 + mb]
        amat = _area_matrix(tex[js], ar[js], n_texels)  # (n_texels, mb)
        for d0 in range(0, nd, db):
            dl = dirs_cube[d0:d0 + db]  # (db, 3)
            if frames is None:
                cos = nrm[js] @ dl.T  # (mb, db)
                face = cos > TOL.grazing_cos
                jj, dd = np.nonzero(face)
                ray_dirs = dl[dd]
            else:
                dw = np.einsum("dk,jkl->jdl", dl, frames[tex[js]])  # (mb, db, 3) world
                cos = np.einsum("jl,jdl->jd", nrm[js], dw)
                face = cos > TOL.grazing_cos
                jj, dd = np.nonzero(face)
                ray_dirs = dw[jj, dd]
            occ = np.asarray(occluded_fn(origins[js[jj]], ray_dirs), dtype=bool)
            if occ.shape != jj.shape:
                raise ShapeError(f"occluded_fn returned {occ.shape}, expected {jj.shape}")
            contrib = np.zeros(cos.shape, dtype=np.float64)
            contrib[jj, dd] = np.where(occ, 0.0, cos[jj, dd])
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
    res = _check_res(res)
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


# --------------------------------------------------------------------------------------------
# closed form


def unoccluded_texels(positions: np.ndarray, normals: np.ndarray, texel_of_sample: np.ndarray,
                      n_texels: int, mesh_points: np.ndarray, *, eps: float | None = None,
                      chunk: int = 1 << 22) -> np.ndarray:
    """Texels whose every sample is unoccluded in every direction of its hemisphere.

    What is detected, exactly: sample j passes iff every vertex y of M_org satisfies
    n_j . (y - x_j) <= eps (the mesh lies below the sample's tangent plane, lifted by eps); a
    texel passes iff all its samples pass (a texel without samples passes: a_vis = 0).

    Why this is exact (and complete): the mesh is a union of triangles, each the convex hull of
    its vertices, so the mesh lies in the half-space {y : n_j . (y - x_j) <= eps}. A ray from the
    offset origin o = x_j + eps n_j along any w with n_j . w > 0 has
    n_j . (o + t w - x_j) = eps + t n_j . w > eps for t > 0, so it hits nothing: V(x_j, w) = 1 for
    every w where (n_j . w)^+ > 0, and a_vis(w) = sum_j (n_j . w)^+ dA_j holds for *all* w
    (the rays avis_cube_maps would cast with the same eps all come back unoccluded).
    Conversely, a vertex y above the lifted plane is reached from o by the direction
    (y - o) / |y - o|, which faces n_j: that ray is occluded (by y or something nearer), so a
    failing sample really is occluded in some direction. The max of the linear function
    n_j . y over the mesh is attained on its convex hull, so only hull vertices are tested
    (scipy ConvexHull / Qhull; all vertices when Qhull cannot build a hull, e.g. a flat mesh).

    positions, normals : (m, 3) float64 samples and geometric normals
    texel_of_sample : (m,) int; mesh_points : (v, 3) float64 vertices of M_org
    eps : default `default_eps(positions)` (the same offset avis_cube_maps uses)
    chunk : bound on the (distinct normals x hull vertices) products held at once
    returns : (n_texels,) bool
    """
    pos, nrm, _, tex, n_texels = _coerce_samples(normals, np.zeros(len(np.asarray(normals))),
                                                 texel_of_sample, n_texels, positions)
    pts = np.asarray(mesh_points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ShapeError(f"mesh_points must be (v, 3), got {pts.shape}")
    if not np.isfinite(pts).all():
        raise NumericalError("mesh_points contains NaN or Inf")
    eps = default_eps(pos) if eps is None else float(eps)
    m = pos.shape[0]
    if m == 0 or pts.shape[0] == 0:
        return np.ones(n_texels, dtype=bool)
    try:
        hull = ConvexHull(pts)
        cand, facets = pts[hull.vertices], hull.equations  # facets: e . y + off <= 0
    except (QhullError, ValueError):
        cand, facets = np.unique(pts, axis=0), np.zeros((0, 4))
    # The support function h(n) = max_y n . y depends on the normal only, so it is bounded
    # once per distinct normal (samples of one triangle share theirs), then refined only where
    # the bounds cannot decide. All three steps are exact inequalities:
    #   lower: h(n) >= max over a subset of the hull vertices (a vertex above -> sample fails);
    #   upper: with centre c, R = max |y - c| and the hull facet (e, off) nearest to n,
    #          h(n) <= n.c + (-off - e.c) + |n - e| R  (a sample on a hull facet passes);
    #   exact: max over all hull vertices, for the undecided normals only.
    uniq, inv = np.unique(nrm + 0.0, axis=0, return_inverse=True)
    inv = inv.ravel()
    thresh = np.einsum("ji,ji->j", nrm, pos) + eps  # sample passes iff h(n_j) <= thresh_j
    sub = cand[np.linspace(0, cand.shape[0] - 1, min(cand.shape[0], 256)).astype(np.int64)]
    lower = (uniq @ sub.T).max(axis=1)  # (U,)
    centre = cand.mean(axis=0)
    radius = float(np.linalg.norm(cand - centre, axis=1).max())
    upper = uniq @ centre + radius
    if facets.shape[0]:
        _, near = cKDTree(facets[:, :3]).query(uniq)
        e, off = facets[near, :3], facets[near, 3]
        via_facet = (uniq @ centre - off - np.einsum("ui,i->u", e, centre)
                     + np.linalg.norm(uniq - e, axis=1) * radius)
        upper = np.minimum(upper, via_facet)
    ok = thresh >= upper[inv]
    undecided = ~ok & (thresh >= lower[inv])
    need = np.unique(inv[undecided])
    if need.size:
        step = max(1, int(chunk) // max(cand.shape[0], 1))
        exact = np.empty(need.shape[0], dtype=np.float64)
        for s0 in range(0, need.shape[0], step):  # loop over memory-bounded chunks
            exact[s0:s0 + step] = (uniq[need[s0:s0 + step]] @ cand.T).max(axis=1)
        support = np.full(uniq.shape[0], np.inf)
        support[need] = exact
        ok |= undecided & (thresh >= support[inv])
    bad = np.bincount(tex[~ok], minlength=n_texels)
    return bad == 0


@dataclass(frozen=True)
class ClosedForm:
    """a_vis(t, w) = sum_{k in texel t} areas_k (normals_k . w)^+ for closed-form texels
    ((n . w)^+ counts as 0 at or below TOL.grazing_cos, exactly as the ray path does).

    offsets : (n_texels + 1,) int64 CSR over texels (texels not in closed form own no terms)
    normals : (k,) x 3 float64 unit geometric normals, distinct within a texel
    areas : (k,) float64 summed dA_j of the samples with that normal
    """

    offsets: np.ndarray
    normals: np.ndarray
    areas: np.ndarray

    @property
    def n_texels(self) -> int:
        return int(self.offsets.shape[0] - 1)

    def padded(self, max_elems: int = 1 << 23) -> tuple[np.ndarray, np.ndarray] | None:
        """(normals (n_texels, k_max, 3), areas (n_texels, k_max)) zero-padded per texel, or
        None when n_texels * k_max exceeds max_elems (then evaluation uses the CSR pairs).
        Cached: built once per ClosedForm."""
        cache = self.__dict__.get("_padded")
        if cache is not None and cache[0] == max_elems:
            return cache[1]
        counts = np.diff(self.offsets)
        k_max = int(counts.max()) if counts.size else 0
        result: tuple[np.ndarray, np.ndarray] | None = None
        if self.n_texels * max(k_max, 1) <= max_elems:
            nrm = np.zeros((self.n_texels, k_max, 3))
            area = np.zeros((self.n_texels, k_max))
            owner = np.repeat(np.arange(self.n_texels), counts)
            slot = np.arange(owner.shape[0]) - np.repeat(self.offsets[:-1], counts)
            nrm[owner, slot] = self.normals
            area[owner, slot] = self.areas
            result = (nrm, area)
        self.__dict__["_padded"] = (max_elems, result)  # frozen dataclass: bypass setattr
        return result

    def sum_vectors(self) -> np.ndarray:
        """(n_texels, 3) float64 sum_k areas_k normals_k: a_vis(w) = S . w exactly wherever
        every normals_k . w >= 0 (e.g. a flat texel: one term)."""
        owner = np.repeat(np.arange(self.n_texels), np.diff(self.offsets))
        out = np.zeros((self.n_texels, 3), dtype=np.float64)
        np.add.at(out, owner, self.normals * self.areas[:, None])
        return out


def _merge_terms(owner: np.ndarray, normals: np.ndarray, areas: np.ndarray,
                 n_texels: int) -> ClosedForm:
    """Merge terms with equal (owner, normal), (n.w)^+ a1 + (n.w)^+ a2 = (n.w)^+ (a1 + a2)."""
    keep = (areas > 0) & np.any(normals != 0, axis=1)
    owner, normals, areas = owner[keep], normals[keep], areas[keep]
    if owner.size == 0:
        return ClosedForm(np.zeros(n_texels + 1, np.int64), np.zeros((0, 3)), np.zeros(0))
    rows = np.column_stack([owner.astype(np.float64), normals + 0.0])  # +0.0: -0.0 -> 0.0
    uniq, inv = np.unique(rows, axis=0, return_inverse=True)
    inv = inv.ravel()
    merged_area = np.bincount(inv, weights=areas, minlength=uniq.shape[0])
    u_owner = uniq[:, 0].astype(np.int64)
    offsets = np.searchsorted(u_owner, np.arange(n_texels + 1)).astype(np.int64)
    return ClosedForm(offsets, uniq[:, 1:].copy(), merged_area)


def closed_form_terms(normals: np.ndarray, areas: np.ndarray, texel_of_sample: np.ndarray,
                      n_texels: int, texel_mask: np.ndarray | None = None) -> ClosedForm:
    """The closed-form terms of the texels in texel_mask (all when None).

    normals : (m, 3) float64 geometric normals; areas : (m,) float64
    texel_of_sample : (m,) int; texel_mask : (n_texels,) bool
    returns : ClosedForm (samples with bit-identical normals in a texel merged into one term)
    """
    nrm, ar, tex, n_texels = _coerce_samples(normals, areas, texel_of_sample, n_texels)
    sel = np.ones(tex.shape[0], dtype=bool)
    if texel_mask is not None:
        mask = np.asarray(texel_mask, dtype=bool)
        if mask.shape != (n_texels,):
            raise ShapeError(f"texel_mask must be ({n_texels},), got {mask.shape}")
        sel = mask[tex]
    return _merge_terms(tex[sel], nrm[sel], ar[sel], n_texels)


def eval_closed_form(cf: ClosedForm, texels: np.ndarray, dirs_world: np.ndarray, *,
                     dense_limit: int = 1 << 23) -> np.ndarray:
    """Exact a_vis of closed-form texels at arbitrary directions (no rays, no cube map).

    texels : (n,) int; dirs_world : (n, 3) float64 unit
    dense_limit : use the zero-padded (n_texels, k_max) layout when n_texels * k_max is at
        most this (about 4x faster), else the CSR pairs; both give the same sums
    returns : (n,) float64 (0 for texels without terms)
    """
    t = np.asarray(texels, dtype=np.int64).ravel()
    w = np.asarray(dirs_world, dtype=np.float64)
    if w.shape != (t.shape[0], 3):
        raise ShapeError(f"dirs_world must be ({t.shape[0]}, 3), got {w.shape}")
    if t.size and (t.min() < 0 or t.max() >= cf.n_texels):
        raise ShapeError(f"texels must be in [0, {cf.n_texels})")
    if t.size == 0:
        return np.zeros(0, dtype=np.float64)
    padded = cf.padded(dense_limit)
    if padded is not None:
        # dense (n_texels, k_max) layout: one gather and one einsum per chunk of queries
        nrm_p, area_p = padded
        k_max = max(nrm_p.shape[1], 1)
        out = np.empty(t.shape[0], dtype=np.float64)
        step = max(1, (1 << 22) // k_max)
        for q0 in range(0, t.shape[0], step):  # memory-bounded chunks of queries
            tq = t[q0:q0 + step]
            d = np.einsum("qkj,qj->qk", nrm_p[tq], w[q0:q0 + step])  # (q, k_max)
            out[q0:q0 + step] = np.sum(np.where(d > TOL.grazing_cos, d, 0.0) * area_p[tq],
                                       axis=1)
        return out
    start = cf.offsets[t]
    counts = cf.offsets[t + 1] - start  # (n,)
    query = np.repeat(np.arange(t.shape[0]), counts)  # (pairs,)
    first = np.cumsum(counts) - counts
    term = np.arange(query.shape[0]) - np.repeat(first - start, counts)
    dots = np.einsum("ki,ki->k", cf.normals[term], w[query])
    dots = np.where(dots > TOL.grazing_cos, dots, 0.0) * cf.areas[term]
    return np.bincount(query, weights=dots, minlength=t.shape[0])


def closed_form_maps(cf: ClosedForm, res: int, texels: np.ndarray | None = None, *,
                     max_elems: int = 1 << 24) -> np.ndarray:
    """Closed-form a_vis at the cube-map directions (for coarsening into ray-based parents).

    texels : (r,) int (all texels when None)
    returns : (r, 6, res, res) float64
    """
    res = _check_res(res)
    t = np.arange(cf.n_texels) if texels is None else np.asarray(texels, dtype=np.int64)
    dirs = cube_directions(res).reshape(-1, 3)
    nd = dirs.shape[0]
    counts = cf.offsets[t + 1] - cf.offsets[t]
    row = np.repeat(np.arange(t.shape[0]), counts)
    first = np.cumsum(counts) - counts
    term = np.arange(row.shape[0]) - np.repeat(first - cf.offsets[t], counts)
    out = np.zeros((t.shape[0], nd), dtype=np.float64)
    step = max(1, int(max_elems) // nd)
    for k0 in range(0, term.shape[0], step):  # memory-bounded chunks of terms
        tk = term[k0:k0 + step]
        proj = cf.normals[tk] @ dirs.T  # (k, nd)
        proj = np.where(proj > TOL.grazing_cos, proj, 0.0) * cf.areas[tk, None]
        owner = sp.csr_matrix((np.ones(tk.shape[0]), (row[k0:k0 + step], np.arange(tk.shape[0]))),
                              shape=(t.shape[0], tk.shape[0]))
        out += owner @ proj
    return out.reshape(t.shape[0], 6, res, res)


# --------------------------------------------------------------------------------------------
# hierarchy


def coarsen_maps(maps: np.ndarray) -> np.ndarray:
    """Sum 2 x 2 children into their parent (a_vis is additive over disjoint sample sets).

    maps : (N * N, ...) texels of an N x N atlas level in row-major order (texel = iy * N + ix)
    returns : (N/2 * N/2, ...) same dtype; exact in a shared (world) direction frame
    """
    a = np.asarray(maps)
    n = a.shape[0]
    side = int(round(np.sqrt(n)))
    if side * side != n or side % 2 or side == 0:
        raise ShapeError(f"maps must hold N*N texels with N even, got {n} texels")
    h = side // 2
    b = a.reshape(h, 2, h, 2, *a.shape[1:])
    return b.sum(axis=(1, 3)).reshape(h * h, *a.shape[1:])


def _children(n_side: int) -> np.ndarray:
    """(N/2 * N/2, 4) int64 child texel ids of each parent, row-major."""
    h = n_side // 2
    py, px = np.meshgrid(np.arange(h), np.arange(h), indexing="ij")
    kids = [(2 * py + dy) * n_side + (2 * px + dx) for dy in (0, 1) for dx in (0, 1)]
    return np.stack([k.ravel() for k in kids], axis=1)


@dataclass(frozen=True)
class AvisLevel:
    """Uncompressed a_vis of one mip level (N x N texels, row-major ids iy * N + ix).

    n_side : N; res : cube face side
    closed : (N*N,) bool, texels in closed form (their terms in `cf`)
    bounded : (N*N,) bool, texels whose terms are in `cf`: every closed texel, and ray texels
        with at most `max_terms` distinct normals. For a ray texel the terms give the
        unoccluded projected area, a hard upper bound a_vis(w) <= sum_k A_k (n_k . w)^+ that
        the look-up applies (exact horizon: a_vis -> 0 as w -> grazing for a flat texel, which
        a cube map only resolves to one cube texel)
    cf : ClosedForm over the N*N texels (terms only for bounded texels)
    ray_texels : (r,) int64 ascending, the texels not in closed form
    ray_maps : (r, 6, res, res) float64 world-direction cube maps of those texels
    texel_area : (N*N,) float64 sum of dA_j (for the a_vis -> 0 floor)
    """

    n_side: int
    res: int
    closed: np.ndarray
    bounded: np.ndarray
    cf: ClosedForm
    ray_texels: np.ndarray
    ray_maps: np.ndarray
    texel_area: np.ndarray
    max_terms: int = 256

    def dense_maps(self) -> np.ndarray:
        """(N*N, 6, res, res) float64 maps of every texel (closed form evaluated at the cube
        directions)."""
        n = self.n_side * self.n_side
        out = np.zeros((n, 6, self.res, self.res), dtype=np.float64)
        closed_ids = np.flatnonzero(self.closed)
        out[closed_ids] = closed_form_maps(self.cf, self.res, closed_ids)
        out[self.ray_texels] = self.ray_maps
        return out


_LEVEL_ARRAYS = ("closed", "bounded", "cf_offsets", "cf_normals", "cf_areas", "ray_texels",
                 "ray_maps", "texel_area")


def level_to_arrays(level: AvisLevel) -> dict[str, np.ndarray]:
    """Named arrays of an AvisLevel (for np.savez in the artifact store between the per-tile
    and the top stages); inverse of `level_from_arrays`."""
    return {
        "meta": np.array([level.n_side, level.res, level.max_terms], dtype=np.int64),
        "closed": level.closed, "bounded": level.bounded, "cf_offsets": level.cf.offsets,
        "cf_normals": level.cf.normals, "cf_areas": level.cf.areas,
        "ray_texels": level.ray_texels, "ray_maps": level.ray_maps,
        "texel_area": level.texel_area,
    }


def level_from_arrays(arrays) -> AvisLevel:
    """AvisLevel from `level_to_arrays` output (any mapping of name -> array, e.g. an NpzFile)."""
    missing = [k for k in ("meta", *_LEVEL_ARRAYS) if k not in arrays]
    if missing:
        raise ShapeError(f"a_vis level arrays are missing {missing}")
    n_side, res, max_terms = (int(x) for x in np.asarray(arrays["meta"]))
    level = AvisLevel(
        n_side, res, np.asarray(arrays["closed"], bool), np.asarray(arrays["bounded"], bool),
        ClosedForm(np.asarray(arrays["cf_offsets"], np.int64),
                   np.asarray(arrays["cf_normals"], np.float64),
                   np.asarray(arrays["cf_areas"], np.float64)),
        np.asarray(arrays["ray_texels"], np.int64), np.asarray(arrays["ray_maps"], np.float64),
        np.asarray(arrays["texel_area"], np.float64), max_terms)
    n = n_side * n_side
    if (level.closed.shape != (n,) or level.cf.n_texels != n
            or level.ray_maps.shape != (level.ray_texels.shape[0], 6, res, res)):
        raise ShapeError(f"a_vis level arrays are inconsistent with n_side={n_side}, res={res}")
    return level


def stack_tiles(tiles: list[AvisLevel], tiles_per_side: int) -> AvisLevel:
    """One level from a row-major grid of equally sized tiles (the farm's per-tile results).

    tiles : T * T AvisLevels of side n (tile (ty, tx) at index ty * T + tx, local texel ids
        iy * n + ix), all with one res and max_terms
    returns : AvisLevel of side T * n with texel id (ty n + iy) (T n) + tx n + ix
    """
    t_side = int(tiles_per_side)
    if t_side < 1 or len(tiles) != t_side * t_side:
        raise ShapeError(f"expected {t_side}^2 tiles, got {len(tiles)}")
    n, res, max_terms = tiles[0].n_side, tiles[0].res, tiles[0].max_terms
    if any((t.n_side, t.res, t.max_terms) != (n, res, max_terms) for t in tiles):
        raise ShapeError("tiles must share n_side, res and max_terms")
    side = t_side * n
    iy, ix = np.divmod(np.arange(n * n), n)
    closed = np.zeros(side * side, dtype=bool)
    bounded = np.zeros(side * side, dtype=bool)
    area = np.zeros(side * side)
    owners, normals, areas, ray_ids, ray_maps = [], [], [], [], []
    for k, tile in enumerate(tiles):  # a loop over tiles
        ty, tx = divmod(k, t_side)
        gid = (ty * n + iy) * side + tx * n + ix  # (n*n,) local -> global
        closed[gid], bounded[gid], area[gid] = tile.closed, tile.bounded, tile.texel_area
        owners.append(gid[np.repeat(np.arange(n * n), np.diff(tile.cf.offsets))])
        normals.append(tile.cf.normals)
        areas.append(tile.cf.areas)
        ray_ids.append(gid[tile.ray_texels])
        ray_maps.append(tile.ray_maps)
    cf = _merge_terms(np.concatenate(owners), np.concatenate(normals), np.concatenate(areas),
                      side * side)
    ids = np.concatenate(ray_ids)
    order = np.argsort(ids, kind="stable")
    maps = np.concatenate(ray_maps)[order] if ids.size else np.zeros((0, 6, res, res))
    return AvisLevel(side, res, closed, bounded, cf, ids[order], maps, area, max_terms)


def avis_level(positions: np.ndarray, normals: np.ndarray, areas: np.ndarray,
               texel_of_sample: np.ndarray, n_side: int, res: int, occluded_fn: OccludedFn,
               mesh_points: np.ndarray, *, closed_form: bool = True, max_terms: int = 256,
               ray_eps: float | None = None, max_rays: int = 1 << 21) -> AvisLevel:
    """a_vis of one atlas level: closed form where `unoccluded_texels` proves it exact, rays
    (avis_cube_maps, world directions) elsewhere.

    positions, normals : (m, 3) float64 samples and geometric normals; areas : (m,) float64
    texel_of_sample : (m,) int in [0, n_side^2); mesh_points : (v, 3) float64 M_org vertices
    closed_form : False forces rays for every texel (for measuring what the skip saves)
    max_terms : ray texels with at most this many distinct normals keep their unoccluded
        upper bound (see AvisLevel.bounded); closed texels always keep all their terms
    ray_eps : ray-origin offset and closed-form detection slack; default
        `default_eps(positions)`. When a level is computed in tiles (texel ids local to the
        tile, see `stack_tiles`), pass one scene-wide value so that every tile casts the rays
        the whole level would.
    returns : AvisLevel
    """
    pos, nrm, ar, tex, n_texels = _coerce_samples(normals, areas, texel_of_sample,
                                                  int(n_side) ** 2, positions)
    eps = default_eps(pos) if ray_eps is None else float(ray_eps)
    if closed_form:
        closed = unoccluded_texels(pos, nrm, tex, n_texels, mesh_points, eps=eps)
    else:
        closed = np.zeros(n_texels, dtype=bool)
    cf, bounded = _bounded_terms(closed_form_terms(nrm, ar, tex, n_texels), closed,
                                 int(max_terms))
    ray_texels = np.flatnonzero(~closed)
    maps = avis_cube_maps(pos, nrm, ar, tex, n_texels, None, res, occluded_fn,
                          skip_texels=closed, ray_eps=eps, max_rays=max_rays, dtype=np.float64)
    area = np.bincount(tex, weights=ar, minlength=n_texels)
    return AvisLevel(int(n_side), int(res), closed, bounded, cf, ray_texels, maps[ray_texels],
                     area, int(max_terms))


def _bounded_terms(cf: ClosedForm, closed: np.ndarray,
                   max_terms: int) -> tuple[ClosedForm, np.ndarray]:
    """Keep the terms of closed texels and of texels with <= max_terms terms."""
    counts = np.diff(cf.offsets)
    bounded = closed | (counts <= max_terms)
    owner = np.repeat(np.arange(cf.n_texels), counts)
    keep = bounded[owner]
    return _merge_terms(owner[keep], cf.normals[keep], cf.areas[keep], cf.n_texels), bounded


def coarsen_level(level: AvisLevel) -> AvisLevel:
    """The parent level (N/2 x N/2) by exact additivity in world directions.

    A parent is in closed form iff its four children are (the union of sample sets that are
    each unoccluded in their hemispheres is unoccluded; terms concatenated, equal normals
    merged). Otherwise its map is the sum of the children's maps, closed-form children
    evaluated at the cube directions. The parents' texel frames are only needed at look-up.
    """
    n = level.n_side
    if n % 2 or n == 0:
        raise ShapeError(f"level n_side must be even to coarsen, got {n}")
    kids = _children(n)  # (P, 4)
    n_par = kids.shape[0]
    closed = level.closed[kids].all(axis=1)
    # terms of parents whose four children are bounded: children's terms re-owned, merged
    parent_of = np.empty(n * n, dtype=np.int64)
    parent_of[kids.ravel()] = np.repeat(np.arange(n_par), 4)
    owner_child = np.repeat(np.arange(n * n), np.diff(level.cf.offsets))
    owner = parent_of[owner_child]
    keep = level.bounded[kids].all(axis=1)[owner]
    cf, bounded = _bounded_terms(
        _merge_terms(owner[keep], level.cf.normals[keep], level.cf.areas[keep], n_par),
        closed, level.max_terms)
    bounded &= level.bounded[kids].all(axis=1)
    ray_par = np.flatnonzero(~closed)
    row_of = np.full(n * n, -1, dtype=np.int64)
    row_of[level.ray_texels] = np.arange(level.ray_texels.shape[0])
    maps = np.zeros((ray_par.shape[0], 6, level.res, level.res), dtype=np.float64)
    for c in range(4):  # the four children
        kid = kids[ray_par, c]
        is_ray = row_of[kid] >= 0
        maps[is_ray] += level.ray_maps[row_of[kid[is_ray]]]
        if (~is_ray).any():
            maps[~is_ray] += closed_form_maps(level.cf, level.res, kid[~is_ray])
    area = level.texel_area[kids].sum(axis=1)
    return AvisLevel(n // 2, level.res, closed, bounded, cf, ray_par, maps, area,
                     level.max_terms)


# --------------------------------------------------------------------------------------------
# compressed table and look-up


@dataclass(frozen=True)
class AvisTable:
    """Compressed a_vis of one level, ready for look-ups.

    res : cube face side
    frames : (n_texels, 3, 3) float64 texel frames, rows (t, b, n)
    texel_area : (n_texels,) float64
    closed : (n_texels,) bool; cf : ClosedForm (exact, any direction, for closed texels;
        the unoccluded upper bound for the other `bounded` texels)
    bounded : (n_texels,) bool
    ray_row : (n_texels,) int64 row of the texel in `haar` (-1 for closed-form texels)
    haar : HaarCoeffs of the (n_ray, 6, res, res) world-direction cube maps: for a bounded
        ray texel the *visible fraction* F = a_vis / U (U the unoccluded projected area, its
        closed form; F in [0, 1]), otherwise a_vis itself. Look-up: U F at the taps (U exact
        at each tap direction), interpolated, then min(., U(w)) with U exact at w: the
        horizon is exact and compression only touches the smoother masking fraction
        (about 4x lower error at the seed's kept fraction, benchmarks/avis_methods.py)
    """

    res: int
    frames: np.ndarray
    texel_area: np.ndarray
    closed: np.ndarray
    bounded: np.ndarray
    cf: ClosedForm
    ray_row: np.ndarray
    haar: HaarCoeffs

    @property
    def n_texels(self) -> int:
        return int(self.closed.shape[0])

    def to_arrays(self) -> dict[str, np.ndarray]:
        """Named arrays (what the payload writer stores; float32 Haar values)."""
        return {
            "meta": np.array([self.res, self.haar.res], dtype=np.int64),
            "frames": self.frames, "texel_area": self.texel_area, "closed": self.closed,
            "bounded": self.bounded, "cf_offsets": self.cf.offsets,
            "cf_normals": self.cf.normals, "cf_areas": self.cf.areas, "ray_row": self.ray_row,
            "haar_offsets": self.haar.offsets, "haar_indices": self.haar.indices,
            "haar_values": self.haar.values,
        }

    @classmethod
    def from_arrays(cls, arrays) -> AvisTable:
        """Inverse of `to_arrays` (any mapping of name -> array)."""
        need = ("meta", "frames", "texel_area", "closed", "bounded", "cf_offsets", "cf_normals",
                "cf_areas", "ray_row", "haar_offsets", "haar_indices", "haar_values")
        missing = [k for k in need if k not in arrays]
        if missing:
            raise ShapeError(f"a_vis table arrays are missing {missing}")
        res = int(np.asarray(arrays["meta"])[0])
        ray_row = np.asarray(arrays["ray_row"], np.int64)
        n_ray = int(ray_row.max()) + 1 if ray_row.size else 0
        haar = HaarCoeffs(res, (n_ray, 6), np.asarray(arrays["haar_offsets"], np.int64),
                          np.asarray(arrays["haar_indices"], np.int32),
                          np.asarray(arrays["haar_values"]))
        if haar.n_maps != n_ray * 6:
            raise ShapeError(f"haar_offsets describe {haar.n_maps} maps, ray_row needs "
                             f"{n_ray * 6}")
        cf = ClosedForm(np.asarray(arrays["cf_offsets"], np.int64),
                        np.asarray(arrays["cf_normals"], np.float64),
                        np.asarray(arrays["cf_areas"], np.float64))
        return cls(res, np.asarray(arrays["frames"], np.float64),
                   np.asarray(arrays["texel_area"], np.float64),
                   np.asarray(arrays["closed"], bool), np.asarray(arrays["bounded"], bool), cf,
                   ray_row, haar)

    def evaluate(self, texels: np.ndarray, dirs_texel: np.ndarray, *,
                 interp: str = "bilinear",
                 floor: float = TOL.avis_floor) -> tuple[np.ndarray, np.ndarray]:
        """a_vis at view directions given in each texel's frame.

        texels : (n,) int in [0, n_texels)
        dirs_texel : (n, 3) float64 directions in the texel frame (t, b, n); need not be unit
        interp : "bilinear" (continuous across cube edges) or "nearest" cube-map texel
        floor : relative floor; see returns
        returns : (a (n,) float64 >= 0, valid (n,) bool). valid is False where
            a <= floor * texel_area (grazing or fully masked: the a_vis -> 0 limit), where the
            direction is zero or non-finite, and for empty texels; there a = 0 and the
            renderer must use zero radiance for the texel instead of dividing by a_vis.
        """
        t = np.asarray(texels, dtype=np.int64).ravel()
        d = np.asarray(dirs_texel, dtype=np.float64)
        n = t.shape[0]
        if d.shape != (n, 3):
            raise ShapeError(f"dirs_texel must be ({n}, 3), got {d.shape}")
        if n and (t.min() < 0 or t.max() >= self.n_texels):
            raise ShapeError(f"texels must be in [0, {self.n_texels}), got "
                             f"[{t.min()}, {t.max()}]")
        if interp not in ("bilinear", "nearest"):
            raise SettingsError(f"interp must be 'bilinear' or 'nearest', got {interp!r}")
        length = np.linalg.norm(d, axis=1)
        dir_ok = np.isfinite(length) & (length > 0)
        d = np.divide(d, length[:, None], out=np.zeros_like(d), where=dir_ok[:, None])
        w = to_world(self.frames[t], d)  # (n, 3)
        a = np.zeros(n, dtype=np.float64)
        cl = self.closed[t]
        if cl.any():
            a[cl] = eval_closed_form(self.cf, t[cl], w[cl])
        rq = np.flatnonzero(~cl)
        if rq.size:
            bnd = self.bounded[t[rq]]
            a[rq] = self._eval_maps(self.ray_row[t[rq]], w[rq], interp, t[rq], bnd)
            bq = rq[bnd]
            if bq.size:  # a_vis <= U, exact at w (a_vis -> 0 at the horizon with U)
                a[bq] = np.minimum(a[bq], eval_closed_form(self.cf, t[bq], w[bq]))
        a = np.maximum(a, 0.0)
        valid = dir_ok & (a > floor * self.texel_area[t]) & (self.texel_area[t] > 0)
        return np.where(valid, a, 0.0), valid

    def _eval_maps(self, rows: np.ndarray, w: np.ndarray, interp: str, texels: np.ndarray,
                   bounded: np.ndarray) -> np.ndarray:
        """a_vis from the Haar maps. For bounded texels the maps hold F = a_vis / U: nearest
        returns U(w) F(texel); bilinear interpolates the products U(tap) F(tap) over the four
        taps (so a lossless table interpolates a_vis itself, and compression only touches F)."""
        res = self.res
        face, iu, iv, fu, fv = dirs_to_cube(w, res)
        if interp == "nearest":
            val = eval_haar_point(self.haar, rows * 6 + face, iu, iv)
            if bounded.any():
                val[bounded] = (np.clip(val[bounded], 0.0, 1.0)
                                * eval_closed_form(self.cf, texels[bounded], w[bounded]))
            return val
        # Seamless bilinear: the four taps are texel centres of the face's plane extended by
        # one texel. A tap inside the face is read directly; a tap beyond an edge is turned
        # back into a direction and read by a bilinear look-up (clamped to that face) on the
        # face it falls on, so the result is continuous across cube edges and corners.
        u0 = np.floor(fu)
        v0 = np.floor(fv)
        au, av = fu - u0, fv - v0
        tu = np.concatenate([u0, u0 + 1, u0, u0 + 1])  # (4n,)
        tv = np.concatenate([v0, v0, v0 + 1, v0 + 1])
        f4 = np.tile(face, 4)
        r4 = np.tile(rows, 4)
        taps = np.empty(tu.shape[0], dtype=np.float64)
        inside = (tu >= 0) & (tu <= res - 1) & (tv >= 0) & (tv <= res - 1)
        taps[inside] = eval_haar_point(self.haar, r4[inside] * 6 + f4[inside],
                                       tu[inside].astype(np.int64), tv[inside].astype(np.int64))
        sc = 2.0 * (tu + 0.5) / res - 1.0
        tc = 2.0 * (tv + 0.5) / res - 1.0
        basis = _FACE_BASIS[f4]  # (4n, 3, 3)
        tap_dirs = basis[:, 0] + sc[:, None] * basis[:, 1] + tc[:, None] * basis[:, 2]
        out = ~inside
        if out.any():
            tf, _, _, tfu, tfv = dirs_to_cube(tap_dirs[out], res)
            taps[out] = self._bilinear_in_face(r4[out], tf, tfu, tfv)
        b4 = np.tile(bounded, 4)
        if b4.any():  # F at the taps times U exactly at the tap directions
            td = tap_dirs[b4] / np.linalg.norm(tap_dirs[b4], axis=1, keepdims=True)
            taps[b4] = np.clip(taps[b4], 0.0, 1.0) * eval_closed_form(
                self.cf, np.tile(texels, 4)[b4], td)
        wts = np.concatenate([(1 - au) * (1 - av), au * (1 - av), (1 - au) * av, au * av])
        return np.sum((taps * wts).reshape(4, -1), axis=0)

    def _bilinear_in_face(self, rows: np.ndarray, face: np.ndarray, fu: np.ndarray,
                          fv: np.ndarray) -> np.ndarray:
        """Bilinear look-up with coordinates clamped to the face's texel centres."""
        res = self.res
        fu = np.clip(fu, 0.0, res - 1.0)
        fv = np.clip(fv, 0.0, res - 1.0)
        u0 = np.minimum(np.floor(fu).astype(np.int64), max(res - 2, 0))
        v0 = np.minimum(np.floor(fv).astype(np.int64), max(res - 2, 0))
        u1, v1 = np.minimum(u0 + 1, res - 1), np.minimum(v0 + 1, res - 1)
        au, av = fu - u0, fv - v0
        mi = np.tile(rows * 6 + face, 4)
        taps = eval_haar_point(self.haar, mi, np.concatenate([u0, u1, u0, u1]),
                               np.concatenate([v0, v0, v1, v1])).reshape(4, -1)
        wts = np.stack([(1 - au) * (1 - av), au * (1 - av), (1 - au) * av, au * av])
        return np.sum(taps * wts, axis=0)


def _fill_along(f: np.ndarray, ok: np.ndarray, axis: int) -> tuple[np.ndarray, np.ndarray]:
    """Fill undefined entries with the nearest defined entry along one axis (ties: lower
    index). Vectorized: forward and backward running maxima of the defined indices."""
    n = f.shape[axis]
    shape = [1] * f.ndim
    shape[axis] = n
    pos = np.arange(n).reshape(shape)
    prev = np.maximum.accumulate(np.where(ok, pos, -1), axis=axis)
    nxt = n - 1 - np.maximum.accumulate(np.flip(np.where(ok, n - 1 - pos, -1), axis=axis),
                                        axis=axis)
    nxt = np.flip(nxt, axis=axis)  # index of the next defined entry, n when none
    d_prev = np.where(prev >= 0, pos - prev, n + 1)
    d_next = np.where(nxt < n, nxt - pos, n + 1)
    src = np.where(d_prev <= d_next, prev, nxt)
    found = np.minimum(d_prev, d_next) <= n
    filled = np.take_along_axis(f, np.clip(src, 0, n - 1), axis=axis)
    return np.where(ok, f, np.where(found, filled, 0.0)), ok | found


def visible_fraction(maps: np.ndarray, unoccluded: np.ndarray) -> np.ndarray:
    """F = a_vis / U on cube maps. Where U = 0 (F undefined) F takes the value of the nearest
    defined texel of the same face along its column, else along its row, so that bilinear
    look-ups just above the horizon and the Haar transform see a piecewise-constant extension
    rather than a jump to 0; faces with no defined texel are 0.

    maps, unoccluded : (r, 6, res, res) float64 a_vis and its unoccluded bound U >= a_vis
    returns : (r, 6, res, res) float64 in [0, 1]
    """
    a = np.asarray(maps, dtype=np.float64)
    u = np.asarray(unoccluded, dtype=np.float64)
    if a.shape != u.shape or a.ndim < 2:
        raise ShapeError(f"maps and unoccluded must share a (..., res, res) shape, got "
                         f"{a.shape} and {u.shape}")
    defined = u > 0
    f = np.clip(np.divide(a, u, out=np.zeros_like(a), where=defined), 0.0, 1.0)
    f, defined = _fill_along(f, defined, axis=-2)  # along columns (iv)
    f, _ = _fill_along(f, defined, axis=-1)  # then rows (iu), for columns without values
    return f


def compress_level(level: AvisLevel, frames: np.ndarray, keep_fraction: float) -> AvisTable:
    """AvisTable of a level: closed-form terms as they are, Haar for the ray-based texels.

    frames : (N*N, 3, 3) float64 texel frames of this level (rows t, b, n)
    keep_fraction : Haar coefficients kept per cube face (texelbake.haar.compress_haar)
    """
    n = level.n_side * level.n_side
    frames = np.asarray(frames, dtype=np.float64)
    if frames.shape != (n, 3, 3):
        raise ShapeError(f"frames must be ({n}, 3, 3), got {frames.shape}")
    ray_row = np.full(n, -1, dtype=np.int64)
    ray_row[level.ray_texels] = np.arange(level.ray_texels.shape[0])
    maps = level.ray_maps.copy()  # (n_ray, 6, res, res)
    frac = level.bounded[level.ray_texels]
    if frac.any():
        unocc = closed_form_maps(level.cf, level.res, level.ray_texels[frac])
        maps[frac] = visible_fraction(maps[frac], unocc)
    haar = compress_haar(maps, keep_fraction)
    return AvisTable(level.res, frames, level.texel_area, level.closed, level.bounded, level.cf,
                     ray_row, haar)
