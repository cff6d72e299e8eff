"""Visible projected area a_vis (texelbake.cpm.avis): cube maps, rays vs closed form, the height-field
acceptance (c), the a_vis -> 0 limit, hierarchy additivity and the compressed look-up table."""

import numpy as np
import pytest

from tests.helpers.avis_scenes import (
    grid_mesh,
    periodic_height,
    sample_faces,
    texel_of_latlong,
    texel_of_xy,
    tile3x3,
    uv_sphere,
)
from texelbake.cpm.avis import (
    AvisLevel,
    AvisTable,
    avis_cube_maps,
    avis_from_visibility,
    avis_level,
    avis_ortho_grids,
    closed_form_maps,
    closed_form_terms,
    coarsen_level,
    coarsen_maps,
    compress_level,
    cube_directions,
    cube_solid_angles,
    default_eps,
    dirs_to_cube,
    eval_closed_form,
    geometric_normals,
    level_from_arrays,
    level_to_arrays,
    stack_tiles,
    unoccluded_samples,
    unoccluded_texels,
    visible_fraction,
)
from texelbake.cpm.avis.maps import never_occluded
from texelbake.errors import NumericalError, SettingsError, ShapeError
from texelbake.geometry.raycast import RayCaster
from texelbake.tol import TOL

# ------------------------------------------------------------------------------------ scenes


def _heightfield(k=32, q=2, n_side=4, amp=0.05, seed=1):
    h = periodic_height(amp, seed=seed)
    pts, faces = grid_mesh(k, h)
    # 3x3 periodic tiling holds every occluder of a ray leaving the central tile with
    # theta <= 80 deg iff the height range is below tan(10 deg) (a ray rises by the range
    # within range * tan(80) < 1 period): checked, not assumed.
    assert np.ptp(pts[:, 2]) < np.tan(np.radians(10.0))
    tp, tf = tile3x3(pts, faces)
    pos, nrm, ar, _ = sample_faces(pts, faces, q, seed=seed + 1)
    return {"pts": pts, "faces": faces, "caster": RayCaster(tp, tf), "mesh_points": tp,
            "pos": pos, "nrm": nrm, "ar": ar, "tex": texel_of_xy(pos, n_side), "n_side": n_side}


def _sphere(n_side=4, q=2):
    pts, faces = uv_sphere(12, 24)
    pos, nrm, ar, _ = sample_faces(pts, faces, q, seed=3)
    return {"pts": pts, "faces": faces, "caster": RayCaster(pts, faces), "pos": pos,
            "nrm": nrm, "ar": ar, "tex": texel_of_latlong(pos, n_side), "n_side": n_side}


def _plate_scene(hole=True):
    """A ground grid (4 x 4 cells on [0,1]^2) and a horizontal plate at z = 0.3 over cell (1, 1).
    With hole=True the ground cell under the plate is removed, so texel 5 holds only the plate."""
    pts, faces = grid_mesh(4, lambda x, y: 0.0 * x)
    cells = np.arange(faces.shape[0]) % 16  # grid_mesh: two triangle sets in cell order
    if hole:
        faces = faces[cells != 5]
    plate_p = np.array([[0.25, 0.25, 0.3], [0.5, 0.25, 0.3], [0.5, 0.5, 0.3], [0.25, 0.5, 0.3]])
    plate_f = np.array([[0, 1, 2], [0, 2, 3]]) + pts.shape[0]
    all_p = np.concatenate([pts, plate_p])
    all_f = np.concatenate([faces, plate_f])
    pos, nrm, ar, _ = sample_faces(all_p, all_f, 4, seed=5)
    return {"pts": all_p, "faces": all_f, "caster": RayCaster(all_p, all_f), "pos": pos,
            "nrm": nrm, "ar": ar, "tex": texel_of_xy(pos, 4), "n_side": 4}


def _maps(s, res, **kw):
    n = s["n_side"] ** 2
    return avis_cube_maps(s["pos"], s["nrm"], s["ar"], s["tex"], n, None, res,
                          s["caster"].occluded, dtype=np.float64, **kw)


def _frames_identity(n):
    return np.broadcast_to(np.eye(3), (n, 3, 3)).copy()


# ------------------------------------------------------------------------------ directions


@pytest.mark.parametrize("res", [1, 4, 16])
def test_cube_directions_round_trip(res):
    d = cube_directions(res)
    assert d.shape == (6, res, res, 3) and d.dtype == np.float64
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0, atol=1e-15)
    face, iu, iv, fu, fv = dirs_to_cube(d.reshape(-1, 3), res)
    f_t, v_t, u_t = np.meshgrid(np.arange(6), np.arange(res), np.arange(res), indexing="ij")
    assert np.array_equal(face, f_t.ravel()) and np.array_equal(iu, u_t.ravel())
    assert np.array_equal(iv, v_t.ravel())
    np.testing.assert_allclose(fu, u_t.ravel(), atol=1e-12)
    np.testing.assert_allclose(fv, v_t.ravel(), atol=1e-12)


def test_cube_solid_angles():
    om = cube_solid_angles(16)
    assert om.shape == (6, 16, 16)
    np.testing.assert_allclose(om.sum(), 4 * np.pi, rtol=1e-13)  # closed form: the sphere
    # second method: midpoint rule on a 64 x 64 sub-grid of one texel, dOmega = dA / r^3
    x0, x1 = -1 + 2 * 3 / 16, -1 + 2 * 4 / 16
    y0, y1 = -1 + 2 * 9 / 16, -1 + 2 * 10 / 16
    s = (np.arange(64) + 0.5) / 64
    xx, yy = np.meshgrid(x0 + (x1 - x0) * s, y0 + (y1 - y0) * s)
    num = np.sum((x1 - x0) * (y1 - y0) / 64**2 / (1 + xx**2 + yy**2) ** 1.5)
    np.testing.assert_allclose(om[4, 9, 3], num, rtol=1e-4)  # midpoint rule O(h^2) ~ 1e-5


def test_dirs_to_cube_degenerate_and_shape():
    face, iu, iv, _, _ = dirs_to_cube(np.array([[0.0, 0, 0], [np.nan, 0, 1]]), 8)
    assert face.shape == (2,) and np.all((iu >= 0) & (iu < 8)) and np.all((iv >= 0) & (iv < 8))
    with pytest.raises(ShapeError):
        dirs_to_cube(np.zeros((3, 2)), 8)
    with pytest.raises(SettingsError):
        cube_directions(0)


# --------------------------------------------------------------------------- from visibility


def test_avis_from_visibility_brute_force(rng):
    m, d, nt = 50, 7, 4
    nrm = rng.normal(size=(m, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    ar = rng.random(m)
    tex = rng.integers(0, nt, m)
    dirs = rng.normal(size=(d, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    vis = rng.random((m, d)) > 0.3
    got = avis_from_visibility(vis, nrm, ar, tex, nt, dirs)
    want = np.zeros((nt, d))
    for j in range(m):  # brute force reference: the definition, one sample at a time
        want[tex[j]] += vis[j] * np.maximum(nrm[j] @ dirs.T, 0) * ar[j]
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-15)
    per_sample = np.broadcast_to(dirs, (m, d, 3))
    np.testing.assert_allclose(avis_from_visibility(vis, nrm, ar, tex, nt, per_sample), want,
                               rtol=1e-12, atol=1e-15)


def test_never_occluded_is_the_unoccluded_area_without_rays(rng):
    """`never_occluded` gives the same maps, bit for bit, as an occlusion test that answers
    "never" for every ray it is handed, in world and texel frames, and hands no ray out."""
    m, nt, res = 40, 3, 4
    pos = rng.normal(size=(m, 3))
    nrm = rng.normal(size=(m, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    ar, tex = rng.random(m), rng.integers(0, nt, m)
    frames = np.stack([np.linalg.qr(rng.normal(size=(3, 3)))[0] for _ in range(nt)])
    asked = []

    def answers_never(origins, dirs):
        asked.append(len(origins))
        return np.zeros(len(origins), dtype=bool)

    for fr in (None, frames):
        want = avis_cube_maps(pos, nrm, ar, tex, nt, fr, res, answers_never, dtype=np.float64)
        got = avis_cube_maps(pos, nrm, ar, tex, nt, fr, res, never_occluded, dtype=np.float64)
        np.testing.assert_array_equal(got, want)
    assert sum(asked) > 0  # the other path did cast
    cos = np.maximum(nrm @ cube_directions(res).reshape(-1, 3).T, 0.0)
    cos[cos <= TOL.grazing_cos] = 0.0
    ref = np.zeros((nt, cos.shape[1]))
    np.add.at(ref, tex, ar[:, None] * cos)  # the definition, (n_j . w)^+ dA_j per texel
    np.testing.assert_allclose(avis_cube_maps(pos, nrm, ar, tex, nt, None, res, never_occluded,
                                              dtype=np.float64).reshape(nt, -1), ref,
                               rtol=1e-12, atol=1e-15)


def test_input_errors(rng):
    nrm = np.tile([0.0, 0, 1], (3, 1))
    with pytest.raises(ShapeError):
        avis_from_visibility(np.ones((3, 2), bool), nrm, np.ones(3), np.array([0, 1, 5]), 2,
                             np.eye(3)[:2])
    with pytest.raises(NumericalError):
        avis_from_visibility(np.ones((3, 2), bool), nrm, np.array([1, np.nan, 1]),
                             np.zeros(3, int), 1, np.eye(3)[:2])
    with pytest.raises(ShapeError):
        avis_from_visibility(np.ones((3, 2), bool), nrm, np.ones(3), np.zeros(3, int), 1,
                             np.eye(3))


# ---------------------------------------------------------------- acceptance (c): height field


def test_heightfield_total_is_projected_base_area():
    """Sum over texels of a_vis(w) = A_base cos(theta) for a height field without overhangs.

    Exact for the continuous periodic surface (the projection of one period along w tiles the
    plane perpendicular to w, area A_base cos theta). What remains is the visibility
    discretization at shadow boundaries (each sample is wholly seen or not): measured 0.25 %
    worst at 4 samples per triangle (0.07 % at 36) on this field, so the acceptance bound 1 %
    has a 4x margin without being loose enough to hide a missing (n.w)^+, a wrong area or
    offset, or a lost texel (each of those costs > 1 %).
    """
    s = _heightfield()
    res = 8
    maps = _maps(s, res)
    assert maps.shape == (16, 6, res, res)
    dirs = cube_directions(res).reshape(-1, 3)
    total = maps.reshape(16, -1).sum(axis=0)
    theta = np.degrees(np.arccos(np.clip(dirs[:, 2], -1, 1)))
    sel = theta < 80.0
    assert sel.sum() > 100
    rel = np.abs(total[sel] - dirs[sel, 2]) / dirs[sel, 2]  # A_base = 1
    assert rel.max() < 0.01, rel.max()
    # the masking is real: without visibility the total exceeds cos(theta) at grazing angles
    unmasked = avis_from_visibility(np.ones((s["pos"].shape[0], dirs.shape[0]), bool),
                                    s["nrm"], s["ar"], s["tex"], 16, dirs).sum(axis=0)
    assert np.max((unmasked[sel] - dirs[sel, 2]) / dirs[sel, 2]) > 0.05


def test_heightfield_table_lookup_total(rng):
    """The same identity through the compressed table at random directions (lossless Haar,
    seamless bilinear on res 16). The look-up total is the bilinear interpolant of the total
    map (same taps for every texel), so its error is the 0.5 % sampling error at the cube
    directions plus the bilinear error on a ~0.1 rad grid (~2e-3 absolute on a unit-slope
    function, measured): 0.67 % worst at theta = 75 deg, within the 1 % acceptance."""
    s = _heightfield(k=32, q=2, n_side=2)
    lvl = avis_level(s["pos"], s["nrm"], s["ar"], s["tex"], 2, 16, s["caster"].occluded,
                     s["mesh_points"], max_terms=1024)
    assert not lvl.closed.any()  # bumps everywhere: nothing provably unoccluded
    assert lvl.bounded.all()  # 512 facets per texel: the visible fraction F is stored
    direct = AvisLevel(lvl.n_side, lvl.res, lvl.closed, np.zeros(4, bool), lvl.cf,
                       lvl.ray_texels, lvl.ray_maps, lvl.texel_area)
    n = 300
    cos_t = rng.uniform(np.cos(np.radians(80)), 1.0, n)
    phi = rng.uniform(0, 2 * np.pi, n)
    sin_t = np.sqrt(1 - cos_t**2)
    w = np.column_stack([sin_t * np.cos(phi), sin_t * np.sin(phi), cos_t])
    for level in (lvl, direct):  # F times exact U, and a_vis itself
        table = compress_level(level, _frames_identity(4), 1.0)
        tot = np.zeros(n)
        for t in range(4):  # four texels
            a, valid = table.evaluate(np.full(n, t), w)
            assert valid.all()
            tot += a
        rel = np.abs(tot - cos_t) / cos_t
        assert rel.max() < 0.01, rel.max()


# ------------------------------------------------------------------------------ closed form


def test_closed_form_equals_rays_on_convex_object():
    s = _sphere()
    n = s["n_side"] ** 2
    closed = unoccluded_texels(s["pos"], s["nrm"], s["tex"], n, s["pts"])
    assert closed.shape == (n,) and closed.all()
    rays = _maps(s, 8)
    cf = closed_form_terms(s["nrm"], s["ar"], s["tex"], n, closed)
    # merged: a texel holds as many terms as distinct triangles, not samples
    assert cf.normals.shape[0] < s["pos"].shape[0] / 3
    closed_maps = closed_form_maps(cf, 8)
    scale = rays.max()
    np.testing.assert_allclose(closed_maps, rays, rtol=1e-12, atol=1e-13 * scale)
    assert (rays > 0).mean() > 0.2 and (rays == 0).mean() > 0.2  # both regimes exercised


def test_closed_form_any_direction_brute_force(rng):
    s = _sphere(n_side=2)
    cf = closed_form_terms(s["nrm"], s["ar"], s["tex"], 4)
    n = 200
    texels = rng.integers(0, 4, n)
    w = rng.normal(size=(n, 3))
    w /= np.linalg.norm(w, axis=1, keepdims=True)
    got = eval_closed_form(cf, texels, w)
    dots = w @ s["nrm"].T  # (n, m): brute force over every sample
    contrib = np.where(dots > TOL.grazing_cos, dots, 0.0) * s["ar"]
    want = np.sum(contrib * (s["tex"][None, :] == texels[:, None]), axis=1)
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-15)
    pairs = eval_closed_form(cf, texels, w, dense_limit=0)  # the CSR-pair path
    np.testing.assert_allclose(pairs, want, rtol=1e-12, atol=1e-15)
    # single-vector form where every term faces w: a_vis = S . w
    sv = cf.sum_vectors()
    ok = np.array([np.all(cf.normals[cf.offsets[t]:cf.offsets[t + 1]] @ wi > 0)
                   for t, wi in zip(texels, w, strict=True)])
    assert ok.any()
    np.testing.assert_allclose(got[ok], np.einsum("ij,ij->i", sv[texels[ok]], w[ok]),
                               rtol=1e-12)


def test_detection_refuses_occluded_texels():
    s = _plate_scene(hole=True)
    closed = unoccluded_texels(s["pos"], s["nrm"], s["tex"], 16, s["pts"])
    assert closed[5] and closed.sum() == 1  # the plate top; every ground texel sees the plate
    rays = _maps(s, 8)
    cf = closed_form_terms(s["nrm"], s["ar"], s["tex"], 16, closed)
    np.testing.assert_allclose(closed_form_maps(cf, 8, np.array([5])), rays[[5]], rtol=1e-12,
                               atol=1e-15)
    # completeness, per sample: the ray towards a mesh point above the sample's tangent plane
    # (inside the plate) is occluded, as the proof in unoccluded_texels says
    ground = s["tex"] != 5
    above = np.array([0.3, 0.4, 0.3])
    o = s["pos"][ground] + 1e-6 * s["nrm"][ground]
    assert s["caster"].occluded(o, above - o).all()
    # and the cube rays see the occlusion: rays < unoccluded closed form for refused texels
    cf_all = closed_form_terms(s["nrm"], s["ar"], s["tex"], 16)
    unocc = closed_form_maps(cf_all, 8)
    assert np.all(np.max(unocc - rays, axis=(1, 2, 3))[~closed] > 0)


def test_detection_catches_occluder_coarse_rays_miss():
    """A thin needle in one corner: at every direction of a coarse cube map the far texels look
    unoccluded, yet detection refuses them (detected, not assumed)."""
    pts, faces = grid_mesh(4, lambda x, y: 0.0 * x)
    needle = np.array([[0.02, 0.02, 0.0], [0.025, 0.02, 0.0], [0.02, 0.025, 0.0],
                       [0.0225, 0.0225, 0.5]])
    nf = np.array([[0, 1, 3], [1, 2, 3], [2, 0, 3]]) + pts.shape[0]
    all_p, all_f = np.concatenate([pts, needle]), np.concatenate([faces, nf])
    pos, nrm, ar, _ = sample_faces(pts, faces, 3, seed=7)
    tex = texel_of_xy(pos, 4)
    caster = RayCaster(all_p, all_f)
    rays = avis_cube_maps(pos, nrm, ar, tex, 16, None, 2, caster.occluded, dtype=np.float64)
    cf = closed_form_terms(nrm, ar, tex, 16)
    coarse_says_free = np.all(np.isclose(rays, closed_form_maps(cf, 2), rtol=1e-12,
                                         atol=1e-15), axis=(1, 2, 3))
    assert coarse_says_free[15]  # the far corner texel looks free to 24 directions
    closed = unoccluded_texels(pos, nrm, tex, 16, all_p)
    assert not closed.any()
    assert unoccluded_texels(pos, nrm, tex, 16, pts).all()  # without the needle: all exact


def test_unoccluded_texels_empty_and_errors():
    out = unoccluded_texels(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, int), 3,
                            np.eye(3))
    assert out.shape == (3,) and out.all()
    with pytest.raises(ShapeError):
        unoccluded_texels(np.zeros((2, 3)), np.zeros((2, 3)), np.zeros(2, int), 1,
                          np.zeros((4, 2)))


# ------------------------------------------------------------------------ the a_vis -> 0 limit


def test_avis_to_zero_limit():
    """Ground texel 0 lies wholly under a plate: from above it is fully masked. Grazing and
    below-horizon directions of a flat texel give a_vis -> 0: exactly 0 (valid False, the
    renderer uses zero radiance there) from one cube pixel below the horizon on, and within that
    pixel no more than the bilinear weight of the one tap above it. No NaN/Inf anywhere."""
    pts, faces = grid_mesh(4, lambda x, y: 0.0 * x)
    plate_p = np.array([[-0.2, -0.2, 0.05], [0.7, -0.2, 0.05], [0.7, 0.7, 0.05],
                        [-0.2, 0.7, 0.05]])
    all_p = np.concatenate([pts, plate_p])
    all_f = np.concatenate([faces, np.array([[0, 1, 2], [0, 2, 3]]) + pts.shape[0]])
    pos, nrm, ar, _ = sample_faces(pts, faces, 2, seed=9)  # samples on the ground only
    tex = texel_of_xy(pos, 2)
    caster = RayCaster(all_p, all_f)
    lvl = avis_level(pos, nrm, ar, tex, 2, 8, caster.occluded, all_p)
    assert not lvl.closed.any()
    table = compress_level(lvl, _frames_identity(4), 0.1)
    th = np.radians([0.0, 30.0, 89.9, 90.0 - 1e-10, 90.0, 120.0])
    w = np.column_stack([np.sin(th), np.zeros_like(th), np.cos(th)])
    a0, v0 = table.evaluate(np.zeros(6, int), w)  # texel 0: under the plate
    assert np.all(np.isfinite(a0)) and not v0[0] and a0[0] == 0.0
    assert not v0[5] and a0[5] == 0.0
    # texel 3 ([0.5, 1]^2) is partly open from above (x > 0.7 or y > 0.7: area 0.21 of 0.25)
    a3, v3 = table.evaluate(np.full(6, 3), w)
    assert v3[:2].all() and not v3[5] and a3[5] == 0.0
    # at the horizon (+X face centre, res 8) two taps sit 0.125 above it and two below, where
    # U = 0: a <= 1/2 * A * 0.125 / |(1, 0.125)| (the look-up is linear, not clamped to U(w))
    tap_u = 0.25 * 0.125 / np.hypot(1.0, 0.125)
    for a in (a0, a3):
        assert np.all(a[3:5] >= 0.0) and np.all(a[3:5] <= 0.5 * tap_u * (1 + 1e-9)), a
    assert 0.15 < a3[0] < 0.25
    # the floor is relative to the texel area: cos(89.9 deg) * A is far above 1e-9 * A
    assert a3[2] > TOL.avis_floor * 0.25 or not v3[2]
    # a zero or NaN direction and an empty texel are invalid, not errors
    a, v = table.evaluate(np.array([3, 3]), np.array([[0.0, 0, 0], [np.nan, 0, 1]]))
    assert not v.any() and np.all(a == 0)


def test_empty_texel_and_negative_haar_clamped():
    s = _heightfield(k=8, q=2, n_side=2)
    keep = s["tex"] != 1  # texel 1 gets no samples
    lvl = avis_level(s["pos"][keep], s["nrm"][keep], s["ar"][keep], s["tex"][keep], 2, 8,
                     s["caster"].occluded, s["mesh_points"])
    assert lvl.texel_area[1] == 0
    table = compress_level(lvl, _frames_identity(4), 0.02)  # heavy truncation: ringing
    d = cube_directions(8).reshape(-1, 3)
    for t in range(4):
        a, v = table.evaluate(np.full(d.shape[0], t), d, interp="nearest")
        assert np.all(a >= 0) and np.all(np.isfinite(a))
        if t == 1:
            assert not v.any()


# ---------------------------------------------------------------------------- hierarchy


def test_coarsen_maps_shapes_and_errors(rng):
    m = rng.random((16, 6, 2, 2))
    p = coarsen_maps(m)
    assert p.shape == (4, 6, 2, 2)
    np.testing.assert_allclose(p[0], m[0] + m[1] + m[4] + m[5])
    with pytest.raises(ShapeError):
        coarsen_maps(rng.random((9, 3)))


def test_coarsen_level_equals_direct_parent():
    """Additivity in world directions: the parent level from its children equals the parent
    computed directly from all its samples (same rays, different summation order)."""
    s = _plate_scene(hole=True)
    child = avis_level(s["pos"], s["nrm"], s["ar"], s["tex"], 4, 4, s["caster"].occluded,
                       s["pts"])
    assert child.closed.sum() == 1  # mixed: one closed child (the plate) under a ray parent
    parent = coarsen_level(child)
    tex2 = texel_of_xy(s["pos"], 2)
    direct = avis_level(s["pos"], s["nrm"], s["ar"], tex2, 2, 4, s["caster"].occluded, s["pts"])
    assert np.array_equal(parent.closed, direct.closed)
    np.testing.assert_allclose(parent.dense_maps(), direct.dense_maps(), rtol=1e-12,
                               atol=1e-15)
    np.testing.assert_allclose(parent.texel_area, direct.texel_area, rtol=1e-12)


def test_coarsen_closed_form_is_exact():
    s = _sphere(n_side=4)
    child = avis_level(s["pos"], s["nrm"], s["ar"], s["tex"], 4, 4, s["caster"].occluded,
                       s["pts"])
    assert child.closed.all() and child.ray_maps.shape[0] == 0  # no rays cast at all
    parent = coarsen_level(child)
    assert parent.closed.all()
    tex2 = texel_of_latlong(s["pos"], 2)
    cf2 = closed_form_terms(s["nrm"], s["ar"], tex2, 4)
    assert np.array_equal(parent.cf.offsets, cf2.offsets)  # equal normals merged
    np.testing.assert_allclose(parent.cf.areas, cf2.areas, rtol=1e-12)
    np.testing.assert_array_equal(parent.cf.normals, cf2.normals)


def test_compress_level_lookup_matches_maps():
    """Table look-ups at cube-texel centres reproduce the (lossless) maps; closed-form texels
    are answered exactly at any direction; texel-frame directions are rotated."""
    s = _plate_scene(hole=True)
    lvl = avis_level(s["pos"], s["nrm"], s["ar"], s["tex"], 4, 8, s["caster"].occluded,
                     s["pts"])
    # a rotated frame for every texel: the look-up must rotate texel-frame dirs to world
    ang = np.linspace(0, 1, 16)
    frames = np.zeros((16, 3, 3))
    frames[:, 0] = np.column_stack([np.cos(ang), np.sin(ang), 0 * ang])
    frames[:, 1] = np.column_stack([-np.sin(ang), np.cos(ang), 0 * ang])
    frames[:, 2] = [0, 0, 1]
    table = compress_level(lvl, frames, 1.0)
    dense = lvl.dense_maps().reshape(16, -1)
    d = cube_directions(8).reshape(-1, 3)
    for t in (0, 5, 10):
        local = d @ frames[t].T  # world -> texel frame
        for interp in ("nearest", "bilinear"):
            a, valid = table.evaluate(np.full(d.shape[0], t), local, interp=interp)
            want = np.where(dense[t] > TOL.avis_floor * lvl.texel_area[t], dense[t], 0.0)
            # float32 Haar values: 1e-6 relative to the largest coefficient
            np.testing.assert_allclose(a, want, rtol=0, atol=2e-6 * dense[t].max())
            assert np.array_equal(valid, want > 0) or t == 5


def test_level_validation():
    with pytest.raises(ShapeError):
        coarsen_level(AvisLevel(3, 4, np.zeros(9, bool), np.zeros(9, bool), closed_form_terms(
            np.zeros((0, 3)), np.zeros(0), np.zeros(0, int), 9), np.arange(9),
            np.zeros((9, 6, 4, 4)), np.zeros(9)))


# --------------------------------------------------------------------- second method: ortho


def test_ortho_grid_agrees_with_closed_form_on_sphere():
    s = _sphere(n_side=2)
    ortho = avis_ortho_grids(s["caster"], s["pos"], s["tex"], 4, 4, grid_res=96)
    assert ortho.shape == (4, 6, 4, 4) and ortho.dtype == np.float32
    cf = closed_form_terms(s["nrm"], s["ar"], s["tex"], 4)
    truth = closed_form_maps(cf, 4)
    # totals: pixel-count area of the whole silhouette, jittered: ~0.5 % at 96^2 rays
    np.testing.assert_allclose(ortho.sum(axis=0), truth.sum(axis=0), rtol=0.01)
    # per texel, nearest-sample assignment and pixel quantization at texel borders: ~5 %
    big = truth > 0.2 * truth.max()
    rel = np.abs(ortho[big] - truth[big]) / truth[big]
    assert np.median(rel) < 0.05


def test_deterministic():
    s = _heightfield(k=8, q=2, n_side=2)
    a = avis_cube_maps(s["pos"], s["nrm"], s["ar"], s["tex"], 4, None, 4, s["caster"].occluded,
                       max_rays=5000)
    b = avis_cube_maps(s["pos"], s["nrm"], s["ar"], s["tex"], 4, None, 4, s["caster"].occluded)
    assert a.dtype == np.float32 and a.shape == (4, 6, 4, 4)
    np.testing.assert_allclose(a, b, rtol=1e-6)  # batching changes only summation order
    c = avis_cube_maps(s["pos"], s["nrm"], s["ar"], s["tex"], 4, None, 4, s["caster"].occluded,
                       max_rays=5000)
    assert a.tobytes() == c.tobytes()


def test_texel_frame_cube_equals_rotated_world():
    """A texel-frame cube map (frames=) equals the world map evaluated at the rotated
    directions: with one shared frame, texel-frame cube texel d is world direction d @ F."""
    s = _heightfield(k=8, q=2, n_side=2)
    ang = 0.4
    F = np.array([[np.cos(ang), np.sin(ang), 0], [-np.sin(ang), np.cos(ang), 0], [0, 0, 1.0]])
    frames = np.broadcast_to(F, (4, 3, 3)).copy()
    tex_maps = avis_cube_maps(s["pos"], s["nrm"], s["ar"], s["tex"], 4, frames, 4,
                              s["caster"].occluded, dtype=np.float64)
    d_world = cube_directions(4).reshape(-1, 3) @ F
    n = s["pos"].shape[0]
    origins = s["pos"] + default_eps(s["pos"]) * s["nrm"]
    vis = ~s["caster"].occluded(np.repeat(origins, 96, axis=0),
                                np.tile(d_world, (n, 1))).reshape(n, 96)
    want = avis_from_visibility(vis, s["nrm"], s["ar"], s["tex"], 4, d_world)
    np.testing.assert_allclose(tex_maps.reshape(4, -1), want, rtol=1e-9, atol=1e-12)


# ------------------------------------------------------------------ visible-fraction storage


def test_visible_fraction_fill():
    u = np.zeros((1, 6, 4, 4))
    u[0, 0, :2] = 2.0  # defined on the two upper rows of face 0 only
    a = np.zeros_like(u)
    a[0, 0, :2] = np.array([[1.0, 2.0, 0.5, 0.0], [1.0, 1.0, 1.0, 1.0]])
    f = visible_fraction(a, u)
    np.testing.assert_allclose(f[0, 0, :2], a[0, 0, :2] / 2.0)
    # undefined rows of face 0 take the nearest defined texel (the row above, same column);
    # faces without any U stay 0
    np.testing.assert_allclose(f[0, 0, 2], f[0, 0, 1])
    np.testing.assert_allclose(f[0, 0, 3], f[0, 0, 1])
    assert np.all(f[0, 1:] == 0) and f.min() >= 0 and f.max() <= 1
    with pytest.raises(ShapeError):
        visible_fraction(a, u[..., :2])


def test_fraction_storage_beats_direct_and_respects_bound():
    """Bounded ray texels store F = a_vis / U and multiply by the exact U at look-up: at the
    seed's kept fraction this must be more accurate than compressing a_vis directly, and can
    never exceed the unoccluded area (nor leak where it is zero, e.g. below the horizon)."""
    s = _heightfield(k=16, q=2, n_side=4)
    args = (s["pos"], s["nrm"], s["ar"], s["tex"], 4, 16, s["caster"].occluded,
            s["mesh_points"])
    lvl = avis_level(*args)
    assert lvl.bounded.all() and not lvl.closed.any()
    direct = AvisLevel(lvl.n_side, lvl.res, lvl.closed, np.zeros(16, bool), lvl.cf,
                       lvl.ray_texels, lvl.ray_maps, lvl.texel_area)
    d = cube_directions(16).reshape(-1, 3)
    dense = lvl.dense_maps().reshape(16, -1)
    errs = []
    for level in (lvl, direct):
        table = compress_level(level, _frames_identity(16), 0.065)
        a = np.stack([table.evaluate(np.full(d.shape[0], t), d, interp="nearest")[0]
                      for t in range(16)])
        errs.append(np.linalg.norm(a - dense) / np.linalg.norm(dense))
        if level is lvl:
            bound = closed_form_maps(lvl.cf, 16).reshape(16, -1)
            assert np.all(a <= bound * (1 + 1e-12))
            assert np.all(a[bound == 0] == 0) and (bound == 0).mean() > 0.3
    assert errs[0] < 0.7 * errs[1], errs


# ----------------------------------------------------------------- tiles, storage, normals


def test_geometric_normals():
    pts, faces = uv_sphere(6, 8)
    fid = np.array([0, 5, 17, 30])
    n = geometric_normals(pts, faces, fid)
    cr = np.cross(pts[faces[fid, 1]] - pts[faces[fid, 0]], pts[faces[fid, 2]] - pts[faces[fid, 0]])
    np.testing.assert_allclose(n, cr / np.linalg.norm(cr, axis=1, keepdims=True), rtol=1e-14)
    assert geometric_normals(pts, faces, np.zeros(0, int)).shape == (0, 3)
    with pytest.raises(ShapeError):
        geometric_normals(pts, faces, np.array([faces.shape[0]]))


def test_tiles_stack_to_the_whole_level():
    """The plate scene's 4 x 4 level computed as four 2 x 2 tiles (local texel ids, one
    scene-wide ray_eps) and stacked equals the level computed at once."""
    s = _plate_scene(hole=True)
    eps = default_eps(s["pos"])
    whole = avis_level(s["pos"], s["nrm"], s["ar"], s["tex"], 4, 4, s["caster"].occluded,
                       s["pts"], ray_eps=eps)
    iy, ix = np.divmod(s["tex"], 4)
    tiles = []
    for ty in range(2):
        for tx in range(2):
            sel = (iy // 2 == ty) & (ix // 2 == tx)
            local = (iy[sel] % 2) * 2 + ix[sel] % 2
            tiles.append(avis_level(s["pos"][sel], s["nrm"][sel], s["ar"][sel], local, 2, 4,
                                    s["caster"].occluded, s["pts"], ray_eps=eps))
    stacked = stack_tiles(tiles, 2)
    assert np.array_equal(stacked.closed, whole.closed)
    assert np.array_equal(stacked.ray_texels, whole.ray_texels)
    assert np.array_equal(stacked.cf.offsets, whole.cf.offsets)
    np.testing.assert_allclose(stacked.dense_maps(), whole.dense_maps(), rtol=1e-12, atol=1e-15)
    with pytest.raises(ShapeError):
        stack_tiles(tiles[:3], 2)


def test_level_and_table_arrays_round_trip():
    import io

    s = _plate_scene(hole=True)
    lvl = avis_level(s["pos"], s["nrm"], s["ar"], s["tex"], 4, 4, s["caster"].occluded,
                     s["pts"])
    buf = io.BytesIO()
    np.savez(buf, **level_to_arrays(lvl))
    buf.seek(0)
    back = level_from_arrays(np.load(buf))
    assert back.n_side == 4 and back.res == 4 and back.max_terms == lvl.max_terms
    assert np.array_equal(back.dense_maps(), lvl.dense_maps())
    table = compress_level(lvl, _frames_identity(16), 0.1)
    buf = io.BytesIO()
    np.savez(buf, **table.to_arrays())
    buf.seek(0)
    t2 = AvisTable.from_arrays(np.load(buf))
    d = cube_directions(4).reshape(-1, 3)
    for t in (0, 5, 15):
        a1, v1 = table.evaluate(np.full(d.shape[0], t), d)
        a2, v2 = t2.evaluate(np.full(d.shape[0], t), d)
        assert np.array_equal(a1, a2) and np.array_equal(v1, v2)
    with pytest.raises(ShapeError):
        level_from_arrays({"meta": np.array([4, 4, 256])})


def test_unoccluded_detection_equals_brute_force():
    """Per sample (one texel per sample), the bounded hull test equals the definition: every
    mesh vertex on or below the sample's tangent plane lifted by eps."""
    pts, faces = uv_sphere(14, 28, bump=lambda t, p: np.where(
        t > np.pi / 2, 0.06 * np.sin(4 * t) * np.cos(5 * p), 0.0))
    pos, nrm, _, _ = sample_faces(pts, faces, 2, seed=4)
    eps = default_eps(pos)
    got = unoccluded_texels(pos, nrm, np.arange(pos.shape[0]), pos.shape[0], pts, eps=eps)
    brute = np.max(nrm @ pts.T - np.einsum("ij,ij->i", nrm, pos)[:, None], axis=1) <= eps
    assert 0.2 < brute.mean() < 0.9  # both outcomes well represented
    assert np.array_equal(got, brute)


def test_cube_maps_skip_casts_no_rays_and_shape_errors():
    s = _plate_scene(hole=True)
    calls = []

    def counting(o, d):
        calls.append(len(o))
        return s["caster"].occluded(o, d)

    skip = np.zeros(16, bool)
    skip[5] = True
    full = _maps(s, 4)
    part = avis_cube_maps(s["pos"], s["nrm"], s["ar"], s["tex"], 16, None, 4, counting,
                          skip_texels=skip, dtype=np.float64)
    assert np.all(part[5] == 0) and np.array_equal(part[~skip], full[~skip])
    n5 = int(np.sum(s["tex"] == 5))
    facing = int(np.sum(s["nrm"][s["tex"] != 5] @ cube_directions(4).reshape(-1, 3).T
                        > TOL.grazing_cos))
    assert sum(calls) == facing and n5 > 0  # one ray per facing pair, none for texel 5
    with pytest.raises(ShapeError):
        avis_cube_maps(s["pos"], s["nrm"], s["ar"], s["tex"], 16, np.zeros((3, 3, 3)), 4,
                       counting)
    with pytest.raises(ShapeError):
        avis_cube_maps(s["pos"], s["nrm"], s["ar"], s["tex"], 16, None, 4, counting,
                       skip_texels=np.zeros(3, bool))
    with pytest.raises(ShapeError):
        avis_cube_maps(s["pos"][:5], s["nrm"], s["ar"], s["tex"], 16, None, 4, counting)


def test_free_samples_cast_no_rays_and_change_nothing():
    """Samples `unoccluded_samples` proves free (the plate's top, over ground that is occluded
    by it) cast no ray and their texels' maps are bit-identical to the all-rays maps; with the
    caster's own `occluded` (float32 rays built from the pairs) and with any other function."""
    s = _plate_scene(hole=False)
    free = unoccluded_samples(s["pos"], s["nrm"], s["pts"], eps=default_eps(s["pos"]))
    per_texel = unoccluded_texels(s["pos"], s["nrm"], s["tex"], 16, s["pts"])
    assert np.array_equal(per_texel, np.bincount(s["tex"][~free], minlength=16) == 0)
    mixed = np.unique(s["tex"][free])
    assert free.any() and not per_texel[mixed].any()  # free samples inside ray texels
    calls = []

    def counting(o, d):
        calls.append(len(o))
        return s["caster"].occluded(o, d)

    full = _maps(s, 4)
    assert np.array_equal(_maps(s, 4, free_samples=free), full)
    part = avis_cube_maps(s["pos"], s["nrm"], s["ar"], s["tex"], 16, None, 4, counting,
                          free_samples=free, dtype=np.float64)
    assert np.array_equal(part, full)
    facing = s["nrm"] @ cube_directions(4).reshape(-1, 3).T > TOL.grazing_cos
    assert sum(calls) == int(facing[~free].sum()) < int(facing.sum())
    with pytest.raises(ShapeError):
        _maps(s, 4, free_samples=free[:3])
    with pytest.raises(SettingsError):
        avis_cube_maps(s["pos"], s["nrm"], s["ar"], s["tex"], 16, _frames_identity(16), 4,
                       counting, free_samples=free)


def test_visible_fraction_nearest_fill_brute_force():
    rng = np.random.default_rng(1)
    u = (rng.random((3, 6, 8, 8)) > 0.6).astype(float)
    a = rng.random(u.shape) * u
    f = visible_fraction(a, u)
    for idx in np.ndindex(u.shape):  # reference: nearest defined entry of the column
        r, fc, i, j = idx
        if u[idx] > 0:
            assert f[idx] == a[idx]
            continue
        col = np.flatnonzero(u[r, fc, :, j] > 0)
        if col.size:
            k = col[np.argmin(np.abs(col - i) + 1e-9 * (col > i))]  # ties: lower index
            assert f[idx] == a[r, fc, k, j]


def _nearest(defined: np.ndarray, i: int) -> int | None:
    """Index of the defined entry nearest i (ties: the lower), None when there is none."""
    at = np.flatnonzero(defined)
    return int(at[np.argmin(np.abs(at - i) + 1e-9 * (at > i))]) if at.size else None


def test_visible_fraction_fill_faces_brute_force():
    """Faces defined everywhere, nowhere, and in part, with columns that hold no defined entry
    (filled along their row from the filled columns): every entry against a loop over the
    rule (nearest defined entry of the column, else of the row after the column fill, else 0)."""
    rng = np.random.default_rng(7)
    for res in (2, 4, 16):
        u = (rng.random((4, 6, res, res)) > rng.random((4, 6, 1, 1))) * rng.random((4, 6, res, res))
        u[:, 0] = rng.random((4, res, res)) + 0.1  # defined everywhere
        u[:, 1] = 0.0  # defined nowhere
        u[:, 2, :, : res // 2] = 0.0  # columns without a defined entry
        a = rng.random(u.shape) * u * 1.5  # F above 1 is clipped
        f = visible_fraction(a, u)
        for r, fc in np.ndindex(4, 6):  # reference: a loop over faces and entries
            ok = u[r, fc] > 0
            g = np.clip(np.divide(a[r, fc], u[r, fc], out=np.zeros((res, res)), where=ok), 0, 1)
            col = g.copy()
            ok_col = ok.copy()
            for i, j in np.ndindex(res, res):
                if not ok[i, j] and (k := _nearest(ok[:, j], i)) is not None:
                    col[i, j], ok_col[i, j] = g[k, j], True
            want = col.copy()
            for i, j in np.ndindex(res, res):
                if not ok_col[i, j]:
                    k = _nearest(ok_col[i, :], j)
                    want[i, j] = 0.0 if k is None else col[i, k]
            np.testing.assert_array_equal(f[r, fc], want)


def test_unique_rows_equals_numpys_unique_of_rows():
    """The lexsort of columns gives numpy's `unique(axis=0, return_inverse=True)`: the same
    rows, bit for bit, in the same order, on repeated rows with zeros and ties in the first
    columns, one row and none."""
    from texelbake.arrays import unique_rows

    rng = np.random.default_rng(5)
    base = np.round(rng.normal(size=(40, 3)), 1)
    base[::5, 0] = 0.0
    base[::3, 1] = base[0, 1]
    for a in (base[rng.integers(0, 40, 500)] + 0.0, base[:1], np.zeros((0, 3))):
        want, want_inv = np.unique(a, axis=0, return_inverse=True)
        got, inv = unique_rows(a)
        assert got.tobytes() == want.tobytes() and got.shape == want.shape
        assert np.array_equal(inv, want_inv.ravel())


def test_table_through_a_usdc_file_and_the_packed_layout_read_alike(tmp_path):
    """The table's arrays authored on a prim of a .usdc layer, saved and read back
    (`author_array`, `_read_arrays`: indices as uint[], values as half[]) give the same
    table, bit for bit; the packed layout of earlier bakes (index and value bits in one
    uint32) still reads to it."""
    from pxr import Usd

    from texelbake.usd.read import _read_arrays
    from texelbake.usd.write import author_array

    s = _plate_scene(hole=True)
    lvl = avis_level(s["pos"], s["nrm"], s["ar"], s["tex"], 4, 4, s["caster"].occluded,
                     s["pts"])
    table = compress_level(lvl, _frames_identity(16), 0.1)
    arrays = table.to_arrays()
    assert arrays["haar_half"].dtype == np.float16 and "haar_packed" not in arrays
    path = tmp_path / "table.usdc"
    stage = Usd.Stage.CreateNew(str(path))
    prim = stage.DefinePrim("/T")
    for name, arr in arrays.items():
        author_array(prim, name, arr)
    stage.GetRootLayer().Save()
    back = Usd.Stage.Open(str(path))
    read = _read_arrays(back.GetPrimAtPath("/T"))
    packed = dict(arrays)
    packed["haar_packed"] = (packed.pop("haar_index")
                             | (packed.pop("haar_half").view(np.uint16).astype(np.uint32) << 16))
    for got in (AvisTable.from_arrays(read), AvisTable.from_arrays(packed)):
        assert np.array_equal(got.haar.indices, table.haar.indices)
        assert got.haar.values.tobytes() == table.haar.values.tobytes()
        assert np.array_equal(got.haar.offsets, table.haar.offsets)
