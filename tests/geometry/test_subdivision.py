"""Catmull–Clark refinement with limit positions (texelbake.geometry.subdivision), checked
against closed forms of the B-spline surface a regular quad grid defines and against deep
refinement (a second method) at extraordinary vertices."""

from __future__ import annotations

import numpy as np
import pytest

from texelbake.errors import ShapeError
from texelbake.geometry.subdivision import SUBDIVISION_LEVELS, catmull_clark, refinement_levels


def _grid(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(n+1)^2 points at integer x, y with z = x^2 + y^2; (n^2,) counts, (4 n^2,) indices."""
    xs = np.arange(n + 1, dtype=np.float64)
    gx, gy = np.meshgrid(xs, xs, indexing="ij")
    pts = np.stack([gx.ravel(), gy.ravel(), (gx ** 2 + gy ** 2).ravel()], axis=1)
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    quads = np.stack([idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]], -1).reshape(-1)
    return pts, np.full(n * n, 4, dtype=np.int64), quads


def _cube() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    pts = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], dtype=float)
    quads = np.array([[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4],
                      [1, 5, 7, 3]])
    return pts, np.full(6, 4, dtype=np.int64), quads.reshape(-1)


def test_regular_grid_lands_on_its_bspline_surface():
    # a uniform cubic B-spline with control points c_i = i^2 is the curve x^2 + 1/3 (its value
    # at a knot is (c_{i-1} + 4 c_i + c_{i+1}) / 6), and x_i = i gives x exactly: the tensor
    # surface of z = x^2 + y^2 is z = x^2 + y^2 + 2/3 wherever the cage is regular (two rings
    # in from the boundary); every refined point lies on it (rounding only)
    pts, counts, quads = _grid(8)
    ref = catmull_clark(counts, quads, pts.shape[0], 2)
    p = ref.vertex_matrix @ pts
    inner = (p[:, :2].min(axis=1) >= 2) & (p[:, :2].max(axis=1) <= 6)
    assert inner.sum() > 200
    np.testing.assert_allclose(p[inner, 2], (p[inner, :2] ** 2).sum(axis=1) + 2 / 3, atol=1e-12)
    # the boundary y = 0 is the cubic B-spline of its own control points: x^2 + 1/3
    edge = (np.abs(p[:, 1]) < 1e-12) & (p[:, 0] >= 1) & (p[:, 0] <= 7)
    assert edge.sum() > 20
    np.testing.assert_allclose(p[edge, 2], p[edge, 0] ** 2 + 1 / 3, atol=1e-12)
    # edgeAndCorner: the four cage corners stay where they are
    for corner in (0, 8, 72, 80):
        assert np.min(np.linalg.norm(p - pts[corner], axis=1)) < 1e-12


def test_limit_positions_agree_with_deep_refinement_at_extraordinary_vertices():
    # the cube's corners have valence 3: their limit positions from the closed form after two
    # levels against seven levels of plain refinement, which converges to the limit at a rate
    # of ~4^-k of the cage's size (7 levels: ~1e-4 bound, 6e-7 seen)
    pts, counts, quads = _cube()
    exact = catmull_clark(counts, quads, 8, 2).vertex_matrix @ pts
    deep = catmull_clark(counts, quads, 8, 7, limit=False).vertex_matrix @ pts
    np.testing.assert_allclose(exact[:8], deep[:8], atol=1e-4)
    # the limit surface of a symmetric cage is symmetric: the corners at 0.25 and 0.75
    np.testing.assert_allclose(np.sort(np.unique(np.round(exact[:8], 9))), [0.25, 0.75])


def test_refinement_shapes_parents_and_affine_weights():
    # a pentagon and a triangle sharing an edge: each corner becomes one quad, then four
    pts = np.array([[0, 0, 0], [2, 0, 0], [3, 1.5, 0], [1, 3, 0], [-1, 1.5, 0], [1.5, -2, 0]],
                   dtype=float)
    counts, idx = np.array([5, 3]), np.array([0, 1, 2, 3, 4, 1, 0, 5])
    ref = catmull_clark(counts, idx, 6, 2)
    assert ref.counts.shape == (32,) and (ref.counts == 4).all()
    assert ref.indices.shape == (128,) and ref.indices.dtype == np.int64
    np.testing.assert_array_equal(np.bincount(ref.face_parent), [20, 12])
    # every refined point and face-varying value is an affine combination of the cage's
    np.testing.assert_allclose(ref.vertex_matrix.sum(axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(ref.fv_matrix.sum(axis=1), 1.0, atol=1e-12)
    assert ref.vertex_matrix.shape == (ref.num_points, 6) and ref.fv_matrix.shape == (128, 8)
    # a planar cage stays in its plane
    np.testing.assert_allclose((ref.vertex_matrix @ pts)[:, 2], 0.0, atol=1e-15)
    # face-varying values refine bilinearly: per cage corner c one child quad whose corners
    # hold c's value, the midpoint toward the next corner, the face's mean, the midpoint
    # from the previous corner
    one = catmull_clark(counts, idx, 6, 1)
    uv = (one.fv_matrix @ pts[idx, :2]).reshape(8, 4, 2)
    nxt = np.array([1, 2, 3, 4, 0, 6, 7, 5])
    prv = np.array([4, 0, 1, 2, 3, 7, 5, 6])
    face_mean = np.repeat([pts[idx[:5], :2].mean(0), pts[idx[5:], :2].mean(0)], [5, 3], axis=0)
    cage_uv = pts[idx, :2]
    np.testing.assert_allclose(uv[:, 0], cage_uv, atol=1e-15)
    np.testing.assert_allclose(uv[:, 1], (cage_uv + cage_uv[nxt]) / 2, atol=1e-15)
    np.testing.assert_allclose(uv[:, 2], face_mean, atol=1e-15)
    np.testing.assert_allclose(uv[:, 3], (cage_uv + cage_uv[prv]) / 2, atol=1e-15)


def test_levels_are_capped_by_the_quad_budget_and_bad_input_is_refused():
    # the Teapot's 1236 quads: one level (4944 quads); a cube's 6: five (6144 quads)
    assert refinement_levels(np.full(1236, 4)) == SUBDIVISION_LEVELS == 1
    assert refinement_levels(np.full(6, 4)) == 5
    assert refinement_levels(np.full(6, 4), max_levels=3) == 3
    assert refinement_levels(np.full(1000, 4), levels=2) == 2
    assert refinement_levels(np.full(1000, 4), 2, max_quads=10_000) == 1  # 16k > 10k at 2
    assert refinement_levels(np.full(10**6, 4), max_quads=10) == 1  # never below one level
    with pytest.raises(ShapeError, match="sum"):
        catmull_clark([4], [0, 1, 2], 3)
    with pytest.raises(ShapeError, match="out of"):
        catmull_clark([3], [0, 1, 5], 3)
    with pytest.raises(ShapeError, match="boundary"):
        catmull_clark([3], [0, 1, 2], 3, boundary="smooth")
