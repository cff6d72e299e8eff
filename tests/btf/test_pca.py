"""Batched PCA of Laplacian BRDFs (seed 001, §3.2)."""

import numpy as np
import pytest

from texelbake.btf.pca import pca_batched
from texelbake.errors import SettingsError, ShapeError


def _recon(res):
    return np.einsum("btn,bnd->btd", res.weights, res.components.astype(np.float64))


def test_all_components_reconstruct_exactly(rng):
    x = rng.standard_normal((3, 12, 30))
    res = pca_batched(x, 12)
    # float32 components, float64 weights projected on them: ~1e-7 relative
    assert np.abs(_recon(res) - x).max() < 1e-5
    assert res.n_effective.tolist() == [12, 12, 12]


def test_error_equals_sum_of_dropped_eigenvalues(rng):
    # independent truth: numpy's eigenvalues of X^T X (the uncentred covariance)
    x = rng.standard_normal((2, 25, 18)) * np.geomspace(3.0, 0.1, 18)
    ev = np.linalg.eigvalsh(np.einsum("btd,bte->bde", x, x))[:, ::-1]  # descending
    errors = []
    for n in (1, 2, 4, 8, 16):
        res = pca_batched(x, n, method="exact")
        err = ((_recon(res) - x) ** 2).sum(axis=(1, 2))
        # float32 storage of the components: relative 1e-6 of the total energy
        assert np.allclose(err, ev[:, n:].sum(axis=1), rtol=1e-5, atol=1e-6 * (x**2).sum())
        errors.append(err)
    errors = np.array(errors)
    assert np.all(np.diff(errors, axis=0) < 0)  # strictly decreasing with n


def test_randomized_matches_exact_on_decaying_spectrum(rng):
    t, d, r = 300, 350, 30
    u = np.linalg.qr(rng.standard_normal((t, r)))[0]
    v = np.linalg.qr(rng.standard_normal((d, r)))[0]
    x = (u * np.geomspace(100.0, 0.01, r)) @ v.T + 1e-3 * rng.standard_normal((t, d))
    x = np.stack([x, 0.5 * x]).astype(np.float32)
    ex = pca_batched(x, 8, method="exact")
    rd = pca_batched(x, 8, method="randomized", oversample=8, power_iters=3, seed=1)
    assert rd.method == "randomized" and ex.method == "exact"
    err_ex = ((_recon(ex) - x) ** 2).sum()
    err_rd = ((_recon(rd) - x) ** 2).sum()
    assert err_rd <= err_ex * 1.01  # within 1 % of the optimal (Eckart-Young) error
    # same sign convention: components agree entry-wise
    assert np.abs(rd.components - ex.components).max() < 1e-3


def test_fewer_texels_than_components(rng):
    x = rng.standard_normal((3, 4, 50))
    res = pca_batched(x, [8, 2, 6])
    assert res.weights.shape == (3, 4, 8) and res.components.shape == (3, 8, 50)
    assert res.n_effective.tolist() == [4, 2, 4]
    assert np.all(res.components[0, 4:] == 0) and np.all(res.components[1, 2:] == 0)
    rec = _recon(res)
    assert np.abs(rec[0] - x[0]).max() < 1e-5  # 4 texels, 4 components: exact
    assert np.abs(rec[2] - x[2]).max() < 1e-5


def test_zero_and_constant_data():
    x = np.zeros((2, 10, 7))
    x[1] = 3.0  # rank 1
    res = pca_batched(x, 4)
    assert np.all(np.isfinite(res.weights)) and np.all(np.isfinite(res.components))
    assert res.n_effective.tolist() == [0, 1]
    assert np.all(res.weights[0] == 0)
    assert np.abs(_recon(res) - x).max() < 1e-5


def test_sign_normalisation_is_deterministic(rng):
    x = rng.standard_normal((2, 40, 30)).astype(np.float32)
    a = pca_batched(x, 5)
    b = pca_batched(x.copy(), 5)
    assert a.components.tobytes() == b.components.tobytes()
    assert a.weights.tobytes() == b.weights.tobytes()
    neg = pca_batched(-x, 5)  # a sign flip of the data only flips the weights
    assert np.array_equal(neg.components, a.components)
    assert np.allclose(neg.weights, -a.weights, atol=1e-5)
    big = np.abs(a.components).argmax(axis=-1)
    assert np.all(np.take_along_axis(a.components, big[..., None], -1) > 0)
    r1 = pca_batched(x, 5, method="randomized", seed=3)
    r2 = pca_batched(x, 5, method="randomized", seed=3)
    assert r1.components.tobytes() == r2.components.tobytes()


def test_pca_errors():
    with pytest.raises(ShapeError):
        pca_batched(np.zeros((3, 4)), 2)
    with pytest.raises(SettingsError):
        pca_batched(np.zeros((2, 3, 4)), [1, 2, 3])
    with pytest.raises(SettingsError):
        pca_batched(np.zeros((1, 3, 4)), 2, method="svd")
    with pytest.raises(ShapeError, match="NaN"):
        pca_batched(np.full((1, 3, 4), np.nan), 2)
    empty = pca_batched(np.zeros((1, 0, 4)), 2)
    assert empty.weights.shape == (1, 0, 2) and empty.components.dtype == np.float32
