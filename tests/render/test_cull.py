"""Eye rays that miss everything a frame shows are not traced (`trace.tracer.culled`): the
box test against brute force, and a small object's frame identical with and without it."""

from __future__ import annotations

import numpy as np

from tests.helpers.render import distant, icosphere, model
from texelbake.trace import camera as cam_mod
from texelbake.trace.org import OrgScene, render_model, shade_org
from texelbake.trace.tracer import accumulate, enters_box


def test_enters_box_against_points_along_the_ray(rng):
    box = np.array([[-1.0, -0.5, 0.0], [1.0, 0.5, 0.25]])
    o = rng.uniform(-2, 2, (2000, 3))
    d = rng.normal(size=(2000, 3))
    d[:200, 1:] = 0.0  # axis-aligned rays: zero components
    d[200:300, 0] = 0.0
    o[200:250, 0] = -1.0  # ... starting on a slab plane
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    got = enters_box(o, d, box)
    t = np.linspace(0.0, 8.0, 4001)  # step 2e-3: brute force on points along each ray
    pts = o[:, None, :] + t[None, :, None] * d[:, None, :]
    inside = np.all((pts >= box[0] - 1e-9) & (pts <= box[1] + 1e-9), axis=2).any(axis=1)
    # a ray grazing a corner within the step can be missed by the points: allow those only
    assert np.all(got[inside]) and np.mean(got != inside) < 0.002
    assert got.sum() > 50 and (~got).sum() > 50


def test_a_small_object_renders_the_same_with_and_without_the_cull():
    pts, faces = icosphere(3)
    asset = model(pts, faces, normals=pts, lights=[distant(np.array([0.3, 0.2, 0.9]), 3.0)])
    # the unit sphere about 20 px across in a 96² frame: most eye rays miss it
    cam = cam_mod.look_at((0.5, 1.0, 16.0), (0.0, 0.0, 0.0), 96, 96, fov_deg=36.0)
    culled = render_model(asset, cam, spp=4, seed=2)
    scene = OrgScene(asset)
    img, rays, cov = accumulate(cam, 4, 2, lambda o, d: shade_org(scene, o, d))
    np.testing.assert_array_equal(culled.image, img.astype(np.float32))
    np.testing.assert_array_equal(culled.coverage, cov.astype(np.float32))
    assert culled.rays_cast == rays  # a culled eye ray counts as one ray
    assert 0.0 < cov.mean() < 0.1  # the object is small in the frame, and seen


def test_box_pixels_hold_every_eye_ray_that_enters_the_box(rng):
    from texelbake.trace.camera import box_pixels
    from texelbake.trace.tracer import progressive

    box = np.array([[-0.4, -0.3, -0.2], [0.5, 0.2, 0.3]])
    cam = cam_mod.look_at((1.0, 2.0, 6.0), (0.2, 0.0, 0.0), 64, 48, fov_deg=40.0)
    pix = box_pixels(cam, box)
    off = rng.random((8, 64 * 48, 2))  # eight random eye rays through every pixel
    o, d = cam_mod.eye_rays(cam, off)
    enters = enters_box(o, d, box).reshape(8, -1).any(axis=0)
    assert enters.sum() > 20 and np.all(np.isin(np.flatnonzero(enters), pix))
    assert pix.size < 0.5 * 64 * 48  # and the rectangle is much smaller than the frame
    behind = cam_mod.look_at((0.0, 0.0, 0.0), (0.0, 0.0, 5.0), 16, 16, fov_deg=40.0)
    assert box_pixels(behind, box) is None  # the camera inside the box: every pixel
    # the budgeted frames (equal-time) see the object only inside the rectangle, and the
    # rest of the frame is background
    pts, faces = icosphere(2)
    scene = OrgScene(model(pts * 0.2, faces, normals=pts,
                           lights=[distant(np.array([0.3, 0.2, 0.9]), 3.0)]))
    img, _, cov, spp, _ = progressive(cam, 1, lambda oo, dd: shade_org(scene, oo, dd), 0.05,
                                      scene.eye_box)
    inside = np.zeros(64 * 48, bool)
    inside[box_pixels(cam, scene.eye_box)] = True
    assert cov.reshape(-1)[~inside].max() == 0 and cov.max() > 0 and spp >= 1
