import itertools

import numpy as np
import pytest

from texelbake.cpm.column_sampling import (
    column_probabilities,
    eckart_young_error,
    energy_rank,
    fit_weights,
    leverage_probabilities,
    pivoted_qr_columns,
    projection_error,
    sample_columns,
    svd_float64,
    top_singular,
    uniform_probabilities,
)
from texelbake.errors import SettingsError, ShapeError


def low_rank(rng, d, m, r, noise=0.0):
    A = rng.random((d, r)) @ rng.random((r, m))
    return A + noise * rng.random((d, m))


def brute_probabilities(R, k):
    """Table 2 from numpy's full SVD and the explicit residual Sigma_{rho-k} V_{rho-k}^T."""
    _, s, Vt = np.linalg.svd(R, full_matrices=False)
    rho = int(np.sum(s > 1e-12 * s[0]))
    Vk = Vt[:k].T  # (m, k)
    t1 = np.sum(Vk**2, axis=1) / np.sum(Vk**2)
    res = s[k:rho, None] * Vt[k:rho]  # (rho - k, m)
    if rho == k:
        return t1
    rn = np.linalg.norm(res, axis=0)
    t3 = rn**2 / np.sum(res**2)
    mix = np.linalg.norm(Vk, axis=1) * rn
    t2 = mix / mix.sum()
    return (t1 + t2 + t3) / 3.0


# ------------------------------------------------------------------------------------ SVD


@pytest.mark.parametrize("method", ["full", "gram", "auto"])
@pytest.mark.parametrize("shape", [(200, 30), (30, 50), (64, 64)])
def test_svd_float64_matches_numpy(method, shape, rng):
    R = low_rank(rng, *shape, r=8, noise=1e-3)
    U, s, Vt = svd_float64(R, method)
    r = min(shape)
    assert U.shape == (shape[0], r) and s.shape == (r,) and Vt.shape == (r, shape[1])
    assert U.dtype == s.dtype == Vt.dtype == np.float64
    s_ref = np.linalg.svd(R, compute_uv=False)
    if method == "gram" or (method == "auto" and shape[0] >= 2 * shape[1]):
        # Gram: eigenvalues of R^T R have absolute error ~ m eps s_1^2, so s_r is resolved to
        # ~ m eps s_1^2 / s_r; below sqrt(m eps) s_1 it is reported as 0
        floor = np.sqrt(shape[1] * np.finfo(float).eps) * s_ref[0]
        res = s_ref > floor
        tol = 10 * shape[1] * np.finfo(float).eps * s_ref[0] ** 2 / s_ref[res]
        assert np.all(np.abs(s[res] - s_ref[res]) <= tol)
        assert np.all(s[~res] == 0.0)
        atol = 2 * floor
    else:
        np.testing.assert_allclose(s, s_ref, rtol=0, atol=1e-12 * s_ref[0])
        atol = 1e-12 * s_ref[0]
    np.testing.assert_allclose(U * s @ Vt, R, rtol=0, atol=atol)


def test_svd_empty_and_errors():
    U, s, Vt = svd_float64(np.zeros((5, 0)))
    assert U.shape == (5, 0) and s.shape == (0,) and Vt.shape == (0, 0)
    with pytest.raises(ShapeError):
        svd_float64(np.zeros(5))
    with pytest.raises(SettingsError):
        svd_float64(np.ones((4, 2)), method="qr")


def test_top_singular_lowrank_matches_full(rng):
    R = low_rank(rng, 1024, 300, r=6, noise=1e-4)
    _, s_full, _ = np.linalg.svd(R, full_matrices=False)
    k_ref = energy_rank(s_full, 0.97)
    for method in ("lowrank", "gram", "full"):
        U, s, Vt, k = top_singular(R, 0.97, method=method)
        assert k == k_ref
        np.testing.assert_allclose(s[:k], s_full[:k], rtol=1e-10)
    _, _, _, k0 = top_singular(np.zeros((10, 4)), 0.97)
    assert k0 == 0


# ------------------------------------------------------------------------------ energy rank


def test_energy_rank_brute_force(rng):
    for _ in range(20):
        s = np.sort(rng.random(12) ** 3)[::-1]
        psi = rng.uniform(0.5, 0.999)
        e = s**2
        k_ref = next(k for k in range(1, 13) if e[:k].sum() >= psi * e.sum())
        assert energy_rank(s, psi) == k_ref


def test_energy_rank_edge_cases():
    assert energy_rank(np.zeros(5), 0.97) == 0  # all-zero R
    assert energy_rank(np.zeros(0), 0.97) == 0
    assert energy_rank(np.array([3.0, 2.0, 1.0]), 1.0) == 3  # psi = 1 despite rounding
    assert energy_rank(np.array([1.0, 0.0, 0.0]), 0.97) == 1  # rank 1
    # partial spectrum with the exact total: not reached -> r + 1
    assert energy_rank(np.array([1.0]), 0.97, total=2.0) == 2
    with pytest.raises(SettingsError):
        energy_rank(np.ones(3), 0.0)


# ---------------------------------------------------------------------- Table 2 probabilities


@pytest.mark.parametrize("k", [1, 3, 5])
def test_column_probabilities_match_brute_force(k, rng):
    R = low_rank(rng, 150, 40, r=8, noise=1e-2)
    U, s, Vt = svd_float64(R, "gram")
    p = column_probabilities(U, s, Vt, k, col_energy=np.sum(R * R, axis=0))
    assert p.shape == (40,) and np.all(p >= 0)
    assert abs(p.sum() - 1.0) < 1e-12
    # from Gram's V vs numpy's SVD: agreement limited by Gram rounding, ~1e-12 here
    np.testing.assert_allclose(p, brute_probabilities(R, k), atol=1e-10)
    # without col_energy (residual from the triplets) the same
    p2 = column_probabilities(*svd_float64(R, "full"), k)
    np.testing.assert_allclose(p2, brute_probabilities(R, k), atol=1e-10)


def test_column_probabilities_k_equals_rank(rng):
    # rank-3 R and k = 3: residual terms are 0/0 -> defined as 0, p = leverage / k.
    # Without the handling the residual terms are NaN (0/0) or rounding noise.
    R = low_rank(rng, 100, 20, r=3)
    U, s, Vt = svd_float64(R)
    p = column_probabilities(U, s, Vt, 3, col_energy=np.sum(R * R, axis=0))
    assert np.all(np.isfinite(p))
    lev = np.sum(np.linalg.svd(R)[2][:3] ** 2, axis=0) / 3.0
    np.testing.assert_allclose(p, lev, atol=1e-10)
    # k above the rank is clamped to the rank
    np.testing.assert_allclose(column_probabilities(U, s, Vt, 7), lev, atol=1e-10)


def test_column_probabilities_zero_columns_never_drawn(rng):
    R = low_rank(rng, 80, 30, r=5, noise=1e-3)
    R[:, [0, 7, 8]] = 0.0  # fully occluded samples
    U, s, Vt = svd_float64(R)
    p = column_probabilities(U, s, Vt, 2, col_energy=np.sum(R * R, axis=0))
    assert np.all(p[[0, 7, 8]] == 0.0)
    idx = sample_columns(p, 500, np.random.default_rng(0))
    assert not set(idx.tolist()) & {0, 7, 8}


def test_column_probabilities_all_zero():
    U, s, Vt = svd_float64(np.zeros((10, 4)))
    p = column_probabilities(U, s, Vt, 0)
    assert p.shape == (4,) and np.all(p == 0.0)
    assert sample_columns(p, 5, np.random.default_rng(0)).shape == (0,)


def test_probabilities_specular_dynamic_range_auto_equals_full(rng):
    # five columns 1e6 brighter (a specular lobe): the Gram route loses the tail singular
    # vectors, but Table 2 only needs V_k and exact residual column norms; where k reaches into
    # the unresolved tail (k = 6 here, psi within 1e-12 of 1) top_singular must switch to the
    # full SVD. Without that switch the k = 6 probabilities are off by ~0.1.
    R = low_rank(rng, 1024, 64, r=12, noise=1e-4)
    R[:, :5] *= 1e6
    ce = np.sum(R * R, axis=0)
    U, s, Vt = svd_float64(R, "full")
    cum = np.cumsum(s**2) / np.sum(s**2)
    for k in (1, 3, 5, 6):
        Ua, sa, Vta, ka = top_singular(R, cum[k - 1], method="auto")
        assert ka == k
        pa = column_probabilities(Ua, sa, Vta, k, col_energy=ce)
        pf = column_probabilities(U, s, Vt, k, col_energy=ce)
        assert np.all(np.isfinite(pa))
        # both exact to ~1e-13 (measured); 1e-9 leaves margin across BLAS builds
        np.testing.assert_allclose(pa, pf, atol=1e-9)


def test_leverage_and_uniform(rng):
    R = low_rank(rng, 60, 12, r=4)
    _, s, Vt = svd_float64(R)
    p = leverage_probabilities(s, Vt, 2)
    np.testing.assert_allclose(p, np.sum(np.linalg.svd(R)[2][:2] ** 2, 0) / 2, atol=1e-10)
    u = uniform_probabilities(4, np.array([1.0, 0.0, 2.0, 3.0]))
    np.testing.assert_allclose(u, [1 / 3, 0, 1 / 3, 1 / 3])


# ----------------------------------------------------------------------------- sampling


def test_sample_columns_dedup_deterministic_and_distribution():
    p = np.array([0.5, 0.0, 0.3, 0.2])
    a = sample_columns(p, 10, np.random.default_rng(4))
    b = sample_columns(p, 10, np.random.default_rng(4))
    assert a.dtype == np.int64 and a.tobytes() == b.tobytes()
    assert np.all(np.diff(a) > 0)  # sorted unique: duplicates removed
    assert 1 not in a
    # i.i.d. draws follow p: counts of 20000 single draws within 4 sigma of binomial means
    rng = np.random.default_rng(1)
    draws = np.array([sample_columns(p, 1, rng)[0] for _ in range(20000)])
    counts = np.bincount(draws, minlength=4)
    sigma = np.sqrt(20000 * p * (1 - p))
    assert np.all(np.abs(counts - 20000 * p) <= 4 * sigma + 1e-9)
    assert sample_columns(p, 0, rng).shape == (0,)
    with pytest.raises(SettingsError):
        sample_columns(p, -1, rng)
    with pytest.raises(ShapeError):
        sample_columns(np.array([0.5, -0.1]), 1, rng)


def test_sample_columns_duplicates_collapse():
    # one column carries all the mass: c draws are c duplicates -> one column
    p = np.array([0.0, 1.0, 0.0])
    np.testing.assert_array_equal(sample_columns(p, 16, np.random.default_rng(0)), [1])


def test_pivoted_qr_columns(rng):
    R = low_rank(rng, 50, 10, r=10)
    R[:, 3] *= 100.0
    R[:, 6] = 0.0
    cols = pivoted_qr_columns(R, 10)
    assert cols[0] == 3  # largest norm pivots first
    assert 6 not in cols  # zero column dropped
    assert pivoted_qr_columns(R, 0).shape == (0,)


# ------------------------------------------------------------------------------ weights


def brute_nnls(C, t):
    """Enumerate active sets: the NNLS optimum is the best feasible unconstrained LS on a subset."""
    best, best_res = np.zeros(C.shape[1]), np.linalg.norm(t)
    for r in range(1, C.shape[1] + 1):
        for sub in itertools.combinations(range(C.shape[1]), r):
            x, *_ = np.linalg.lstsq(C[:, sub], t, rcond=None)
            if np.all(x >= -1e-12):
                res = np.linalg.norm(C[:, sub] @ x - t)
                if res < best_res - 1e-14:
                    best_res = res
                    best = np.zeros(C.shape[1])
                    best[list(sub)] = np.clip(x, 0, None)
    return best, best_res


def test_fit_weights_nnls_brute_force(rng):
    for _ in range(10):
        C = rng.standard_normal((30, 5))
        t = rng.standard_normal(30)
        a = fit_weights(C, t, "nnls")
        ref, ref_res = brute_nnls(C, t)
        assert np.all(a >= 0)
        # optimal residual to rounding; alpha unique since C has full column rank
        assert abs(np.linalg.norm(C @ a - t) - ref_res) < 1e-10
        np.testing.assert_allclose(a, ref, atol=1e-8)


def test_fit_weights_clamp_is_pinv_clamped(rng):
    C = rng.standard_normal((30, 4))
    t = rng.standard_normal(30)
    a = fit_weights(C, t, "clamp")
    np.testing.assert_allclose(a, np.clip(np.linalg.pinv(C) @ t, 0, None), atol=1e-12)


def test_fit_weights_exact_recovery_and_dynamic_range(rng):
    # R 1 inside the cone of C: both methods recover alpha, even across a 1e7 column range
    C = rng.random((200, 4)) * np.array([1e-3, 1.0, 1e4, 1.0])
    alpha = np.array([2.0, 0.5, 3e-4, 1.0])
    for method in ("nnls", "clamp"):
        np.testing.assert_allclose(fit_weights(C, C @ alpha, method), alpha, rtol=1e-8)


def test_fit_weights_degenerate(rng):
    C = rng.random((20, 3))
    # all-zero target: alpha = 0 (and the SNR of a zero target is +inf, see test_cpm)
    assert np.all(fit_weights(C, np.zeros(20)) == 0.0)
    # zero column: weight 0, others fitted
    Cz = C.copy()
    Cz[:, 1] = 0.0
    a = fit_weights(Cz, Cz @ np.array([1.0, 5.0, 2.0]), "nnls")
    assert a[1] == 0.0
    np.testing.assert_allclose(a[[0, 2]], [1.0, 2.0], rtol=1e-8)
    # duplicate columns: the fit is as good as with one copy, finite, non-negative
    Cd = np.column_stack([C[:, 0], C[:, 0], C[:, 2]])
    t = C[:, 0] * 3.0 + C[:, 2]
    for method in ("nnls", "clamp"):
        ad = fit_weights(Cd, t, method)
        assert np.all(np.isfinite(ad)) and np.all(ad >= 0)
        np.testing.assert_allclose(Cd @ ad, t, rtol=1e-8)
    assert fit_weights(np.zeros((5, 0)), np.ones(5)).shape == (0,)
    with pytest.raises(ShapeError):
        fit_weights(C, np.ones(3))
    with pytest.raises(SettingsError):
        fit_weights(C, np.ones(20), "lsq")


# ------------------------------------------------------------------- errors vs Eckart-Young


def test_eckart_young_closed_form(rng):
    R = low_rank(rng, 40, 15, r=6, noise=1e-2)
    U, s, Vt = np.linalg.svd(R, full_matrices=False)
    for c in (1, 3, 6):
        Rc = U[:, :c] * s[:c] @ Vt[:c]
        ref = np.linalg.norm(R - Rc) / np.linalg.norm(R)
        assert abs(eckart_young_error(s, c) - ref) < 1e-12


def test_projection_error_never_below_eckart_young(rng):
    # property: for any c columns, ||R - C C^+ R|| >= ||R - R_c|| (Eckart-Young); also checks
    # projection_error against an independent least-squares residual
    for trial in range(25):
        d, m = rng.integers(20, 60), rng.integers(5, 25)
        R = low_rank(rng, d, m, r=int(rng.integers(1, 6)), noise=10.0 ** rng.uniform(-6, -1))
        _, s, _ = np.linalg.svd(R, full_matrices=False)
        for c in (1, 2, 4):
            cols = np.sort(rng.choice(m, size=c, replace=False))
            err = projection_error(R, cols)
            X, *_ = np.linalg.lstsq(R[:, cols], R, rcond=None)
            ref = np.linalg.norm(R - R[:, cols] @ X) / np.linalg.norm(R)
            assert abs(err - ref) < 1e-9, trial
            assert err >= eckart_young_error(s, c) - 1e-12, (trial, c)
    assert projection_error(np.zeros((4, 3)), np.array([0])) == 0.0
    R = low_rank(rng, 10, 4, r=4)
    assert projection_error(R, np.arange(4)) < 1e-12
    assert projection_error(R, np.zeros(0, dtype=np.int64)) == 1.0


# ----------------------------------------------------------------------- the benchmark


def test_benchmark_run_on_arrays(rng):
    # benchmarks/column_sampling.py run() on small arrays (no ray casting): every method
    # reports, none beats the Eckart-Young floor, medians are finite
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[2] / "benchmarks" / "column_sampling.py"
    spec = importlib.util.spec_from_file_location("bench_column_sampling", path)
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    texels = []
    for _ in range(2):
        base = rng.random((64, 4, 3))
        mix = rng.random((4, 30))
        R = np.einsum("dkx,km->dmx", base, mix) + 1e-3 * rng.random((64, 30, 3))
        Rh = np.einsum("dkx,km->dmx", rng.random((16, 4, 3)), mix)
        texels.append(
            {
                "R": R,
                "avis": np.full(64, 2.0),
                "R_heldout": Rh,
                "avis_heldout": np.full(16, 2.0),
                "texel_area": 2.0,
            }
        )
    res = bench.run(texels, cs=(1, 4), n_trials=2)
    assert res["below_floor"] == []
    assert set(res["methods"]) == set(bench.METHODS)
    for mth in bench.METHODS:
        for c in ("1", "4"):
            row = res["methods"][mth][c]
            assert all(np.isfinite(row[key]) for key in ("matrix", "insample", "heldout"))
            assert row["matrix"] >= res["eckart_young"][c] - 1e-9


def test_benchmark_synthetic_texels_physical():
    # the ridge generator behind the measurements: shapes, R >= 0, and a_vis bounded by the
    # unoccluded projected area sum_j dA_j (n_j . w)+ <= sum_j dA_j
    import importlib.util
    from pathlib import Path

    pytest.importorskip("open3d")
    path = Path(__file__).resolve().parents[2] / "benchmarks" / "column_sampling.py"
    spec = importlib.util.spec_from_file_location("bench_column_sampling2", path)
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    (tex,) = bench.synthetic_texels(1, m=24, n_i=4, n_o=4, n_heldout=8, seed=1, n_sub=8)
    assert tex["R"].shape == (16, 24, 3) and tex["R_heldout"].shape == (8, 24, 3)
    assert tex["R_sub"].shape == (16, 24, 3)
    for key in ("R", "R_heldout", "R_sub"):
        assert np.all(tex[key] >= 0) and np.all(np.isfinite(tex[key]))
    for key in ("avis", "avis_heldout", "avis_sub"):
        assert np.all(tex[key] >= 0) and np.all(tex[key] <= tex["texel_area"] * (1 + 1e-12))
    # sharp ridges: some entries vanish (shadowed, masked or below a facet's own horizon)
    assert np.any(tex["R"][:, :, 1] == 0.0)
