"""Texel assignment g(p) and texel frames (seed 000, §4.1).

Every sample x_j of M_org goes to the texel of M1's atlas under its exact closest point on
M1 (triangle id + float64 barycentrics → uv → texel); the seed's k-d tree over samples of
M1 approximates this. Mip level ℓ is the atlas at resolution N_ℓ = N / 2^ℓ and its texel
(r, c) holds the samples of its four children (2r + i, 2c + j) — the seed's box filter — so
a level-ℓ texel is the level-0 texel shifted right by ℓ bits in row and column.

Texel convention (see `texelbake.geometry.atlas`): row 0 at the top, row = floor((1 - v) N),
col = floor(u N), flat index row * N + col.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from texelbake.errors import SettingsError, ShapeError
from texelbake.geometry.atlas import Atlas, rasterize_atlas
from texelbake.geometry.mesh import Mesh, check_points
from texelbake.geometry.raycast import RayCaster
from texelbake.tol import TOL


def uv_to_texel(uv: object, resolution: int) -> tuple[np.ndarray, np.ndarray]:
    """Texel (row, col) containing each uv at resolution N (uv outside [0,1] is clamped).

    uv : (n, 2) float64
    returns : (row (n,) int64, col (n,) int64)
    """
    uv = np.asarray(uv, dtype=np.float64)
    if uv.ndim != 2 or uv.shape[1] != 2:
        raise ShapeError(f"uv must have shape (n, 2), got {uv.shape}")
    n = int(resolution)
    col = np.clip(np.floor(uv[:, 0] * n), 0, n - 1).astype(np.int64)
    row = np.clip(np.floor((1.0 - uv[:, 1]) * n), 0, n - 1).astype(np.int64)
    return row, col


def texel_centers_uv(resolution: int) -> np.ndarray:
    """(N*N, 2) float64 uv of every texel centre, in flat order row * N + col."""
    n = int(resolution)
    row, col = np.divmod(np.arange(n * n, dtype=np.int64), n)
    return np.column_stack([(col + 0.5) / n, 1.0 - (row + 0.5) / n])


def bilinear_texels(uv: object, resolution: int) -> tuple[np.ndarray, np.ndarray]:
    """The four texels around each uv and their bilinear weights (clamped at the border),
    for filtered look-ups (trilinear = two levels of this).

    uv : (n, 2) float64
    returns : (index (n, 4) int64 flat texel ids, weight (n, 4) float64 summing to 1)
    """
    uv = np.asarray(uv, dtype=np.float64)
    if uv.ndim != 2 or uv.shape[1] != 2:
        raise ShapeError(f"uv must have shape (n, 2), got {uv.shape}")
    n = int(resolution)
    x = np.clip(uv[:, 0] * n - 0.5, 0.0, n - 1.0)  # continuous column of texel centres
    y = np.clip((1.0 - uv[:, 1]) * n - 0.5, 0.0, n - 1.0)
    c0 = np.minimum(np.floor(x).astype(np.int64), n - 1)
    r0 = np.minimum(np.floor(y).astype(np.int64), n - 1)
    c1 = np.minimum(c0 + 1, n - 1)
    r1 = np.minimum(r0 + 1, n - 1)
    fx = x - c0
    fy = y - r0
    index = np.stack([r0 * n + c0, r0 * n + c1, r1 * n + c0, r1 * n + c1], axis=1)
    weight = np.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy], axis=1)
    return index, weight


def _part1by1(x: np.ndarray) -> np.ndarray:
    """The bits of x (< 2^32) spread to the even places of a 64-bit word."""
    x = x.astype(np.uint64) & np.uint64(0xFFFFFFFF)
    for shift, mask in ((16, 0x0000FFFF0000FFFF), (8, 0x00FF00FF00FF00FF),
                        (4, 0x0F0F0F0F0F0F0F0F), (2, 0x3333333333333333),
                        (1, 0x5555555555555555)):  # five bit-spreading steps
        x = (x | (x << np.uint64(shift))) & np.uint64(mask)
    return x


def morton(row: np.ndarray, col: np.ndarray) -> np.ndarray:
    """Z-order code of texel (row, col) (int64; row's bits in the odd places): the texels of an
    aligned 2^l x 2^l block, i.e. one texel of level l, are the 4^l consecutive codes from
    morton(r << l, c << l). The geometry stage orders samples by it (`sample_zorder`), so a
    shard finds its tile's samples without reading every sample's texel."""
    code = (_part1by1(np.asarray(row)) << np.uint64(1)) | _part1by1(np.asarray(col))
    return code.astype(np.int64)


#: samples `assign_texels` takes at a time (~0.4 KB of temporaries each)
ASSIGN_CHUNK = 1 << 20


@dataclass(frozen=True, eq=False)
class TexelAssignment:
    """Samples grouped by texel at every mip level.

    resolution : N (level 0); n_levels : L; level ℓ has N >> ℓ texels per side
    prim : (m,) int64 M1 triangle under each sample's closest point
    bary : (m, 3) float64 barycentrics of that closest point
    uv : (m, 2) float64 atlas uv of the closest point
    distance : (m,) float64 sample-to-M1 distance
    row, col : (m,) int64 level-0 texel
    offsets : L arrays (N_ℓ² + 1,) int64 — texel p at level ℓ holds
        offsets[ℓ][p + 1] - offsets[ℓ][p] samples (`samples_of` lists them; the sorted order
        of all samples, L x m int64, is not kept: 1.3 GB at 512²)
    """

    resolution: int
    n_levels: int
    prim: np.ndarray
    bary: np.ndarray
    uv: np.ndarray
    distance: np.ndarray
    row: np.ndarray
    col: np.ndarray
    offsets: tuple[np.ndarray, ...]

    def _check_level(self, level: int) -> int:
        level = int(level)
        if not 0 <= level < self.n_levels:
            raise SettingsError(f"level must be in [0, {self.n_levels}), got {level}")
        return level

    def resolution_at(self, level: int) -> int:
        return self.resolution >> self._check_level(level)

    def texel_index(self, level: int) -> np.ndarray:
        """(m,) int64 flat texel id of every sample at `level`."""
        level = self._check_level(level)
        n_l = self.resolution >> level
        return (self.row >> level) * n_l + (self.col >> level)

    def counts(self, level: int) -> np.ndarray:
        """(N_ℓ²,) int64 samples per texel."""
        return np.diff(self.offsets[self._check_level(level)])

    def samples_of(self, level: int, texel: int) -> np.ndarray:
        """(k,) int64 ids of the samples in texel `texel` (flat id) at `level`."""
        level = self._check_level(level)
        off = self.offsets[level]
        texel = int(texel)
        if not 0 <= texel < off.shape[0] - 1:
            raise SettingsError(f"texel must be in [0, {off.shape[0] - 1}), got {texel}")
        return np.flatnonzero(self.texel_index(level) == texel)  # ascending, as a stable sort

    def occupied(self, level: int) -> np.ndarray:
        """(k,) int64 flat ids of the texels holding at least one sample, ascending."""
        return np.flatnonzero(self.counts(level) > 0)


def assign_texels(
    sample_positions: object,
    m1: Mesh,
    atlas: Atlas,
    n_levels: int,
    *,
    caster: RayCaster | None = None,
    normals: object = None,
    occluder: RayCaster | None = None,
    chunk: int = ASSIGN_CHUNK,
) -> TexelAssignment:
    """Assign every sample to its texel at every mip level by exact closest point on M1
    (seed 000 §4.1: "based on Euclidean distances").

    With `normals`, a sample whose closest point lies behind its own surface (more than
    BEHIND_DEG from its normal) takes instead the point of M1 that a ray from it along its
    normal hits, when there is one: where M1 has a sheet on each side of a thin part (a wrap,
    `geometry.hierarchy.wrap`) the mortar between a wall's blocks is nearer the back sheet
    but is seen through the front one (a departure from the seed; docs/decisions.md).
    With `occluder` (M_org) as well, a sample whose closest M1 face does not face its own way
    (normals more than FACING_DEG apart: the side walls of the gaps between the blocks, 90°
    from both sheets) takes the point of M1 that a ray along its *bent normal* hits, the mean
    of the BENT_RAYS hemisphere directions in which M_org does not occlude it: the way out
    through which it is seen.

    sample_positions : (m, 3) float64 points on M_org
    m1 : M1 (same faces as atlas.mesh); atlas : from build_atlas
    n_levels : L >= 1; N must be divisible by 2^(L-1) so every level has whole texels
    caster : a RayCaster over atlas.mesh to reuse (built when None)
    normals : None, or (m, 3) the samples' geometric normals (outward; need not be unit)
    occluder : None, or a RayCaster over M_org (the bent-normal rule; needs `normals`)
    chunk : samples assigned at a time (memory only: the result does not depend on it)
    returns : TexelAssignment
    """
    pts = check_points(sample_positions, "sample_positions")
    n_levels = int(n_levels)
    n = int(atlas.resolution)
    if n_levels < 1:
        raise SettingsError(f"n_levels must be >= 1, got {n_levels}")
    if n % (1 << (n_levels - 1)) != 0:
        raise SettingsError(
            f"atlas resolution {n} must be divisible by 2^(n_levels-1) = {1 << (n_levels - 1)}"
        )
    if m1.num_faces != atlas.mesh.num_faces:
        raise ShapeError(
            f"m1 has {m1.num_faces} faces but the atlas mesh has {atlas.mesh.num_faces}"
        )
    m = pts.shape[0]
    if caster is None:
        caster = RayCaster(atlas.mesh.vertices, atlas.mesh.faces)
    nrm = None
    if normals is not None and m:
        nrm = check_points(normals, "normals")
        if nrm.shape[0] != m:
            raise ShapeError(f"normals must be ({m}, 3) like sample_positions, got {nrm.shape}")
    face_normals = m1.face_normals()  # of M1: a few thousand faces
    prim = np.zeros(m, np.int64)
    bary = np.zeros((m, 3))
    uv = np.zeros((m, 2))
    distance = np.zeros(m)
    # every sample's assignment depends on that sample only (its closest point, its rays), so
    # samples go in chunks: the temporaries of the rules stay at `chunk` samples whatever the
    # atlas size (memory), with the result of one pass over all
    for a in range(0, m, int(chunk)):
        b = min(a + int(chunk), m)
        prim[a:b], bary[a:b], uv[a:b], distance[a:b] = assign_rows(
            pts[a:b], None if nrm is None else nrm[a:b], atlas, caster, occluder, face_normals)
    row, col = uv_to_texel(uv, n)
    offsets = []
    for level in range(n_levels):  # a handful of mip levels
        n_l = n >> level
        idx = (row >> level) * n_l + (col >> level)
        counts = np.bincount(idx, minlength=n_l * n_l)
        offsets.append(np.concatenate([[0], np.cumsum(counts)]).astype(np.int64))
    return TexelAssignment(
        resolution=n,
        n_levels=n_levels,
        prim=prim,
        bary=bary,
        uv=uv,
        distance=distance,
        row=row,
        col=col,
        offsets=tuple(offsets),
    )


def assign_rows(p: np.ndarray, nrm: np.ndarray | None, atlas: Atlas, caster: RayCaster,
                occluder: RayCaster | None, face_normals: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """`assign_texels`' rules for the samples `p` (k, 3) with their normals (or None): (prim,
    bary (k, 3), atlas uv (k, 2), distance) of each. Each row depends on its sample only.
    caster : over atlas.mesh; face_normals : of atlas.mesh."""
    closest, pr, bary2 = caster.closest_points(p)
    ba = np.column_stack([1.0 - bary2[:, 0] - bary2[:, 1], bary2])  # (k, 3)
    if nrm is not None:
        n_unit = nrm / np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-300)
        closest, pr, ba = _own_side(p, n_unit, closest, pr, ba, caster)
        if occluder is not None:
            closest, pr, ba = _bent_side(p, n_unit, closest, pr, ba, caster, occluder,
                                         face_normals)
    uv = np.einsum("mk,mkd->md", ba, atlas.corner_uvs[pr])
    return pr, ba, uv, np.linalg.norm(closest - p, axis=1)


#: a closest point further than this from a sample's normal lies behind its surface
BEHIND_DEG = 120.0


def _take_hits(pts: np.ndarray, idx: np.ndarray, dirs: np.ndarray, closest: np.ndarray,
               prim: np.ndarray, bary: np.ndarray, caster: RayCaster
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Samples `idx` take the point of M1 that a ray from them along `dirs` (one per sample,
    unit) hits, where it hits; the others keep theirs. Returns new arrays."""
    if idx.size == 0:
        return closest, prim, bary
    hits = caster.cast(pts[idx], dirs)
    got = np.flatnonzero(hits.hit)
    sel = idx[got]
    closest, prim, bary = closest.copy(), prim.copy(), bary.copy()
    closest[sel] = pts[sel] + hits.t[got, None] * dirs[got]
    prim[sel] = hits.prim[got]
    bary[sel] = hits.bary3()[got]
    return closest, prim, bary


def _own_side(pts: np.ndarray, n: np.ndarray, closest: np.ndarray, prim: np.ndarray,
              bary: np.ndarray, caster: RayCaster
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`assign_texels`' own-side rule: samples whose closest point on M1 is behind them take
    the hit of a ray along their (unit) normal `n` instead (where that ray hits M1)."""
    delta = closest - pts
    dist = np.linalg.norm(delta, axis=1)
    behind = np.einsum("ij,ij->i", delta, n) < math.cos(math.radians(BEHIND_DEG)) * dist
    # a sample on M1 itself (M1 = M_org where it is not simplified) has no side to be on
    far = dist > TOL.ray_offset * caster.bbox_diag
    idx = np.flatnonzero(behind & far)
    return _take_hits(pts, idx, n[idx], closest, prim, bary, caster)


#: a closest M1 face whose normal is further than this from a sample's faces another way
FACING_DEG = 60.0
#: hemisphere directions per sample for its bent normal
BENT_RAYS = 16


def _bent_side(pts: np.ndarray, n: np.ndarray, closest: np.ndarray, prim: np.ndarray,
               bary: np.ndarray, caster: RayCaster, occluder: RayCaster,
               face_normals: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`assign_texels`' bent-normal rule (see there; `n` unit normals), all candidates' rays
    in one batch."""
    from texelbake.geometry.basis import tangent_frames
    from texelbake.geometry.directions import hemisphere_directions
    from texelbake.geometry.raycast import offset_origins

    facing = np.einsum("ij,ij->i", face_normals[prim], n)
    idx = np.flatnonzero(facing < math.cos(math.radians(FACING_DEG)))
    if idx.size == 0:
        return closest, prim, bary
    local = hemisphere_directions(BENT_RAYS, seed=0)  # (K, 3)
    frames = tangent_frames(n[idx])  # (c, 3, 3)
    dirs = np.einsum("kj,cjl->ckl", local, frames).reshape(-1, 3)  # (c K, 3) world
    origins = offset_origins(pts[idx], n[idx], bbox_diag=occluder.bbox_diag)
    free = ~occluder.occluded(np.repeat(origins, BENT_RAYS, axis=0), dirs
                              ).reshape(idx.size, BENT_RAYS)
    bent = np.einsum("ck,ckj->cj", free.astype(np.float64), dirs.reshape(idx.size, BENT_RAYS, 3))
    length = np.linalg.norm(bent, axis=1)
    ok = free.any(axis=1) & (length > 1e-9)
    return _take_hits(pts, idx[ok], bent[ok] / length[ok, None], closest, prim, bary, caster)


def texel_surface_points(
    atlas: Atlas, level: int = 0
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The point of M1 under every texel centre at `level` (the "position map" a normal-map
    or albedo bake shoots rays from, and the texel footprint of rendering look-ups).

    returns : (points (N_ℓ², 3) float64, normals (N_ℓ², 3) float64 unit geometric normals of
        M1, face (N_ℓ²,) int64 M1 triangle or -1, valid (N_ℓ²,) bool — False where the centre
        is outside every chart; those rows are zero)
    """
    n_l = int(atlas.resolution) >> int(level)
    if n_l < 1:
        raise SettingsError(f"level {level} leaves no texels of the {atlas.resolution} atlas")
    face, bary, _ = rasterize_atlas(atlas.corner_uvs, n_l)
    valid = face >= 0
    safe = np.where(valid, face, 0)
    tri = atlas.mesh.triangles()[safe]  # (N_ℓ², 3, 3)
    points = np.where(valid[:, None], np.einsum("nk,nkd->nd", bary, tri), 0.0)
    normals = np.where(valid[:, None], atlas.mesh.face_normals()[safe], 0.0)
    return points, normals, face, valid
