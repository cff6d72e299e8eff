"""Dense, area-weighted, stratified point samples X on M_org (seed 000, §4.1).

Each sample x_j carries the quantities the apparent-reflectance matrix needs (seed 000,
Eq. 7: n_j, the material at x_j, and ΔA_j): its shading normal, material id, texture
coordinates of M_org and the area ΔA_j it stands for. Counts per triangle follow its area
(largest remainder), every triangle of nonzero area gets at least one sample, and the
samples of one triangle share its area equally, so Σ_j ΔA_j equals the surface area up to
floating-point summation.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np

from texelbake.errors import ShapeError
from texelbake.geometry.mesh import (
    bbox_diagonal,
    check_faces,
    check_points,
    face_normals,
    triangle_areas,
)
from texelbake.tol import TOL

# fractional part of the golden ratio: the Kronecker (Fibonacci-lattice) step of the
# second coordinate of the per-triangle stratified point set
_GOLDEN = 0.6180339887498949


@dataclass(frozen=True, eq=False)
class Samples:
    """m surface samples.

    positions : (m, 3) float64
    normals : (m, 3) float64 unit shading normals (corner normals interpolated, else geometric)
    face : (m,) int64 triangle of M_org holding the sample
    bary : (m, 3) float64 barycentric weights of the triangle's corners
    uv : (m, 2) float64 M_org texture coordinates (zeros when none were given)
    material : (m,) int32 material index (zeros when none was given)
    area : (m,) float64 ΔA_j
    """

    positions: np.ndarray
    normals: np.ndarray
    face: np.ndarray
    bary: np.ndarray
    uv: np.ndarray
    material: np.ndarray
    area: np.ndarray

    def __len__(self) -> int:
        return int(self.positions.shape[0])

    def subset(self, index: np.ndarray) -> Samples:
        """Samples at `index` ((k,) int64 or (m,) bool)."""
        return Samples(
            self.positions[index],
            self.normals[index],
            self.face[index],
            self.bary[index],
            self.uv[index],
            self.material[index],
            self.area[index],
        )


def empty_samples() -> Samples:
    return Samples(
        np.zeros((0, 3)),
        np.zeros((0, 3)),
        np.zeros(0, np.int64),
        np.zeros((0, 3)),
        np.zeros((0, 2)),
        np.zeros(0, np.int32),
        np.zeros(0),
    )


def allocate_counts(areas: np.ndarray, n_samples: int, eps_area: float = 0.0) -> np.ndarray:
    """Samples per triangle: one for every triangle with area > eps_area, the remaining
    n_samples - (#such triangles) split in proportion to area by largest remainder (ties
    broken by triangle index).

    areas : (f,) float64
    returns : (f,) int64 summing to max(n_samples, #triangles with area > eps_area)
    """
    areas = np.asarray(areas, dtype=np.float64)
    live = areas > eps_area
    counts = live.astype(np.int64)
    rest = int(n_samples) - int(counts.sum())
    total = float(areas[live].sum())
    if rest <= 0 or total <= 0:
        return counts
    quota = np.where(live, areas, 0.0) * (rest / total)  # (f,)
    base = np.floor(quota).astype(np.int64)
    left = rest - int(base.sum())
    if left > 0:
        order = np.argsort(-(quota - base), kind="stable")
        base[order[:left]] += 1
    return counts + base


#: every triangle gets a sample while the triangles are at most this many times the requested
#: count (small features stay represented); a finer mesh gets this many times the request, drawn
#: by area (`systematic_counts`), so the samples, and every stage that reads them, follow the
#: atlas and not the triangle count (a 1.5 M-triangle wall at a 16² atlas: 1.5 M samples, the
#: a_vis tile ~9 G ray pairs, before; 65 k after, `benchmarks/million.py`)
SAMPLES_PER_REQUEST_CAP = 4


def systematic_counts(areas: np.ndarray, eps_area: float, m: int, seed: int
                      ) -> tuple[np.ndarray, np.ndarray]:
    """m samples over the triangles with area > eps_area by systematic sampling of their
    cumulative area in face order: sample k falls at (k + o) / m of the total area (o in
    [0, 1) from the seed), in the triangle whose share of the cumulative area holds it. Every
    sample then stands for total / m of the surface: returns (counts (f,) int64 summing to m,
    represented area (f,) float64 = counts · total / m, what `SurfaceSampler` splits among a
    triangle's samples). Unbiased: a triangle's expected represented area is its area, and
    any run of consecutive faces is represented to within total / m of its area."""
    a = np.where(np.asarray(areas, dtype=np.float64) > eps_area, areas, 0.0)
    cum = np.cumsum(a)
    total = float(cum[-1]) if cum.size else 0.0
    if m <= 0 or total <= 0.0:
        return np.zeros(a.shape[0], np.int64), np.zeros(a.shape[0])
    offset = float(np.random.default_rng([int(seed), 0x5359]).random())
    u = (np.arange(m, dtype=np.float64) + offset) * (total / m)
    face = np.minimum(np.searchsorted(cum, u, side="right"), a.shape[0] - 1)
    counts = np.bincount(face, minlength=a.shape[0]).astype(np.int64)
    return counts, counts * (total / m)


def square_to_triangle(u: np.ndarray) -> np.ndarray:
    """Area-preserving map of the unit square onto the triangle (Heitz 2019, "A Low-Distortion
    Map Between Triangle and Square"), which keeps stratification better than the sqrt map.

    u : (m, 2) float64 in [0, 1)^2
    returns : (m, 3) float64 barycentric weights
    """
    u1 = u[:, 0]
    u2 = u[:, 1]
    upper = u2 > u1
    b0 = np.where(upper, 0.5 * u1, u1 - 0.5 * u2)
    b1 = np.where(upper, u2 - 0.5 * u1, 0.5 * u2)
    return np.column_stack([b0, b1, 1.0 - b0 - b1])


def stratified_unit_square(counts: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """For each triangle i, counts[i] points in [0,1)^2 forming a jittered Fibonacci lattice:
    point k is ((k + ξ) / c, frac(s + k φ)) with ξ uniform per point and a random shift s per
    triangle (Cranley–Patterson rotation), so each horizontal stratum of height 1/c holds one
    point and the second coordinate is low-discrepancy.

    counts : (f,) int64
    returns : (sum(counts), 2) float64, grouped by triangle in order
    """
    counts = np.asarray(counts, dtype=np.int64)
    m = int(counts.sum())
    starts = np.cumsum(counts) - counts
    tri = np.repeat(np.arange(counts.shape[0]), counts)  # (m,)
    k = np.arange(m, dtype=np.int64) - starts[tri]  # index inside the triangle
    shift = np.asarray(rng.random(counts.shape[0]))[tri]
    return _stratified(k, counts[tri], shift, rng.random(m))


def _stratified(k: np.ndarray, c: np.ndarray, shift: np.ndarray, jitter: np.ndarray
                ) -> np.ndarray:
    """Point k of a triangle with c points, its triangle's shift and its own jitter."""
    u1 = (k + jitter) / c.astype(np.float64)
    u2 = np.mod(shift + k * _GOLDEN, 1.0)
    return np.column_stack([np.minimum(u1, np.nextafter(1.0, 0.0)), u2])


#: samples whose attributes `sample_surface` computes at a time
SAMPLE_CHUNK = 1 << 20


class SurfaceSampler:
    """The samples of `sample_surface`, made a chunk of consecutive samples at a time.

    Every sample depends only on its triangle, its index inside the triangle, its triangle's
    shift and its own jitter; the jitters are one PCG64 stream drawn in sample order, so any
    chunking gives the same samples bit for bit (a test holds it). m : the sample count;
    total_area : Σ ΔA_j, the area of the sampled triangles (summed per triangle, not per
    sample, so it does not depend on the chunking either); uniform : every triangle is
    sampled at one density (no `face_density`)."""

    def __init__(self, pts, fcs, counts, areas, seed, corner_normals, corner_uvs,
                 face_material, uniform: bool = True, normal_input=None) -> None:
        self.pts, self.fcs, self.counts, self.areas = pts, fcs, counts, areas
        self.corner_normals, self.corner_uvs = corner_normals, corner_uvs
        self.face_material = face_material
        self.normal_input = normal_input
        self.uniform = bool(uniform)
        self.seed = int(seed)
        self.m = int(counts.sum())
        self.total_area = float(areas[counts > 0].sum())

    def chunks(self, chunk: int = SAMPLE_CHUNK) -> Iterator[tuple[int, Samples]]:
        """(first sample id, Samples) for consecutive blocks of at most `chunk` samples."""
        if self.m == 0:
            return
        pts, fcs, counts = self.pts, self.fcs, self.counts
        rng = np.random.default_rng(self.seed)
        shift = np.asarray(rng.random(counts.shape[0]))  # (f,) one per triangle, then jitters
        ends = np.cumsum(counts)
        starts = ends - counts
        face_geo = face_normals(pts, fcs)  # (f, 3); sampled faces are nondegenerate: unit
        share = self.areas / np.maximum(counts, 1)
        for a in range(0, self.m, int(chunk)):  # loop over chunks (memory bound)
            b = min(a + int(chunk), self.m)
            j = np.arange(a, b, dtype=np.int64)
            fa = np.searchsorted(ends, j, side="right")  # (k,) = np.repeat(range(f), counts)
            bary = square_to_triangle(
                _stratified(j - starts[fa], counts[fa], shift[fa], rng.random(b - a)))
            yield a, self._attributes(fa, bary, face_geo, share)

    def _attributes(self, fa, ba, face_geo, share) -> Samples:
        pts, corner = self.pts, self.fcs[fa]  # (k, 3) vertex ids; per-corner sums keep
        positions = (  # temporaries at (k, 3)
            ba[:, 0:1] * pts[corner[:, 0]]
            + ba[:, 1:2] * pts[corner[:, 1]]
            + ba[:, 2:3] * pts[corner[:, 2]]
        )
        geo = face_geo[fa]
        if self.corner_normals is None:
            normals = geo
        else:
            cn = self.corner_normals[fa]  # (k, 3, 3)
            interp = ba[:, 0:1] * cn[:, 0] + ba[:, 1:2] * cn[:, 1] + ba[:, 2:3] * cn[:, 2]
            length = np.linalg.norm(interp, axis=1, keepdims=True)
            good = (length[:, 0] > TOL.brdf_eps) & np.isfinite(length[:, 0])
            normals = np.where(good[:, None],
                               interp / np.where(good, length[:, 0], 1.0)[:, None], geo)
        uv = (np.einsum("mk,mkd->md", ba, self.corner_uvs[fa]) if self.corner_uvs is not None
              else np.zeros((len(fa), 2)))
        material = (np.zeros(len(fa), np.int32) if self.face_material is None
                    else self.face_material[fa])
        if self.normal_input is not None:  # the materials' normal maps
            normals = self.normal_input.apply(fa, ba, normals, uv, material)
        return Samples(positions, normals, fa.astype(np.int64), ba, uv, material, share[fa])


def surface_sampler(
    points: object,
    faces: object,
    n_samples: int,
    seed: int,
    *,
    corner_normals: object | None = None,
    corner_uvs: object | None = None,
    face_material: object | None = None,
    face_density: object | None = None,
    normal_input: object | None = None,
    eps: float = TOL.zero_area,
) -> SurfaceSampler:
    """`sample_surface`'s samples as a `SurfaceSampler` (same arguments, checked here)."""
    pts = check_points(points)
    fcs = check_faces(faces, pts.shape[0])
    f = fcs.shape[0]
    if corner_normals is not None:
        corner_normals = np.asarray(corner_normals, dtype=np.float64)
        if corner_normals.shape != (f, 3, 3):
            raise ShapeError(f"corner_normals must be ({f}, 3, 3), got {corner_normals.shape}")
    if corner_uvs is not None:
        corner_uvs = np.asarray(corner_uvs, dtype=np.float64)
        if corner_uvs.shape != (f, 3, 2):
            raise ShapeError(f"corner_uvs must be ({f}, 3, 2), got {corner_uvs.shape}")
    if face_material is not None:
        face_material = np.asarray(face_material)
        if face_material.shape != (f,):
            raise ShapeError(f"face_material must be ({f},), got {face_material.shape}")
        face_material = face_material.astype(np.int32)
    if face_density is not None:
        face_density = np.asarray(face_density, dtype=np.float64)
        if face_density.shape != (f,) or not np.all((face_density > 0) & (face_density <= 1)):
            raise ShapeError(f"face_density must be ({f},) in (0, 1], got shape "
                             f"{face_density.shape}")
    if f == 0 or int(n_samples) <= 0:
        counts, areas = np.zeros(f, np.int64), np.zeros(f)
    else:
        areas = triangle_areas(pts, fcs)  # (f,)
        eps_area = eps * bbox_diagonal(pts) ** 2
        cap = SAMPLES_PER_REQUEST_CAP * int(n_samples)
        if int(np.count_nonzero(areas > eps_area)) > cap:
            counts, areas = systematic_counts(areas, eps_area, cap, seed)
        elif face_density is None:
            counts = allocate_counts(areas, int(n_samples), eps_area)
        else:
            live = areas > eps_area
            dense = np.where(live, areas * face_density, 0.0)  # the density-weighted areas
            scale = float(dense.sum() / areas[live].sum()) if live.any() else 1.0
            counts = allocate_counts(dense, int(round(int(n_samples) * scale)), 0.0)
    return SurfaceSampler(pts, fcs, counts, areas, seed, corner_normals, corner_uvs,
                          face_material, uniform=face_density is None,
                          normal_input=normal_input)


def sample_surface(points: object, faces: object, n_samples: int, seed: int, *,
                   chunk: int = SAMPLE_CHUNK, **options: Any) -> Samples:
    """Area-weighted, per-triangle stratified samples of a triangle mesh.

    points : (n, 3) float64; faces : (f, 3) int64
    n_samples : requested count m; the result has max(m, #nondegenerate triangles) samples
        so every triangle with area > eps * bbox_diag**2 is represented (degenerate
        triangles get none), up to SAMPLES_PER_REQUEST_CAP · m: a mesh of more triangles
        gets that many samples drawn by area (`systematic_counts`)
    seed : seeds the jitter and shifts; equal inputs give byte-identical output
    options : `surface_sampler`'s keywords:
    corner_normals : (f, 3, 3) float64 or None — shading normals per face corner; where the
        interpolated normal is zero or not finite the sample takes the geometric normal
    corner_uvs : (f, 3, 2) float64 or None
    face_material : (f,) int32 or None
    face_density : (f,) float64 in (0, 1] or None — each face's sample density relative to the
        request's (`geometry.density`): the m · Σ d a / Σ a samples are split by d · area, and
        a face's samples still share its area, so Σ ΔA is the surface area. Not applied when the
        triangles outnumber SAMPLES_PER_REQUEST_CAP · m (they are drawn by area)
    normal_input : a `geometry.normal_input.NormalInput` of the mesh (its materials' normal
        maps decoded into the shading normals; needs face_material and corner_uvs) or None
    chunk : samples whose attributes are computed at a time (memory only: the result does
        not depend on it; `surface_sampler` gives the chunks without the whole)
    returns : Samples, grouped by triangle in face order; ΔA of a triangle's samples is
        its area / its count (its represented area / its count when drawn by area). Empty (typed) when nothing has area or n_samples <= 0.
    """
    sampler = surface_sampler(points, faces, n_samples, seed, **options)
    parts = [smp for _, smp in sampler.chunks(chunk)]
    if not parts:
        return empty_samples()
    if len(parts) == 1:
        return parts[0]
    return Samples(*(np.concatenate([getattr(p, k) for p in parts]) for k in
                     ("positions", "normals", "face", "bary", "uv", "material", "area")))
