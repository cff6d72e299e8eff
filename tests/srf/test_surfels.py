"""Surface reflectance fields, item 2: impostor surfels carrying p0, r0 and (u0, v0)
spanning an elliptical footprint (seed 002 §5.1, Table 1)."""

from __future__ import annotations

import numpy as np
import pytest

from tests.helpers.render import icosphere
from texelbake.deform.impostor import decode_frames
from texelbake.errors import SettingsError, ShapeError
from texelbake.srf.surfels import surfels_from_mesh


def _random_points_in(v, f, n, seed=0):
    rng = np.random.default_rng(seed)
    face = rng.integers(0, len(f), n)
    b = rng.random((n, 2))
    flip = b.sum(axis=1) > 1
    b[flip] = 1 - b[flip]
    t = v[f[face]]
    return face, t[:, 0] + b[:, :1] * (t[:, 1] - t[:, 0]) + b[:, 1:] * (t[:, 2] - t[:, 0])


def _covered_by_every_corner(s, n=4000):
    face, x = _random_points_in(s.mesh_vertices, s.mesh_faces, n)
    ok = np.ones(n, bool)
    for k in range(3):
        c = s.mesh_faces[face, k]
        d = x - s.p0[c]
        a = np.einsum("ij,ij->i", d, s.u0[c]) / s.su[c]
        b = np.einsum("ij,ij->i", d, s.v0[c]) / s.sv[c]
        ok &= a * a + b * b <= 1.0 + 1e-9
    return ok


def test_surfels_cover_their_triangles_and_carry_table1():
    pts, faces = icosphere(1)
    s = surfels_from_mesh(pts, faces, spacing=0.2)
    e = np.concatenate([s.mesh_faces[:, [0, 1]], s.mesh_faces[:, [1, 2]]])
    assert np.linalg.norm(s.mesh_vertices[e[:, 0]] - s.mesh_vertices[e[:, 1]], axis=1).max() <= 0.2
    assert len(s) == len(s.mesh_vertices) > len(pts)
    assert _covered_by_every_corner(s).all()
    rot = decode_frames(s.r0, s.u0, s.v0)  # Table 1: R0 from the stored Rodrigues vector
    np.testing.assert_allclose(rot[:, :, 0], s.u0, atol=1e-9)
    np.testing.assert_allclose(rot[:, :, 1], s.v0, atol=1e-9)
    # outward normals on the sphere
    assert np.all(np.einsum("ij,ij->i", s.normal, s.p0) > 0.9 * np.linalg.norm(s.p0, axis=1))


def test_anisotropic_mesh_gets_elliptical_footprints():
    # a strip 1 x 0.05 of long thin triangles
    xs = np.linspace(0, 1, 3)
    v = np.array([[x, y, 0.0] for y in (0.0, 0.05) for x in xs])
    f = np.array([[0, 1, 4], [0, 4, 3], [1, 2, 5], [1, 5, 4]])
    s = surfels_from_mesh(v, f, spacing=1.0)
    assert np.any(np.maximum(s.su, s.sv) > 3 * np.minimum(s.su, s.sv))
    assert _covered_by_every_corner(s).all()


def test_surfel_errors():
    with pytest.raises(ShapeError, match="faces"):
        surfels_from_mesh(np.zeros((3, 3)), np.zeros((0, 3), np.int64))
    with pytest.raises(ShapeError, match="NaN"):
        surfels_from_mesh(np.full((3, 3), np.nan), [[0, 1, 2]])
    with pytest.raises(ShapeError, match="indices"):
        surfels_from_mesh(np.eye(3), [[0, 1, 3]])
    with pytest.raises(SettingsError, match="spacing"):
        surfels_from_mesh(np.eye(3), [[0, 1, 2]], spacing=0.0)
