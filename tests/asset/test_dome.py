"""DomeLight as importance-sampled distant lights (texelbake.asset.dome), against closed forms:
a constant dome L over a Lambertian plane gives the irradiance π L, and under a parallel
square occluder π L (1 − F) with F the square's form factor; a textured dome against a brute
force sum over its pixels; and the lat-long layout of UsdLux read from a USD stage."""

from __future__ import annotations

import numpy as np
import pytest
from pxr import Gf, Sdf, UsdGeom, UsdLux

from tests.helpers.usd_stages import new_stage, triangle_mesh, write_png
from texelbake.asset import load_asset
from texelbake.asset.dome import DOME_SAMPLES, dome_lights, latlong_directions, sample_latlong
from texelbake.errors import ShapeError
from texelbake.geometry.raycast import RayCaster
from texelbake.trace.shade import direct_radiance

Y_TO_Z = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])  # dome +Y -> world +Z
CONSTANT = np.ones((32, 64, 3))


def _irradiance(lights, normal, occluder=None) -> float:
    """E at the origin of a surface with `normal` (Lambertian radiance times π / ρ)."""
    n = np.asarray(normal, dtype=np.float64)[None, :]
    rad, _ = direct_radiance(np.zeros((1, 3)), n, n, n, lights,
                             lambda s, wi, wo: np.full((s.shape[0], 3), 1.0 / np.pi),
                             occluder, 1e-6)
    return float(rad[0, 0]) * np.pi


def _square_form_factor(half: float, h: float) -> float:
    """Form factor from a point to a parallel square of side 2 half centred h above it: four
    a x a rectangles seen from below a corner, F_c = (1 / 2π) [X / √(1 + X²) atan(Y / √(1 + X²))
    + Y / √(1 + Y²) atan(X / √(1 + Y²))], X = Y = half / h (Howell's catalogue, C-11)."""
    x = half / h
    r = np.sqrt(1.0 + x * x)
    return float(4.0 * (2.0 * x / r * np.arctan(x / r)) / (2.0 * np.pi))


def test_constant_dome_gives_pi_l_on_an_open_plane():
    # seed 0: within 3 % (the stratified estimate's spread over seeds is 0.9 % at 256
    # directions: 3 sigma); averaged over 50 seeds within 0.5 % (its standard error 0.13 %):
    # the estimate is unbiased, not tuned to one draw
    lights = dome_lights("/Dome", 2.0 * CONSTANT, Y_TO_Z)
    assert len(lights) == DOME_SAMPLES and all(lt.kind == "distant" for lt in lights)
    assert _irradiance(lights, [0, 0, 1]) == pytest.approx(2.0 * np.pi, rel=0.03)
    est = []
    for seed in range(50):
        d, rad, pdf = sample_latlong(CONSTANT, DOME_SAMPLES, seed)
        est.append(float(np.mean(np.maximum(d[:, 1], 0.0) * rad[:, 0] / pdf)))
    assert np.mean(est) == pytest.approx(np.pi, rel=0.005)


def test_constant_dome_under_a_square_occluder():
    # a 2 x 2 square 1 above the point: F = 0.554, E = π L (1 - F); the visible sky is a
    # ring, a discontinuous integrand: the spread over seeds is 4 % (measured), the bound 12 %
    # for seed 0 and 2 % for the mean of 20 seeds (3 sigma / sqrt(20) = 2.7 % rounded down
    # as the mean's error was 1.4 %)
    sq = np.array([[-1.0, -1.0, 1.0], [1.0, -1.0, 1.0], [1.0, 1.0, 1.0], [-1.0, 1.0, 1.0]])
    occ = RayCaster(sq, np.array([[0, 1, 2], [0, 2, 3]]))
    truth = np.pi * (1.0 - _square_form_factor(1.0, 1.0))
    assert _square_form_factor(1.0, 1.0) == pytest.approx(0.5541, abs=1e-4)
    assert _irradiance(dome_lights("/D", CONSTANT, Y_TO_Z), [0, 0, 1], occ) == pytest.approx(
        truth, rel=0.12)
    mean = np.mean([_irradiance(dome_lights("/D", CONSTANT, Y_TO_Z, seed=s), [0, 0, 1], occ)
                    for s in range(20)])
    assert mean == pytest.approx(truth, rel=0.03)


def test_textured_dome_against_a_sum_over_its_pixels():
    # a dim sky with a small bright "sun" patch: importance sampling puts directions there
    rng = np.random.default_rng(1)
    h, w = 16, 32
    sky = 0.2 + 0.1 * rng.random((h, w, 3))
    sky[4:6, 20:22] = 40.0
    # brute force: every pixel supersampled 16 x 16, L cos+ dω summed (dω = 2π² sin θ du dv)
    k = 16
    uu, vv = np.meshgrid((np.arange(w * k) + 0.5) / (w * k), (np.arange(h * k) + 0.5) / (h * k))
    dirs = latlong_directions(uu.ravel(), vv.ravel())
    d_omega = 2 * np.pi ** 2 * np.sin(np.pi * vv.ravel()) / (w * k * h * k)
    lum = np.repeat(np.repeat(sky, k, axis=0), k, axis=1).reshape(-1, 3)
    for normal in ([0.0, 1.0, 0.0], [0.6, 0.8, 0.0]):
        truth = float((lum[:, 0] * np.maximum(dirs @ normal, 0) * d_omega).sum())
        est = _irradiance(dome_lights("/D", sky, np.eye(3)), normal)
        assert est == pytest.approx(truth, rel=0.03), normal
    # the sun's pixels hold 2 % of the map but most of its power: most directions go there
    d, _, _ = sample_latlong(sky, DOME_SAMPLES)
    sun = latlong_directions(np.array([21 / 32]), np.array([5 / 16]))[0]
    assert np.mean(d @ sun > np.cos(np.radians(20))) > 0.5
    with pytest.raises(ShapeError, match="radiance"):
        sample_latlong(np.ones((4, 8)), 16)


def test_latlong_layout_and_a_dome_read_from_usd(tmp_path):
    # UsdLux (OpenEXR): u = 0.5 at the equator is +Z, u = 0.25 is +X, the top row +Y
    np.testing.assert_allclose(latlong_directions(np.array([0.5, 0.25, 0.5]),
                                                  np.array([0.5, 0.5, 0.0])),
                               np.eye(3)[[2, 0, 1]], atol=1e-12)
    # a map lit only on its left half (u < 0.5: longitudes +π..0, the +X side)
    px = np.zeros((8, 16, 3), dtype=np.uint8)
    px[:, :8] = 255
    write_png(tmp_path / "env.png", px)
    stage = new_stage(tmp_path / "a.usda")  # Y-up
    triangle_mesh(stage, "/Root/T", [(0, 0, 0), (1, 0, 0), (0, 1, 0)], [0, 1, 2])
    dome = UsdLux.DomeLight.Define(stage, "/Root/Env")
    dome.CreateTextureFileAttr(Sdf.AssetPath("./env.png"))
    dome.CreateIntensityAttr(2.0)
    dome.CreateColorAttr(Gf.Vec3f(1.0, 0.5, 0.25))
    stage.Save()
    asset = load_asset(tmp_path / "a.usda")
    domes = [lt for lt in asset.lights if lt.path.startswith("/Root/Env/")]
    assert len(domes) == DOME_SAMPLES and not any("Dome" in w for w in asset.warnings)
    dirs = np.array([lt.direction for lt in domes])
    scale = np.array([lt.radiance_scale for lt in domes])
    assert (dirs[scale[:, 0] > 0, 0] >= -1e-9).all()  # every lit direction on the +X side
    # the colour and intensity scale the radiance: E on a +X plane = 2 (1, .5, .25) × the
    # half-lit dome's π (a +X plane sees exactly the lit half)
    e = (scale * np.maximum(dirs[:, :1], 0)).sum(axis=0)
    np.testing.assert_allclose(e, 2.0 * np.pi * np.array([1.0, 0.5, 0.25]), rtol=0.03)
    # the dome's transform turns it: rotated 180 degrees about Y, the lit half is -X
    UsdGeom.Xformable(dome).AddRotateYOp().Set(180.0)
    stage.Save()
    turned = [lt for lt in load_asset(tmp_path / "a.usda").lights if lt.path.startswith("/Root")]
    lit = np.array([lt.direction for lt in turned if lt.radiance_scale[0] > 0])
    assert (lit[:, 0] <= 1e-9).all()
