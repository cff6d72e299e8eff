import numpy as np
import pytest

from texelbake.errors import SettingsError
from texelbake.geometry.directions import (
    balanced_pairs,
    heldout_pairs,
    hemisphere_directions,
    product_pairs,
)


@pytest.mark.parametrize("n", [1, 7, 64, 100])
def test_hemisphere_shape_unit_upper(n):
    w = hemisphere_directions(n, seed=3)
    assert w.shape == (n, 3) and w.dtype == np.float64
    np.testing.assert_allclose(np.linalg.norm(w, axis=1), 1.0, atol=1e-15)
    assert np.all(w[:, 2] > 0.0)


def test_hemisphere_empty_and_errors():
    w = hemisphere_directions(0)
    assert w.shape == (0, 3) and w.dtype == np.float64
    with pytest.raises(SettingsError):
        hemisphere_directions(-1)
    with pytest.raises(SettingsError):
        hemisphere_directions(2.5)


def test_hemisphere_deterministic_and_seeded():
    a, b = hemisphere_directions(64, seed=5), hemisphere_directions(64, seed=5)
    assert a.tobytes() == b.tobytes()
    assert not np.allclose(a, hemisphere_directions(64, seed=6))


def test_hemisphere_uniform_in_solid_angle():
    # Uniform on the hemisphere: E[z] = 1/2, E[z^2] = 1/3, E[x] = E[y] = 0, E[x^2] = 1/3.
    # A scrambled Sobol' set of 1024 points integrates these smooth functions with error
    # O(log n / n) ~ 1e-3; 4e-3 leaves margin. A cosine-weighted set would give E[z] = 2/3.
    w = hemisphere_directions(1024, seed=0)
    assert abs(w[:, 2].mean() - 0.5) < 4e-3
    assert abs((w[:, 2] ** 2).mean() - 1.0 / 3.0) < 4e-3
    assert abs(w[:, 0].mean()) < 4e-3 and abs(w[:, 1].mean()) < 4e-3
    assert abs((w[:, 0] ** 2).mean() - 1.0 / 3.0) < 4e-3


def test_hemisphere_low_discrepancy_beats_random():
    # independent truth: the same integral with i.i.d. points has error ~ 0.29/sqrt(n); the
    # low-discrepancy set must be clearly better on average over seeds
    n = 256
    qmc_err = np.mean([abs(hemisphere_directions(n, s)[:, 2].mean() - 0.5) for s in range(8)])
    rng = np.random.default_rng(0)
    mc_err = np.mean([abs(rng.random(n).mean() - 0.5) for _ in range(8)])
    assert qmc_err < 0.3 * mc_err


def test_product_pairs_convention():
    n_i, n_o = 3, 5
    ri, ro = product_pairs(n_i, n_o)
    assert ri.dtype == np.int64 and ro.shape == (15,)
    for r in range(n_i * n_o):  # brute force: row r = i * n_o + o
        assert ri[r] * n_o + ro[r] == r
    assert product_pairs(0, 4)[0].shape == (0,)


def test_heldout_pairs():
    wi, wo = heldout_pairs(200, seed=1)
    assert wi.shape == wo.shape == (200, 3)
    np.testing.assert_allclose(np.linalg.norm(wi, axis=1), 1.0, atol=1e-15)
    assert np.all(wi[:, 2] > 0) and np.all(wo[:, 2] > 0)
    wi2, wo2 = heldout_pairs(200, seed=1)
    assert wi.tobytes() == wi2.tobytes() and wo.tobytes() == wo2.tobytes()
    # a different sequence from the grid: no held-out direction equals a grid direction
    grid = hemisphere_directions(256, seed=1)
    assert np.min(np.linalg.norm(wi[:, None] - grid[None], axis=2)) > 1e-9
    assert not np.allclose(wi, wo)
    assert heldout_pairs(0)[0].shape == (0, 3)


def test_balanced_pairs():
    ri, ro = balanced_pairs(16, 32, 256, seed=2)
    assert ri.dtype == ro.dtype == np.int64 and ri.shape == ro.shape == (256,)
    key = ri * 32 + ro
    assert np.all(np.diff(key) > 0)  # sorted, no duplicate pair
    # exactly balanced: each light 16 times, each view 8 times
    assert np.all(np.bincount(ri, minlength=16) == 16)
    assert np.all(np.bincount(ro, minlength=32) == 8)
    a = balanced_pairs(16, 32, 256, seed=2)
    assert a[0].tobytes() == ri.tobytes() and a[1].tobytes() == ro.tobytes()
    assert not np.array_equal(balanced_pairs(16, 32, 256, seed=3)[1], ro)
    # d = n_i * n_o is the full product grid
    fi, fo = balanced_pairs(4, 6, 24)
    pi, po = product_pairs(4, 6)
    np.testing.assert_array_equal(fi, pi)
    np.testing.assert_array_equal(fo, po)
    assert balanced_pairs(4, 4, 0)[0].shape == (0,)
    with pytest.raises(SettingsError):
        balanced_pairs(16, 32, 100)
    with pytest.raises(SettingsError):
        balanced_pairs(2, 2, 8)
