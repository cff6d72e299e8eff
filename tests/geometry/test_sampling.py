"""Surface sampling: ΔA sums, samples on the surface, stratification, determinism."""

from __future__ import annotations

import numpy as np
import pytest

from tests.helpers.meshes import bumpy_sphere, plane_grid, soup
from texelbake.errors import NumericalError, ShapeError
from texelbake.geometry.closest import closest_point_on_triangles
from texelbake.geometry.mesh import Mesh, bbox_diagonal, weld
from texelbake.geometry.raycast import RayCaster
from texelbake.geometry.sampling import (
    SAMPLES_PER_REQUEST_CAP,
    allocate_counts,
    sample_surface,
    square_to_triangle,
    stratified_unit_square,
    surface_sampler,
)


@pytest.fixture(scope="module")
def bumpy():
    return bumpy_sphere(3)  # 1280 faces


def test_sum_of_area_equals_surface_area(bumpy):
    v, f = bumpy
    s = sample_surface(v, f, 20_000, seed=1)
    total = Mesh(v, f).area()
    # acceptance: ΣΔA equals the area to 1e-9 relative (each triangle's share is area/count,
    # so only float summation error remains, ~1e-16 * sqrt(m))
    assert abs(s.area.sum() - total) <= 1e-9 * total
    assert s.area.dtype == np.float64 and (s.area > 0).all()


def test_samples_lie_on_the_surface(bumpy):
    v, f = bumpy
    s = sample_surface(v, f, 5_000, seed=2)
    diag = bbox_diagonal(v)
    # closest point on the whole mesh (Embree picks the triangle, float64 re-projection)
    closest, _, _ = RayCaster(v, f).closest_points(s.positions)
    dist = np.linalg.norm(closest - s.positions, axis=1)
    assert dist.max() < 1e-6 * diag
    # and the stated barycentrics rebuild the position on the stated face
    rebuilt = np.einsum("mk,mkd->md", s.bary, v[f[s.face]])
    np.testing.assert_allclose(rebuilt, s.positions, atol=1e-12 * diag)
    assert (s.bary >= -1e-15).all() and np.allclose(s.bary.sum(axis=1), 1.0)


def test_every_triangle_has_a_sample_and_counts_follow_area(bumpy):
    v, f = bumpy
    # add one degenerate (zero-area) triangle: it must get no sample
    f = np.vstack([f, [[0, 0, 1]]])
    n_req = 6_000
    s = sample_surface(v, f, n_req, seed=3)
    counts = np.bincount(s.face, minlength=f.shape[0])
    assert (counts[:-1] >= 1).all() and counts[-1] == 0
    assert counts.sum() == n_req
    # independent check of the allocation: 1 each + the rest proportional to area,
    # so each count is 1 + floor(quota) or 1 + ceil(quota)
    areas = Mesh(v, f).areas()[:-1]
    quota = (n_req - areas.shape[0]) * areas / areas.sum()
    assert ((counts[:-1] - 1 >= np.floor(quota)) & (counts[:-1] - 1 <= np.ceil(quota))).all()


def test_fewer_samples_than_triangles_still_covers_every_triangle():
    v, f = plane_grid(4, 4)  # 32 triangles: up to SAMPLES_PER_REQUEST_CAP x 8 requested
    assert f.shape[0] == SAMPLES_PER_REQUEST_CAP * 8
    s = sample_surface(v, f, 8, seed=0)
    assert len(s) == f.shape[0]
    assert np.array_equal(np.bincount(s.face), np.ones(f.shape[0], dtype=np.int64))


def test_a_mesh_far_finer_than_the_request_is_sampled_by_area():
    # 20,480 triangles of uneven area, 500 requested: 2,000 samples (the cap), not one per
    # triangle. Independent checks: the sample areas sum to the surface area (each stands for
    # total / m); any run of consecutive faces gets the area it has to within one sample's
    # share (systematic sampling of the cumulative area), so each eighth of the faces' area,
    # by the cumulative sum computed here, is represented to within total / m
    v, f = bumpy_sphere(5)
    n_req = 500
    m = SAMPLES_PER_REQUEST_CAP * n_req
    s = sample_surface(v, f, n_req, seed=4)
    assert len(s) == m < f.shape[0]
    areas = Mesh(v, f).areas()
    total = float(areas.sum())
    assert abs(s.area.sum() - total) <= 1e-9 * total
    np.testing.assert_allclose(s.area, total / m, rtol=1e-12)
    cum = np.concatenate([[0.0], np.cumsum(areas)])
    edges = np.searchsorted(cum, np.linspace(0.0, total, 9)[1:-1])  # face index per eighth
    for a, b in zip(np.concatenate([[0], edges]), np.concatenate([edges, [f.shape[0]]]),
                    strict=True):
        got = s.area[(s.face >= a) & (s.face < b)].sum()
        assert abs(got - (cum[b] - cum[a])) <= total / m * (1 + 1e-9)
    # the samples lie on their faces, reruns are identical, and another seed moves them
    rebuilt = np.einsum("mk,mkd->md", s.bary, v[f[s.face]])
    np.testing.assert_allclose(rebuilt, s.positions, atol=1e-12 * bbox_diagonal(v))
    again = sample_surface(v, f, n_req, seed=4)
    assert np.array_equal(again.positions, s.positions)
    assert not np.array_equal(sample_surface(v, f, n_req, seed=5).face, s.face)


def test_allocation_is_largest_remainder():
    counts = allocate_counts(np.array([1.0, 1.0, 2.0, 0.0]), 10)
    # 1 each for the 3 live triangles, 7 left: quotas 1.75, 1.75, 3.5 -> 1, 1, 3 + 2 by
    # remainder (0.75, 0.75 beat 0.5)
    assert counts.tolist() == [3, 3, 4, 0]


def test_seeded_determinism(bumpy):
    v, f = bumpy
    a = sample_surface(v, f, 3_000, seed=7)
    b = sample_surface(v, f, 3_000, seed=7)
    c = sample_surface(v, f, 3_000, seed=8)
    for name in ("positions", "normals", "face", "bary", "uv", "material", "area"):
        assert getattr(a, name).tobytes() == getattr(b, name).tobytes()
    assert not np.array_equal(a.positions, c.positions)


def test_stratified_beats_independent_sampling_on_one_triangle():
    # integral of x^2 over the triangle (0,0),(1,0),(0,1) is 1/12; its area is 1/2, so the
    # mean of x^2 over uniform points is 1/6
    v = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    f = np.array([[0, 1, 2]])
    n = 256
    errs = []
    for seed in range(20):
        s = sample_surface(v, f, n, seed=seed)
        errs.append(np.sum(s.area * s.positions[:, 0] ** 2) - 1.0 / 12.0)
    rms_strat = float(np.sqrt(np.mean(np.square(errs))))
    # iid uniform: std of x^2 is sqrt(E[x^4] - E[x^2]^2) = sqrt(1/15 - 1/36); times area/sqrt(n)
    rms_iid = 0.5 * np.sqrt(1.0 / 15.0 - 1.0 / 36.0) / np.sqrt(n)
    assert rms_strat < rms_iid / 4


def test_square_to_triangle_is_area_preserving():
    # a uniform grid of the square maps to points whose mean is the centroid (1/3 each)
    g = (np.arange(200) + 0.5) / 200
    u = np.stack(np.meshgrid(g, g), axis=-1).reshape(-1, 2)
    b = square_to_triangle(u)
    assert (b >= 0).all() and np.allclose(b.sum(axis=1), 1.0)
    np.testing.assert_allclose(b.mean(axis=0), [1 / 3, 1 / 3, 1 / 3], atol=1e-4)


def test_attributes_are_interpolated():
    v, f = plane_grid(3, 3, size=2.0)
    sv, sf = soup(v, f)
    rng = np.random.default_rng(0)
    corner_uvs = sv[sf][..., :2] * 0.5  # uv = (x, y) / 2, an affine function of position
    corner_normals = rng.normal(size=(sf.shape[0], 3, 3))
    material = np.arange(sf.shape[0], dtype=np.int32) % 3
    s = sample_surface(
        sv,
        sf,
        500,
        seed=0,
        corner_normals=corner_normals,
        corner_uvs=corner_uvs,
        face_material=material,
    )
    np.testing.assert_allclose(s.uv, s.positions[:, :2] * 0.5, atol=1e-14)
    expect = np.einsum("mk,mkd->md", s.bary, corner_normals[s.face])
    expect /= np.linalg.norm(expect, axis=1, keepdims=True)
    np.testing.assert_allclose(s.normals, expect, atol=1e-12)
    assert np.array_equal(s.material, material[s.face]) and s.material.dtype == np.int32
    # computed 37 samples at a time (the memory bound, issue 15): bit for bit the same
    parts = sample_surface(sv, sf, 500, seed=0, corner_normals=corner_normals,
                           corner_uvs=corner_uvs, face_material=material, chunk=37)
    for name in ("positions", "normals", "face", "bary", "uv", "material", "area"):
        assert np.array_equal(getattr(parts, name), getattr(s, name)), name


def test_geometric_normals_without_corner_normals(bumpy):
    v, f = bumpy
    s = sample_surface(v, f, 2_000, seed=0)
    np.testing.assert_allclose(s.normals, Mesh(v, f).face_normals()[s.face], atol=1e-15)


def test_empty_and_bad_inputs():
    s = sample_surface(np.zeros((0, 3)), np.zeros((0, 3), np.int64), 100, seed=0)
    assert s.positions.shape == (0, 3) and s.area.dtype == np.float64 and s.face.dtype == np.int64
    v, f = plane_grid(1, 1)
    assert len(sample_surface(v, f, 0, seed=0)) == 0
    bad = v.copy()
    bad[1, 2] = np.nan
    with pytest.raises(NumericalError, match="row 1"):
        sample_surface(bad, f, 10, seed=0)
    with pytest.raises(ShapeError, match="corner_normals"):
        sample_surface(v, f, 10, seed=0, corner_normals=np.zeros((5, 3, 3)))
    with pytest.raises(ShapeError, match="outside"):
        sample_surface(v, f + 10, 10, seed=0)


def test_weld_soup_recovers_mesh(bumpy):
    v, f = bumpy
    sv, sf = soup(v, f)
    welded, vmap, kept = weld(sv, sf)
    assert welded.num_vertices == v.shape[0] and kept.all()
    np.testing.assert_array_equal(welded.vertices[vmap], sv)
    np.testing.assert_allclose(welded.area(), Mesh(v, f).area(), rtol=1e-12)


def test_closest_point_on_triangles_is_the_projection():
    # a point q of a convex set is the projection of p iff (p - q).(x - q) <= 0 for every x
    # of the set; for a triangle checking the three corners suffices
    rng = np.random.default_rng(4)
    n = 2000
    a, b, c = (rng.normal(size=(n, 3)) for _ in range(3))
    p = rng.normal(size=(n, 3)) * 2
    q, w = closest_point_on_triangles(p, a, b, c)
    assert (w >= -1e-12).all() and np.allclose(w.sum(axis=1), 1.0)
    for x in (a, b, c):
        assert (np.einsum("nd,nd->n", p - q, x - q) <= 1e-9).all()


def test_bad_corner_normals_fall_back_to_geometric():
    v, f = plane_grid(2, 2)
    cn = np.zeros((f.shape[0], 3, 3))  # zero normals everywhere
    cn[0] = np.nan  # and NaN on face 0
    s = sample_surface(v, f, 64, seed=0, corner_normals=cn)
    np.testing.assert_array_equal(s.normals, np.tile([0.0, 0.0, 1.0], (len(s), 1)))


def test_chunked_sampler_draws_the_one_shot_stratified_set(bumpy):
    """`SurfaceSampler.chunks` draws the jitters a chunk at a time from one PCG64 stream (the
    geometry stage spools 16.8 M samples at 512²): its barycentrics equal those of the
    one-shot `stratified_unit_square` over all counts, for chunks of 1, 37 and everything,
    and Σ ΔA is the sampler's per-triangle total."""
    v, f = bumpy
    sampler = surface_sampler(v, f, 3_000, seed=5)
    expect = square_to_triangle(stratified_unit_square(sampler.counts,
                                                       np.random.default_rng(5)))
    for chunk in (1, 37, sampler.m):
        parts = list(sampler.chunks(chunk))
        assert [a for a, _ in parts] == list(range(0, sampler.m, chunk))
        bary = np.concatenate([p.bary for _, p in parts])
        assert bary.tobytes() == expect.tobytes(), chunk
    area = np.concatenate([p.area for _, p in sampler.chunks(100)])
    assert area.sum() == pytest.approx(sampler.total_area, rel=1e-12)
    assert sampler.total_area == pytest.approx(Mesh(v, f).area(), rel=1e-12)
