"""RayCaster: analytic hits on a plane, occlusion against a box, batching, empty input."""

from __future__ import annotations

import numpy as np
import pytest

from tests.helpers.meshes import box, icosphere
from texelbake.errors import NumericalError, ShapeError
from texelbake.geometry.closest import closest_point_on_triangles
from texelbake.geometry.raycast import RayCaster, _finite_rows, _nonzero_rows, offset_origins
from texelbake.tol import TOL

# Embree works in float32: distances of order 1 carry ~1e-7 relative error, and an
# intersection computed from float32 origins/directions is good to a few ulps of the
# coordinates, so 1e-5 absolute is a safe bound at unit scale.
F32_ATOL = 1e-5

PLANE_V = np.array([[-1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [1.0, 1.0, 0.0], [-1.0, 1.0, 0.0]])
PLANE_F = np.array([[0, 1, 2], [0, 2, 3]])


def _slab(o: np.ndarray, d: np.ndarray, lo: np.ndarray, hi: np.ndarray):
    """Independent ray/box test (slab method): entry and exit t per ray, inf when missed."""
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        t1 = (lo - o) * inv
        t2 = (hi - o) * inv
    tmin = np.nanmax(np.minimum(t1, t2), axis=1)
    tmax = np.nanmin(np.maximum(t1, t2), axis=1)
    hit = (tmax >= np.maximum(tmin, 0.0)) & (tmax > 0)
    return np.where(hit, np.maximum(tmin, 0.0), np.inf), np.where(hit, tmax, np.inf)


def test_ray_hits_plane_at_analytic_t(rng):
    caster = RayCaster(PLANE_V, PLANE_F)
    n = 5000
    target = np.column_stack([rng.uniform(-0.95, 0.95, size=(n, 2)), np.zeros(n)])
    height = rng.uniform(0.1, 3.0, size=n)
    dirs = rng.normal(size=(n, 3))
    dirs[:, 2] = -np.abs(dirs[:, 2]) - 0.2  # always downwards
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    # origin above the target along -dir, at height h: t = h / |d_z|
    t_true = height / -dirs[:, 2]
    origins = target - t_true[:, None] * dirs
    hits = caster.cast(origins, dirs * rng.uniform(0.5, 2.0, size=(n, 1)))  # lengths ignored
    assert hits.hit.all()
    np.testing.assert_allclose(hits.t, t_true, rtol=1e-5, atol=F32_ATOL)
    # triangle 0 holds x >= y, triangle 1 holds y > x (away from the diagonal)
    clear = np.abs(target[:, 0] - target[:, 1]) > 1e-4
    assert np.array_equal(hits.prim[clear], (target[clear, 1] > target[clear, 0]).astype(int))
    rebuilt = np.einsum("nk,nkd->nd", hits.bary3(), PLANE_V[PLANE_F[hits.prim]])
    np.testing.assert_allclose(rebuilt, target, atol=F32_ATOL)
    np.testing.assert_allclose(hits.normal, np.tile([0.0, 0.0, 1.0], (n, 1)), atol=1e-7)
    assert caster.rays_cast == n


def test_rays_that_miss():
    caster = RayCaster(PLANE_V, PLANE_F)
    o = np.array([[0.0, 0.0, 1.0], [5.0, 5.0, 1.0], [0.0, 0.0, 1.0]])
    d = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [0.0, 0.0, 0.0]])  # away, outside, zero
    hits = caster.cast(o, d)
    assert not hits.hit.any()
    assert np.isinf(hits.t).all() and (hits.prim == -1).all()
    assert not caster.occluded(o, d).any()


def test_occlusion_against_a_box(rng):
    lo, hi = np.array([0.0, 0.0, 0.0]), np.array([1.0, 2.0, 0.5])
    v, f = box(lo, hi)
    caster = RayCaster(v, f)
    n = 20_000
    origins = rng.uniform(-2.0, 3.0, size=(n, 3))
    inside = ((origins > lo - 0.01) & (origins < hi + 0.01)).all(axis=1)
    origins, n = origins[~inside], int((~inside).sum())
    # aim rays at random points around the box so both outcomes are common
    aim = rng.uniform(lo - 0.5, hi + 0.5, size=(n, 3))
    dirs = aim - origins
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    t_in, t_out = _slab(origins, dirs, lo, hi)
    # drop rays that only graze an edge or corner (chord shorter than float32 noise)
    with np.errstate(invalid="ignore"):
        chord = np.where(np.isfinite(t_in), t_out - t_in, np.inf)
    clear = chord > 1e-4
    occ = caster.occluded(origins, dirs)
    assert np.array_equal(occ[clear], np.isfinite(t_in)[clear])
    assert 0.1 < occ.mean() < 0.9  # the test sees both outcomes
    hits = caster.cast(origins, dirs)
    sel = clear & np.isfinite(t_in)
    np.testing.assert_allclose(hits.t[sel], t_in[sel], atol=F32_ATOL)
    # tmax: a scalar or per-ray segment ending before the box is not occluded
    hit_idx = np.flatnonzero(sel & (t_in > 0.01))
    short = t_in[hit_idx] * 0.99
    long = t_in[hit_idx] * 1.01
    assert not caster.occluded(origins[hit_idx], dirs[hit_idx], tmax=short).any()
    assert caster.occluded(origins[hit_idx], dirs[hit_idx], tmax=long).all()
    mixed = np.where(np.arange(hit_idx.shape[0]) % 2 == 0, short, np.inf)
    got = caster.occluded(origins[hit_idx], dirs[hit_idx], tmax=mixed)
    assert np.array_equal(got, np.arange(hit_idx.shape[0]) % 2 == 1)
    assert not caster.occluded(origins[hit_idx], dirs[hit_idx], tmax=0.0).any()


def test_batch_boundaries_do_not_change_results(rng):
    v, f = icosphere(2)
    caster = RayCaster(v, f)
    n = 1001
    o = rng.uniform(-2, 2, size=(n, 3))
    d = rng.normal(size=(n, 3))
    tmax = rng.uniform(0.1, 4.0, size=n)
    big_occ = caster.occluded(o, d, tmax=tmax)
    big_hit = caster.cast(o, d)
    for batch in (1, 7, 1000):
        assert np.array_equal(caster.occluded(o, d, tmax=tmax, batch=batch), big_occ)
        h = caster.cast(o, d, batch=batch)
        assert np.array_equal(h.t, big_hit.t) and np.array_equal(h.prim, big_hit.prim)
        assert np.array_equal(h.bary, big_hit.bary)
    pts, prim, bary = caster.closest_points(o, batch=13)
    pts2, prim2, bary2 = caster.closest_points(o)
    assert np.array_equal(prim, prim2) and np.array_equal(pts, pts2)


def test_empty_input_gives_typed_empty_arrays():
    caster = RayCaster(PLANE_V, PLANE_F)
    e = np.zeros((0, 3))
    occ = caster.occluded(e, e)
    assert occ.shape == (0,) and occ.dtype == bool
    h = caster.cast(e, e)
    assert h.t.shape == (0,) and h.t.dtype == np.float64
    assert h.prim.shape == (0,) and h.prim.dtype == np.int64
    assert h.bary.shape == (0, 2) and h.normal.shape == (0, 3)
    p, prim, b = caster.closest_points(e)
    assert p.shape == (0, 3) and prim.dtype == np.int64 and b.shape == (0, 2)
    # an empty scene: nothing is hit
    empty = RayCaster(np.zeros((0, 3)), np.zeros((0, 3), np.int64))
    assert not empty.occluded(np.zeros((2, 3)), np.ones((2, 3))).any()
    assert (empty.cast(np.zeros((2, 3)), np.ones((2, 3))).prim == -1).all()


def test_closest_points_match_brute_force(rng):
    v, f = icosphere(1)
    caster = RayCaster(v, f)
    q = rng.normal(size=(300, 3)) * 1.5
    pts, prim, bary = caster.closest_points(q)
    # brute force: project every query onto every triangle in float64
    tri = v[f]
    m = q.shape[0]
    qq = np.repeat(q, f.shape[0], axis=0)
    cand, _ = closest_point_on_triangles(
        qq, np.tile(tri[:, 0], (m, 1)), np.tile(tri[:, 1], (m, 1)), np.tile(tri[:, 2], (m, 1))
    )
    best = np.linalg.norm(cand - qq, axis=1).reshape(m, -1).min(axis=1)
    got = np.linalg.norm(pts - q, axis=1)
    # Embree ranks triangles in float32: the chosen one is optimal up to ~1e-6 at unit scale
    np.testing.assert_allclose(got, best, atol=1e-6)
    rebuilt = np.einsum("nk,nkd->nd", np.column_stack([1 - bary.sum(axis=1), bary]), tri[prim])
    np.testing.assert_allclose(rebuilt, pts, atol=1e-12)
    assert caster.points_queried == m


def test_offset_origins_and_input_checks():
    p = np.array([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0]])
    n = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0]])
    out = offset_origins(p, n)
    np.testing.assert_allclose(out - p, n * TOL.ray_offset * 2.0)
    np.testing.assert_allclose(offset_origins(p, n, 0.5) - p, 0.5 * n)
    np.testing.assert_allclose(offset_origins(p, n, bbox_diag=10.0) - p, n * TOL.ray_offset * 10)
    caster = RayCaster(PLANE_V, PLANE_F)
    with pytest.raises(ShapeError, match="origins"):
        caster.occluded(np.zeros((3, 2)), np.zeros((3, 2)))
    with pytest.raises(ShapeError, match="dirs"):
        caster.cast(np.zeros((3, 3)), np.zeros((4, 3)))
    with pytest.raises(NumericalError):
        RayCaster(np.full((3, 3), np.nan), np.array([[0, 1, 2]]))
    with pytest.raises(ShapeError):
        RayCaster(PLANE_V, PLANE_F + 4)


def test_offset_origins_avoid_self_hits(rng):
    v, f = icosphere(3)
    caster = RayCaster(v, f)
    prim = rng.integers(0, f.shape[0], 4000)
    w = rng.dirichlet(np.ones(3), size=4000)
    pts = np.einsum("nk,nkd->nd", w, v[f[prim]])
    nrm = np.cross(v[f[prim, 1]] - v[f[prim, 0]], v[f[prim, 2]] - v[f[prim, 0]])
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    # from outside a convex sphere, rays into the outer hemisphere never hit it
    d = rng.normal(size=(4000, 3))
    d *= np.sign(np.einsum("nd,nd->n", d, nrm))[:, None]
    assert not caster.occluded(offset_origins(pts, nrm, bbox_diag=caster.bbox_diag), d).any()


def test_non_finite_rays_are_not_cast():
    caster = RayCaster(PLANE_V, PLANE_F)
    o = np.array([[0.0, 0.0, 1.0], [np.nan, 0.0, 1.0], [0.0, 0.0, 1.0], [0.1, 0.1, 1.0]])
    d = np.array([[0.0, 0.0, -1.0], [0.0, 0.0, -1.0], [np.inf, 0.0, -1.0], [0.0, 0.0, -1.0]])
    assert caster.occluded(o, d).tolist() == [True, False, False, True]
    assert caster.occluded(o, d, tmax=np.array([2.0, 2.0, 2.0, np.nan])).tolist() == [
        True,
        False,
        False,
        False,
    ]
    assert caster.cast(o, d).hit.tolist() == [True, False, False, True]
    with pytest.raises(ShapeError, match="tmax"):
        caster.occluded(o, d, tmax=np.ones(3))


def test_rays_outside_float32_are_dead_not_cast():
    """Rays to infinity are checked on the float32 block Embree receives
    (`raycast._escape_block`): an origin or direction beyond float32's range, or a direction
    whose components all round to 0 there, is never occluded, as NaN and zero rays are; the
    rays beside them are unaffected (a batch-wide flag would clear or keep them all)."""
    caster = RayCaster(PLANE_V, PLANE_F)
    o = np.array([[0.0, 0.0, 1.0], [1e300, 0.0, 1.0], [0.0, 0.0, 1.0], [0.1, 0.1, 1.0],
                  [0.0, 0.0, 1.0]])
    d = np.array([[0.0, 0.0, -1.0], [0.0, 0.0, -1.0], [0.0, 0.0, -1e-50], [0.0, 0.0, -1.0],
                  [0.0, -1e39, -1.0]])
    assert caster.occluded(o, d).tolist() == [True, False, False, True, False]
    # the same rays in batches of one: each ray's answer is its own
    assert caster.occluded(o, d, batch=1).tolist() == [True, False, False, True, False]


def test_occluded_pairs_equals_occluded_on_the_gathered_rays():
    """`occluded_pairs(o, d, jj, dd)` answers `occluded(o[jj], d[dd])`, on a box with rays from
    inside, outside and beyond float32 (those and zero directions dead), whatever the batch;
    indices out of range are refused."""
    v, f = box()
    caster = RayCaster(v, f)
    rng = np.random.default_rng(3)
    o = np.concatenate([rng.uniform(-0.5, 1.5, (40, 3)), [[1e300, 0.0, 0.0], [np.nan, 0, 0]]])
    d = np.concatenate([rng.normal(size=(30, 3)), [[0.0, 0.0, 0.0], [0.0, 1e-50, 0.0]]])
    jj = np.concatenate([rng.integers(0, 42, 900), [40, 41, 7, 8]])
    dd = np.concatenate([rng.integers(0, 32, 900), [3, 5, 30, 31]])
    want = caster.occluded(o[jj], d[dd])
    assert 0.2 < want.mean() < 0.9
    assert np.array_equal(caster.occluded_pairs(o, d, jj, dd), want)
    assert np.array_equal(caster.occluded_pairs(o, d, jj, dd, batch=7), want)
    assert not caster.occluded_pairs(o, d, jj[-4:], dd[-4:]).any()
    ok = (jj < 40) & (dd < 30)  # every ray live: the path that skips the liveness gathers
    assert np.array_equal(caster.occluded_pairs(o[:40], d[:30], jj[ok], dd[ok], batch=64),
                          want[ok])
    with pytest.raises(ShapeError):
        caster.occluded_pairs(o, d, np.array([42]), np.array([0]))
    with pytest.raises(ShapeError):
        caster.occluded_pairs(o, d, jj, dd[:-1])
    with pytest.raises(ShapeError):
        caster.occluded_pairs(o[:, :2], d, jj, dd)


def test_row_checks_on_the_bits_equal_numpys_reductions():
    """`_finite_rows` and `_nonzero_rows` answer `np.isfinite(a).all(axis=1)` and
    `np.any(a != 0, axis=1)` on every kind of float32: random bit patterns (NaNs, infinities,
    denormals among them) and rows of ±0, inf, NaN and the smallest denormal."""
    rng = np.random.default_rng(11)
    bits = rng.integers(0, 2**32, size=(20000, 3), dtype=np.uint64).astype(np.uint32)
    special = np.array([0.0, -0.0, np.inf, -np.inf, np.nan, 1e-45, 1.0], np.float32)
    rows = special[np.stack(np.meshgrid(*[np.arange(7)] * 3), -1).reshape(-1, 3)]
    for a in (bits.view(np.float32), rows):
        with np.errstate(invalid="ignore"):
            assert np.array_equal(_finite_rows(a), np.isfinite(a).all(axis=1))
            assert np.array_equal(_nonzero_rows(a), np.any(a != 0, axis=1))
