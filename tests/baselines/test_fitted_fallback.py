"""The fitted UsdPreviewSurface fallback (`texelbake.baselines.fitted_fallback`): each truth
here is computed independently, by `brdf.analytic.preview_surface` on known inputs."""

from __future__ import annotations

import numpy as np
import pytest

from texelbake.baselines.fitted_fallback import (
    basis_views,
    cell_views,
    fit_directions,
    fit_preview,
    render_fit,
    sample_terms,
    targets,
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


def _wrms(fit_l: np.ndarray, tgt: np.ndarray) -> np.ndarray:
    """The objective's relative RMS per texel, restated: |L - T| / |T| over pairs and channels."""
    return np.sqrt(((fit_l - tgt) ** 2).sum(axis=(1, 2, 3)) / (tgt ** 2).sum(axis=(1, 2, 3)))


def _normals(t: int, rng) -> np.ndarray:
    n = np.c_[0.3 * rng.standard_normal((t, 2)), np.ones(t)]
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def test_recovers_specular_workflow_inputs_exactly(rng):
    # a target that is itself a specular-workflow preview surface (cell means by a dense
    # quadrature) is recovered at its roughness: residual ~0 and the generating inputs back
    t = 6
    nrm = _normals(t, rng)
    d = rng.uniform(0.05, 0.9, (t, 3))
    s = rng.uniform(0.0, 0.09, (t, 3))
    r = rng.uniform(0.3, 1.0, t)  # lobes the dense quadrature resolves
    k = fit_directions().shape[0]
    tgt = np.concatenate([_radiance({"useSpecularWorkflow": 1, "diffuseColor": d[i],
                                     "specularColor": s[i], "roughness": r[i]}, nrm[i:i + 1])
                          for i in range(t)])
    out = fit_preview(tgt, np.ones((t, k, k), bool), nrm, r)
    # to the importance sampling's accuracy (256 half vectors a light; measured ~1-3 %)
    np.testing.assert_allclose(out["diffuseColor"], d, atol=0.03)
    np.testing.assert_allclose(out["specularColor"], s, atol=0.03)
    assert out["residual"].max() < 0.03


def test_metal_beside_dielectric_is_resolved_by_the_specular_workflow(rng):
    # half a gold-like metal, half a green dielectric, one roughness: the averaged inputs
    # (metallic 0.5, mean diffuseColor) miss it; the fit puts both F0s in specularColor and
    # the dielectric's share in diffuseColor, all but the metal's tinted Fresnel edge (F90 =
    # albedo, white in the specular workflow)
    t = 3
    nrm = _normals(t, rng)
    metal = {"metallic": 1.0, "diffuseColor": (0.9, 0.6, 0.2), "roughness": 0.4}
    diel = {"metallic": 0.0, "diffuseColor": (0.1, 0.5, 0.3), "roughness": 0.4}
    tgt = 0.5 * (_radiance(metal, nrm) + _radiance(diel, nrm))
    k = fit_directions().shape[0]
    out = fit_preview(tgt, np.ones((t, k, k), bool), nrm, np.full(t, 0.4))
    averaged = _radiance({"metallic": 0.5, "diffuseColor": (0.5, 0.55, 0.25),
                          "roughness": 0.4}, nrm)
    rel_avg = _wrms(averaged, tgt)
    assert out["residual"].max() < 0.06
    assert np.all(out["residual"] < rel_avg / 3.0)
    f0 = 0.5 * (np.array([0.9, 0.6, 0.2]) + 0.04)  # R = ((1 - 1.5) / 2.5)² = 0.04
    np.testing.assert_allclose(out["specularColor"], np.tile(f0, (t, 1)), atol=0.06)
    # the reported residual is what the fitted inputs reproduce, measured independently
    np.testing.assert_allclose(out["residual"], _wrms(render_fit(out, nrm), tgt), rtol=1e-6)


def test_a_texel_no_lobe_matches_gets_its_best_fit_and_its_residual(rng):
    # a deep V-groove's look: lit from the normal it is bright, any tilted light or view sees
    # the walls' shadows (masking darkens every pair off the normal by (n·l)^6 (n·v)^6): no
    # UsdPreviewSurface lobe reproduces it; the fit stays in the spec's ranges, is no worse
    # than the best grey Lambertian (closed form), and reports a residual the test measures
    t = 2
    nrm = np.tile([0.0, 0.0, 1.0], (t, 1))
    dirs = fit_directions()
    k = dirs.shape[0]
    zz = (dirs[:, None, 2] * dirs[None, :, 2]) ** 6  # (k, k)
    lam = _radiance({"useSpecularWorkflow": 1, "diffuseColor": (0.8, 0.8, 0.8)}, nrm)
    tgt = lam * zz[None, :, :, None]
    out = fit_preview(tgt, np.ones((t, k, k), bool), nrm, np.full(t, 0.5))
    for key in ("diffuseColor", "specularColor", "roughness"):
        assert np.all((out[key] >= 0.0) & (out[key] <= 1.0))
    # no worse than any grey Lambertian of that roughness (a dense scan of diffuseColor)
    one = _radiance({"useSpecularWorkflow": 1, "diffuseColor": (1, 1, 1), "roughness": 0.5}, nrm)
    zero = _radiance({"useSpecularWorkflow": 1, "diffuseColor": (0, 0, 0), "roughness": 0.5},
                     nrm)
    scan = np.min([_wrms(x * (one - zero) + zero, tgt) for x in np.linspace(0, 1, 201)], axis=0)
    assert np.all(out["residual"] <= scan + 0.02)  # + the lobe's quadrature difference
    assert np.all(out["residual"] > 0.2)  # reported: this texel is not matched
    np.testing.assert_allclose(out["residual"], _wrms(render_fit(out, nrm), tgt), rtol=1e-6)


def test_coarse_texel_fits_the_sum_of_its_children_not_one_of_them(rng):
    # a 2x2 block of texels alternating black and white (the finest level's checkerboard):
    # the coarse texel's target is the area- and view-weighted mean of the children's sums,
    # so its fit is the mean grey's, never one child's colour (no aliasing through the levels)
    nrm = np.tile([0.0, 0.0, 1.0], (4, 1))
    dirs = fit_directions()
    k = dirs.shape[0]
    albedo = np.array([0.0, 0.8, 0.8, 0.0])
    f = np.stack([_radiance({"useSpecularWorkflow": 1, "diffuseColor": (a, a, a),
                             "roughness": 0.5}, nrm[:1])[0]
                  / np.maximum(dirs[:, None, None, 2], 1e-300) for a in albedo])  # (4, k, k, 3)
    vis = np.tile(dirs[:, 2], (4, 1))  # unshadowed, cosines on the flat texels
    num, den = sample_terms(f, vis, vis, np.ones(4))
    tgt, valid = targets(num.sum(0, keepdims=True), den.sum(0, keepdims=True), k)
    out = fit_preview(tgt, valid, nrm[:1], np.full(1, 0.5))
    np.testing.assert_allclose(out["diffuseColor"], 0.4, atol=0.01)
    assert out["residual"][0] < 0.02


def test_bad_shapes_name_the_arrays():
    k = fit_directions().shape[0]
    with pytest.raises(ShapeError, match="fit_preview"):
        fit_preview(np.zeros((2, k, k, 3)), np.ones((2, k, k), bool), np.zeros((3, 3)),
                    np.zeros(2))
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


def test_lobe_cells_match_a_dense_quadrature(rng):
    # the importance-sampled cell means of the lobe against a 48² uniform quadrature of each
    # cell, where the quadrature resolves the lobe: 256 half vectors a light put few views in
    # a cell of a broad lobe (measured: 3.4 % of the largest cell at roughness 0.4, 27 % at 0.8,
    # where the lobe is a tenth of the diffuse's radiance)
    nrm = _normals(2, rng)
    for r, tol in ((0.4, 0.04), (0.8, 0.35)):
        p = {"useSpecularWorkflow": 1, "diffuseColor": (0.0, 0.0, 0.0),
             "specularColor": (1.0, 1.0, 1.0), "roughness": r}
        fit = render_fit({"diffuseColor": np.zeros((2, 3)), "specularColor": np.ones((2, 3)),
                          "roughness": np.full(2, r)}, nrm)
        dense = _radiance(p, nrm, strata=48)
        assert np.abs(fit - dense).max() < tol * dense.max(), r


def test_fit_is_deterministic_bit_for_bit(rng):
    t = 5
    k = fit_directions().shape[0]
    nrm = _normals(t, rng)
    tgt = rng.uniform(0.0, 0.5, (t, k, k, 3))
    r = rng.uniform(0.0, 1.0, t)
    a = fit_preview(tgt, np.ones((t, k, k), bool), nrm, r)
    b = fit_preview(tgt.copy(), np.ones((t, k, k), bool), nrm.copy(), r.copy())
    for key in a:
        assert a[key].tobytes() == b[key].tobytes()
