"""The fitted UsdPreviewSurface fallback's measure (`texelbake.baselines.fitted_fallback`):
each truth here is computed independently, by `brdf.analytic.preview_surface` on known inputs
and a dense uniform quadrature of every view cell."""

from __future__ import annotations

import numpy as np
import pytest

from texelbake.baselines.fitted_fallback import (
    basis_views,
    cell_views,
    fit_directions,
    gain_sums,
    model_cells,
    sample_terms,
    shrunk_gain,
)
from texelbake.brdf.analytic import preview_surface
from texelbake.errors import ShapeError
from texelbake.geometry.basis import tangent_frames


def _radiance(params: dict, normal: np.ndarray, strata: int = 24) -> np.ndarray:
    """L(l, v) = f_ps (n·l)⁺ of one set of inputs on every texel's normal (t, k, k, 3), each
    view cell's mean by a dense uniform quadrature (strata² views a cell: the independent
    truth for the fit's importance-sampled lobe)."""
    dirs = fit_directions()
    g = (np.arange(strata) + 0.5) / strata
    uu = np.stack(np.meshgrid(g, g, indexing="ij"), axis=-1).reshape(-1, 2)
    views = cell_views(np.broadcast_to(uu[:, None, :], (uu.shape[0], 9, 2))).transpose(1, 0, 2)
    t, k, m = normal.shape[0], dirs.shape[0], views.shape[1]
    fr = tangent_frames(normal)
    li = np.einsum("tij,kj->tki", fr, dirs)
    vo = np.einsum("tij,kmj->tkmi", fr, views)
    out = np.zeros((t, k, k, 3))
    for i in range(k):  # light by light, every view of every cell at once
        wi = np.broadcast_to(li[:, i, None, None, :], (t, k, m, 3)).reshape(-1, 3)
        f = preview_surface(params, wi, vo.reshape(-1, 3)).reshape(t, k, m, 3).mean(axis=2)
        out[:, i] = f * np.maximum(li[:, i, 2], 0.0)[:, None, None]
    return out


def _normals(t: int, rng) -> np.ndarray:
    n = np.c_[0.3 * rng.standard_normal((t, 2)), np.ones(t)]
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def test_bad_shapes_name_the_arrays():
    k = fit_directions().shape[0]
    with pytest.raises(ShapeError, match="roughness"):
        model_cells({}, {"roughness": np.zeros(3)}, np.tile([0.0, 0.0, 1.0], (2, 1)), True)
    with pytest.raises(ShapeError, match="sample_terms"):
        sample_terms(np.zeros((2, k, k, 3)), np.zeros((2, k)), np.zeros((3, k)), np.ones(2))


def test_cell_views_lie_in_their_cells(rng):
    # each view drawn for cell o lies in o's ring band (0-20°, 20-50°, 50-80° from the normal)
    # and within ±45° in azimuth of direction o; the stratified views average near it
    dirs = fit_directions()
    k = dirs.shape[0]
    v = cell_views(rng.random((500, k, 2)))
    np.testing.assert_allclose(np.linalg.norm(v, axis=2), 1.0, atol=1e-12)
    theta = np.degrees(np.arccos(v[..., 2]))
    band = np.array([(0, 20)] + [(20, 50)] * 4 + [(50, 80)] * 4)
    assert np.all((theta >= band[:, 0] - 1e-9) & (theta <= band[:, 1] + 1e-9))
    dphi = np.angle(np.exp(1j * (np.arctan2(v[..., 1], v[..., 0])
                                 - np.arctan2(dirs[:, 1], dirs[:, 0]))))
    assert np.all(np.abs(np.degrees(dphi[:, 1:])) <= 45.0 + 1e-9)
    mean = basis_views().mean(axis=1)
    cos = np.einsum("kj,kj->k", mean / np.linalg.norm(mean, axis=1, keepdims=True), dirs)
    assert np.all(cos > np.cos(np.radians(6.0)))


def test_model_cells_match_a_dense_quadrature(rng):
    # the cell means against a 48² uniform quadrature of each cell: a diffuse-dominated metallic-0
    # material on the stratified views (4² a cell), and a lobe by importance sampling where
    # the quadrature resolves it: 256 half vectors a light put few views in a cell of a broad
    # lobe (measured: 3.4 % of the largest cell at roughness 0.4, 27 % at 0.8, where the lobe
    # is a tenth of the diffuse's radiance)
    nrm = _normals(2, rng)
    base = np.array([[0.8, 0.5, 0.2], [0.3, 0.6, 0.9]])
    for r, tol in ((0.4, 0.04), (0.8, 0.35)):
        const = {"useSpecularWorkflow": 1, "specularColor": (1.0, 1.0, 1.0)}
        got = model_cells(const, {"diffuseColor": np.zeros((2, 3)), "roughness": np.full(2, r)},
                          nrm, lobe=True)
        dense = _radiance({**const, "diffuseColor": (0.0, 0.0, 0.0), "roughness": r}, nrm, 48)
        assert np.abs(got - dense).max() < tol * dense.max(), r
    const = {"useSpecularWorkflow": 1, "specularColor": (0.0, 0.0, 0.0)}
    got = model_cells(const, {"diffuseColor": base, "roughness": np.full(2, 0.5)}, nrm, False)
    for i in range(2):  # texel by texel: each its own colour
        dense = _radiance({**const, "diffuseColor": base[i], "roughness": 0.5}, nrm[i:i + 1], 48)
        assert np.abs(got[i] - dense[0]).max() < 0.03 * dense.max()


def test_gain_recovers_a_known_gain_and_shrinks_toward_one(rng):
    # targets made of the model at a known gain: λ = 0 recovers it exactly; λ > 0 lies between
    # it and 1 at the closed-form weight 1/(1 + λ); λ = ∞ is 1; pairs left out do not count
    t, k = 6, fit_directions().shape[0]
    l0 = rng.uniform(0.0, 0.2, (t, k, k, 3))
    dl = rng.uniform(0.1, 0.5, (t, k, k, 3))
    g_true = rng.uniform(0.3, 1.5, (t, 3))
    tgt = l0 + g_true[:, None, None, :] * dl
    valid = rng.random((t, k, k)) > 0.3
    tgt_noisy = np.where(valid[..., None], tgt, 100.0)  # garbage where not valid
    sdd, sdr = gain_sums(l0, dl, tgt_noisy, valid)
    np.testing.assert_allclose(shrunk_gain(sdd, sdr, 0.0), g_true, rtol=1e-12)
    np.testing.assert_allclose(shrunk_gain(sdd, sdr, 3.0), 1.0 + (g_true - 1.0) / 4.0,
                               rtol=1e-12)
    assert np.array_equal(shrunk_gain(sdd, sdr, float("inf")), np.ones((t, 3)))
    # a texel no pair sees keeps gain 1
    sdd0, sdr0 = gain_sums(l0, dl, tgt, np.zeros((t, k, k), bool))
    assert np.array_equal(shrunk_gain(sdd0, sdr0, 0.0), np.ones((t, 3)))


def test_model_cells_are_deterministic_bit_for_bit(rng):
    t = 5
    nrm = _normals(t, rng)
    p = {"diffuseColor": rng.uniform(0, 1, (t, 3)), "roughness": rng.uniform(0, 1, t)}
    const = {"metallic": 1.0}
    for lobe in (False, True):
        a = model_cells(const, p, nrm, lobe)
        b = model_cells(dict(const), {k: v.copy() for k, v in p.items()}, nrm.copy(), lobe)
        assert a.tobytes() == b.tobytes()
