"""Batched ray casting and closest points over open3d's Embree scene.

`RayCaster` wraps `open3d.t.geometry.RaycastingScene` (Embree, float32): arrays of rays go in
as large batches (default 2**20 rays), no Python per ray. Directions are normalized here, so
every distance is in scene units along a unit direction.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np
import open3d as o3d

from texelbake.errors import ShapeError
from texelbake.geometry.closest import closest_point_on_triangles
from texelbake.geometry.mesh import bbox_diagonal, check_faces, check_points
from texelbake.tol import TOL

DEFAULT_BATCH = 2**20
#: rounds of re-casting past cut-out hits: a ray still on a cut surface after this many
#: layers is taken to pass them all (stacked foliage cards are a few layers deep)
MAX_CUTOUT_ROUNDS = 16


class CutoutTest(Protocol):
    """What a caster asks of cut-out surfaces (`texelbake.brdf.opacity.Cutout`).

    faces : (f,) bool, the faces that can be cut
    cut(prim (k,) int64, bary (k, 2) float64) -> (k,) bool: the hit is on a cut point
    cut_uv(prim (k,) int64, uv (k, 2) float64) -> (k,) bool: the point at the mesh's uv is cut
    """

    @property
    def faces(self) -> np.ndarray: ...

    def cut(self, prim: np.ndarray, bary: np.ndarray) -> np.ndarray: ...

    def cut_uv(self, prim: np.ndarray, uv: np.ndarray) -> np.ndarray: ...


@dataclass(frozen=True, eq=False)
class RayHits:
    """First hits of n rays.

    t : (n,) float64 distance along the unit direction, inf when missed
    prim : (n,) int64 triangle index, -1 when missed
    bary : (n, 2) float64 (u, v): hit = (1 - u - v) p0 + u p1 + v p2 of triangle `prim`
        (open3d's convention); zeros when missed
    normal : (n, 3) float64 unit geometric normal of the hit triangle; zeros when missed
    """

    t: np.ndarray
    prim: np.ndarray
    bary: np.ndarray
    normal: np.ndarray

    @property
    def hit(self) -> np.ndarray:
        """(n,) bool."""
        return self.prim >= 0

    def bary3(self) -> np.ndarray:
        """(n, 3) float64 barycentric weights of (p0, p1, p2)."""
        return np.column_stack([1.0 - self.bary[:, 0] - self.bary[:, 1], self.bary])


def _coerce_points(x: object, name: str) -> np.ndarray:
    """x as (n, 3) float64 (no copy when it already is), shape checked."""
    a = np.asarray(x, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3:
        raise ShapeError(f"{name} must have shape (n, 3), got {a.shape}")
    return a


def _coerce_rays(origins: object, dirs: object) -> tuple[np.ndarray, np.ndarray]:
    """origins, dirs as (n, 3) float64 (no copy when they already are), shapes checked."""
    o = _coerce_points(origins, "origins")
    d = np.asarray(dirs, dtype=np.float64)
    if d.shape != o.shape:
        raise ShapeError(f"dirs must have the shape of origins {o.shape}, got {d.shape}")
    return o, d


def _ray_lengths(o: np.ndarray, d: np.ndarray) -> np.ndarray:
    """(n,) length of each direction, 0 for rays that cannot be cast (zero, NaN or Inf
    direction or NaN/Inf origin)."""
    length = np.sqrt(np.einsum("ij,ij->i", d, d))
    fin = np.isfinite(o)  # columns combined by hand: all(axis=1) over 3 is a slow reduction
    bad = ~(np.isfinite(length) & fin[:, 0] & fin[:, 1] & fin[:, 2])
    if bad.any():
        length = np.where(bad, 0.0, length)
    return length


def _check_rays(origins: object, dirs: object) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Coerce rays; return (origins (n,3), dirs (n,3) as given, `_ray_lengths`)."""
    o, d = _coerce_rays(origins, dirs)
    return o, d, _ray_lengths(o, d)


_ONES6 = np.ones(6, dtype=np.float32)
_ONES3 = np.ones(3, dtype=np.float32)
_HARMLESS = (0.0, 0.0, 0.0, 0.0, 0.0, 1.0)


def _escape_block(o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(b, 6) float32 rays [o, d] for rays with no tmax, and (b,) live, read off the float32
    block Embree gets: a ray with a non-finite entry there (NaN, inf, beyond float32's range) or
    a direction whose three float32 components are 0 is dead (never occluded) and made harmless.
    One cast and two matrix-vector products instead of float64 lengths and finiteness tests of
    the input (17 % of the a_vis stage was spent checking rays)."""
    rays = np.empty((o.shape[0], 6), dtype=np.float32)
    with np.errstate(invalid="ignore", over="ignore"):
        rays[:, :3] = o
        rays[:, 3:] = d
        # NaN and inf propagate through the sum (inf - inf is NaN)
        live = np.isfinite(rays @ _ONES6) & (np.abs(rays[:, 3:]) @ _ONES3 > 0)
    if not live.all():
        rays[~live] = _HARMLESS
    return rays, live


_EXPONENT = np.uint32(0x7F800000)
_MAGNITUDE = np.uint32(0x7FFFFFFF)


def _finite_rows(a32: np.ndarray) -> np.ndarray:
    """(k,) bool: every entry of the row of (k, 3) float32 `a32` is finite, read off the bits
    (all exponent bits set: inf or NaN). The same as `np.isfinite(a32).all(axis=1)`, without
    numpy's slow reduction over rows of three (docs/decisions.md, "A ray's checks and
    directions are paid once per texel")."""
    u = a32.view(np.uint32)
    return ((u[:, 0] & _EXPONENT) != _EXPONENT) & ((u[:, 1] & _EXPONENT) != _EXPONENT) & \
        ((u[:, 2] & _EXPONENT) != _EXPONENT)


def _nonzero_rows(a32: np.ndarray) -> np.ndarray:
    """(k,) bool: the row of (k, 3) float32 `a32` has an entry other than ±0 (NaN counts),
    as `np.any(a32 != 0, axis=1)` but on the bits (`_finite_rows`)."""
    u = a32.view(np.uint32)
    return ((u[:, 0] | u[:, 1] | u[:, 2]) & _MAGNITUDE) != 0


def _ray_block(o: np.ndarray, d: np.ndarray, scale: np.ndarray | None, live: np.ndarray | None):
    """(b, 6) float32 rays [o, d * scale]; rays not `live` become harmless (origin 0, dir +z)."""
    rays = np.empty((o.shape[0], 6), dtype=np.float32)
    with np.errstate(invalid="ignore", over="ignore"):  # dead rays are overwritten below
        rays[:, :3] = o
        if scale is None:
            rays[:, 3:] = d
        else:
            rays[:, 3:] = d * scale[:, None]
    if live is not None and not live.all():
        rays[~live] = _HARMLESS
    return rays


def offset_origins(
    points: object, normals: object, eps: float | None = None, *, bbox_diag: float | None = None
) -> np.ndarray:
    """Move ray origins off the surface along the normal to avoid self-intersection.

    points : (n, 3) float64
    normals : (n, 3) float64, unit (oriented to the side the rays leave from)
    eps : absolute offset; default TOL.ray_offset * bbox_diag (bbox of `points` when
        `bbox_diag` is not given; pass the scene's diagonal for consistency across batches)
    returns : (n, 3) float64
    """
    p = np.asarray(points, dtype=np.float64)
    nrm = np.asarray(normals, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or nrm.shape != p.shape:
        raise ShapeError(f"points and normals must both be (n, 3), got {p.shape} and {nrm.shape}")
    if eps is None:
        diag = bbox_diagonal(p) if bbox_diag is None else float(bbox_diag)
        eps = TOL.ray_offset * diag
    return p + float(eps) * nrm


class RayCaster:
    """Ray queries against one triangle mesh (built once).

    points : (n, 3) float64, faces : (f, 3) int64. Stored in Embree as float32.
    nthreads : 0 = open3d's default (all cores).
    cutout : a `CutoutTest` (None: every face is opaque). With one, `cast` and `occluded` pass
        through cut points: open3d's Embree scene takes no any-hit filter, so a ray whose
        hit is cut is cast again from just past it, the rays of a batch together, for at most
        `MAX_CUTOUT_ROUNDS` rounds; an occlusion test's occluded rays are cast to find their
        first uncut hit. Without one every query is the plain Embree call.
    Attributes `rays_cast` and `points_queried` count the work done, for rays/s figures.
    """

    def __init__(self, points: object, faces: object, *, nthreads: int = 0,
                 cutout: CutoutTest | None = None) -> None:
        pts = check_points(points)
        fcs = check_faces(faces, pts.shape[0])
        if cutout is not None and np.asarray(cutout.faces).shape != (fcs.shape[0],):
            raise ShapeError(f"cutout.faces must be ({fcs.shape[0]},), got "
                             f"{np.asarray(cutout.faces).shape}")
        self.cutout = cutout
        self.points = pts
        self.faces = fcs
        self.nthreads = int(nthreads)
        self.bbox_diag = bbox_diagonal(pts)
        self.rays_cast = 0
        self.points_queried = 0
        self._scene = o3d.t.geometry.RaycastingScene(nthreads=self.nthreads)
        if fcs.shape[0] > 0:
            # kept on the instance: from_numpy shares memory with these arrays
            self._vertices32 = np.ascontiguousarray(pts, dtype=np.float32)
            self._faces32 = np.ascontiguousarray(fcs, dtype=np.uint32)
            self._scene.add_triangles(
                o3d.core.Tensor.from_numpy(self._vertices32),
                o3d.core.Tensor.from_numpy(self._faces32),
            )
        self._empty = fcs.shape[0] == 0

    @property
    def num_faces(self) -> int:
        return int(self.faces.shape[0])

    def occluded(
        self,
        origins: object,
        dirs: object,
        tmax: float | np.ndarray = np.inf,
        batch: int = DEFAULT_BATCH,
    ) -> np.ndarray:
        """True where the ray from origin along dir hits the mesh at 0 < t < tmax.

        origins, dirs : (n, 3) float64 (dirs need not be unit; zero / non-finite rays are
            never occluded)
        tmax : scalar or (n,) float64 distance along the unit direction (inf allowed;
            NaN or <= 0 means not occluded)
        returns : (n,) bool
        """
        out = self._occluded_opaque(origins, dirs, tmax, batch)
        if self.cutout is not None and out.any():
            o, d = _coerce_rays(origins, dirs)
            idx = np.flatnonzero(out)
            tm = np.broadcast_to(np.asarray(tmax, dtype=np.float64), (o.shape[0],))
            out[idx] = self._cast_through(o[idx], d[idx], batch).t < tm[idx]
        return out

    def _occluded_opaque(self, origins: object, dirs: object, tmax: float | np.ndarray,
                         batch: int) -> np.ndarray:
        o, d = _coerce_rays(origins, dirs)
        n = o.shape[0]
        tm = np.asarray(tmax, dtype=np.float64)
        if tm.ndim and tm.shape != (n,):
            raise ShapeError(f"tmax must be a scalar or ({n},), got {tm.shape}")
        out = np.zeros(n, dtype=bool)
        if n == 0 or self._empty:
            return out
        self.rays_cast += n
        batch = max(int(batch), 1)
        if tm.ndim == 0 and np.isinf(tm) and tm > 0:
            # the common case: directions go to Embree as given (it does not need unit ones)
            for start in range(0, n, batch):  # a loop over large batches, not rays
                sl = slice(start, min(start + batch, n))
                rays, lv = _escape_block(o[sl], d[sl])
                out[sl] = self._test(rays, np.inf) & lv
            return out
        length = _ray_lengths(o, d)
        live = length > 0
        # Embree takes one scalar tfar per call: rays with a finite tmax get their direction
        # scaled to length tmax and tfar = 1; those with tmax = inf keep tfar = inf.
        tm = np.broadcast_to(tm, (n,))
        finite = live & np.isfinite(tm) & (tm > 0)
        infinite = live & (tm == np.inf)
        for group, tfar in ((finite, 1.0), (infinite, np.inf)):
            idx = np.flatnonzero(group)
            for start in range(0, idx.shape[0], batch):
                sel = idx[start : start + batch]
                scale = tm[sel] / length[sel] if tfar == 1.0 else None
                out[sel] = self._test(_ray_block(o[sel], d[sel], scale, None), tfar)
        return out

    def occluded_pairs(self, origins: object, dirs: object, jj: np.ndarray, dd: np.ndarray,
                       batch: int = DEFAULT_BATCH) -> np.ndarray:
        """`occluded(origins[jj], dirs[dd])` (tmax inf), with Embree's float32 rays built from
        the pairs directly: a sample's origin is paired with many directions (a_vis, the
        visibility of R), so the float64 gathers and per-ray checks of `occluded` are skipped.
        A ray whose origin or direction has a non-finite float32 entry, or whose direction is
        0 in float32, is dead (never occluded), as in `occluded`.

        origins : (a, 3), dirs : (b, 3) float64; jj, dd : (k,) int indices into them
        returns : (k,) bool
        """
        o, d = _coerce_points(origins, "origins"), _coerce_points(dirs, "dirs")
        jj, dd = np.asarray(jj, dtype=np.int64), np.asarray(dd, dtype=np.int64)
        if jj.shape != dd.shape or jj.ndim != 1:
            raise ShapeError(f"jj and dd must be (k,) alike, got {jj.shape} and {dd.shape}")
        n = jj.shape[0]
        out = np.zeros(n, dtype=bool)
        if n == 0 or self._empty:
            return out
        for name, idx, size in (("jj", jj, o.shape[0]), ("dd", dd, d.shape[0])):
            if idx.min() < 0 or idx.max() >= size:
                raise ShapeError(f"{name} out of [0, {size})")
        self.rays_cast += n
        with np.errstate(invalid="ignore", over="ignore"):
            o32, d32 = o.astype(np.float32), d.astype(np.float32)
        live_o = _finite_rows(o32)
        live_d = _finite_rows(d32) & _nonzero_rows(d32)
        if not live_o.all():
            o32[~live_o] = _HARMLESS[:3]
        if not live_d.all():
            d32[~live_d] = _HARMLESS[3:]
        # a point as one 12-byte item: np.take of items (indices checked above, so mode
        # "clip" clips nothing and skips the buffered bounds check) into a contiguous block,
        # then copied as float32 columns into the ray block's halves: ~4x numpy's fancy
        # indexing of (k, 3) rows, and ~1.7x a take straight into the strided halves (numpy
        # copies void items to a strided `out` one by one)
        o_item = o32.view("V12").ravel()
        d_item = d32.view("V12").ravel()
        all_live = bool(live_o.all() and live_d.all())
        batch = max(int(batch), 1)
        for start in range(0, n, batch):  # a loop over large batches, not rays
            sl = slice(start, start + batch)
            k = jj[sl].shape[0]
            rays = np.empty((k, 6), dtype=np.float32)
            rays[:, :3] = np.take(o_item, jj[sl], mode="clip").view(np.float32).reshape(k, 3)
            rays[:, 3:] = np.take(d_item, dd[sl], mode="clip").view(np.float32).reshape(k, 3)
            hit = self._test(rays, np.inf)
            out[sl] = hit if all_live else hit & live_o[jj[sl]] & live_d[dd[sl]]
        if self.cutout is not None and out.any():
            idx = np.flatnonzero(out)
            out[idx] = self._cast_through(o[jj[idx]], d[dd[idx]], batch).hit
        return out

    def _test(self, rays: np.ndarray, tfar: float) -> np.ndarray:
        res = self._scene.test_occlusions(
            o3d.core.Tensor.from_numpy(rays), tfar=tfar, nthreads=self.nthreads
        )
        return res.numpy()

    def cast(self, origins: object, dirs: object, batch: int = DEFAULT_BATCH) -> RayHits:
        """First hit of each ray (see RayHits).

        origins, dirs : (n, 3) float64 (dirs need not be unit; zero / non-finite rays miss)
        """
        if self.cutout is None:
            return self._cast_opaque(origins, dirs, batch)
        o, d = _coerce_rays(origins, dirs)
        return self._cast_through(o, d, batch)

    def _cast_through(self, o: np.ndarray, d: np.ndarray, batch: int) -> RayHits:
        """First uncut hits: the rays whose hit is cut are cast again from past it (t is
        still measured from the original origin); after MAX_CUTOUT_ROUNDS they miss."""
        cutout = self.cutout
        assert cutout is not None  # only called with one
        hits = self._cast_opaque(o, d, batch)
        t, prim, bary, normal = hits.t.copy(), hits.prim.copy(), hits.bary.copy(), \
            hits.normal.copy()
        length = _ray_lengths(o, d)
        unit = d / np.where(length > 0, length, 1.0)[:, None]
        step = TOL.ray_offset * self.bbox_diag
        todo = np.flatnonzero(prim >= 0)
        for _ in range(MAX_CUTOUT_ROUNDS):  # a few rounds, each one batch of every ray left
            todo = todo[cutout.faces[prim[todo]]]
            todo = todo[cutout.cut(prim[todo], bary[todo])]
            if todo.size == 0:
                break
            start = t[todo] + step
            again = self._cast_opaque(o[todo] + start[:, None] * unit[todo], unit[todo], batch)
            t[todo] = start + again.t
            prim[todo], bary[todo], normal[todo] = again.prim, again.bary, again.normal
            todo = todo[again.prim >= 0]
        else:
            todo = todo[cutout.faces[prim[todo]]]
            todo = todo[cutout.cut(prim[todo], bary[todo])]
        if todo.size:  # still on a cut surface: passes them all
            t[todo], prim[todo], bary[todo], normal[todo] = np.inf, -1, 0.0, 0.0
        return RayHits(t, prim, bary, normal)

    def _cast_opaque(self, origins: object, dirs: object, batch: int) -> RayHits:
        o, d, length = _check_rays(origins, dirs)
        n = o.shape[0]
        t = np.full(n, np.inf)
        prim = np.full(n, -1, dtype=np.int64)
        bary = np.zeros((n, 2))
        normal = np.zeros((n, 3))
        if n == 0 or self._empty:
            return RayHits(t, prim, bary, normal)
        self.rays_cast += n
        live = length > 0
        inv_len = np.divide(1.0, length, out=np.zeros_like(length), where=live)
        invalid = np.uint32(o3d.t.geometry.RaycastingScene.INVALID_ID)
        batch = max(int(batch), 1)
        for start in range(0, n, batch):
            sl = slice(start, min(start + batch, n))
            rays = _ray_block(o[sl], d[sl], inv_len[sl], live[sl])  # unit directions
            res = self._scene.cast_rays(o3d.core.Tensor.from_numpy(rays), nthreads=self.nthreads)
            pid = res["primitive_ids"].numpy()
            hit = (pid != invalid) & live[sl]
            t[sl] = np.where(hit, res["t_hit"].numpy().astype(np.float64), np.inf)
            prim[sl] = np.where(hit, pid.astype(np.int64), -1)
            bary[sl] = np.where(hit[:, None], res["primitive_uvs"].numpy(), 0.0)
            normal[sl] = np.where(hit[:, None], res["primitive_normals"].numpy(), 0.0)
        return RayHits(t, prim, bary, normal)

    def closest_points(
        self, queries: object, batch: int = DEFAULT_BATCH
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Closest point on the mesh to each query.

        Embree (float32) picks the triangle; the point and barycentrics are then recomputed
        on that triangle in float64, so they are exact for the chosen triangle.
        queries : (n, 3) float64
        returns : (points (n, 3) float64, prim (n,) int64, bary (n, 2) float64 (u, v) with
            point = (1 - u - v) p0 + u p1 + v p2). With an empty mesh: NaN points, prim -1.
        """
        q = check_points(queries, "queries")
        n = q.shape[0]
        if self._empty or n == 0:
            return np.full((n, 3), np.nan), np.full(n, -1, dtype=np.int64), np.zeros((n, 2))
        self.points_queried += n
        prim = np.empty(n, dtype=np.int64)
        batch = max(int(batch), 1)
        for start in range(0, n, batch):
            stop = min(start + batch, n)
            res = self._scene.compute_closest_points(
                o3d.core.Tensor.from_numpy(np.ascontiguousarray(q[start:stop], dtype=np.float32)),
                nthreads=self.nthreads,
            )
            prim[start:stop] = res["primitive_ids"].numpy().astype(np.int64)
        tri = self.points[self.faces[prim]]  # (n, 3, 3)
        points, w = closest_point_on_triangles(q, tri[:, 0], tri[:, 1], tri[:, 2])
        return points, prim, np.ascontiguousarray(w[:, 1:])
