"""Seed 002 §4: warps and their Jacobians, the local impostor parameterization (Table 1) and
the look-up rotation L (Eqs. 7–10), each against an independent computation."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tests.helpers.render import icosphere
from texelbake.deform import impostor as imp
from texelbake.deform.lbs import SkinWarp, transfer_weights
from texelbake.deform.lookup import (
    deformed_tangents,
    interpolate,
    lookup_rotation,
    orthogonalize,
    rest_frames_at,
)
from texelbake.deform.warps import (
    AffineWarp,
    MeshWarp,
    central_jacobian,
    parse_warp,
    triangle_jacobians,
)
from texelbake.errors import SettingsError, ShapeError

BOUNDS = np.array([[-0.3, 0.0, -0.2], [0.3, 2.0, 0.2]])


def _rng_points(n=200, seed=0):
    rng = np.random.default_rng(seed)
    return BOUNDS[0] + rng.random((n, 3)) * (BOUNDS[1] - BOUNDS[0])


def _random_rotation(seed=1):
    q, _ = np.linalg.qr(np.random.default_rng(seed).normal(size=(3, 3)))
    return q * np.sign(np.linalg.det(q))


# --------------------------------------------------------------------------- warps


@pytest.mark.parametrize("spec", ["twist:angle=90", "bend:angle=90", "bend:angle=-60,toward=z",
                                  "sine:amplitude=0.1,periods=2", "stretch:x=1,y=2,z=1",
                                  "rigid:angle=40,axis=x,tx=1"])
def test_exact_jacobian_matches_central_differences(spec):
    w = parse_warp(spec, BOUNDS)
    p = _rng_points()
    jac = w.jacobian(p)
    assert jac.shape == (len(p), 3, 3)
    for k in range(3):  # Eq. 6 along each axis, at the justified step
        d = np.zeros_like(p)
        d[:, k] = 1.0
        cd = central_jacobian(w, p, d)
        # truncation ~ ε² |Ψ'''| with ε = 1e-5 · diag: ~1e-9 here
        np.testing.assert_allclose(cd, jac[:, :, k], atol=1e-7)


def test_bend_and_twist_closed_forms():
    p = _rng_points()
    bend = parse_warp("bend:angle=90", BOUNDS)
    r = 2.0 / (math.pi / 2)  # length / angle
    # points on the axis (x = z = 0) land on the arc of radius R about (R, 0, 0)
    axis_pts = np.column_stack([np.zeros(20), np.linspace(0, 2, 20), np.zeros(20)])
    q = bend.positions(axis_pts)
    np.testing.assert_allclose(np.linalg.norm(q - [r, 0, 0], axis=1), r, atol=1e-12)
    np.testing.assert_allclose(q[-1], [r, r, 0], atol=1e-12)  # quarter circle: ends at (R, R)
    twist = parse_warp("twist:angle=90", BOUNDS)
    q = twist.positions(p)
    np.testing.assert_allclose(np.hypot(q[:, 0], q[:, 2]), np.hypot(p[:, 0], p[:, 2]),
                               atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(twist.jacobian(p)), 1.0, atol=1e-12)  # isochoric


def test_parse_warp_errors_name_the_field():
    with pytest.raises(SettingsError, match="unknown warp 'wobble'"):
        parse_warp("wobble:angle=3", BOUNDS)
    with pytest.raises(SettingsError, match=r"warp\.angel"):
        parse_warp("twist:angel=90", BOUNDS)
    with pytest.raises(SettingsError, match=r"warp\.angle.*number"):
        parse_warp("twist:angle=ninety", BOUNDS)
    with pytest.raises(SettingsError, match=r"warp\.axis"):
        parse_warp("bend:axis=w", BOUNDS)
    with pytest.raises(SettingsError, match=r"warp\.toward"):
        parse_warp("bend:axis=y,toward=y", BOUNDS)
    with pytest.raises(SettingsError, match="key=value"):
        parse_warp("twist:90", BOUNDS)


def test_mesh_warp_triangle_jacobian_is_the_affine_map_in_plane():
    v, f = icosphere(1)
    a = np.array([[1.0, 0.3, 0.0], [0.0, 2.0, 0.1], [0.2, 0.0, 0.7]])
    jac, ok = triangle_jacobians(v, v @ a.T, f)
    assert ok.all()
    e1 = v[f[:, 1]] - v[f[:, 0]]
    np.testing.assert_allclose(np.einsum("nij,nj->ni", jac, e1), e1 @ a.T, atol=1e-12)
    q = _random_rotation()
    jac, _ = triangle_jacobians(v, v @ q.T, f)
    np.testing.assert_allclose(jac, np.broadcast_to(q, jac.shape), atol=1e-12)
    mw = MeshWarp(v, 1.5 * v @ q.T + 1.0, f)  # a similarity: reproduced exactly
    # inside, and outside where the closest point is a corner or an edge (the M_i vertices)
    pts = np.concatenate([0.9 * v[:10], 1.3 * v[:10], 1.2 * (v[f[:5, 0]] + v[f[:5, 1]]) / 2])
    np.testing.assert_allclose(mw.positions(pts), 1.5 * pts @ q.T + 1.0, atol=1e-9)
    np.testing.assert_allclose(mw.jacobian(pts), np.broadcast_to(1.5 * q, (25, 3, 3)),
                               atol=1e-9)
    with pytest.raises(ShapeError):
        MeshWarp(v, v[:-1], f)


def test_mesh_warp_vertex_jacobians_are_interpolated():
    # a twist's own Jacobian at the vertices, interpolated on the closest rest triangle: equal
    # to it at the vertices and the barycentric mix inside (a coarse triangle's affine map is
    # one constant J, the twist's varies across it); positions are the affine map's
    v, f = icosphere(1)
    tw = parse_warp("twist:angle=90", np.array([v.min(axis=0), v.max(axis=0)]))
    jv = tw.jacobian(v)
    mw = MeshWarp(v, tw.positions(v), f, vertex_jacobians=jv)
    np.testing.assert_allclose(mw.jacobian(v), jv, atol=1e-12)
    bary = np.array([0.2, 0.3, 0.5])
    inside = np.einsum("k,nkj->nj", bary, v[f])
    np.testing.assert_allclose(mw.jacobian(inside), np.einsum("k,nkij->nij", bary, jv[f]),
                               atol=1e-9)
    tri = MeshWarp(v, tw.positions(v), f)
    np.testing.assert_allclose(mw.positions(inside), tri.positions(inside), atol=1e-12)
    assert np.abs(tri.jacobian(v) - jv).max() > 0.05  # the constant per-triangle field
    with pytest.raises(ShapeError, match="vertex_jacobians"):
        MeshWarp(v, v, f, vertex_jacobians=jv[:-1])


def test_skin_warp_jacobian_and_no_influence():
    v, f = icosphere(1)
    rng = np.random.default_rng(3)
    w = rng.random((len(v), 2))
    w[0] = 0.0  # a vertex with no skin influence
    m = np.stack([np.eye(4), np.eye(4)])
    m[1, :3, :3] = _random_rotation(4)
    m[1, :3, 3] = [0.2, -0.1, 0.3]
    skin = SkinWarp(m, v, f, w)
    pos = skin.positions(v)
    jac = skin.jacobian(v)
    np.testing.assert_allclose(pos[0], v[0], atol=0)  # stays at rest
    np.testing.assert_allclose(jac[0], np.eye(3), atol=0)
    # J = Σ w_j A_j: the derivative of p ↦ Σ w_j (A_j p + t_j) with the weights held fixed
    wn = w / np.maximum(w.sum(axis=1, keepdims=True), 1e-300)
    for k in range(3):
        e = np.zeros(3)
        e[k] = 1e-6
        fixed = [sum(wn[i, j] * (m[j, :3, :3] @ x + m[j, :3, 3]) for j in range(2))
                 + (1 - wn[i].sum()) * x for i, x in ((i, v[i] + s * e) for i in range(1, 5)
                                                      for s in (1, -1))]
        cd = (np.array(fixed[0::2]) - np.array(fixed[1::2])) / 2e-6
        np.testing.assert_allclose(cd, jac[1:5, :, k], atol=1e-8)
    # transferred weights: bounded influences, renormalised
    tw = transfer_weights(0.99 * v, v, f, rng.random((len(v), 6)), max_influences=4)
    assert ((tw > 0).sum(axis=1) <= 4).all()
    np.testing.assert_allclose(tw.sum(axis=1), 1.0, atol=1e-12)


# --------------------------------------------------------------------------- Rodrigues


def test_rodrigues_round_trip_and_near_180():
    rng = np.random.default_rng(5)
    axis = rng.normal(size=(50, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    ang = np.concatenate([rng.uniform(0, math.pi, 45),
                          math.pi - np.array([1e-3, 1e-5, 1e-7, 0.0, 0.0])])
    r = axis * np.tan(ang / 2)[:, None]
    r[-2:] = 0.0
    rot = np.stack([imp._skew(axis[i:i + 1])[0] for i in range(50)])
    mats = np.eye(3)[None] + np.sin(ang)[:, None, None] * rot + (
        1 - np.cos(ang))[:, None, None] * (rot @ rot)  # Rodrigues' rotation formula
    got, valid = imp.matrix_to_rodrigues(mats)
    assert not valid[-2:].any() and valid[:-2].all()  # 180° (to rounding): reported, no inf
    assert np.isfinite(got).all()
    np.testing.assert_allclose(got[:-3], r[:-3], rtol=1e-8, atol=1e-12)
    back = imp.rodrigues_to_matrix(got[:-2])
    np.testing.assert_allclose(back, mats[:-2], atol=1e-9)


def test_impostor_frames_stay_away_from_180_over_the_whole_sphere():
    v, f = icosphere(2)
    v = np.concatenate([v, [[0, 0, -1.0], [0, 0, 1.0]]])  # exact poles (isolated: no faces)
    nrm = np.concatenate([v[:-2], [[0, 0, -1.0], [0, 0, 1.0]]])
    # frames for arbitrary normals, incl. n0 = −z exactly, through a one-triangle-per-normal
    # mesh: a tiny triangle facing each normal
    base = imp.tangent_frames(nrm)
    tri_v = np.concatenate([v, v + 1e-3 * base[:, 0], v + 1e-3 * base[:, 1]])
    n = len(v)
    tri_f = np.column_stack([np.arange(n), np.arange(n) + n, np.arange(n) + 2 * n])
    uv = np.tile(np.array([[0, 0], [1.0, 0], [0, 1.0]]), (n, 1, 1))
    params = imp.impostor_params(tri_v, tri_f, uv)
    r0 = imp.decode_frames(params.r0[:n], params.u0[:n], params.v0[:n])
    ang = np.degrees(imp.rotation_angle(imp.rodrigues_to_matrix(params.r0[:n])))
    assert ang.max() <= imp.MAX_ANGLE_DEG, ang.max()
    # R0 decodes to (u0, v0, n0), n0 the face normal, u0 a quarter turn of the atlas tangent
    np.testing.assert_allclose(r0[:, :, 0], params.u0[:n], atol=1e-12)
    np.testing.assert_allclose(r0[:, :, 1], params.v0[:n], atol=1e-12)
    np.testing.assert_allclose(r0[:, :, 2], nrm, atol=1e-9)
    along = np.abs(np.einsum("ij,ij->i", params.u0[:n], base[:, 0]))
    across = np.abs(np.einsum("ij,ij->i", params.u0[:n], base[:, 1]))
    np.testing.assert_allclose(np.maximum(along, across), 1.0, atol=1e-9)
    # without the lower-hemisphere flip, n0 = −z would be a 180° rotation
    assert np.degrees(imp.rotation_angle(r0[-2:-1]))[0] == pytest.approx(180.0)


# --------------------------------------------------------------------------- look-up


def _mesh_params():
    v, f = icosphere(2)
    v = v * [0.3, 1.0, 0.3] + [0, 1.0, 0]
    rng = np.random.default_rng(2)
    uv = rng.random((len(f), 3, 2))
    return v, f, imp.impostor_params(v, f, uv)


def test_rigid_motion_lookup_is_the_inverse_rotation():
    v, f, prm = _mesh_params()
    q = _random_rotation(7)
    warp = AffineWarp(q, np.array([0.5, -1.0, 2.0]))
    r0 = imp.decode_frames(prm.r0, prm.u0, prm.v0)
    for method in ("exact", "central"):
        u, vv = deformed_tangents(warp, prm.p0, prm.u0, prm.v0, method)
        lrot, valid = lookup_rotation(r0, u, vv)
        assert valid.all()
        np.testing.assert_allclose(lrot, np.broadcast_to(q.T, lrot.shape), atol=1e-10)
    # inside triangles, from interpolated tangents
    rng = np.random.default_rng(8)
    prim = rng.integers(0, len(f), 100)
    bary = rng.dirichlet(np.ones(3), 100)
    u, vv = deformed_tangents(warp, prm.p0, prm.u0, prm.v0)
    lrot, _ = lookup_rotation(rest_frames_at(interpolate(r0[:, :, 0], f, prim, bary),
                                             interpolate(r0[:, :, 1], f, prim, bary)),
                              interpolate(u, f, prim, bary), interpolate(vv, f, prim, bary))
    np.testing.assert_allclose(lrot, np.broadcast_to(q.T, lrot.shape), atol=1e-10)


def test_uniform_scale_lookup_is_identity():
    _, _, prm = _mesh_params()
    warp = parse_warp("scale:s=2.5", BOUNDS)
    u, vv = deformed_tangents(warp, prm.p0, prm.u0, prm.v0)
    lrot, valid = lookup_rotation(imp.decode_frames(prm.r0, prm.u0, prm.v0), u, vv)
    assert valid.all()
    np.testing.assert_allclose(lrot, np.broadcast_to(np.eye(3), lrot.shape), atol=1e-12)


def test_shear_frame_minimises_summed_squared_angles():
    rng = np.random.default_rng(11)
    u = rng.normal(size=(30, 3))
    v = rng.normal(size=(30, 3))
    ub, vb, nb, valid = orthogonalize(u, v)
    assert valid.all()
    uh = u / np.linalg.norm(u, axis=1, keepdims=True)
    vh = v / np.linalg.norm(v, axis=1, keepdims=True)

    def cost(a):  # (n, m) angles of candidate orthonormal pairs in the plane, rotated by a
        e1 = uh
        e2 = np.cross(nb, e1)
        cu = np.cos(a)[None, :, None] * e1[:, None] + np.sin(a)[None, :, None] * e2[:, None]
        cv = np.cross(nb[:, None], cu)
        ang_u = np.arccos(np.clip(np.einsum("nmk,nk->nm", cu, uh), -1, 1))
        ang_v = np.arccos(np.clip(np.einsum("nmk,nk->nm", cv, vh), -1, 1))
        return ang_u ** 2 + ang_v ** 2, cu

    grid = np.linspace(-math.pi, math.pi, 20001)
    c, _ = cost(grid)
    best = grid[np.argmin(c, axis=1)]
    for _ in range(4):  # refine around the brute-force minimum
        step = 2 * (grid[1] - grid[0])
        grid_n = np.linspace(-step, step, 201)
        cand = best[:, None] + grid_n[None, :]
        cc = np.stack([cost(cand[i])[0][i] for i in range(len(best))])
        best = cand[np.arange(len(best)), np.argmin(cc, axis=1)]
        grid = grid_n
    e2 = np.cross(nb, uh)
    brute = np.cos(best)[:, None] * uh + np.sin(best)[:, None] * e2
    err = np.arccos(np.clip(np.einsum("ij,ij->i", brute, ub), -1, 1))
    assert err.max() < 1e-6, err.max()
    np.testing.assert_allclose(np.einsum("ij,ij->i", ub, vb), 0.0, atol=1e-12)


def test_sine_warp_is_a_shear_and_lookup_is_a_rotation():
    _, _, prm = _mesh_params()
    warp = parse_warp("sine:amplitude=0.2", BOUNDS)
    u, vv = deformed_tangents(warp, prm.p0, prm.u0, prm.v0, "central")
    lrot, valid = lookup_rotation(imp.decode_frames(prm.r0, prm.u0, prm.v0), u, vv)
    assert valid.all()
    np.testing.assert_allclose(lrot @ np.transpose(lrot, (0, 2, 1)),
                               np.broadcast_to(np.eye(3), lrot.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(lrot), 1.0, atol=1e-12)


def test_singular_jacobian_no_nan_and_fallback():
    # stretch with a zero factor: every tangent plane containing x collapses
    warp = parse_warp("stretch:x=0,y=1,z=1", BOUNDS)
    u0 = np.array([[1.0, 0, 0], [0, 1.0, 0], [1.0, 0, 0]])
    v0 = np.array([[0, 0, 1.0], [0, 0, 1.0], [0, 1.0, 0]])
    p0 = np.zeros((3, 3))
    u, v = deformed_tangents(warp, p0, u0, v0)
    r0 = np.stack([u0, v0, np.cross(u0, v0)], axis=2)
    lrot, valid = lookup_rotation(r0, u, v)
    assert valid.tolist() == [False, True, False]
    assert np.isfinite(lrot).all()
    np.testing.assert_allclose(lrot[[0, 2]], np.broadcast_to(np.eye(3), (2, 3, 3)), atol=0)
    # with the deformed surface's normal as fallback: a proper rotation taking it to n0
    fb = np.array([[0, 1.0, 0], [0, 0, 0], [0, 0, 1.0]])
    lrot, valid = lookup_rotation(r0, u, v, fallback_normal=fb)
    assert np.isfinite(lrot).all()
    np.testing.assert_allclose(np.linalg.det(lrot), 1.0, atol=1e-12)
    np.testing.assert_allclose(np.einsum("nij,nj->ni", lrot[[0, 2]], fb[[0, 2]]),
                               r0[[0, 2], :, 2], atol=1e-12)
    # the bend's centre of curvature: J has rank 2 there, no NaN
    bend = parse_warp("bend:angle=90", BOUNDS)
    centre = np.array([[2.0 / (math.pi / 2), 1.0, 0.0]])
    u, v = deformed_tangents(bend, centre, np.array([[1.0, 0, 0]]), np.array([[0, 1.0, 0]]))
    lrot, valid = lookup_rotation(np.eye(3)[None], u, v)
    assert not valid[0] and np.isfinite(lrot).all()


def test_shapes_and_errors():
    with pytest.raises(ShapeError):
        orthogonalize(np.zeros((2, 3)), np.zeros((3, 3)))
    with pytest.raises(SettingsError, match="jacobian"):
        deformed_tangents(parse_warp("twist", BOUNDS), np.zeros((1, 3)), np.zeros((1, 3)),
                          np.zeros((1, 3)), method="forward")
    prm = imp.impostor_params(np.zeros((0, 3)), np.zeros((0, 3), np.int64))
    assert prm.r0.shape == (0, 3)


def test_interpolation_across_mixed_quarter_turns():
    from texelbake.deform.lookup import align_quarter_turns

    # three corners with the same frame up to quarter turns: their plain average is degenerate
    u0 = np.array([[1.0, 0, 0], [0, 1.0, 0], [-1.0, 0, 0]])[None]
    v0 = np.array([[0, 1.0, 0], [-1.0, 0, 0], [0, -1.0, 0]])[None]
    q = _random_rotation(9)
    u, v = u0 @ q.T, v0 @ q.T
    bary = np.array([[0.3, 0.3, 0.4]])
    assert np.linalg.norm(np.einsum("nk,nkj->nj", bary, u0)) < 0.5
    a0, b0, a, b = align_quarter_turns(u0, v0, u, v)
    np.testing.assert_allclose(a0[0], np.tile([1.0, 0, 0], (3, 1)), atol=1e-15)
    r0 = rest_frames_at(np.einsum("nk,nkj->nj", bary, a0), np.einsum("nk,nkj->nj", bary, b0))
    lrot, valid = lookup_rotation(r0, np.einsum("nk,nkj->nj", bary, a),
                                  np.einsum("nk,nkj->nj", bary, b))
    assert valid.all()
    np.testing.assert_allclose(lrot[0], q.T, atol=1e-12)


def test_subdivide_keeps_the_surface_and_the_atlas():
    from texelbake.deform.refine import refine_levels, subdivide

    v, f = icosphere(1)
    rng = np.random.default_rng(12)
    cuv = rng.random((len(f), 3, 2))
    v2, f2, c2, (x2,), parent = subdivide(v, f, cuv, (v[:, :2],))
    n_edges = len(np.unique(np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]],
                                                    f[:, [2, 0]]]), axis=1), axis=0))
    assert len(v2) == len(v) + n_edges and len(f2) == 4 * len(f)  # midpoints shared
    np.testing.assert_array_equal(v2[: len(v)], v)
    np.testing.assert_allclose(x2, v2[:, :2], atol=1e-15)  # per-vertex arrays interpolated
    # each child's corners lie on its parent's plane, with the parent's linear uv map there
    tri = v[f[parent]]
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    for k in range(3):
        q = v2[f2[:, k]] - tri[:, 0]
        gram = np.einsum("nij,nkj->nik", np.stack([e1, e2], 1), np.stack([e1, e2], 1))
        rhs = np.stack([np.einsum("ij,ij->i", q, e1), np.einsum("ij,ij->i", q, e2)], 1)
        st = np.linalg.solve(gram, rhs[..., None])[..., 0]  # (n, 2) coordinates in the plane
        np.testing.assert_allclose(tri[:, 0] + st[:, :1] * e1 + st[:, 1:] * e2,
                                   v2[f2[:, k]], atol=1e-12)
        c = cuv[parent]
        uv = c[:, 0] + st[:, :1] * (c[:, 1] - c[:, 0]) + st[:, 1:] * (c[:, 2] - c[:, 0])
        np.testing.assert_allclose(c2[:, k], uv, atol=1e-12)
    longest = np.linalg.norm(v[f[:, 1]] - v[f[:, 0]], axis=1).max()
    assert refine_levels(v, f, longest * 1.01) == 0
    assert refine_levels(v, f, longest / 3.0) == 2
    assert refine_levels(v, f, longest / 1e9) == 4
