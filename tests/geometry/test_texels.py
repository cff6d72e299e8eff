"""Texel assignment g(p) per mip level, CSR grouping and texel frames."""

from __future__ import annotations

import numpy as np
import pytest

from tests.helpers.meshes import bumpy_sphere, plane_grid, random_rotation
from texelbake.errors import SettingsError, ShapeError
from texelbake.geometry.atlas import atlas_uv_of_points, build_atlas, rasterize_atlas
from texelbake.geometry.closest import closest_point_on_triangles
from texelbake.geometry.hierarchy import simplify_hierarchy
from texelbake.geometry.mesh import Mesh
from texelbake.geometry.raycast import RayCaster
from texelbake.geometry.sampling import sample_surface
from texelbake.geometry.texel_frames import FrameSums, texel_frames
from texelbake.geometry.texels import (
    assign_texels,
    bilinear_texels,
    texel_centers_uv,
    texel_surface_points,
    uv_to_texel,
)

N = 64
LEVELS = 4


@pytest.fixture(scope="module")
def sphere():
    v, f = bumpy_sphere(4, amplitude=0.03)
    (m1,) = simplify_hierarchy(v, f, 1, target_faces=600)
    atlas = build_atlas(m1, N)
    s = sample_surface(v, f, 20_000, seed=0)
    return v, f, m1, atlas, s, assign_texels(s.positions, m1, atlas, LEVELS)


@pytest.fixture(scope="module")
def tilted_plane():
    rng = np.random.default_rng(3)
    rot = random_rotation(rng)
    v, f = plane_grid(12, 12, size=2.0)
    v = v @ rot.T + np.array([0.3, -0.2, 0.7])
    normal = rot @ np.array([0.0, 0.0, 1.0])
    (m1,) = simplify_hierarchy(v, f, 1, target_faces=16)
    atlas = build_atlas(m1, 32)
    corner_normals = np.broadcast_to(normal, (f.shape[0], 3, 3))
    s = sample_surface(v, f, 8000, seed=1, corner_normals=corner_normals)
    return v, f, m1, atlas, s, assign_texels(s.positions, m1, atlas, 3), normal


def test_every_sample_is_assigned_once(sphere):
    *_, s, a = sphere
    m = len(s)
    for level in range(LEVELS):
        assert a.counts(level).sum() == m
        listed = np.concatenate([a.samples_of(level, t) for t in a.occupied(level)])
        assert np.array_equal(np.sort(listed), np.arange(m))
        assert a.offsets[level].shape == ((N >> level) ** 2 + 1,)


def test_assignment_in_chunks_is_the_one_pass_assignment(sphere):
    """The memory bound (issue 15): samples assigned `chunk` at a time, with both side rules
    on (normals, and M_org as occluder), give the arrays of one pass bit for bit."""
    v, f, m1, atlas, s, _ = sphere
    kw = {"normals": s.normals, "occluder": RayCaster(v, f)}
    one = assign_texels(s.positions, m1, atlas, LEVELS, chunk=len(s), **kw)
    parts = assign_texels(s.positions, m1, atlas, LEVELS, chunk=777, **kw)
    for name in ("prim", "bary", "uv", "distance", "row", "col"):
        assert np.array_equal(getattr(one, name), getattr(parts, name)), name
    for level in range(LEVELS):
        assert np.array_equal(one.offsets[level], parts.offsets[level])


def test_parent_counts_are_sums_of_their_four_children(sphere):
    *_, a = sphere
    for level in range(LEVELS - 1):
        n = N >> level
        child = a.counts(level).reshape(n // 2, 2, n // 2, 2)
        parent = a.counts(level + 1).reshape(n // 2, n // 2)
        np.testing.assert_array_equal(child.sum(axis=(1, 3)), parent)


def test_sample_texel_contains_its_uv(sphere):
    *_, a = sphere
    for level in range(LEVELS):
        n = N >> level
        row, col = np.divmod(a.texel_index(level), n)
        u, v = a.uv[:, 0], a.uv[:, 1]
        assert ((u >= col / n) & (u <= (col + 1) / n)).all()
        assert ((1 - v >= row / n) & (1 - v <= (row + 1) / n)).all()


def test_csr_lookup_matches_a_scan(sphere):
    *_, a = sphere
    for level in (0, 2):
        idx = a.texel_index(level)
        for texel in np.unique(idx)[::37]:
            np.testing.assert_array_equal(a.samples_of(level, texel), np.flatnonzero(idx == texel))
    assert np.array_equal(a.occupied(0), np.unique(a.texel_index(0)))


def test_assignment_is_the_exact_closest_point(sphere):
    v, f, m1, atlas, s, a = sphere
    # brute force over all M1 triangles in float64 for a subset of samples
    sub = np.arange(0, len(s), 97)
    q = s.positions[sub]
    tri = m1.triangles()
    k, nf = q.shape[0], tri.shape[0]
    qq = np.repeat(q, nf, axis=0)
    cand, _ = closest_point_on_triangles(
        qq, np.tile(tri[:, 0], (k, 1)), np.tile(tri[:, 1], (k, 1)), np.tile(tri[:, 2], (k, 1))
    )
    best = np.linalg.norm(cand - qq, axis=1).reshape(k, nf).min(axis=1)
    # Embree ranks candidate triangles in float32 (~1e-7 relative); the distance is then
    # exact in float64 on the chosen triangle
    np.testing.assert_allclose(a.distance[sub], best, atol=1e-6 * m1.bbox_diag)
    # the uv is the atlas uv at the stated barycentrics of the stated triangle
    expect = np.einsum("mk,mkd->md", a.bary, atlas.corner_uvs[a.prim])
    np.testing.assert_allclose(a.uv, expect, atol=1e-15)


def test_frames_are_orthonormal_and_right_handed(sphere):
    v, f, m1, atlas, s, a = sphere
    for level in (0, 2):
        frames, valid = texel_frames(a, s.normals, s.area, m1, atlas, level)
        n = N >> level
        assert frames.shape == (n * n, 3, 3) and valid.shape == (n * n,)
        np.testing.assert_allclose(
            frames @ frames.transpose(0, 2, 1), np.broadcast_to(np.eye(3), frames.shape), atol=1e-12
        )
        np.testing.assert_allclose(np.linalg.det(frames), 1.0, atol=1e-12)
        assert np.array_equal(valid, a.counts(level) > 0)  # no cancelling normals on a sphere
        # n is the normalized area-weighted mean normal (independent bincount-free sum)
        idx = a.texel_index(level)
        for texel in np.flatnonzero(valid)[::53]:
            sel = idx == texel
            mean = (s.area[sel, None] * s.normals[sel]).sum(axis=0)
            np.testing.assert_allclose(frames[texel, 2], mean / np.linalg.norm(mean), atol=1e-12)


def test_flat_plane_frames_have_the_plane_normal_and_the_uv_tangent(tilted_plane):
    v, f, m1, atlas, s, a, normal = tilted_plane
    frames, valid = texel_frames(a, s.normals, s.area, m1, atlas, 0)
    assert valid.any() and (~valid).any()  # charts leave empty texels
    np.testing.assert_allclose(
        frames[valid, 2], np.broadcast_to(normal, (valid.sum(), 3)), atol=1e-14
    )
    # empty texels still get an orthonormal frame; those under a chart take its normal
    np.testing.assert_allclose(
        frames @ frames.transpose(0, 2, 1), np.broadcast_to(np.eye(3), frames.shape), atol=1e-12
    )
    # t points where u grows: step in u from the texel centre and compare 3-D directions
    face, bary, _ = rasterize_atlas(atlas.corner_uvs, 32)
    inner = np.flatnonzero(valid & (face >= 0))
    centres = texel_centers_uv(32)[inner]
    p0 = np.einsum("nk,nkd->nd", bary[inner], m1.triangles()[face[inner]])
    # on a plane the uv map of one triangle extends affinely: the position at u + du
    tri_uv = atlas.corner_uvs[face[inner]]
    du = 1e-3
    target = centres + np.array([du, 0.0])
    e1, e2 = tri_uv[:, 1] - tri_uv[:, 0], tri_uv[:, 2] - tri_uv[:, 0]
    rel = target - tri_uv[:, 0]
    det = e1[:, 0] * e2[:, 1] - e2[:, 0] * e1[:, 1]
    w1 = (rel[:, 0] * e2[:, 1] - e2[:, 0] * rel[:, 1]) / det
    w2 = (e1[:, 0] * rel[:, 1] - rel[:, 0] * e1[:, 1]) / det
    w = np.column_stack([1 - w1 - w2, w1, w2])
    p1 = np.einsum("nk,nkd->nd", w, m1.triangles()[face[inner]])
    step = (p1 - p0) / np.linalg.norm(p1 - p0, axis=1, keepdims=True)
    np.testing.assert_allclose(frames[inner, 0], step, atol=1e-9)


def test_empty_texel_frames_are_flagged():
    v, f = plane_grid(4, 4)
    m1 = Mesh(v, f)
    atlas = build_atlas(m1, 16)
    # a single sample: exactly one texel is valid at level 0
    a = assign_texels(np.array([[0.5, 0.5, 0.0]]), m1, atlas, 2)
    frames, valid = texel_frames(a, np.array([[0.0, 0.0, 1.0]]), np.array([1.0]), m1, atlas, 0)
    assert valid.sum() == 1 and valid[a.texel_index(0)[0]]
    np.testing.assert_allclose(frames[valid, 2], [[0.0, 0.0, 1.0]], atol=1e-15)
    # opposite normals cancel: the texel has samples but no mean normal
    pts = np.array([[0.5, 0.5, 0.0], [0.5, 0.5, 0.0]])
    a2 = assign_texels(pts, m1, atlas, 1)
    nrm = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]])
    frames2, valid2 = texel_frames(a2, nrm, np.ones(2), m1, atlas, 0)
    assert not valid2.any()
    np.testing.assert_allclose(np.linalg.det(frames2), 1.0, atol=1e-12)
    # no samples at all: typed, all invalid
    a3 = assign_texels(np.zeros((0, 3)), m1, atlas, 2)
    assert a3.counts(1).sum() == 0 and a3.prim.dtype == np.int64
    frames3, valid3 = texel_frames(a3, np.zeros((0, 3)), np.zeros(0), m1, atlas, 1)
    assert frames3.shape == (64, 3, 3) and not valid3.any()


def test_uv_texel_helpers():
    n = 8
    centres = texel_centers_uv(n)
    row, col = uv_to_texel(centres, n)
    np.testing.assert_array_equal(row * n + col, np.arange(n * n))
    assert uv_to_texel(np.array([[0.0, 1.0]]), n) == (0, 0)  # top-left corner
    assert tuple(x[0] for x in uv_to_texel(np.array([[1.0, 0.0]]), n)) == (n - 1, n - 1)
    # bilinear weights reproduce a linear function of the texel centres exactly (inside)
    rng = np.random.default_rng(0)
    uv = rng.uniform(0.5 / n, 1 - 0.5 / n, size=(200, 2))
    idx, w = bilinear_texels(uv, n)
    np.testing.assert_allclose(w.sum(axis=1), 1.0)
    field = 2.0 * centres[:, 0] - 3.0 * centres[:, 1] + 0.5
    np.testing.assert_allclose((w * field[idx]).sum(axis=1), 2 * uv[:, 0] - 3 * uv[:, 1] + 0.5)


def test_bad_arguments(tilted_plane):
    v, f, m1, atlas, s, a, _ = tilted_plane
    with pytest.raises(SettingsError, match="divisible"):
        assign_texels(s.positions, m1, atlas, 7)  # 32 is not divisible by 2^6
    with pytest.raises(SettingsError, match="level"):
        a.counts(3)
    with pytest.raises(ShapeError, match="faces"):
        assign_texels(s.positions, Mesh(v, f), atlas, 2)
    with pytest.raises(ShapeError, match="normals"):
        texel_frames(a, s.normals[:5], s.area, m1, atlas, 0)


def test_texel_surface_points_lie_on_m1_at_their_uv(sphere):
    v, f, m1, atlas, s, a = sphere
    pts, nrm, face, valid = texel_surface_points(atlas, 1)
    n = N >> 1
    assert pts.shape == (n * n, 3) and valid.any() and (~valid).any()
    assert not pts[~valid].any() and (face[~valid] == -1).all()
    # independent check: the point's atlas uv (closest point on M1 -> uv) is the texel centre
    uv, prim, dist = atlas_uv_of_points(pts[valid], atlas)
    assert dist.max() < 1e-9 * m1.bbox_diag
    np.testing.assert_allclose(uv, texel_centers_uv(n)[valid], atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(nrm[valid], axis=1), 1.0)


def test_own_side_rule_sends_samples_to_the_sheet_they_face():
    """M1 as a slab's two sheets, the front at z = 1 (normal +z) and the back at z = -0.5
    (normal -z), around samples on the plane z = 0 facing +z: the closest point is on the
    back sheet, behind the samples' surface; with their normals they go to the front sheet,
    straight above (the hit of a ray along the normal), and without them to the back."""
    from tests.helpers.meshes import box

    v, f = box((-2.0, -2.0, -0.5), (3.0, 3.0, 1.0))  # sides 2 away from the samples
    m1 = Mesh(v, f)
    atlas = build_atlas(m1, 32)
    rng = np.random.default_rng(5)
    pts = np.column_stack([0.1 + 0.8 * rng.random((500, 2)), np.zeros(500)])
    nrm = np.tile([0.0, 0.0, 1.0], (500, 1))
    plain = assign_texels(pts, m1, atlas, 1)
    own = assign_texels(pts, m1, atlas, 1, normals=nrm)
    fn = m1.face_normals()
    assert (fn[plain.prim, 2] < -0.99).all()  # closest: the back sheet
    assert (fn[own.prim, 2] > 0.99).all()  # own side: the front sheet
    tri = m1.vertices[m1.faces[own.prim]]
    hit = np.einsum("nk,nkj->nj", own.bary, tri)
    # Embree's float32 barycentrics on a box 5 units wide: ~5 x 6e-8 per coordinate
    np.testing.assert_allclose(hit, pts + [0.0, 0.0, 1.0], atol=2e-6)
    np.testing.assert_allclose(own.distance, 1.0, atol=2e-6)
    # samples facing the back sheet keep their closest point
    back = assign_texels(pts, m1, atlas, 1, normals=-nrm)
    assert np.array_equal(back.prim, plain.prim)
    with pytest.raises(ShapeError, match="normals"):
        assign_texels(pts, m1, atlas, 1, normals=nrm[:3])


def test_bent_normal_rule_sends_a_gap_wall_to_the_sheet_it_is_seen_through():
    """Two blocks 0.2 apart on a plane, inside a slab M1 (front sheet z = 1, back z = -0.1):
    samples low on a block's side wall facing the gap are nearest the back sheet, 90° from
    their normal (the own-side rule does not move them). Seen only through the gap's opening
    above, with M_org as occluder they go to the front sheet; samples on the blocks' tops
    stay where they were."""
    from tests.helpers.meshes import box
    from texelbake.geometry.raycast import RayCaster

    v, f = box((-2.0, -2.0, -0.1), (3.0, 3.0, 1.0))
    m1 = Mesh(v, f)
    atlas = build_atlas(m1, 32)
    parts = [box((0.0, 0.0, 0.0), (1.0, 1.0, 0.9)), box((1.2, 0.0, 0.0), (2.2, 1.0, 0.9)),
             plane_grid(2, 2, size=4.0)]
    verts, faces, base = [], [], 0
    for pv, pf in parts:
        verts.append(pv)
        faces.append(pf + base)
        base += len(pv)
    org = RayCaster(np.concatenate(verts), np.concatenate(faces))
    rng = np.random.default_rng(7)
    k = 300
    wall = np.column_stack([np.ones(k), 0.3 + 0.4 * rng.random(k), 0.02 + 0.05 * rng.random(k)])
    top = np.column_stack([0.2 + 0.6 * rng.random((k, 2)), np.full(k, 0.9)])
    pts = np.concatenate([wall, top])
    nrm = np.concatenate([np.tile([1.0, 0.0, 0.0], (k, 1)), np.tile([0.0, 0.0, 1.0], (k, 1))])
    own = assign_texels(pts, m1, atlas, 1, normals=nrm)
    bent = assign_texels(pts, m1, atlas, 1, normals=nrm, occluder=org)
    fn = m1.face_normals()
    assert (fn[own.prim[:k], 2] < -0.99).all()  # the gap wall: the back sheet, 90° away
    assert (fn[bent.prim[:k], 2] > 0.99).all()  # seen through the opening: the front sheet
    assert np.array_equal(bent.prim[k:], own.prim[k:])  # the tops face the front already
    # the front-sheet point lies above the gap (between the blocks, x in [1, 1.2] give or take
    # the slope of the bent normal over the 0.93 climb)
    tri = m1.vertices[m1.faces[bent.prim[:k]]]
    hit = np.einsum("nk,nkj->nj", bent.bary[:k], tri)
    assert (hit[:, 0] > 1.0).all() and np.median(hit[:, 0]) < 1.6
    # assigned 37 at a time (the memory bound, issue 15), with both rules firing: bit for bit
    parts = assign_texels(pts, m1, atlas, 1, normals=nrm, occluder=org, chunk=37)
    for name in ("prim", "bary", "uv", "distance", "row", "col"):
        assert np.array_equal(getattr(parts, name), getattr(bent, name)), name


def test_frame_sums_in_chunks_are_the_one_pass_frames(sphere):
    """The geometry stage's pass over spooled samples (issue 15, memory): `FrameSums` fed
    chunks of 777 samples in order gives `texel_frames`' frames and flags bit for bit at every
    level, the nearest-sample fallback (texels whose centre has no M1 face) included."""
    _, _, m1, atlas, s, a = sphere
    for level in range(LEVELS):
        one, valid = texel_frames(a, s.normals, s.area, m1, atlas, level)
        acc = FrameSums(atlas, N >> level)
        assert (acc.under < 0).any()  # the fallback is exercised
        for i in range(0, len(s), 777):
            sl = slice(i, i + 777)
            acc.add(a.row[sl] >> level, a.col[sl] >> level, s.normals[sl], s.area[sl],
                    a.uv[sl], a.prim[sl])
        frames, valid2 = acc.frames(atlas)
        assert np.array_equal(valid, valid2) and frames.tobytes() == one.tobytes(), level
