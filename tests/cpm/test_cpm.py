import math
from fractions import Fraction

import mpmath
import numpy as np
import pytest

from texelbake.cpm.assemble import SNR_EXACT_DB, percentiles
from texelbake.cpm.column_sampling import fit_weights
from texelbake.cpm.fit import (
    TexelFit,
    channel_correlation,
    evaluate_fit,
    fit_texel,
    reconstruct,
)
from texelbake.cpm.matrix import (
    avis_floor,
    avis_on_grid,
    filtered_reflectance,
    reflectance_matrix,
    reflectance_pairs,
    snr_db,
)
from texelbake.cpm.texel_fit import FitParams, storable_weights
from texelbake.errors import NumericalError, SettingsError, ShapeError
from texelbake.geometry.directions import heldout_pairs, hemisphere_directions, product_pairs
from texelbake.tol import TOL


def _fit_texel(R, avis, seed=0, texel_area=None, rows="eq7", **params):
    """`fit_texel` with FitParams from keywords."""
    return fit_texel(R, avis, FitParams(**params), seed=seed, texel_area=texel_area, rows=rows)

N_I = N_O = 12


def phong(n_s, mat, wi, wo, kd, ks, exps):
    """Modified Phong f_r (b, m, ch) for paired wi, wo (b, 3), sample normals n_s (m, 3)."""
    refl = 2.0 * (wi @ n_s.T)[:, :, None] * n_s[None] - wi[:, None, :]  # (b, m, 3)
    ca = np.clip(np.einsum("bmx,bx->bm", refl, wo), 0.0, None)  # (b, m)
    e = exps[mat]
    spec = ks[mat][None, :] * (e + 2.0) / (2.0 * np.pi) * ca ** e[None, :]
    return kd[mat][None, :, :] / np.pi + spec[:, :, None]


def texel(rng, m=40, kd=None, ks=(0.0, 0.5), exps=(1.0, 30.0), vis_p=0.8, tilt=0.5):
    """A random texel: tilted normals, two materials, random visibility, on an N_I x N_O grid."""
    kd = np.array([[0.6, 0.3, 0.2], [0.1, 0.2, 0.5]]) if kd is None else np.asarray(kd)
    ks, exps = np.asarray(ks, float), np.asarray(exps, float)
    n_s = np.column_stack([rng.uniform(-tilt, tilt, (m, 2)), np.ones(m)])
    n_s /= np.linalg.norm(n_s, axis=1, keepdims=True)
    mat = rng.integers(0, 2, m)
    area = rng.uniform(0.5, 1.5, m) / m
    wi, wo = hemisphere_directions(N_I, 1), hemisphere_directions(N_O, 2)
    vis_i, vis_o = rng.random((m, N_I)) < vis_p, rng.random((m, N_O)) < vis_p
    cos_i, cos_o = n_s @ wi.T, n_s @ wo.T

    def brdf(ri, ro):
        return phong(n_s, mat, wi[ri], wo[ro], kd, ks, exps)

    R = reflectance_matrix(brdf, vis_i, vis_o, cos_i, cos_o, area)
    _, ro = product_pairs(N_I, N_O)
    avis = avis_on_grid(vis_o, cos_o, area)[ro]
    return {
        "R": R,
        "avis": avis,
        "area": area,
        "n_s": n_s,
        "mat": mat,
        "wi": wi,
        "wo": wo,
        "vis_i": vis_i,
        "vis_o": vis_o,
        "brdf": brdf,
        "kd": kd,
        "ks": ks,
        "exps": exps,
    }


def flat_lambert(m=30, rho=(0.5, 0.3, 0.2), extra_wo=None, rng=None):
    """All samples share the texel normal and albedo, no occlusion (issue 3 acceptance (a))."""
    rng = rng or np.random.default_rng(0)
    rho = np.asarray(rho)
    wi, wo = hemisphere_directions(N_I, 1), hemisphere_directions(N_O, 2)
    if extra_wo is not None:
        wo = np.vstack([wo, extra_wo])
    area = rng.uniform(0.5, 2.0, m)
    n_s = np.tile([0.0, 0.0, 1.0], (m, 1))
    cos_i, cos_o = n_s @ wi.T, n_s @ wo.T
    f = np.broadcast_to(rho / np.pi, (len(wi), len(wo), m, 3))
    vis_i, vis_o = np.ones((m, len(wi)), bool), np.ones((m, len(wo)), bool)
    R = reflectance_matrix(f, vis_i, vis_o, cos_i, cos_o, area)
    ri, ro = product_pairs(len(wi), len(wo))
    avis = avis_on_grid(vis_o, cos_o, area)[ro]
    return R, avis, wi[ri], wo[ro], rho, area


# ----------------------------------------------------------------------- the matrix R


def test_reflectance_matrix_brute_force(rng):
    t = texel(rng, m=6)
    R = t["R"]
    assert R.shape == (N_I * N_O, 6, 3) and R.dtype == np.float64
    cos_i, cos_o = t["n_s"] @ t["wi"].T, t["n_s"] @ t["wo"].T
    for i in range(N_I):  # brute force: Eq. 4 x dA entry by entry (tiny sizes)
        for o in range(0, N_O, 3):
            f = t["brdf"](np.array([i]), np.array([o]))[0]  # (m, 3)
            for j in range(6):
                ref = (
                    t["vis_i"][j, i]
                    * t["vis_o"][j, o]
                    * f[j]
                    * max(cos_i[j, i], 0.0)
                    * max(cos_o[j, o], 0.0)
                    * t["area"][j]
                )
                np.testing.assert_allclose(R[i * N_O + o, j], ref, rtol=1e-14, atol=0)
    # the array form and the callable form agree exactly
    ri, ro = product_pairs(N_I, N_O)
    f_all = t["brdf"](ri, ro).reshape(N_I, N_O, 6, 3)
    R2 = reflectance_matrix(f_all, t["vis_i"], t["vis_o"], cos_i, cos_o, t["area"])
    np.testing.assert_array_equal(R, R2)
    # paired form on the grid's own pairs reproduces the product form
    Rp = reflectance_pairs(
        t["brdf"](ri, ro),
        t["vis_i"][:, ri],
        t["vis_o"][:, ro],
        cos_i[:, ri],
        cos_o[:, ro],
        t["area"],
    )
    np.testing.assert_allclose(Rp, R, rtol=1e-15, atol=0)


def test_avis_on_grid_brute_force(rng):
    t = texel(rng, m=9)
    cos_o = t["n_s"] @ t["wo"].T
    av = avis_on_grid(t["vis_o"], cos_o, t["area"])
    ref = [
        sum(t["area"][j] * max(cos_o[j, o], 0) for j in range(9) if t["vis_o"][j, o])
        for o in range(N_O)
    ]
    np.testing.assert_allclose(av, ref, rtol=1e-14)


def test_matrix_shape_errors(rng):
    t = texel(rng, m=5)
    cos_i = t["n_s"] @ t["wi"].T
    cos_o = t["n_s"] @ t["wo"].T
    with pytest.raises(ShapeError):
        reflectance_matrix(
            np.ones((N_I, N_O, 4, 3)), t["vis_i"], t["vis_o"], cos_i, cos_o, t["area"]
        )
    with pytest.raises(ShapeError):
        reflectance_matrix(t["brdf"], t["vis_i"], t["vis_o"], cos_i[:, :3], cos_o, t["area"])
    with pytest.raises(ShapeError):
        reflectance_matrix(
            lambda ri, ro: np.ones((len(ri), 4, 3)), t["vis_i"], t["vis_o"], cos_i, cos_o, t["area"]
        )
    with pytest.raises(NumericalError):
        avis_on_grid(t["vis_o"], cos_o, np.full(5, np.nan))


# ------------------------------------------------------------- Eq. 7 and the a_vis -> 0 limit


def test_filtered_reflectance_avis_zero_limit():
    rw = np.array([[1.0, 2.0], [3e-20, 1e-20], [0.0, 0.0], [5.0, 5.0]])
    avis = np.array([0.5, 1e-20, 0.0, 2.0])
    with np.errstate(all="raise"):  # no division by zero, no 0/0 anywhere
        fbar, valid = filtered_reflectance(rw, avis, eps=1e-9)
    np.testing.assert_array_equal(valid, [True, False, False, True])
    np.testing.assert_array_equal(fbar, [[2.0, 4.0], [0, 0], [0, 0], [2.5, 2.5]])
    f1, v1 = filtered_reflectance(rw[:, 0], avis, eps=1e-9)
    assert f1.shape == (4,) and v1.sum() == 2
    with pytest.raises(ShapeError):
        filtered_reflectance(rw, avis[:3], eps=0.0)


def test_grazing_and_fully_masked_rows(rng):
    # view directions exactly at the horizon (cos = 0) and one below TOL.grazing_cos: a_vis = 0
    grazing = np.array([[1.0, 0.0, 0.0], [np.sqrt(1 - 1e-14), 0.0, 1e-7]])
    assert grazing[1, 2] < TOL.grazing_cos
    R, avis, wi_r, wo_r, rho, area = flat_lambert(extra_wo=grazing)
    n_o = N_O + 2
    bad = np.isin(np.arange(len(avis)) % n_o, [N_O, N_O + 1])
    assert np.all(avis[bad] == 0.0) and np.all(R[bad] == 0.0)
    fit = _fit_texel(R, avis)
    fbar, valid = reconstruct(fit, R, avis, avis_floor(area.sum()))
    assert np.all(np.isfinite(fbar)) and not np.any(valid[bad]) and np.all(valid[~bad])
    assert np.all(fbar[bad] == 0.0)
    assert fit.valid and math.isfinite(fit.snr_db_insample)

    # fully masked view directions in a random texel: rows of R and a_vis are zero
    t = texel(rng, m=30)
    vis_o = t["vis_o"].copy()
    vis_o[:, [2, 5]] = False
    cos_i, cos_o = t["n_s"] @ t["wi"].T, t["n_s"] @ t["wo"].T
    R = reflectance_matrix(t["brdf"], t["vis_i"], vis_o, cos_i, cos_o, t["area"])
    _, ro = product_pairs(N_I, N_O)
    avis = avis_on_grid(vis_o, cos_o, t["area"])[ro]
    with np.errstate(divide="raise", invalid="raise"):
        fit = _fit_texel(R, avis, texel_area=t["area"].sum(), seed=1)
    assert fit.valid and np.all(np.isfinite(fit.weights)) and np.isfinite(fit.snr_db_insample)


def test_no_valid_row_and_empty_texel():
    fit = _fit_texel(np.ones((8, 3, 1)), np.zeros(8))
    assert not fit.valid and fit.c == 0 and "a_vis" in fit.reason
    empty = _fit_texel(np.zeros((16, 0, 3)), np.ones(16))
    assert not empty.valid and empty.c == 0 and empty.k == 0
    assert empty.columns.shape == (0,) and empty.columns.dtype == np.int64
    assert empty.weights.shape == (0, 3) and empty.weights.dtype == np.float32


# --------------------------------------------------------------------------------- SNR


def test_snr_db_closed_form_and_limits():
    ref = np.array([[3.0, 4.0], [0.0, 0.0]])
    apx = np.array([[3.0, 3.0], [0.0, 1.0]])
    assert snr_db(ref, apx) == pytest.approx(10 * math.log10(25 / 2))
    assert snr_db(ref, apx, np.array([True, False])) == pytest.approx(10 * math.log10(25))
    z = np.zeros((3, 2))
    assert snr_db(z, z) == math.inf  # zero target reproduced by alpha = 0
    assert snr_db(z, z + 1.0) == -math.inf
    assert snr_db(ref, ref) == math.inf
    assert snr_db(ref, apx, np.zeros(2, bool)) == math.inf  # nothing to measure
    with pytest.raises(ShapeError):
        snr_db(ref, apx[:1])


def test_snr_db_extreme_scale_against_exact_fractions(rng):
    # values near 1e-200 (squares underflow in float64) and 1e150 (squares overflow): the SNR
    # must match exact rational arithmetic
    for scale in (1e-200, 1.0, 1e150):
        ref = rng.random((50, 3)) * scale
        apx = ref * (1 + 1e-3 * rng.standard_normal((50, 3)))
        sig = sum(Fraction(x) ** 2 for x in ref.ravel())
        noi = sum(
            (Fraction(a) - Fraction(b)) ** 2 for a, b in zip(ref.ravel(), apx.ravel(), strict=True)
        )
        exact = 10 * math.log10(sig / noi)
        assert snr_db(ref, apx) == pytest.approx(exact, abs=1e-9)


# ----------------------------------------------------------------------- the texel fit


def test_flat_lambertian_exact(rng):
    # issue 3 acceptance (a): f_bar = rho / pi cos(theta_i) to 1e-6, one characteristic point
    R, avis, wi_r, wo_r, rho, area = flat_lambert()
    fit = _fit_texel(R, avis, texel_area=area.sum())
    assert fit.c == 1 and fit.k == 1 and fit.valid and fit.eps_reached
    fbar, valid = reconstruct(fit, R, avis, avis_floor(area.sum()))
    assert valid.all()
    truth = rho[None, :] / np.pi * wi_r[:, 2:3]
    np.testing.assert_allclose(fbar, truth, rtol=0, atol=1e-6)
    # held-out pairs too: it is exact, not fitted
    wi_h, wo_h = heldout_pairs(64, seed=3)
    m = R.shape[1]
    n_s = np.tile([0.0, 0.0, 1.0], (m, 1))
    Rh = reflectance_pairs(
        np.broadcast_to(rho / np.pi, (64, m, 3)),
        np.ones((m, 64), bool),
        np.ones((m, 64), bool),
        n_s @ wi_h.T,
        n_s @ wo_h.T,
        area,
    )
    avis_h = avis_on_grid(np.ones((m, 64), bool), n_s @ wo_h.T, area)
    fbar_h, _ = reconstruct(fit, Rh, avis_h, avis_floor(area.sum()))
    np.testing.assert_allclose(fbar_h, rho[None] / np.pi * wi_h[:, 2:3], atol=1e-6)
    assert evaluate_fit(fit, Rh, avis_h, avis_floor(area.sum())) > 100.0


def test_rank1_with_occluded_and_duplicate_columns():
    # identical columns (duplicates of one sample) plus all-zero columns (fully occluded
    # samples): one point, weight = the number of live copies, zero columns never selected
    R, avis, *_ = flat_lambert(m=12, rng=np.random.default_rng(1))
    col = R[:, :1, :]
    Rd = np.concatenate([np.repeat(col, 9, axis=1), np.zeros((R.shape[0], 4, 3))], axis=1)
    avis_d = avis * 0 + avis.max()  # any positive a_vis
    fit = _fit_texel(Rd, avis_d)
    assert fit.c == 1 and fit.columns[0] < 9
    np.testing.assert_allclose(fit.weights, 9.0, rtol=1e-6)
    assert fit.snr_db_insample > 120  # exact up to float32 weights


def test_one_sample_texel():
    R, avis, *_ = flat_lambert(m=1)
    fit = _fit_texel(R, avis)
    assert fit.c == 1 and fit.columns.tolist() == [0]
    np.testing.assert_allclose(fit.weights, 1.0, rtol=1e-6)


def test_all_zero_R():
    fit = _fit_texel(np.zeros((20, 5, 3)), np.ones(20))
    assert fit.valid and fit.c == 0 and fit.snr_db_insample == math.inf
    assert fit.weights.shape == (0, 3)


def test_c_max_below_k(rng):
    R = rng.random((144, 30, 1))  # generic: full rank, k ~ 25 at psi = 0.999
    fit = _fit_texel(R, np.ones(144), psi=0.999, c_max=3)
    assert fit.k > 3 and 1 <= fit.c <= 3 and fit.c_capped
    assert "c_max" in fit.reason and fit.valid


def test_specular_dynamic_range_snr_against_mpmath(rng):
    # a sharp Phong lobe (exponent 2000) beside a dim diffuse material: R spans > 1e6
    t = texel(
        rng,
        m=40,
        kd=[[1e-4, 1e-4, 1e-4], [1e-4, 2e-4, 3e-4]],
        ks=(0.0, 1.0),
        exps=(1.0, 2000.0),
        vis_p=0.9,
        tilt=0.3,
    )
    R, avis = t["R"], t["avis"]
    pos = R[R > 0]
    assert pos.max() / pos.min() > 1e6
    fit = _fit_texel(R, avis, texel_area=t["area"].sum(), c_max=40)
    assert np.all(np.isfinite(fit.weights)) and np.isfinite(fit.snr_db_insample)
    # independent SNR in 50-digit arithmetic from the returned float32 weights
    mpmath.mp.dps = 50
    eps = avis_floor(t["area"].sum())
    w = fit.weights.astype(np.float64)
    sig = mpmath.mpf(0)
    noi = mpmath.mpf(0)
    for r in range(R.shape[0]):  # loop in the test's reference only
        if not avis[r] > eps:
            continue
        a = mpmath.mpf(avis[r])
        for x in range(3):
            ref = mpmath.fsum(mpmath.mpf(v) for v in R[r, :, x]) / a
            apx = (
                mpmath.fsum(
                    mpmath.mpf(w[k, x]) * mpmath.mpf(R[r, j, x]) for k, j in enumerate(fit.columns)
                )
                / a
            )
            sig += ref**2
            noi += (ref - apx) ** 2
    exact = float(10 * mpmath.log10(sig / noi))
    # float64 sums of ~40 terms carry ~1e-15 relative error; at SNR <= 150 dB the difference
    # ref - apx keeps >= 1e-8 relative accuracy, i.e. < 1e-6 dB
    assert fit.snr_db_insample == pytest.approx(exact, abs=1e-6)


def test_weighted_points_vs_brute_force_sum(rng):
    # (b): R 1 by brute force against the weighted characteristic points at the reported SNR
    t = texel(rng, m=40)
    fit = _fit_texel(t["R"], t["avis"], texel_area=t["area"].sum(), seed=3)
    eps = avis_floor(t["area"].sum())
    ri, ro = product_pairs(N_I, N_O)
    cos_i, cos_o = t["n_s"] @ t["wi"].T, t["n_s"] @ t["wo"].T
    f = t["brdf"](ri, ro)  # (d, m, 3)
    brute = np.zeros((len(ri), 3))
    for j in range(40):  # Eq. 7's sum sample by sample
        g = (
            t["vis_i"][j, ri]
            * t["vis_o"][j, ro]
            * np.clip(cos_i[j, ri], 0, None)
            * np.clip(cos_o[j, ro], 0, None)
            * t["area"][j]
        )
        brute += f[:, j] * g[:, None]
    apx = np.zeros_like(brute)
    for k, j in enumerate(fit.columns):
        apx += t["R"][:, j] * fit.weights[k].astype(np.float64)
    av = t["avis"]
    ok = av > eps
    ref_f, apx_f = brute[ok] / av[ok, None], apx[ok] / av[ok, None]
    snr = 10 * np.log10(np.sum(ref_f**2) / np.sum((ref_f - apx_f) ** 2))
    assert fit.snr_db_insample == pytest.approx(snr, abs=1e-8)
    assert fit.eps_reached == (fit.snr_db_insample >= 30.0)
    # every stored point carries weight (drawn points NNLS left at 0 are dropped)
    assert fit.c == fit.columns.size and np.all(np.any(fit.weights != 0, axis=1))


def test_nnls_never_worse_than_clamp_on_the_same_points(rng):
    # for a fixed C, NNLS minimises ||C alpha - R 1|| over alpha >= 0 and the seed's clamped
    # pseudo-inverse is one feasible alpha: NNLS is never worse on the row sums
    t = texel(rng, m=40)
    fit = _fit_texel(t["R"], t["avis"], weights="nnls", c_max=8, seed=2)
    clamp = _fit_texel(t["R"], t["avis"], weights="clamp", c_max=8, seed=2)
    assert np.all(fit.weights >= 0) and np.all(clamp.weights >= 0)
    for x in range(3):
        C = t["R"][:, fit.columns, x]
        target = t["R"][:, :, x].sum(axis=1)
        a_n = fit_weights(C, target, "nnls")
        a_c = fit_weights(C, target, "clamp")
        assert np.linalg.norm(C @ a_n - target) <= np.linalg.norm(C @ a_c - target) * (1 + 1e-9)


def test_batching(rng):
    # low-rank texel of 200 samples processed with n_batch = 40: same quality target reached
    base = texel(rng, m=4)["R"]  # (d, 4, 3)
    mix = rng.random((4, 200))
    R = np.einsum("dkx,km->dmx", base, mix)
    avis = np.full(R.shape[0], 1.0)
    fb = _fit_texel(R, avis, n_batch=40, c_max=8, seed=0)
    fu = _fit_texel(R, avis, c_max=8, seed=0)
    for fit in (fb, fu):
        assert fit.valid and fit.eps_reached and fit.c <= 8 * 3
        assert np.all(np.diff(fit.columns) > 0) and fit.columns.max() < 200
    # a pool of batch selections larger than n_batch is reduced again (20 batches x <= 5
    # points > n_batch = 10): the recursion terminates and the result is still a valid fit
    mix2 = rng.random((4, 200))
    R2 = np.einsum("dkx,km->dmx", base[:, :, :1], mix2)
    fr = _fit_texel(R2, avis, n_batch=10, c_max=8, seed=1)
    assert fr.valid and 1 <= fr.c <= 8 and fr.columns.max() < 200
    assert fr.snr_db_insample > 20.0  # rank-4 texel: a few columns already fit well
    with pytest.raises(SettingsError):
        _fit_texel(R, avis, n_batch=1)


def test_colour_modes(rng):
    # red and blue materials on disjoint samples: channels decorrelated -> per-channel points
    t = texel(rng, m=30, kd=[[0.8, 0.0, 0.0], [0.0, 0.0, 0.8]], ks=(0.0, 0.0))
    assert channel_correlation(t["R"]) < 0.5
    fit = _fit_texel(t["R"], t["avis"], texel_area=t["area"].sum())
    assert fit.colour_mode == "per_channel" and fit.k_channels.shape == (3,)
    red_only = t["mat"][fit.columns] == 0
    # a point chosen for the red channel is a red sample: its blue weight carries nothing
    assert np.all(fit.weights[red_only, 2] == 0.0) and np.all(fit.weights[~red_only, 0] == 0.0)
    # grey albedo: channels proportional -> one shared selection on luminance
    g = texel(rng, m=30, kd=[[0.5, 0.5, 0.5], [0.2, 0.2, 0.2]])
    assert channel_correlation(g["R"]) > 0.999
    assert _fit_texel(g["R"], g["avis"]).colour_mode == "luminance"
    forced = _fit_texel(t["R"], t["avis"], colour="luminance")
    assert forced.colour_mode == "luminance" and forced.k_channels.shape == (1,)


def test_deterministic_and_serializable(rng, tmp_path):
    t = texel(rng, m=40)
    a = _fit_texel(t["R"], t["avis"], seed=7)
    b = _fit_texel(t["R"], t["avis"], seed=7)
    assert a.columns.tobytes() == b.columns.tobytes() and a.weights.tobytes() == b.weights.tobytes()
    assert a.snr_db_insample == b.snr_db_insample
    np.savez(tmp_path / "fit.npz", **a.to_dict())
    back = TexelFit.from_dict(dict(np.load(tmp_path / "fit.npz")))
    assert back.columns.dtype == np.int64 and back.weights.dtype == np.float32
    np.testing.assert_array_equal(back.columns, a.columns)
    np.testing.assert_array_equal(back.weights, a.weights)
    assert (back.k, back.c, back.colour_mode, back.valid) == (a.k, a.c, a.colour_mode, a.valid)
    assert back.snr_db_insample == a.snr_db_insample and math.isnan(back.snr_db_heldout)


def test_fit_input_errors():
    with pytest.raises(NumericalError):
        _fit_texel(np.full((4, 2, 1), np.nan), np.ones(4))
    with pytest.raises(NumericalError):
        _fit_texel(np.ones((4, 2, 1)), np.array([1.0, np.inf, 1.0, 1.0]))
    with pytest.raises(ShapeError):
        _fit_texel(np.ones((4, 2)), np.ones(4))
    with pytest.raises(ShapeError):
        _fit_texel(np.ones((4, 2, 1)), np.ones(3))
    for bad in ({"psi": 0.0}, {"c_max": 0}, {"n_trials": 0}, {"colour": "rgb"}, {"weights": "x"}):
        with pytest.raises(SettingsError):
            _fit_texel(np.ones((4, 2, 1)), np.ones(4), **bad)


def test_channel_correlation_matches_numpy(rng):
    R = rng.random((20, 7, 3))
    R[:, :, 2] = 0.3 * R[:, :, 0] + 0.1 * rng.random((20, 7))
    ref = np.corrcoef(R.reshape(-1, 3).T).min()
    assert channel_correlation(R) == pytest.approx(ref, abs=1e-10)
    const = R.copy()
    const[:, :, 1] = 0.5  # zero-variance channel: correlates with everything
    ref2 = np.corrcoef(const.reshape(-1, 3)[:, [0, 2]].T).min()
    assert channel_correlation(const) == pytest.approx(ref2, abs=1e-10)
    assert channel_correlation(R[:, :, :1]) == 1.0


def test_weights_past_float32_range_are_dropped_not_stored_as_inf():
    """NNLS weights 1/scale of a vanishing column: past float32 they would be stored as inf and
    poison the next level's R with inf x 0 = NaN (the small bolt at 32²); they become 0."""

    w = np.array([[0.5, 2.0], [1e39, 3.0], [np.nan, 1.0], [-1e300, np.inf]])
    out = storable_weights(w)
    assert out.dtype == np.float32 and np.isfinite(out).all()
    np.testing.assert_array_equal(out, np.array([[0.5, 2.0], [0.0, 3.0], [0.0, 1.0],
                                                 [0.0, 0.0]], np.float32))


def test_small_texel_keeps_every_candidate_and_holds_between_the_grid(rng):
    """small="all": a texel of m <= c_max samples keeps all of them at weight 1, so Eq. 7 holds
    at directions the grid never sampled (checked against a brute-force sum over the samples on
    an independent, finer grid with its own visibility); the seed's bisection ("fit") stops at
    the smallest c reaching eps_db on the grid and is measurably worse there. Above c_max the
    two settings are the same fit."""
    t = texel(rng, m=40, exps=(1.0, 60.0))
    area = t["area"]
    eps = avis_floor(area.sum())
    # an independent 20 x 20 grid: other directions, their own random visibility
    wi_h, wo_h = hemisphere_directions(20, 7), hemisphere_directions(20, 8)
    vis_ih, vis_oh = rng.random((40, 20)) < 0.8, rng.random((40, 20)) < 0.8
    ri, ro = product_pairs(20, 20)

    def brdf_h(a, b):
        return phong(t["n_s"], t["mat"], wi_h[a], wo_h[b], t["kd"], t["ks"], t["exps"])

    R_h = reflectance_matrix(brdf_h, vis_ih, vis_oh, t["n_s"] @ wi_h.T, t["n_s"] @ wo_h.T, area)
    avis_h = avis_on_grid(vis_oh, t["n_s"] @ wo_h.T, area)[ro]
    brute = np.zeros((len(ri), 3))
    for j in range(40):  # Eq. 7's numerator sample by sample, not through R's sum
        brute += R_h[:, j]
    ok = avis_h > eps
    fitted = _fit_texel(t["R"], t["avis"], texel_area=area.sum(), seed=3, c_max=64, small="fit")
    kept = _fit_texel(t["R"], t["avis"], texel_area=area.sum(), seed=3, c_max=64, small="all")
    assert fitted.c < 40
    assert kept.c == 40 and np.array_equal(kept.columns, np.arange(40))
    assert np.all(kept.weights == 1.0) and kept.weights.dtype == np.float32
    assert kept.snr_db_insample > 250.0  # round-off only (float64: ~300 dB)

    def held(fit):
        apx = np.einsum("dcx,cx->dx", R_h[:, fit.columns], fit.weights.astype(np.float64))
        return snr_db(brute[ok] / avis_h[ok, None], apx[ok] / avis_h[ok, None])

    assert held(kept) > 250.0
    assert held(fitted) < 60.0  # 30 dB on the grid, off it the drawn points miss lobes
    # above c_max the setting changes nothing
    a = _fit_texel(t["R"], t["avis"], texel_area=area.sum(), seed=3, c_max=20, small="all")
    b = _fit_texel(t["R"], t["avis"], texel_area=area.sum(), seed=3, c_max=20, small="fit")
    assert np.array_equal(a.columns, b.columns) and np.array_equal(a.weights, b.weights)
    with pytest.raises(SettingsError, match="small"):
        _fit_texel(t["R"], t["avis"], small="some")
    # a rank-1 texel's one point is exact everywhere: it stays one point
    R1, avis1, _, _, _, area1 = flat_lambert(m=30)
    one = _fit_texel(R1, avis1, texel_area=area1.sum(), small="all")
    assert one.c == 1 and one.snr_db_insample >= 100.0


def test_report_percentiles_count_exact_texels():
    """+inf (an exact texel's SNR) counts as SNR_EXACT_DB when asked, instead of being left out
    of the median (which would report the worst texels only); NaN is always left out."""
    x = np.array([10.0, 20.0, np.inf, np.inf, np.nan])
    assert percentiles(x)["p50"] == 15.0 and percentiles(x)["n"] == 2
    got = percentiles(x, SNR_EXACT_DB)
    assert got["n"] == 4 and got["p50"] == pytest.approx((20.0 + SNR_EXACT_DB) / 2)
    assert got["max"] == SNR_EXACT_DB
