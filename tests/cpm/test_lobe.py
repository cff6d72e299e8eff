"""Widened characteristic points (`texelbake.cpm.lobe`, BakeSettings.point_lobe="widened"): a
cell's variance against a brute-force loop and closed forms, the widened BRDF in the fit's
product kernel and in the renderer's per-row path against `widen_material` evaluated row by
row (a roughness texture included), and on a curved glossy square the held-out SNR the
widened points reach against the narrow ones."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from schemas.settings import BakeSettings
from tests.cpm.test_classify import SETTINGS, _grid_samples, _inputs
from texelbake import brdf as brdf_mod
from texelbake.brdf import sample_texture
from texelbake.brdf.widened import widen_material
from texelbake.cpm.brdf_product import brdf_product
from texelbake.cpm.level import level_candidates
from texelbake.cpm.level_batched import fit_level_batched
from texelbake.cpm.lobe import VAR_MAX, cell_variance
from texelbake.geometry.basis import tangent_frames
from texelbake.model import Material, Texture

GLOSS = Material("/m/gloss", "preview", {"diffuseColor": (0.05, 0.05, 0.05), "roughness": 0.25,
                                          "metallic": 1.0})
PHONG = Material("/m/phong", "phong", {"diffuseColor": (0.2, 0.3, 0.4),
                                       "specularColor": (0.5, 0.5, 0.5), "exponent": 60.0})
LAMBERT = Material("/m/lambert", "lambert", {"diffuseColor": (0.5, 0.3, 0.2)})


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _brute_cells(nrm, mat, weight, var, points):
    """The module docstring's definition, one candidate at a time."""
    num = np.zeros(len(points))
    den = np.zeros(len(points))
    for j in range(len(nrm)):  # loop over candidates: the independent reference
        best, best_cos = -1, -np.inf
        for q, p in enumerate(points):
            if mat[p] != mat[j]:
                continue
            c = float(np.dot(nrm[j], nrm[p]))
            if c > best_cos:
                best, best_cos = q, c
        if best < 0:
            continue
        c = min(best_cos, 1.0)
        slope2 = 0.0 if c >= 1.0 - 1e-12 else ((1 - c * c) / (c * c) if c > 0 else np.inf)
        w = float(np.abs(weight[j]).mean())
        num[best] += w * min(var[j] + 0.5 * slope2, VAR_MAX)
        den[best] += w
    return np.divide(num, den, out=np.zeros_like(num), where=den > 0)


def test_cell_variance_equals_a_brute_force_loop():
    rng = np.random.default_rng(3)
    m = 200
    nrm = _unit(rng.normal(size=(m, 3)) * [0.4, 0.4, 1.0] + [0, 0, 1.5])
    mat = rng.integers(0, 2, m)
    weight = rng.uniform(0.1, 1.0, (m, 3))
    var = rng.uniform(0.0, 0.05, m)
    points = np.array([3, 17, 40, 41, 99, 150])
    got = cell_variance(nrm, mat, weight, var, points)
    np.testing.assert_allclose(got, _brute_cells(nrm, mat, weight, var, points), rtol=1e-12,
                               atol=1e-15)


def test_cell_variance_closed_forms():
    """A ring of normals at angle t about the point's: tan^2 t / 2 (equal weights, the point
    itself adding 0 with its weight); one normal: exactly 0; a candidate past 90 degrees:
    VAR_MAX; a material no point has: in no cell."""
    t = 0.3
    ring = np.array([[np.sin(t) * np.cos(a), np.sin(t) * np.sin(a), np.cos(t)]
                     for a in np.linspace(0, 2 * np.pi, 8, endpoint=False)])
    nrm = np.vstack([[0.0, 0.0, 1.0], ring])
    w = np.ones((9, 3))
    got = cell_variance(nrm, np.zeros(9, np.int64), w, None, np.array([0]))
    np.testing.assert_allclose(got, [8 / 9 * np.tan(t) ** 2 / 2], rtol=1e-12)
    flat = np.tile([0.0, 0.6, 0.8], (5, 1))
    assert cell_variance(flat, np.zeros(5, np.int64), np.ones((5, 3)), None,
                         np.array([2]))[0] == 0.0
    back = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]])
    assert cell_variance(back, np.zeros(2, np.int64), np.ones((2, 3)), None,
                         np.array([0]))[0] == pytest.approx(VAR_MAX / 2)
    other = cell_variance(np.vstack([[0.0, 0.0, 1.0], ring[:1]]), np.array([0, 1]),
                          np.ones((2, 3)), None, np.array([0]))
    assert other[0] == 0.0


def _frame_dirs(p: int, n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    v = rng.normal(size=(p, n, 3))
    v[..., 2] = np.abs(v[..., 2]) + 0.2
    return _unit(v)


@pytest.mark.parametrize("material", [GLOSS, PHONG, LAMBERT], ids=lambda m: m.model)
def test_brdf_product_widened_equals_widen_material_row_by_row(material):
    """The fit's product kernel with var against `brdf.evaluate` of `widen_material` on each
    (sample, direction pair) row, one sample at a time; var 0 equals the narrow kernel bit for
    bit."""
    p, A, B = 5, 3, 4
    rng = np.random.default_rng(1)
    nrm = _unit(rng.normal(size=(p, 3)) * 0.2 + [0, 0, 1])
    geo = {"sample_nrm": nrm, "sample_mat": np.zeros(p, np.int64),
           "sample_uv": rng.uniform(size=(p, 2))}
    frames = tangent_frames(nrm)
    wi_l, wo_l = _frame_dirs(p, A, 2), _frame_dirs(p, B, 3)
    wi = np.einsum("pji,paj->pai", frames, wi_l)  # local -> world (frames are orthonormal)
    wo = np.einsum("pji,pbj->pbi", frames, wo_l)
    live = np.ones((A, B, p), bool)
    var = np.array([0.0, 0.01, 0.05, 0.2, 0.6])
    got = brdf_product(geo, [material], np.arange(p), wi, wo, live, var=var)
    for s in range(p):  # loops over samples and pairs: the row-by-row reference
        m = widen_material(material, var[s:s + 1])  # one row's inputs
        for a in range(A):
            for b in range(B):
                ref = brdf_mod.evaluate(m, wi_l[s, a:a + 1], wo_l[s, b:b + 1])[0]
                np.testing.assert_allclose(got[:, s, a, b], ref, rtol=1e-10, atol=1e-12)
    zero = brdf_product(geo, [material], np.arange(p), wi, wo, live, var=np.zeros(p))
    assert np.array_equal(zero, brdf_product(geo, [material], np.arange(p), wi, wo, live))
    if material.model != "lambert":
        assert not np.allclose(got[:, 3], zero[:, 3])  # a widened lobe differs


def test_evaluate_by_face_widened_rows():
    rng = np.random.default_rng(4)
    n = 6
    wi, wo = _frame_dirs(1, n, 5)[0], _frame_dirs(1, n, 6)[0]
    mat = np.array([0, 1, 0, 1, 2, 0])
    var = rng.uniform(0, 0.3, n)
    mats = [GLOSS, PHONG, LAMBERT]
    got = brdf_mod.evaluate_by_face(mats, mat, wi, wo, var=var)
    for r in range(n):  # loop over rows: the reference
        ref = brdf_mod.evaluate(widen_material(mats[mat[r]], var[r:r + 1]), wi[r:r + 1],
                                wo[r:r + 1])
        np.testing.assert_allclose(got[r:r + 1], ref, rtol=1e-12)
    # with sample_index (the inputs resolved per surface sample, then gathered to the rows)
    uv = rng.uniform(size=(2, 2))
    idx = np.array([0, 1, 1, 0, 1, 0])
    got = brdf_mod.evaluate_by_face(mats, mat, wi, wo, uv, sample_index=idx, var=var)
    for r in range(n):  # loop over rows: the reference
        ref = brdf_mod.evaluate(widen_material(mats[mat[r]], var[r:r + 1]), wi[r:r + 1],
                                wo[r:r + 1], uv[idx[r]:idx[r] + 1])
        np.testing.assert_allclose(got[r:r + 1], ref, rtol=1e-12)


def test_a_roughness_texture_is_widened():
    """A UsdPreviewSurface whose roughness is a texture: the fit's product kernel and the
    renderer's rows widen each sample's own roughness, against `widen_material` of a constant
    material at the roughness the texture gives that sample."""
    px = np.linspace(0.1, 0.8, 16, dtype=np.float32).reshape(4, 4, 1)
    tex = Texture("rough.png", px, source_color_space="raw")
    mat = Material("/m/rough", "preview", {"metallic": 1.0, "diffuseColor": (0.6, 0.5, 0.4)},
                   textures={"roughness": tex})
    p, A, B = 4, 2, 3
    rng = np.random.default_rng(7)
    uv = rng.uniform(size=(p, 2))
    nrm = np.tile([0.0, 0.0, 1.0], (p, 1))
    geo = {"sample_nrm": nrm, "sample_mat": np.zeros(p, np.int64), "sample_uv": uv}
    wi_l, wo_l = _frame_dirs(p, A, 8), _frame_dirs(p, B, 9)
    frames = tangent_frames(nrm)
    wi = np.einsum("pji,paj->pai", frames, wi_l)
    wo = np.einsum("pji,pbj->pbi", frames, wo_l)
    var = np.array([0.0, 0.02, 0.1, 0.4])
    got = brdf_product(geo, [mat], np.arange(p), wi, wo, np.ones((A, B, p), bool), var=var)
    rough = sample_texture(tex, uv)[:, 0]
    for s in range(p):  # loops over samples and pairs: the reference
        const = Material("/m/c", "preview", {"metallic": 1.0, "diffuseColor": (0.6, 0.5, 0.4),
                                              "roughness": float(rough[s])})
        m = widen_material(const, var[s:s + 1])
        for a in range(A):
            for b in range(B):
                ref = brdf_mod.evaluate(m, wi_l[s, a:a + 1], wo_l[s, b:b + 1])[0]
                np.testing.assert_allclose(got[:, s, a, b], ref, rtol=1e-9)
                row = brdf_mod.evaluate_by_face([mat], np.zeros(1, np.int64), wi_l[s, a:a + 1],
                                                wo_l[s, b:b + 1], uv[s:s + 1], var=var[s:s + 1])
                np.testing.assert_allclose(row[0], ref, rtol=1e-9)
    narrow = brdf_product(geo, [mat], np.arange(p), wi, wo, np.ones((A, B, p), bool))
    assert np.array_equal(got[:, 0], narrow[:, 0]) and not np.allclose(got[:, 3], narrow[:, 3])


def test_widened_needs_the_batched_fit():
    with pytest.raises(ValueError, match="point_lobe 'widened' needs fit_method 'batched'"):
        BakeSettings(point_lobe="widened", fit_method="per_texel")


def _curved_square(lobe: str, c_max: int = 2):
    """The 2 x 2 square of test_classify with its shading and geometric normals turning about
    y across it (+-0.8 rad: a cylinder's strip seen flat), one glossy metal, 64 samples per
    texel, fitted at level 0 with at most `c_max` points per texel."""
    pos = _grid_samples(8)
    a = 1.6 * (pos[:, 0] - 0.5)
    nrm = np.stack([np.sin(a), np.zeros_like(a), np.cos(a)], axis=1)
    src = _inputs(pos, nrm, materials=(GLOSS,))
    src = dataclasses.replace(src, settings=SETTINGS.model_copy(update={
        "point_lobe": lobe, "c_max": c_max, "texel_classes": "points"}))
    texels = np.arange(4, dtype=np.int64)
    return fit_level_batched(src, 0, texels, level_candidates(src, 0, texels, None))


def test_widened_points_carry_a_curved_glossy_texel_between_the_grid():
    """Two points cannot stand for a glossy strip whose normal turns by 46 degrees: their
    narrow lobes miss the held-out pairs between the grid's. Widened by their cells' spread
    (chosen on the validation pairs), they reproduce the held-out pairs better (the median
    texel by more than 1 dB: the validation pairs can choose wrong in a texel),
    and the payload carries the variances (positive, at most VAR_MAX)."""
    narrow = _curved_square("narrow")
    wide = _curved_square("widened")
    assert "point_var" not in narrow
    var = wide["point_var"]
    assert var.shape == wide["point_sample"].shape
    assert np.all(var >= 0) and np.all(var <= VAR_MAX) and np.any(var > 0)
    gain = wide["snr_ho"] - narrow["snr_ho"]
    assert np.median(gain) > 1.0, (narrow["snr_ho"], wide["snr_ho"])
