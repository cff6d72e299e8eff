"""Surface reflectance fields, item 5 and the frame: EWA elliptical surfel splatting under
a 1:4 stretch (seed 002 Fig. 8) and a capture view reproducing its captured image."""

from __future__ import annotations

import numpy as np
import pytest

from tests.helpers.render import icosphere, quad
from tests.helpers.srf import sphere_asset
from texelbake.deform.warps import parse_warp
from texelbake.geometry.raycast import RayCaster
from texelbake.render.metrics import psnr_db
from texelbake.srf.capture import capture, unit_light
from texelbake.srf.deferred import render_srf, splat_surfels
from texelbake.srf.rig import project
from texelbake.srf.splat import splat
from texelbake.srf.surfels import surfels_from_mesh
from texelbake.trace import camera as cam_mod

CAM = cam_mod.look_at((0.0, 0.0, 6.0), (0.0, 0.0, 0.0), 128, 128)


def _plane_surfels():
    v, f = quad(-0.3, 0.3, -0.3, 0.3, 0.0)
    return surfels_from_mesh(v, f, spacing=0.2)  # ~3 pixels apart (7 diagonally)


def _mesh_coverage(vertices, faces, cam):
    o, d = cam_mod.eye_rays_at(cam, np.arange(cam.width * cam.height),
                               np.full((cam.width * cam.height, 2), 0.5))
    return RayCaster(vertices, faces).cast(o, d).hit


def test_elliptical_splats_close_a_1_to_4_stretch_circular_ones_do_not():
    s = _plane_surfels()
    warp = parse_warp("stretch:x=1,y=4,z=1", np.array([[-0.3, -0.3, 0.0], [0.3, 0.3, 0.0]]))
    inside = _mesh_coverage(warp.positions(s.mesh_vertices), s.mesh_faces, CAM)
    assert inside.sum() > 500
    ell = splat_surfels(s, CAM, warp)
    circ = splat_surfels(s, CAM, warp, circular=True)
    assert ell.covered[inside].all()  # 100 % of the deformed mesh's own coverage
    assert circ.covered[inside].mean() < 0.95  # holes (Fig. 8a)
    # undeformed, both close the surface
    assert splat_surfels(s, CAM, None, circular=True).covered[
        _mesh_coverage(s.mesh_vertices, s.mesh_faces, CAM)].all()


def test_splat_rest_points_invert_an_affine_warp_and_lie_on_eye_rays():
    s = _plane_surfels()
    warp = parse_warp("stretch:x=1,y=4,z=1", np.array([[-0.3, -0.3, 0.0], [0.3, 0.3, 0.0]]))
    g = splat_surfels(s, CAM, warp)
    cv = np.flatnonzero(g.covered)
    a = np.diag([1.0, 4.0, 1.0])
    # Ψ is affine: the first-order inverse of each splat is exact, Ψ⁻¹(p*) = p
    np.testing.assert_allclose(g.p_rest[cv], g.p_star[cv] @ np.linalg.inv(a).T, atol=1e-9)
    # the deformed points lie on the eye rays through the pixel centres
    xy, front = project(CAM, g.p_star[cv])
    iy, ix = np.divmod(cv, CAM.width)
    assert front.all()
    np.testing.assert_allclose(xy, np.column_stack([ix + 0.5, iy + 0.5]), atol=1e-6)


def test_splat_culls_back_faces_and_checks_shapes():
    s = _plane_surfels()
    back = cam_mod.look_at((0.0, 0.0, -6.0), (0.0, 0.0, 0.0), 32, 32)
    assert not splat_surfels(s, back).covered.any()
    with pytest.raises(Exception, match=r"u must be"):
        splat(CAM, s.p0, s.u[:-1], s.v)


@pytest.fixture(scope="module")
def sphere_field(tmp_path_factory):
    store = capture(sphere_asset(2), tmp_path_factory.mktemp("srf") / "sphere", n_cameras=12,
                    n_lights=8, size=32, spp=4)
    pts, faces = icosphere(2)
    return store, surfels_from_mesh(1.03 * pts, faces)  # an enclosing impostor


@pytest.mark.parametrize("c, j", [(0, 0), (5, 3), (11, 7)])
def test_capture_view_under_a_capture_light_reproduces_its_image(sphere_field, c, j):
    store, surf = sphere_field
    res = render_srf(store, surf, store.cameras[c], [unit_light(store.light_dirs[j], 0)])
    ref = store.image(c, j)
    assert psnr_db(res.image, ref) >= 40.0
    assert res.extras["no_camera_fraction"] == 0.0


def test_sorted_and_naive_frames_are_bit_identical(sphere_field):
    store, surf = sphere_field
    cam = cam_mod.auto_frame(np.array([[-1.0, -1, -1], [1, 1, 1]]), 32, 32,
                             view_from=(0.5, 0.2, 1.0))
    warp = parse_warp("twist:angle=40", np.array([[-1.0, -1, -1], [1, 1, 1]]))
    lights = [unit_light(np.array([0.3, 0.8, 0.5]) / np.linalg.norm([0.3, 0.8, 0.5]), 0)]
    a = render_srf(store, surf, cam, lights, warp=warp, executor="sorted")
    b = render_srf(store, surf, cam, lights, warp=warp, executor="naive")
    assert np.array_equal(a.image, b.image)
    assert a.extras["block_reads"] * 10 <= b.extras["block_reads"]
    assert a.image.max() > 0.05


def test_points_no_capture_camera_sees_stay_black(tmp_path):
    # two capture cameras in front (+z): the back of the sphere was never seen
    bounds = np.array([[-1.0, -1, -1], [1, 1, 1]])
    cams = [cam_mod.auto_frame(bounds, 16, 16, view_from=d) for d in ((0.2, 0, 1), (-0.2, 0, 1))]
    store = capture(sphere_asset(1), tmp_path / "front", cameras=cams, n_lights=2, spp=1)
    pts, faces = icosphere(1)
    surf = surfels_from_mesh(1.03 * pts, faces)
    back = cam_mod.auto_frame(bounds, 16, 16, view_from=(0.0, 0.3, -1.0))
    res = render_srf(store, surf, back, [unit_light(store.light_dirs[0], 0)])
    assert res.extras["no_camera_fraction"] > 0.3
    assert np.isfinite(res.image).all()
    seen = render_srf(store, surf, cams[0], [unit_light(store.light_dirs[0], 0)])
    assert seen.extras["no_camera_fraction"] == 0.0


def _deformed_asset(asset, warp, lights):
    import dataclasses

    from texelbake.deform.normals import deform_normals

    corner = deform_normals(warp.jacobian(asset.points)[asset.faces.reshape(-1)],
                            asset.corner_normals.reshape(-1, 3)).reshape(
                                asset.corner_normals.shape)
    return dataclasses.replace(asset, points=warp.positions(asset.points),
                               corner_normals=corner, lights=tuple(lights))


def test_under_a_rotation_srf_through_l_beats_srf_without_l(sphere_field):
    from texelbake.render.metrics import object_errors, object_mask
    from texelbake.trace.org import render_model

    store, surf = sphere_field
    bounds = np.array([[-1.0, -1, -1], [1, 1, 1]])
    warp = parse_warp("rigid:angle=70,axis=y", bounds)
    light = [unit_light(np.array([0.6, 0.3, 0.74]) / np.linalg.norm([0.6, 0.3, 0.74]), 0)]
    cam = cam_mod.auto_frame(bounds, 32, 32, view_from=(0.2, 0.3, 1.0))
    ref = render_model(_deformed_asset(sphere_asset(2), warp, light), cam, 4, seed=1)
    psnr = {}
    for use_l in (True, False):
        res = render_srf(store, surf, cam, light, warp=warp, use_lookup=use_l)
        psnr[use_l] = object_errors(res.image, ref.image,
                                    object_mask(ref.coverage, res.coverage))["psnr_db_object"]
    assert psnr[True] > psnr[False] + 3.0, psnr


def test_a_singular_warp_renders_without_nan(sphere_field):
    store, surf = sphere_field
    warp = parse_warp("stretch:x=0,y=1,z=1", np.array([[-1.0, -1, -1], [1, 1, 1]]))
    cam = cam_mod.auto_frame(np.array([[-1.0, -1, -1], [1, 1, 1]]), 24, 24,
                             view_from=(1.0, 0.2, 0.3))
    res = render_srf(store, surf, cam, [unit_light(store.light_dirs[0], 0)], warp=warp)
    assert np.isfinite(res.image).all()


def test_splat_does_not_depend_on_the_pair_chunk(monkeypatch):
    import texelbake.srf.splat as splat_mod

    s = _plane_surfels()
    whole = splat_surfels(s, CAM)
    monkeypatch.setattr(splat_mod, "PAIR_CHUNK", 500)
    parts = splat_surfels(s, CAM)
    assert np.array_equal(whole.covered, parts.covered)
    np.testing.assert_array_equal(whole.p_rest, parts.p_rest)


def test_splat_depth_stays_on_the_surface_at_grazing_angles():
    # kernel-only fragments of grazing surfels (at the silhouette) must not win the z-test
    # with a hit far along their plane
    pts, faces = icosphere(3)
    s = surfels_from_mesh(pts, faces)
    cam = cam_mod.look_at((0.0, 0.4, 3.2), (0.0, 0.0, 0.0), 96, 96)
    g = splat_surfels(s, cam)
    o, d = cam_mod.eye_rays_at(cam, np.arange(96 * 96), np.full((96 * 96, 2), 0.5))
    hits = RayCaster(pts, faces).cast(o, d)
    both = g.covered & hits.hit
    err = np.abs(np.linalg.norm(g.p_star - cam.position, axis=1) - hits.t)[both]
    assert both.sum() > 2000
    assert err.max() <= np.max(np.maximum(s.su, s.sv))
