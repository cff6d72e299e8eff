"""The filtered baseline maps (issue 21): moments against a per-texel brute force, the hard
cases of the slope transform, the covariance projection and Toksvig's |n̄| -> 0, and AO
against the closed-form form factor of a parallel square."""

from __future__ import annotations

import numpy as np
import pytest

from texelbake import model
from texelbake.baselines.filtered_maps import (
    CHANNELS,
    FIELDS,
    FILTER_TOL,
    ambient_occlusion,
    bake_filtered_levels,
    fallback_roughness,
    slope_covariance,
    slopes,
    toksvig_variance,
)
from texelbake.brdf.analytic import preview_surface
from texelbake.brdf.widened import preview_leadr, toksvig_phong_exponent, widen_material
from texelbake.geometry.raycast import RayCaster


def test_levels_are_area_weighted_means_of_the_same_samples():
    """Every level's texel equals the brute-force area-weighted mean (a loop over texels,
    here only) of the samples assigned to it; moments E[x̃²] >= E[x̃]² hold."""
    rng = np.random.default_rng(3)
    n, m = 4, 400
    row, col = rng.integers(0, n, m), rng.integers(0, n, m)
    row[0], col[0] = 0, 0
    area = rng.uniform(0.5, 1.5, m)
    nrm = rng.normal(size=(m, 3)) * [0.4, 0.4, 0.2] + [0, 0, 1.0]  # n_z well above min_cos
    ao, alb, base, a2 = rng.uniform(size=m), rng.uniform(size=(m, 3)), \
        rng.uniform(size=(m, 3)), rng.uniform(size=m)
    texels = [(row >> lv) * (n >> lv) + (col >> lv) for lv in range(3)]
    maps = bake_filtered_levels(n, 3, texels, area, nrm, ao, alb, base, a2)
    assert [mp.shape for mp in maps] == [(4, 4, len(CHANNELS)), (2, 2, 16), (1, 1, 16)]
    unit = nrm / np.linalg.norm(nrm, axis=1, keepdims=True)
    s = -unit[:, :2] / unit[:, 2:3]
    for lv in range(3):
        nl = n >> lv
        for t in np.unique(texels[lv]):
            sel = texels[lv] == t
            w = area[sel] / area[sel].sum()
            got = maps[lv][t // nl, t % nl].astype(np.float64)
            np.testing.assert_allclose(got[FIELDS["nbar"]], w @ unit[sel], atol=1e-6)
            np.testing.assert_allclose(got[FIELDS["m1"]], w @ s[sel], atol=1e-6)
            np.testing.assert_allclose(got[FIELDS["m2"]][0], w @ s[sel, 0] ** 2, rtol=1e-5)
            np.testing.assert_allclose(got[FIELDS["m2"]][2], w @ (s[sel, 0] * s[sel, 1]),
                                       atol=1e-6)
            np.testing.assert_allclose(got[FIELDS["ao"]][0], w @ ao[sel], atol=1e-6)
            assert got[5] >= got[3] ** 2 - 1e-6


def test_grazing_normals_give_clamped_finite_slopes():
    """n_z -> 0 (and below) in the slope transform: clamped at FILTER_TOL.min_cos, finite,
    along the normal's own azimuth; without the clamp (1, 0, 0) would give -inf."""
    n = np.array([[1.0, 0.0, 0.0], [0.6, 0.0, -0.8], [0.0, 1.0, 1e-12], [0.0, 0.0, 1.0]])
    s = slopes(n)
    assert np.isfinite(s).all()
    assert np.all(np.linalg.norm(s, axis=1) <= 1.0 / FILTER_TOL.min_cos + 1e-9)
    np.testing.assert_allclose(s[0], [-1.0 / FILTER_TOL.min_cos, 0.0])
    np.testing.assert_allclose(s[3], [0.0, 0.0])


def test_non_psd_moments_are_projected_to_the_nearest_covariance():
    """Moments that are not PSD after filtering (E[x̃²] < E[x̃]², or a negative determinant)
    project onto the PSD cone: the result equals numpy's eigh with negative eigenvalues
    clamped (the Frobenius-nearest PSD matrix), with no NaN."""
    m1 = np.array([[1.0, 0.0], [0.0, 0.0], [0.2, -0.1], [0.0, 0.0]])
    m2 = np.array([[0.99, 0.0, 0.0],     # E[x²] - E[x]² = -0.01
                   [1.0, 1.0, 2.0],      # eigenvalues 3, -1
                   [0.05, 0.02, -0.02],  # a valid covariance: kept
                   [np.nan, 0.0, 0.0]])  # not finite: 0
    cov = slope_covariance(m1, m2)
    assert np.isfinite(cov).all()
    for k in range(3):
        raw = np.array([[m2[k, 0] - m1[k, 0] ** 2, m2[k, 2] - m1[k, 0] * m1[k, 1]],
                        [m2[k, 2] - m1[k, 0] * m1[k, 1], m2[k, 1] - m1[k, 1] ** 2]])
        lam, vec = np.linalg.eigh(raw)
        want = vec @ np.diag(np.maximum(lam, 0.0)) @ vec.T
        np.testing.assert_allclose(cov[k], want, atol=1e-12)
        assert np.linalg.eigvalsh(cov[k]).min() >= -1e-12
    np.testing.assert_allclose(cov[1], [[1.5, 1.5], [1.5, 1.5]], atol=1e-12)


def test_cancelling_normals_give_a_bounded_lobe():
    """|n̄| -> 0 (normals that cancel): Toksvig's σ² = (1 - |n̄|)/|n̄| is capped at max_var
    (inf and NaN without the clamp), the widened roughness stays in [0.001, 1], Phong's
    exponent -> 0 (a uniform lobe), and the BRDFs stay finite."""
    var = toksvig_variance(np.array([0.0, 1e-9, np.nan, 0.5, 1.0]))
    assert np.isfinite(var).all() and var.max() <= FILTER_TOL.max_var
    np.testing.assert_allclose(var[3:], [1.0, 0.0])
    mat = model.Material(path="/M", model="preview", params={"roughness": 0.3})
    wide = widen_material(mat, var)
    r = np.asarray(wide.params["roughness"])
    assert np.all((r >= 1e-3) & (r <= 1.0)) and r[0] == 1.0 and r[4] == 0.3
    np.testing.assert_allclose(toksvig_phong_exponent(60.0, np.array([0.0, 1.0])), [0, 60])
    wi = np.tile([0.3, 0.1, 0.9], (5, 1))
    wi /= np.linalg.norm(wi, axis=1, keepdims=True)
    wo = np.tile([0.0, 0.0, 1.0], (5, 1))
    assert np.isfinite(preview_surface({"roughness": r}, wi, wo)).all()
    cov = np.tile(np.eye(2) * FILTER_TOL.max_var, (5, 1, 1))
    spec, diff = preview_leadr({}, wi, wo, np.zeros((5, 2)), cov)
    assert np.isfinite(spec).all() and np.isfinite(diff).all()
    assert np.all(fallback_roughness(np.ones(5), cov) == 1.0)


def test_leadr_preview_lobe_is_the_material_at_zero_variance_and_normalised():
    """With x̄ = 0, Σ = 0, `preview_leadr` is UsdPreviewSurface exactly; with a mean slope and
    a covariance, its NDF still integrates to 1 over projected area (∫ D (h·z) dh = 1, the
    microfacet normalisation LEADR's shear and widening keep), by Monte Carlo."""
    rng = np.random.default_rng(0)
    wi = rng.normal(size=(500, 3))
    wi[:, 2] = np.abs(wi[:, 2])
    wi /= np.linalg.norm(wi, axis=1, keepdims=True)
    wo = rng.normal(size=(500, 3))
    wo[:, 2] = np.abs(wo[:, 2])
    wo /= np.linalg.norm(wo, axis=1, keepdims=True)
    params = {"roughness": 0.45, "diffuseColor": (0.5, 0.3, 0.2), "clearcoat": 0.5}
    spec, diff = preview_leadr(params, wi, wo, np.zeros((500, 2)), np.zeros((500, 2, 2)))
    np.testing.assert_allclose(spec + diff, preview_surface(params, wi, wo), rtol=1e-9,
                               atol=1e-12)
    from texelbake.brdf.widened import _sheared_ggx

    a = np.array([[0.09, 0.02], [0.02, 0.05]])
    mean = np.array([0.2, -0.1])
    h = rng.normal(size=(400_000, 3))
    h[:, 2] = np.abs(h[:, 2])
    h /= np.linalg.norm(h, axis=1, keepdims=True)  # uniform on the hemisphere, pdf 1/(2π)
    k = h.shape[0]
    d = _sheared_ggx(h, np.tile(mean, (k, 1)), np.tile(np.linalg.inv(a), (k, 1, 1)),
                     np.full(k, np.sqrt(np.linalg.det(a))))
    integral = 2.0 * np.pi * np.mean(d * h[:, 2])
    assert abs(integral - 1.0) < 0.03  # Monte Carlo error ~1 % at 4e5 samples


def test_ambient_occlusion_matches_the_form_factor_of_a_parallel_square():
    """AO under a square of half-width a at height h equals 1 - F, F the closed-form form
    factor from a differential area to a parallel rectangle (4 corner rectangles); with
    nothing above, AO = 1 exactly."""
    a, h = 1.0, 1.0
    quad = np.array([[-a, -a, h], [a, -a, h], [a, a, h], [-a, a, h]])
    caster = RayCaster(quad, np.array([[0, 1, 2], [0, 2, 3]]))
    m = 4000
    pts = np.zeros((m, 3))
    nrm = np.tile([0.0, 0.0, 1.0], (m, 1))
    ao = ambient_occlusion(pts, nrm, caster.occluded, n_rays=32, seed=1)

    def corner(x: float, y: float) -> float:
        sx, sy = np.sqrt(1 + x * x), np.sqrt(1 + y * y)
        return (x / sx * np.arctan(y / sx) + y / sy * np.arctan(x / sy)) / (2 * np.pi)

    want = 1.0 - 4.0 * corner(a / h, a / h)  # F = 0.5541 for a = h
    # 128,000 stratified cosine rays: standard error < 0.0015; 0.01 is > 6 of them
    assert abs(ao.mean() - want) < 0.01
    # the underside: nothing in its hemisphere (an open surface with nothing above it)
    open_sky = ambient_occlusion(pts, -nrm, caster.occluded, n_rays=32)
    assert np.all(open_sky == 1.0)


@pytest.mark.parametrize("bad", [(3, 2), (4,)])
def test_shapes_are_checked(bad):
    from texelbake.errors import ShapeError

    with pytest.raises(ShapeError):
        slopes(np.zeros(bad))


def test_filtered_map_with_wrong_channels_is_refused_naming_the_file(tmp_path):
    """A filtered map whose channels are not `CHANNELS` (a foreign or truncated EXR) is an
    AssetError naming the file, not a silently misread map; absent maps read as none."""
    from texelbake.errors import AssetError
    from texelbake.io.images import write_pixels
    from texelbake.usd.read import read_filtered_maps

    assert read_filtered_maps(tmp_path, "a") == []
    good = np.random.default_rng(0).uniform(size=(4, 4, len(CHANNELS))).astype(np.float32)
    write_pixels(tmp_path / "a_filtered_L00.exr", good, "float", channel_names=CHANNELS)
    back = read_filtered_maps(tmp_path, "a")
    assert len(back) == 1 and np.array_equal(back[0], good)  # channel order restored
    write_pixels(tmp_path / "a_filtered_L01.exr", good[..., :3], "float")
    with pytest.raises(AssetError, match="a_filtered_L01.exr"):
        read_filtered_maps(tmp_path, "a")


def test_chunked_passes_give_the_one_pass_maps_and_ao():
    """The export's passes a chunk of samples at a time (issue 15, memory): `FilteredSums`,
    `PreviewSums` and AO over chunks of 37 give the one-pass maps and AO bit for bit (the
    sums continue across chunks; AO's draws are those of the one-pass streams)."""
    from texelbake.baselines.filtered_maps import FilteredSums
    from texelbake.baselines.normal_maps import PreviewSums, bake_preview_maps
    from texelbake.io.chunks import chunk_ranges

    rng = np.random.default_rng(9)
    n, m = 8, 500
    row, col = rng.integers(0, n, m), rng.integers(0, n, m)
    area = rng.uniform(0.5, 1.5, m)
    nrm = rng.normal(size=(m, 3)) * [0.4, 0.4, 0.2] + [0, 0, 1.0]
    ao, alb, base, a2 = rng.uniform(size=m), rng.uniform(size=(m, 3)), \
        rng.uniform(size=(m, 3)), rng.uniform(size=m)
    texels = [(row >> lv) * (n >> lv) + (col >> lv) for lv in range(4)]
    one = bake_filtered_levels(n, 4, texels, area, nrm, ao, alb, base, a2)
    sums = FilteredSums(n, 4)
    mats = [model.Material("/M/a", "lambert", {"diffuseColor": (0.2, 0.5, 0.7)}),
            model.Material("/M/b", "lambert", {"diffuseColor": (0.9, 0.1, 0.3)})]
    mat = rng.integers(0, 2, m).astype(np.int32)
    uv = rng.uniform(size=(m, 2))
    frames = np.linalg.qr(rng.normal(size=(20, 3, 3)))[0]
    face = rng.integers(0, 20, m)
    prev_one = bake_preview_maps(n, texels[0], area, nrm, uv, mat, mats, frames, face)
    prev = PreviewSums(n)
    for a, b in chunk_ranges(m, 37):
        sums.add([t[a:b] for t in texels], area[a:b], nrm[a:b], ao[a:b], alb[a:b], base[a:b],
                 a2[a:b])
        prev.add(texels[0][a:b], area[a:b], nrm[a:b], uv[a:b], mat[a:b], mats, frames,
                 face[a:b])
    for x, y in zip(one, sums.maps(), strict=True):
        assert x.tobytes() == y.tobytes()
    for x, y in zip(prev_one, prev.maps(), strict=True):
        assert x.tobytes() == y.tobytes()
    quad = np.array([[-1.0, -1, 1], [1, -1, 1], [1, 1, 1], [-1, 1, 1]])
    caster = RayCaster(quad, np.array([[0, 1, 2], [0, 2, 3]]))
    pts = rng.uniform(-1, 1, (m, 3)) * [1, 1, 0]
    up = np.tile([0.0, 0.0, 1.0], (m, 1))
    whole = ambient_occlusion(pts, up, caster.occluded, n_rays=8, seed=4)
    parts = np.concatenate([ambient_occlusion(pts[a:b], up[a:b], caster.occluded, n_rays=8,
                                              seed=4, first=a, total=m)
                            for a, b in chunk_ranges(m, 37)])
    assert whole.tobytes() == parts.tobytes() and 0 < whole.mean() < 1


def test_carried_constants_name_specular_color_only_in_the_specular_workflow():
    from texelbake.baselines.filtered_maps import dominant_constants

    metal = model.Material("/M", "preview", {**model.PREVIEW_DEFAULTS, "metallic": 1.0})
    spec = model.Material("/S", "preview", {**model.PREVIEW_DEFAULTS, "useSpecularWorkflow": 1,
                                            "specularColor": (0.3, 0.2, 0.1)})
    area = np.array([1.0, 3.0])
    # the material covering the most area wins
    assert dominant_constants([metal, spec], np.array([0, 1]), area)["specularColor"] == (
        0.3, 0.2, 0.1)
    got = dominant_constants([metal, spec], np.array([0, 1]), area[::-1].copy())
    # the metallic workflow ignores specularColor; an authored one is Blender's Specular Tint
    assert "specularColor" not in got
    assert got["metallic"] == 1.0 and got["useSpecularWorkflow"] == 0
