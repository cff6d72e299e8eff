"""Top-level mean fit (seed 001, Eqs. 5-6) and its divergence guard."""

import numpy as np
import pytest

from texelbake.btf.lut import bonn_directions
from texelbake.btf.phong import fit_phong, phong_eval
from texelbake.errors import ShapeError


def _grid():
    dirs = bonn_directions()[::2]  # 41 directions -> 1681 pairs, light-major
    n = dirs.shape[0]
    return np.repeat(dirs, n, axis=0), np.tile(dirs, (n, 1))


def test_phong_eval_closed_form():
    wi = np.array([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8], [0.0, 0.0, 1.0]])
    wo = np.array([[0.0, 0.0, 1.0], [-0.6, 0.0, 0.8], [0.0, 0.6, -0.8]])
    v = phong_eval((0.1, 0.5, 0.3, 10.0), wi, wo)
    # pair 0: N.L = 1, N.H = 1; pair 1: mirror pair, N.H = 1, N.L = 0.8; pair 2: below horizon
    assert np.allclose(v, [0.1 + 0.5 + 0.3, 0.1 + 0.5 * 0.8 + 0.3, 0.0])
    with pytest.raises(ShapeError):
        phong_eval((0, 0, 0, 1), wi, wo[:2])


def test_fit_recovers_known_parameters_from_far_start():
    wi, wo = _grid()
    truth = (0.04, 0.55, 0.3, 25.0)
    table = phong_eval(truth, wi, wo)
    fit = fit_phong(table, wi, wo, x0=(2.0, -1.0, 5.0, 900.0))  # far: alpha 36x, signs wrong
    assert fit.model == "phong", fit.message
    assert np.allclose(fit.params, truth, rtol=1e-6, atol=1e-9)
    assert fit.rms < 1e-9
    default = fit_phong(table, wi, wo)  # grid start
    assert np.allclose(default.params, truth, rtol=1e-6, atol=1e-9)


def test_fit_ignores_pairs_below_horizon():
    wi, wo = _grid()
    wo = wo.copy()
    wo[::7, 2] *= -1.0  # some view directions below the horizon, with garbage values
    table = phong_eval((0.0, 0.4, 0.2, 12.0), wi, wo)
    table[::7] = 50.0
    fit = fit_phong(table, wi, wo)
    assert fit.model == "phong"
    assert np.allclose(fit.params, (0.0, 0.4, 0.2, 12.0), rtol=1e-6, atol=1e-9)


def test_divergent_fit_falls_back_to_table_and_says_so():
    # adversarial: zero everywhere except one spike at the pair where H = N exactly; the
    # least-squares lobe is a delta, so LM drives alpha to infinity
    wi, wo = _grid()
    table = np.zeros(wi.shape[0])
    spike = np.nonzero((wi[:, 2] == 1.0) & (wo[:, 2] == 1.0))[0]
    table[spike] = 1.0
    fit = fit_phong(table, wi, wo)
    assert fit.model == "table"
    assert fit.params == (0.0, 0.0, 0.0, 0.0)
    assert "rejected" in fit.message and "tabulated mean" in fit.message
    assert "alpha" in fit.message  # the reason names the diverging parameter


def test_unidentifiable_lobe_keeps_diffuse_part(rng):
    # a mean with no lobe at all (plus noise): alpha runs off to 0 or infinity, but dropping
    # the lobe costs nothing, so ka + kd (N.L) is kept instead of the table
    wi, wo = _grid()
    table = 0.2 + 0.3 * wi[:, 2] + 1e-3 * rng.standard_normal(wi.shape[0])
    fit = fit_phong(table, wi, wo)
    assert fit.model == "phong"
    assert np.allclose(fit.params[:2], (0.2, 0.3), atol=1e-3)
    assert fit.rms < 1.1e-3


def test_fit_with_no_valid_pair_keeps_table():
    wi = np.array([[0.0, 0.0, -1.0]])
    fit = fit_phong(np.array([1.0]), wi, wi)
    assert fit.model == "table" and "horizon" in fit.message


def test_fit_shape_error():
    wi, wo = _grid()
    with pytest.raises(ShapeError, match="mean must be"):
        fit_phong(np.zeros(3), wi, wo)


def test_resolvable_alpha_from_the_direction_spacing():
    """(cos(δ/2))^alpha = 1/2 with δ the median nearest-neighbour angle: directions 20
    degrees apart on a great circle resolve alpha = ln(1/2) / ln(cos 10 deg) = 45.2."""
    from texelbake.btf.compress import resolvable_alpha

    t = np.radians(np.arange(0, 81, 20.0))
    dirs = np.stack([np.sin(t), np.zeros_like(t), np.cos(t)], axis=1)
    expect = np.log(0.5) / np.log(np.cos(np.radians(10.0)))
    assert resolvable_alpha(dirs, dirs) == pytest.approx(expect, rel=1e-6)
    # the larger spacing of the two sets decides
    fine = np.stack([np.sin(t / 2), np.zeros_like(t), np.cos(t / 2)], axis=1)
    assert resolvable_alpha(fine, dirs) == pytest.approx(expect, rel=1e-6)


def test_a_lobe_sharper_than_the_sampling_keeps_the_table():
    """The bolt's case: a specular spike sampled on a coarse grid. An exponent beyond what the
    grid resolves would be evaluated between the pairs as highlights the data never had, so
    the fit keeps the tabulated mean; an exactly diffuse mean on the same grid keeps Eq. 5."""
    from texelbake.btf.compress import resolvable_alpha

    wi, wo = _grid()
    cap = resolvable_alpha(wi, wo)
    spiky = phong_eval((0.01, 0.2, 5.0, 3000.0), wi, wo)
    assert fit_phong(spiky, wi, wo).model == "phong"  # unbounded, it chases the spike
    fit = fit_phong(spiky, wi, wo, alpha_max=cap)
    assert fit.model == "table" and "outside" in fit.message
    diffuse = phong_eval((0.0, 0.19, 0.0, 1.0), wi, wo)
    fit = fit_phong(diffuse, wi, wo, alpha_max=cap)
    assert fit.model == "phong" and abs(fit.params[2]) < 1e-9
    np.testing.assert_allclose(fit.params[1], 0.19, rtol=1e-6)
