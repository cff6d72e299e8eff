"""Linear-blend skinning from a rest pose that is not the bind pose (`deform.lbs`): against a
closed-form rig (points made in bind space, posed by explicit per-point sums), the
near-singular blend it refuses, and the shapes and errors."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tests.helpers.meshes import random_rotation
from texelbake.deform.lbs import SkinWarp, bind_points, rest_inverse, skin_blend
from texelbake.errors import ShapeError


def _rigid(rng: np.random.Generator, scale: float = 1.0) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = scale * random_rotation(rng)
    m[:3, 3] = rng.normal(size=3)
    return m


def _rz(deg: float) -> np.ndarray:
    m = np.eye(4)
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    m[:2, :2] = [[c, -s], [s, c]]
    return m


def test_skin_blend_reproduces_skinning_from_bind_space():
    """q in bind space, p = Σ_j w_j B_j q at rest: bind_points(p) = q and skin_blend(p) at any
    T is Σ_j w_j T_j q, each sum written out per point (no shared code with the module)."""
    rng = np.random.default_rng(11)
    n, j = 40, 5
    rest = np.stack([_rigid(rng) for _ in range(j)])
    now = np.stack([_rigid(rng, 1.0 + 0.2 * k) for k in range(j)])  # scales too
    w = rng.random((n, j)) ** 4  # uneven blends, yet moderate relative rotations
    w /= w.sum(axis=1, keepdims=True)
    rest[:, :3, :3] = np.eye(3)  # B_j: translations only, but for two rotated joints
    rest[1, :3, :3] = _rz(40.0)[:3, :3]  # (moderate angles: well-conditioned blends)
    rest[3, :3, :3] = _rz(-25.0)[:3, :3]
    q = rng.normal(size=(n, 3))
    p = np.array([sum(w[i, k] * (rest[k, :3, :3] @ q[i] + rest[k, :3, 3]) for k in range(j))
                  for i in range(n)])
    got_q, valid = bind_points(rest, w, p)
    assert valid.all()
    np.testing.assert_allclose(got_q, q, atol=1e-10)
    want = np.array([sum(w[i, k] * (now[k, :3, :3] @ q[i] + now[k, :3, 3]) for k in range(j))
                     for i in range(n)])
    pos, jac, ok = skin_blend(now, w, p, rest)
    assert ok.all() and pos.shape == (n, 3) and jac.shape == (n, 3, 3)
    np.testing.assert_allclose(pos, want, atol=1e-10)
    # the Jacobian with the weights held fixed, by central differences of the per-point map
    e = 1e-6
    for axis in range(3):
        d = np.zeros(3)
        d[axis] = e
        fd = (skin_blend(now, w, p + d, rest)[0] - skin_blend(now, w, p - d, rest)[0]) / (2 * e)
        np.testing.assert_allclose(fd, jac[:, :, axis], atol=1e-7)
    # at the rest pose every point stays put; SkinWarp on its own vertices is the same map
    np.testing.assert_allclose(skin_blend(rest, w, p, rest)[0], p, atol=1e-12)
    faces = np.array([[0, 1, 2]])
    warp = SkinWarp(now, p, faces, w, rest_transforms=rest)
    np.testing.assert_allclose(warp.positions(p), want, atol=1e-10)
    # without rest transforms T_j maps rest to deformed directly: Σ_j w_j T_j p
    direct = np.array([sum(w[i, k] * (now[k, :3, :3] @ p[i] + now[k, :3, 3]) for k in range(j))
                       for i in range(n)])
    np.testing.assert_allclose(skin_blend(now, w, p)[0], direct, atol=1e-10)


def test_a_near_singular_rest_blend_is_flagged():
    """Two joints 50/50 whose rest rotations differ by θ: the blend's σ_min / σ_max is
    cos(θ/2), flagged below TOL.skin_blend_cond = 0.05 (θ > 174.3°)."""
    p = np.array([[0.3, 0.2, 0.1]])
    w = np.array([[0.5, 0.5]])
    for theta, ok in ((170.0, True), (176.0, False), (180.0, False)):
        rest = np.stack([np.eye(4), _rz(theta)])
        inv, valid = rest_inverse(rest, w)
        assert bool(valid[0]) is ok, theta
        assert np.isfinite(inv).all()
        assert bool(skin_blend(rest, w, p, rest)[2][0]) is ok
    # a point with no influence: valid, stays at rest
    pos, jac, valid = skin_blend(np.stack([_rz(30.0), _rz(60.0)]), np.zeros((1, 2)), p,
                                 np.stack([np.eye(4), _rz(180.0)]))
    np.testing.assert_array_equal(pos, p)
    np.testing.assert_array_equal(jac[0], np.eye(3))
    assert valid.all()


def test_lbs_shapes_and_errors():
    with pytest.raises(ShapeError, match="weights"):
        skin_blend(np.stack([np.eye(4)] * 2), np.ones((3, 3)) / 3, np.zeros((3, 3)))
    with pytest.raises(ShapeError, match="weights"):
        skin_blend(np.stack([np.eye(4)] * 2), np.ones((2, 2)) / 2, np.zeros((3, 3)))
    with pytest.raises(ShapeError, match=r"\(n, 3\)"):
        bind_points(np.stack([np.eye(4)] * 2), np.ones((3, 2)) / 2, np.zeros((3, 2)))
    q, valid = bind_points(np.stack([np.eye(4)] * 2), np.zeros((0, 2)), np.zeros((0, 3)))
    assert q.shape == (0, 3) and valid.shape == (0,)
