"""Tests of texelbake.brdf: the BRDF models, the MERL format, textures and the dispatcher.

Truths used: closed forms (Lambert, Phong at normal incidence, GGX at roughness 1), plain-Python
re-derivations of the UsdPreviewSurface formulas with an explicit half vector, brute-force
Worley distances, hand-computed bilinear texture values, and the analytic BRDF a MERL table
was tabulated from.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from texelbake import brdf, model
from texelbake.brdf import cellular_shader as brdf_cellular
from texelbake.brdf import merl as brdf_merl
from texelbake.errors import AssetError, SettingsError, ShapeError

N_MC = 200_000  # Monte Carlo samples per view direction
VIEW_THETAS_DEG = (0.0, 30.0, 60.0, 80.0)


def _view(theta_deg: float, phi: float = 0.3) -> np.ndarray:
    t = math.radians(theta_deg)
    return np.array([[math.sin(t) * math.cos(phi), math.sin(t) * math.sin(phi), math.cos(t)]])


def _random_pairs(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Upper-hemisphere pairs, uniform in solid angle (reaches grazing angles)."""
    rng = np.random.default_rng(seed)

    def dirs(m):
        z = rng.random(m)
        phi = 2 * np.pi * rng.random(m)
        r = np.sqrt(1 - z * z)
        return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)

    return dirs(n), dirs(n)


# ---------------------------------------------------------------------------------------------
# the models under common property tests
# ---------------------------------------------------------------------------------------------

UV_FIXED = np.random.default_rng(7).random((4096, 2))

PREVIEW_METAL = {"diffuseColor": (0.9, 0.6, 0.3), "metallic": 0.7, "roughness": 0.35}
# diffuse 0.7: the spec's model exceeds albedo 1 at grazing for a white diffuse (see
# test_preview_white_diffuse_exceeds_one_at_grazing)
PREVIEW_DIELECTRIC = {"diffuseColor": (0.7, 0.7, 0.7), "roughness": 0.3, "ior": 1.8}
PREVIEW_SPECULAR = {
    "useSpecularWorkflow": 1,
    "diffuseColor": (0.6, 0.6, 0.6),
    "specularColor": (0.4, 0.4, 0.4),
    "roughness": 0.4,
}
CELLULAR = {"cellScale": 6.0, "borderWidth": 0.2, "borderRoughness": 0.35, "seed": 3}


def _analytic_for_merl(wi, wo):
    return brdf.preview_surface(
        {"diffuseColor": (0.5, 0.3, 0.1), "metallic": 0.2, "roughness": 0.6}, wi, wo
    )


@pytest.fixture(scope="module")
def merl_file(tmp_path_factory):
    table = brdf.tabulate_merl(_analytic_for_merl)
    path = tmp_path_factory.mktemp("merl") / "analytic.binary"
    brdf.write_merl(path, table)
    return path, table


def _models(merl_table):
    """name -> callable (wi, wo) -> f for every model (cellular with a fixed uv per row)."""

    def cell(wi, wo):
        uv = np.resize(UV_FIXED, (wi.shape[0], 2))
        return brdf.cellular(CELLULAR, uv, wi, wo)

    return {
        "lambert": lambda wi, wo: brdf.lambert((0.9, 0.5, 1.0), wi, wo),
        "phong": lambda wi, wo: brdf.phong((0.3, 0.2, 0.1), (0.7, 0.5, 0.3), 40.0, wi, wo),
        "preview_metal": lambda wi, wo: brdf.preview_surface(PREVIEW_METAL, wi, wo),
        "preview_dielectric": lambda wi, wo: brdf.preview_surface(PREVIEW_DIELECTRIC, wi, wo),
        "preview_specular": lambda wi, wo: brdf.preview_surface(PREVIEW_SPECULAR, wi, wo),
        "cellular": cell,
        "merl": lambda wi, wo: brdf.merl_lookup(merl_table, wi, wo),
        "merl_linear": lambda wi, wo: brdf.merl_lookup(merl_table, wi, wo, interpolate=True),
    }


MODEL_NAMES = [
    "lambert",
    "phong",
    "preview_metal",
    "preview_dielectric",
    "preview_specular",
    "cellular",
    "merl",
    "merl_linear",
]


@pytest.mark.parametrize("name", MODEL_NAMES)
def test_non_negative_and_finite(name, merl_file):
    fn = _models(merl_file[1])[name]
    wi, wo = _random_pairs(20_000, seed=1)
    f = fn(wi, wo)
    assert f.shape == (20_000, 3) and f.dtype == np.float64
    assert np.all(np.isfinite(f))
    assert np.all(f >= 0.0)
    assert np.any(f > 0.0)


@pytest.mark.parametrize("name", MODEL_NAMES)
def test_reciprocity(name, merl_file):
    fn = _models(merl_file[1])[name]
    wi, wo = _random_pairs(20_000, seed=2)
    a, b = fn(wi, wo), fn(wo, wi)
    if name == "merl":
        # nearest-bin lookup: swapping maps phi_diff to phi_diff + pi, the same bin up to
        # round-off at bin boundaries ("to the table's symmetry")
        same = np.all(a == b, axis=1)
        assert same.mean() > 0.999
    elif name == "merl_linear":
        # interpolation weights from (theta_h, theta_d, phi_d) computed from wi or from wo:
        # equal up to the round-off of the rotations and atan2 (measured <= 3e-12 relative)
        np.testing.assert_allclose(a, b, rtol=1e-9, atol=0.0)
    else:
        # every model is symmetric term by term; only floating-point reassociation differs
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=0.0)


@pytest.mark.parametrize("name", MODEL_NAMES)
def test_zero_below_horizon_and_for_nan(name, merl_file):
    fn = _models(merl_file[1])[name]
    wi, wo = _random_pairs(1000, seed=3)
    below = wi * np.array([1.0, 1.0, -1.0])
    assert np.all(fn(below, wo) == 0.0)
    assert np.all(fn(wi, below) == 0.0)
    flat = wi.copy()
    flat[:, 2] = 0.0  # exactly grazing
    flat[:, :2] /= np.linalg.norm(flat[:, :2], axis=1, keepdims=True)
    assert np.all(fn(flat, wo) == 0.0)
    bad = wi.copy()
    bad[::2, 0] = np.nan
    assert np.all(fn(bad, wo)[::2] == 0.0)


@pytest.mark.parametrize("name", MODEL_NAMES)
def test_directional_albedo_at_most_one(name, merl_file):
    fn = _models(merl_file[1])[name]
    wo = np.concatenate([_view(t) for t in VIEW_THETAS_DEG])
    mean, err = brdf.directional_albedo(fn, wo, n_samples=N_MC, seed=11)
    # the estimate may exceed the truth by a few standard errors: allow 4 sigma (one-sided
    # p ~ 3e-5 per channel and angle), never more
    assert np.all(mean <= 1.0 + 4.0 * err), (mean, err)


# ---------------------------------------------------------------------------------------------
# closed forms
# ---------------------------------------------------------------------------------------------


def test_lambert_albedo_is_rho():
    rho = np.array([0.9, 0.5, 0.25])
    wo = np.concatenate([_view(t) for t in VIEW_THETAS_DEG])
    mean, err = brdf.directional_albedo(lambda a, b: brdf.lambert(rho, a, b), wo, seed=5)
    # pi * f is constant, so the estimator has zero variance: exact up to the round-off of
    # summing 2e5 equal terms (measured ~4e-12 relative)
    assert np.all(err < 1e-10)
    np.testing.assert_allclose(mean, np.broadcast_to(rho, mean.shape), rtol=1e-10)


def test_phong_albedo_at_normal_incidence_is_kd_plus_ks():
    # at wo = n the mirror direction is n, so the lobe integral is
    # ks (e+2)/(2 pi) * int cos^(e+1) = ks exactly; plus kd
    kd, ks, e = np.array([0.2, 0.1, 0.3]), np.array([0.5, 0.6, 0.1]), 25.0
    mean, err = brdf.directional_albedo(
        lambda a, b: brdf.phong(kd, ks, e, a, b), _view(0.0), n_samples=N_MC, seed=6
    )
    assert np.all(np.abs(mean[0] - (kd + ks)) <= 4.0 * err[0] + 1e-12)


def test_preview_rough_metal_albedo_closed_form():
    # metallic = 1, white albedo, roughness 1: F = 1, D = 1/pi, and Schlick-GGX with k = 1/2
    # gives G/(4 zi zo) = 1/((1+zi)(1+zo)); so rho(wo) = 2 (1 - ln 2) / (1 + cos theta_o).
    params = {"diffuseColor": (1.0, 1.0, 1.0), "metallic": 1.0, "roughness": 1.0}
    wo = np.concatenate([_view(t) for t in VIEW_THETAS_DEG])
    mean, err = brdf.directional_albedo(
        lambda a, b: brdf.preview_surface(params, a, b), wo, n_samples=N_MC, seed=8
    )
    truth = 2.0 * (1.0 - math.log(2.0)) / (1.0 + wo[:, 2])
    assert np.all(np.abs(mean - truth[:, None]) <= 4.0 * err)


# ---------------------------------------------------------------------------------------------
# UsdPreviewSurface against plain-Python values
# ---------------------------------------------------------------------------------------------


def _ref_preview(p: dict, wi, wo) -> list[float]:
    """The spec formulas (see brdf.preview_surface docstring), one direction pair, plain math,
    with an explicit normalised half vector (the module never forms h)."""
    d = p.get("diffuseColor", (0.18, 0.18, 0.18))
    m = p.get("metallic", 0.0)
    ior = p.get("ior", 1.5)
    rough = max(p.get("roughness", 0.5), 0.001)
    cc = p.get("clearcoat", 0.0)
    ccr = max(p.get("clearcoatRoughness", 0.01), 0.001)
    spec_wf = p.get("useSpecularWorkflow", 0)
    hx, hy, hz = wi[0] + wo[0], wi[1] + wo[1], wi[2] + wo[2]
    hl = math.sqrt(hx * hx + hy * hy + hz * hz)
    hx, hy, hz = hx / hl, hy / hl, hz / hl
    ndl, ndv, ndh = wi[2], wo[2], hz
    vdh = wo[0] * hx + wo[1] * hy + wo[2] * hz
    fw = (1.0 - vdh) ** 5
    r2 = ((1.0 - ior) / (1.0 + ior)) ** 2

    def ggx(alpha):
        dd = alpha**2 / (math.pi * (ndh * ndh * (alpha**2 - 1.0) + 1.0) ** 2)
        k = alpha / 2.0
        g = ndl / (ndl * (1 - k) + k) * ndv / (ndv * (1 - k) + k)
        return dd * g / (4.0 * ndl * ndv)

    out = []
    for ch in range(3):
        if spec_wf:
            f0, f90, dc = p["specularColor"][ch], 1.0, d[ch]
        else:
            f0 = (1 - m) * r2 + m * d[ch]
            f90 = (1 - m) + m * d[ch]
            dc = d[ch] * (1 - m)
        fr = f0 + (f90 - f0) * fw
        v = dc / math.pi * (1.0 - fr) + fr * ggx(rough * rough)
        v += cc * (r2 + (1 - r2) * fw) * ggx(ccr * ccr)
        out.append(v)
    return out


def _unit(v):
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v)


HAND_DIRS = [
    (_unit([0.0, 0.0, 1.0]), _unit([0.0, 0.0, 1.0])),  # normal incidence
    (_unit([0.5, 0.1, 0.8]), _unit([-0.45, -0.12, 0.8])),  # near the mirror direction
    (_unit([0.7, 0.2, 0.3]), _unit([0.1, -0.6, 0.5])),  # off-specular
    (_unit([0.95, 0.0, 0.1]), _unit([-0.2, 0.3, 0.9])),  # grazing light
]
HAND_PARAMS = [
    {"diffuseColor": (0.8, 0.5, 0.2), "metallic": 0.4, "roughness": 0.3, "ior": 1.45},
    {"diffuseColor": (0.8, 0.5, 0.2), "metallic": 1.0, "roughness": 0.6},
    {
        "useSpecularWorkflow": 1,
        "diffuseColor": (0.3, 0.6, 0.2),
        "specularColor": (0.9, 0.3, 0.05),
        "roughness": 0.25,
        "metallic": 0.9,  # ignored in the specular workflow
    },
    {"diffuseColor": (0.2, 0.2, 0.7), "roughness": 0.5, "clearcoat": 0.8,
     "clearcoatRoughness": 0.1},
]


@pytest.mark.parametrize("params", HAND_PARAMS)
def test_preview_against_plain_python(params):
    wi = np.array([a for a, _ in HAND_DIRS])
    wo = np.array([b for _, b in HAND_DIRS])
    got = brdf.preview_surface(params, wi, wo)
    want = np.array([_ref_preview(params, a, b) for a, b in HAND_DIRS])
    # same formulas, different evaluation order (closed-form n.h and wo.h): ~1e-15 relative
    np.testing.assert_allclose(got, want, rtol=1e-11, atol=0.0)


def test_preview_white_diffuse_exceeds_one_at_grazing():
    # A documented property of the spec's model (brdf.preview_surface docstring): the diffuse
    # weight (1 - F(wo.h)) ignores the energy the specular lobe takes at grazing view, so a white
    # diffuse reflects more than it receives at 80 deg (measured 1.16). If this ever fails, the
    # model changed away from the spec/Storm formulas.
    params = {"diffuseColor": (1.0, 1.0, 1.0), "roughness": 0.3, "ior": 1.5}
    mean, err = brdf.directional_albedo(
        lambda a, b: brdf.preview_surface(params, a, b), _view(80.0), n_samples=N_MC, seed=26
    )
    assert mean[0, 0] > 1.0 + 4.0 * err[0, 0]
    assert mean[0, 0] < 1.3


def test_preview_by_hand_at_normal_incidence():
    # wi = wo = n, roughness 1, dielectric, ior 1.5, diffuse 0.5: h = n, w = 0, F = F0 = 0.04,
    # D = 1/pi, G/(4 zi zo) = 1/4  ->  f = 0.5/pi * 0.96 + 0.04/(4 pi) = 0.49/pi
    z = np.array([[0.0, 0.0, 1.0]])
    f = brdf.preview_surface({"diffuseColor": (0.5, 0.5, 0.5), "roughness": 1.0}, z, z)
    np.testing.assert_allclose(f, 0.49 / math.pi, rtol=1e-12)


def test_preview_defaults_match_spec():
    # no params at all: diffuse 0.18, roughness 0.5, metallic 0, ior 1.5
    wi = np.array([a for a, _ in HAND_DIRS])
    wo = np.array([b for _, b in HAND_DIRS])
    got = brdf.preview_surface({}, wi, wo)
    want = np.array([_ref_preview({}, a, b) for a, b in HAND_DIRS])
    np.testing.assert_allclose(got, want, rtol=1e-11)


def test_metallic_vs_specular_workflow():
    wi, wo = _random_pairs(5000, seed=9)
    d = (0.6, 0.3, 0.2)
    # metallic 0 with ior 1.5 (F0 = 0.04, F90 = 1) equals the specular workflow with
    # specularColor 0.04: the two workflows agree where the spec says they must
    metal0 = brdf.preview_surface({"diffuseColor": d, "metallic": 0.0, "ior": 1.5}, wi, wo)
    spec = brdf.preview_surface(
        {"useSpecularWorkflow": 1, "diffuseColor": d, "specularColor": (0.04,) * 3}, wi, wo
    )
    np.testing.assert_allclose(metal0, spec, rtol=1e-12)
    # metallic 1: no diffuse at all, F0 = F90 = albedo, i.e. albedo * (the white-metal lobe)
    metal1 = brdf.preview_surface({"diffuseColor": d, "metallic": 1.0}, wi, wo)
    white = brdf.preview_surface({"diffuseColor": (1, 1, 1), "metallic": 1.0}, wi, wo)
    np.testing.assert_allclose(metal1, white * np.array(d), rtol=1e-12)
    # the specular workflow ignores metallic; the metallic workflow ignores specularColor
    spec_m = brdf.preview_surface(
        {"useSpecularWorkflow": 1, "diffuseColor": d, "specularColor": (0.04,) * 3,
         "metallic": 1.0}, wi, wo
    )
    np.testing.assert_array_equal(spec_m, spec)
    metal_s = brdf.preview_surface(
        {"diffuseColor": d, "metallic": 0.0, "specularColor": (1.0, 0.0, 0.0)}, wi, wo
    )
    np.testing.assert_array_equal(metal_s, metal0)
    # and the workflows differ for the same numbers otherwise
    assert np.abs(metal1 - brdf.preview_surface(
        {"useSpecularWorkflow": 1, "diffuseColor": d, "specularColor": d}, wi, wo)).max() > 0.01


def test_preview_per_element_params_match_scalar_calls():
    wi, wo = _random_pairs(3000, seed=10)
    rough = np.where(np.arange(3000) % 2 == 0, 0.2, 0.7)
    got = brdf.preview_surface({"roughness": rough, "metallic": 0.5}, wi, wo)
    even = brdf.preview_surface({"roughness": 0.2, "metallic": 0.5}, wi, wo)
    odd = brdf.preview_surface({"roughness": 0.7, "metallic": 0.5}, wi, wo)
    np.testing.assert_array_equal(got[::2], even[::2])
    np.testing.assert_array_equal(got[1::2], odd[1::2])


def test_preview_sharp_lobe_dynamic_range():
    # roughness clamps at 0.001 (Storm): a mirror-like lobe with a peak/off-peak ratio > 1e6
    # must stay finite and positive
    wi = np.array([_unit([0.3, 0.0, 1.0]), _unit([0.3, 0.0, 1.0])])
    wo = np.array([_unit([-0.3, 0.0, 1.0]), _unit([0.0, 0.5, 1.0])])
    f = brdf.preview_surface({"roughness": 0.0, "metallic": 1.0, "diffuseColor": (1, 1, 1)},
                             wi, wo)
    assert np.all(np.isfinite(f)) and np.all(f > 0)
    assert f[0, 0] / f[1, 0] > 1e6


def test_ggx_conductor_equals_metallic_preview():
    wi, wo = _random_pairs(2000, seed=12)
    f0 = (0.95, 0.7, 0.3)
    a = brdf.ggx_conductor(f0, 0.4, wi, wo)
    # metallic=1 in the preview surface has F90 = albedo, the conductor has F90 = 1: compare the
    # conductor with F0 = 1 (both then have F = 1)
    b = brdf.ggx_conductor((1, 1, 1), 0.4, wi, wo)
    c = brdf.preview_surface({"diffuseColor": (1, 1, 1), "metallic": 1.0, "roughness": 0.4},
                             wi, wo)
    np.testing.assert_allclose(b, c, rtol=1e-12)
    assert np.all(a <= b + 1e-15)


# ---------------------------------------------------------------------------------------------
# MERL
# ---------------------------------------------------------------------------------------------


def test_merl_file_layout(merl_file):
    path, table = merl_file
    raw = path.read_bytes()
    assert len(raw) == 12 + 3 * 90 * 90 * 180 * 8
    assert np.frombuffer(raw[:12], "<i4").tolist() == [90, 90, 180]
    # first stored double is red[0, 0, 0] / (1/1500); a green value is divided by 1.15/1500
    first = np.frombuffer(raw[12:20], "<f8")[0]
    assert first == pytest.approx(table[0, 0, 0, 0] * 1500.0, rel=1e-15)
    g_off = 12 + 8 * (90 * 90 * 180 + 5)
    g = np.frombuffer(raw[g_off : g_off + 8], "<f8")[0]
    assert g == pytest.approx(table[1, 0, 0, 5] * 1500.0 / 1.15, rel=1e-15)


def test_merl_roundtrip_and_invalid(merl_file, tmp_path):
    path, table = merl_file
    back = brdf.read_merl(path)
    assert back.shape == (3, 90, 90, 180) and back.dtype == np.float64
    np.testing.assert_allclose(back, table, rtol=1e-15, atol=0.0)  # x / s * s: 1 ulp
    small = np.full((3, 4, 5, 6), 0.25)
    small[1, 2, 3, 4] = -1.0  # invalid marker
    brdf.write_merl(tmp_path / "s.binary", small)
    got = brdf.read_merl(tmp_path / "s.binary")
    assert got[1, 2, 3, 4] == 0.0
    np.testing.assert_allclose(np.delete(got.ravel(), np.ravel_multi_index((1, 2, 3, 4),
                               small.shape)), 0.25, rtol=1e-15)


def test_merl_lookup_at_bin_centres_is_exact(merl_file):
    _, table = merl_file
    wi, wo = brdf.merl_bin_directions()
    sel = np.flatnonzero((wi[:, 2] > 0.05) & (wo[:, 2] > 0.05))[::37]
    got = brdf.merl_lookup(table, wi[sel], wo[sel])
    np.testing.assert_allclose(got, _analytic_for_merl(wi[sel], wo[sel]), rtol=1e-12)


def test_merl_lookup_vs_analytic(merl_file):
    path, _ = merl_file
    table = brdf.read_merl(path)
    wi, wo = _random_pairs(40_000, seed=13)
    keep = (wi[:, 2] > 0.2) & (wo[:, 2] > 0.2)
    wi, wo = wi[keep], wo[keep]
    truth = _analytic_for_merl(wi, wo)
    near = brdf.merl_lookup(table, wi, wo)
    lin = brdf.merl_lookup(table, wi, wo, interpolate=True)
    # bound from the bin width: a query lies within half a bin of its bin centre on each of
    # the 3 axes, so |error| <~ 0.5 * sum over axes of the largest change between adjacent
    # bins around it. Measured from the table itself (no assumed Lipschitz constant), x2 slack
    # for the curvature of f within a bin.
    th, td, pd = brdf_merl._merl_angles(wi, wo)
    ih = np.clip((np.sqrt(th / (np.pi / 2)) * 90).astype(int), 0, 89)
    i_d = np.clip((td / (np.pi / 2) * 90).astype(int), 0, 89)
    ip = np.clip((pd / np.pi * 180).astype(int), 0, 179)
    t = table

    def step(axis_idx, n, idx):
        lo_, hi_ = np.clip(idx - 1, 0, n - 1), np.clip(idx + 1, 0, n - 1)
        a = [ih, i_d, ip]
        b, c = list(a), list(a)
        b[axis_idx], c[axis_idx] = lo_, hi_
        centre = t[:, a[0], a[1], a[2]]
        return np.maximum(np.abs(t[:, b[0], b[1], b[2]] - centre),
                          np.abs(t[:, c[0], c[1], c[2]] - centre)).T

    bound = 0.5 * (step(0, 90, ih) + step(1, 90, i_d) + step(2, 180, ip))
    err_near = np.abs(near - truth)
    assert np.all(err_near <= 2.0 * bound + 1e-12)
    # trilinear interpolation is second order in the bin width: much better on average
    rel_lin = np.abs(lin - truth).mean() / truth.mean()
    rel_near = err_near.mean() / truth.mean()
    assert rel_lin < 0.25 * rel_near
    assert rel_lin < 2e-3


def test_merl_errors(tmp_path):
    bad = tmp_path / "short.binary"
    bad.write_bytes(np.array([90, 90, 180], "<i4").tobytes() + b"\0" * 80)
    with pytest.raises(AssetError, match="short.binary"):
        brdf.read_merl(bad)
    with pytest.raises(AssetError, match="missing.binary"):
        brdf.read_merl(tmp_path / "missing.binary")
    with pytest.raises(ShapeError):
        brdf.write_merl(tmp_path / "x.binary", np.zeros((90, 90, 180)))
    with pytest.raises(ShapeError):
        brdf.merl_lookup(np.zeros((3, 4, 4)), np.zeros((1, 3)), np.zeros((1, 3)))


# ---------------------------------------------------------------------------------------------
# cellular
# ---------------------------------------------------------------------------------------------


def test_worley_against_brute_force():
    rng = np.random.default_rng(14)
    pts = rng.random((3000, 2)) * 10.0 - 5.0
    f1, f2, cell = brdf.worley(pts, seed=4)
    # brute force: every feature point of cells [-8, 8)^2
    ii, jj = np.meshgrid(np.arange(-8, 8), np.arange(-8, 8), indexing="ij")
    ii, jj = ii.ravel(), jj.ravel()
    sd = np.full(ii.shape, 4)
    fx, fy = brdf_cellular._feature_points(ii, jj, sd)
    assert np.all((fx >= ii) & (fx < ii + 1) & (fy >= jj) & (fy < jj + 1))
    d = np.hypot(pts[:, None, 0] - fx[None], pts[:, None, 1] - fy[None])  # (3000, 256)
    order = np.sort(d, axis=1)
    np.testing.assert_allclose(f1, order[:, 0], rtol=1e-12)
    arg = np.argmin(d, axis=1)
    np.testing.assert_array_equal(cell, np.stack([ii[arg], jj[arg]], axis=1))
    # F2 from 3 x 3 cells is exact except in rare configurations
    assert np.mean(np.abs(f2 - order[:, 1]) < 1e-12) > 0.99
    assert np.all(f2 >= order[:, 1] - 1e-12)


def test_cellular_mask_fraction_and_determinism():
    uv = np.random.default_rng(15).random((50_000, 2))
    fr = [brdf.cellular_mask({"borderWidth": w, "cellScale": 8.0}, uv).mean()
          for w in (0.0, 0.02, 0.04, 0.08)]
    assert fr[0] == 0.0
    assert fr[1] < fr[2] < fr[3]
    # thin borders: the area with F2 - F1 < w grows linearly in w (a band along the edges)
    assert 1.6 < fr[2] / fr[1] < 2.4 and 1.6 < fr[3] / fr[2] < 2.4
    a = brdf.cellular_mask(CELLULAR, uv)
    b = brdf.cellular_mask(CELLULAR, uv)
    np.testing.assert_array_equal(a, b)
    c = brdf.cellular_mask({**CELLULAR, "seed": 4}, uv)
    assert np.mean(a != c) > 0.05


def test_cellular_ids_and_colours():
    s = 8.0
    g = (np.arange(200) + 0.5) / 200
    uv = np.stack(np.meshgrid(g, g, indexing="ij"), axis=-1).reshape(-1, 2)
    ids = brdf.cellular_cell_id({"cellScale": s}, uv)
    # about one cell per unit square of uv * cellScale (plus partial cells on the boundary)
    assert abs(len(np.unique(ids)) - s * s) <= 4 * s + 4
    col = brdf.cellular_color({"cellScale": s}, uv)
    a = np.array(brdf.CELLULAR_DEFAULTS["cellColorA"])
    b = np.array(brdf.CELLULAR_DEFAULTS["cellColorB"])
    t = (col - a) / (b - a)
    np.testing.assert_allclose(t, t[:, :1].repeat(3, axis=1), atol=1e-12)  # on the segment A-B
    # one colour per cell
    for cid in np.unique(ids)[:20]:
        assert np.ptp(col[ids == cid], axis=0).max() == 0.0
    # deterministic bytes across calls
    assert brdf.cellular_cell_id({"cellScale": s}, uv).tobytes() == ids.tobytes()


def test_cellular_brdf_is_lambert_inside_and_metal_on_borders():
    uv = UV_FIXED
    n = uv.shape[0]
    wi, wo = _random_pairs(n, seed=16)
    f = brdf.cellular(CELLULAR, uv, wi, wo)
    border = brdf.cellular_mask(CELLULAR, uv)
    assert 0.1 < border.mean() < 0.9
    inside = brdf.lambert(brdf.cellular_color(CELLULAR, uv), wi, wo)
    np.testing.assert_array_equal(f[~border], inside[~border])
    metal = brdf.ggx_conductor(brdf.CELLULAR_DEFAULTS["borderColor"],
                               CELLULAR["borderRoughness"], wi, wo)
    np.testing.assert_array_equal(f[border], metal[border])


# ---------------------------------------------------------------------------------------------
# textures
# ---------------------------------------------------------------------------------------------


def _tex(pixels, **kw):
    return model.Texture(path="tex.png", pixels=np.asarray(pixels, dtype=np.float32), **kw)


# 2 rows x 3 columns, one channel; row 0 is the TOP of the image
PIX = np.array([[[1.0], [2.0], [4.0]],
                [[8.0], [16.0], [32.0]]])


def test_sample_texture_bilinear_by_hand():
    tex = _tex(PIX, wrap_s="clamp", wrap_t="clamp")
    # texel centres: s = (c + .5)/3, t = 1 - (r + .5)/2. Bottom-left texel (row 1, col 0) = 8.
    uv = np.array([
        [0.5 / 3, 0.25],  # centre of row 1, col 0 -> 8
        [0.5 / 3, 0.75],  # centre of row 0, col 0 -> 1
        [1.0 / 3, 0.25],  # halfway between cols 0 and 1 of row 1 -> (8 + 16)/2
        [1.0 / 3, 0.5],  # centre of the 2x2 block of cols 0-1 -> (1 + 2 + 8 + 16)/4
        [0.5, 0.5 + 0.125],  # col 1 exactly, 3/4 of the way from row 1 to row 0
    ])
    got = brdf.sample_texture(tex, uv)
    want = np.array([[8.0], [1.0], [12.0], [6.75], [0.75 * 2.0 + 0.25 * 16.0]])
    np.testing.assert_allclose(got, want, rtol=1e-12)


def test_sample_texture_wrap_modes():
    # query s = -1/6 (half a texel left of the image, i.e. "column -1" centre), t on row 1
    uv = np.array([[-0.5 / 3, 0.25], [1.0 + 0.5 / 3, 0.25]])
    expect = {
        "repeat": [32.0, 8.0],  # column -1 = column 2; column 3 = column 0
        "clamp": [8.0, 32.0],
        "mirror": [8.0, 32.0],  # column -1 mirrors column 0; column 3 mirrors column 2
        "black": [0.0, 0.0],
    }
    for mode, want in expect.items():
        got = brdf.sample_texture(_tex(PIX, wrap_s=mode, wrap_t="clamp"), uv)[:, 0]
        np.testing.assert_allclose(got, want, rtol=1e-12, err_msg=mode)
    # mirror vs repeat two texels out: column -2 mirrors column 1, repeats column 1 too; column
    # -3 mirrors column 2 and repeats column 0
    uv3 = np.array([[-2.5 / 3, 0.25]])
    assert brdf.sample_texture(_tex(PIX, wrap_s="mirror", wrap_t="clamp"), uv3)[0, 0] == 32.0
    assert brdf.sample_texture(_tex(PIX, wrap_s="repeat", wrap_t="clamp"), uv3)[0, 0] == 8.0
    # black blends with 0 within half a texel of the edge: at s = 0 half of column 0
    uv0 = np.array([[0.0, 0.25]])
    assert brdf.sample_texture(_tex(PIX, wrap_s="black", wrap_t="clamp"), uv0)[0, 0] == 4.0
    # wrap_t acts on t: t = 1.25 repeats to t = 0.25, the centre of row 1 (the bottom row)
    uvt = np.array([[0.5 / 3, 1.25]])
    assert brdf.sample_texture(_tex(PIX, wrap_s="clamp", wrap_t="repeat"), uvt)[0, 0] == 8.0


def test_sample_texture_scale_bias_and_channels():
    rgba = np.stack([PIX[..., 0], 2 * PIX[..., 0], 3 * PIX[..., 0], np.ones((2, 3))], axis=-1)
    tex = _tex(rgba, wrap_s="clamp", wrap_t="clamp", scale=(0.5, 1.0, 2.0, 1.0),
               bias=(1.0, 0.0, -1.0, 0.0))
    got = brdf.sample_texture(tex, np.array([[0.5 / 3, 0.25]]))
    np.testing.assert_allclose(got, [[0.5 * 8 + 1, 16.0, 2 * 24 - 1, 1.0]], rtol=1e-12)
    with pytest.raises(SettingsError, match="tex.png"):
        brdf.sample_texture(_tex(PIX, wrap_s="useMetadataX"), np.zeros((1, 2)))
    assert brdf.sample_texture(_tex(PIX), np.zeros((0, 2))).shape == (0, 1)


# ---------------------------------------------------------------------------------------------
# the dispatcher
# ---------------------------------------------------------------------------------------------


def test_evaluate_picks_each_model(merl_file):
    path, table = merl_file
    wi, wo = _random_pairs(2000, seed=17)
    uv = UV_FIXED[:2000]
    cases = [
        (model.Material("/M/lam", "lambert", {"diffuseColor": (0.2, 0.4, 0.6)}),
         brdf.lambert((0.2, 0.4, 0.6), wi, wo)),
        (model.Material("/M/ph", "phong", {"diffuseColor": (0.2, 0.2, 0.2),
                                           "specularColor": (0.5, 0.5, 0.5), "exponent": 10.0}),
         brdf.phong((0.2,) * 3, (0.5,) * 3, 10.0, wi, wo)),
        (model.Material("/M/pv", "preview", PREVIEW_METAL),
         brdf.preview_surface(PREVIEW_METAL, wi, wo)),
        (model.Material("/M/mt", "merl", {"table": table, "scale": 2.0}),
         2.0 * brdf.merl_lookup(table, wi, wo)),
        (model.Material("/M/mf", "merl", {"file": str(path)}),
         brdf.merl_lookup(table, wi, wo)),
        (model.Material("/M/cel", "cellular", CELLULAR),
         brdf.cellular(CELLULAR, uv, wi, wo)),
    ]
    for mat, want in cases:
        got = brdf.evaluate(mat, wi, wo, uv)
        np.testing.assert_allclose(got, want, rtol=1e-13, err_msg=mat.path)
    # models really differ (the dispatcher cannot be returning one model for all)
    vals = [c[1] for c in cases]
    for i in range(len(vals)):
        for j in range(i + 1, len(vals)):
            assert np.abs(vals[i] - vals[j]).max() > 1e-3


def test_evaluate_textured_inputs():
    wi, wo = _random_pairs(500, seed=18)
    uv = np.random.default_rng(19).random((500, 2))
    rgb = np.random.default_rng(20).random((4, 5, 3))
    tex = _tex(rgb)
    rough_tex = _tex(np.random.default_rng(21).random((3, 3, 1)))
    mat = model.Material("/M/tex", "preview", {"diffuseColor": (9, 9, 9), "metallic": 0.3},
                         textures={"diffuseColor": tex, "roughness": rough_tex})
    got = brdf.evaluate(mat, wi, wo, uv)
    want = brdf.preview_surface(
        {"diffuseColor": brdf.sample_texture(tex, uv), "metallic": 0.3,
         "roughness": brdf.sample_texture(rough_tex, uv)[:, 0]}, wi, wo)
    np.testing.assert_allclose(got, want, rtol=1e-13)
    # a grey (1-channel) texture on a colour input is broadcast to RGB
    grey = model.Material("/M/grey", "lambert", textures={"diffuseColor": rough_tex})
    g = brdf.evaluate(grey, wi, wo, uv)
    np.testing.assert_array_equal(g[:, 0], g[:, 1])
    with pytest.raises(ShapeError, match="/M/tex"):
        brdf.evaluate(mat, wi, wo, None)


def test_diffuse_albedo_per_model(merl_file):
    uv = UV_FIXED[:100]
    d = np.array([0.8, 0.5, 0.2])
    pv = model.Material("/M/pv", "preview", {"diffuseColor": d, "metallic": 0.25})
    np.testing.assert_allclose(brdf.diffuse_albedo(pv, uv), np.tile(0.75 * d, (100, 1)))
    pvs = model.Material("/M/pvs", "preview", {"diffuseColor": d, "metallic": 0.25,
                                               "useSpecularWorkflow": 1})
    np.testing.assert_allclose(brdf.diffuse_albedo(pvs, uv), np.tile(d, (100, 1)))
    ph = model.Material("/M/ph", "phong", {"diffuseColor": d})
    np.testing.assert_allclose(brdf.diffuse_albedo(ph), d[None])
    cel = model.Material("/M/cel", "cellular", CELLULAR)
    np.testing.assert_allclose(brdf.diffuse_albedo(cel, uv), brdf.cellular_color(CELLULAR, uv))
    # merl tabulated from a Lambertian: every bin holds rho/pi, so the normal-incidence albedo
    # is rho to quadrature round-off
    rho = np.array([0.7, 0.4, 0.1])
    lam_table = np.broadcast_to((rho / np.pi)[:, None, None, None], (3, 90, 90, 180))
    mm = model.Material("/M/merl", "merl", {"table": lam_table})
    np.testing.assert_allclose(brdf.diffuse_albedo(mm, uv[:3]), np.tile(rho, (3, 1)),
                               rtol=1e-12)
    # the analytic table: the albedo at normal incidence agrees with Monte Carlo on the
    # analytic BRDF to MC error + tabulation error (0.5 %)
    mf = model.Material("/M/mf", "merl", {"file": str(merl_file[0])})
    mc, err = brdf.directional_albedo(_analytic_for_merl, _view(0.0), n_samples=N_MC, seed=22)
    np.testing.assert_allclose(brdf.diffuse_albedo(mf)[0], mc[0], rtol=5e-3, atol=4 * err.max())


def test_shading_normal_from_normal_map():
    # a normal map stored as 0..1 colours, remapped by the UsdUVTexture scale 2 / bias -1
    n_ts = np.array([0.6, 0.0, 0.8])  # unit tangent-space normal
    img = np.tile((n_ts + 1.0) / 2.0, (2, 2, 1))
    tex = _tex(img, scale=(2.0, 2.0, 2.0, 1.0), bias=(-1.0, -1.0, -1.0, 0.0))
    mat = model.Material("/M/nm", "preview", textures={"normal": tex})
    uv = np.random.default_rng(27).random((5, 2))
    # float32 pixels: (0.8 + 1)/2 = 0.9 is stored to ~3e-8, hence the tolerance
    np.testing.assert_allclose(brdf.shading_normal(mat, uv), np.tile(n_ts, (5, 1)), atol=1e-7)
    # unnormalised constant -> normalised; below the tangent plane -> (0, 0, 1)
    const = model.Material("/M/c", "preview", {"normal": (0.0, 3.0, 4.0)})
    np.testing.assert_allclose(brdf.shading_normal(const), [[0.0, 0.6, 0.8]], rtol=1e-15)
    flipped = model.Material("/M/f", "preview", {"normal": (0.0, 0.0, -1.0)})
    np.testing.assert_array_equal(brdf.shading_normal(flipped), [[0.0, 0.0, 1.0]])
    lam = model.Material("/M/l", "lambert", {})
    np.testing.assert_array_equal(brdf.shading_normal(lam, uv), np.tile([0.0, 0.0, 1.0], (5, 1)))


def test_evaluate_by_face_groups_materials():
    wi, wo = _random_pairs(3000, seed=23)
    uv = UV_FIXED[:3000]
    mats = [
        model.Material("/M/a", "lambert", {"diffuseColor": (0.5, 0.5, 0.5)}),
        model.Material("/M/b", "preview", PREVIEW_SPECULAR),
        model.Material("/M/c", "cellular", CELLULAR),
    ]
    idx = np.random.default_rng(24).integers(0, 3, 3000)
    got = brdf.evaluate_by_face(mats, idx, wi, wo, uv)
    for k, mat in enumerate(mats):
        sel = idx == k
        np.testing.assert_array_equal(got[sel], brdf.evaluate(mat, wi[sel], wo[sel], uv[sel]))
    with pytest.raises(ShapeError, match=r"\[0, 2\]"):
        brdf.evaluate_by_face(mats, np.full(3000, 3), wi, wo, uv)
    assert brdf.evaluate_by_face(mats, np.zeros(0, int), np.zeros((0, 3)),
                                 np.zeros((0, 3))).shape == (0, 3)


def test_sample_index_matches_per_row_uv():
    # CPM layout: m samples, d direction pairs each; inputs resolved per sample then gathered
    m, d = 300, 7
    uv_s = np.random.default_rng(28).random((m, 2))
    rows = np.repeat(np.arange(m), d)
    rng = np.random.default_rng(29)
    rows = rng.permutation(rows)  # any order
    wi, wo = _random_pairs(m * d, seed=30)
    tex = _tex(np.random.default_rng(31).random((5, 4, 3)))
    mats = [
        model.Material("/M/t", "preview", {"metallic": 0.2}, textures={"diffuseColor": tex,
                                                                        "roughness": tex}),
        model.Material("/M/c", "cellular", CELLULAR, textures={"cellColorA": tex}),
        model.Material("/M/l", "lambert", {"diffuseColor": (0.3, 0.3, 0.3)}),
    ]
    for mat in mats:
        want = brdf.evaluate(mat, wi, wo, uv_s[rows])
        got = brdf.evaluate(mat, wi, wo, uv_s, sample_index=rows)
        np.testing.assert_array_equal(got, want, err_msg=mat.path)
    idx = rng.integers(0, 3, m)[rows]  # one material per sample
    want = brdf.evaluate_by_face(mats, idx, wi, wo, uv_s[rows])
    got = brdf.evaluate_by_face(mats, idx, wi, wo, uv_s, sample_index=rows)
    np.testing.assert_array_equal(got, want)
    with pytest.raises(ShapeError, match="sample_index"):
        brdf.evaluate(mats[0], wi, wo, uv_s, sample_index=np.full(m * d, m))
    with pytest.raises(ShapeError, match="sample_index"):
        brdf.evaluate(mats[0], wi, wo, uv_s, sample_index=rows[:5])


def test_errors():
    wi, wo = _random_pairs(10, seed=25)
    with pytest.raises(ShapeError, match="wi"):
        brdf.lambert((1, 1, 1), wi[:, :2], wo)
    with pytest.raises(ShapeError, match="wo"):
        brdf.phong((1, 1, 1), (0, 0, 0), 1.0, wi, wo[:5])
    with pytest.raises(ShapeError, match="diffuseColor"):
        brdf.preview_surface({"diffuseColor": np.ones((4, 3))}, wi, wo)
    with pytest.raises(ShapeError, match="uv"):
        brdf.cellular({}, np.zeros((10, 3)), wi, wo)
    with pytest.raises(SettingsError, match="bogus"):
        brdf.preview_surface({"bogus": 1.0}, wi, wo)
    bad = model.Material("/World/Looks/Weird", "toon", {})
    with pytest.raises(SettingsError, match="/World/Looks/Weird"):
        brdf.evaluate(bad, wi, wo)
    with pytest.raises(SettingsError, match="/World/Looks/Weird"):
        brdf.diffuse_albedo(bad)
    with pytest.raises(SettingsError, match="/M/m"):
        brdf.evaluate(model.Material("/M/m", "merl", {}), wi, wo)
    with pytest.raises(SettingsError):
        brdf.phong((1, 1, 1), (0, 0, 0), -1.0, wi, wo)


def test_empty_inputs():
    e = np.zeros((0, 3))
    assert brdf.lambert((1, 1, 1), e, e).shape == (0, 3)
    assert brdf.phong((1, 1, 1), (1, 1, 1), 5.0, e, e).shape == (0, 3)
    assert brdf.preview_surface({}, e, e).shape == (0, 3)
    assert brdf.cellular({}, np.zeros((0, 2)), e, e).shape == (0, 3)
    assert brdf.merl_lookup(np.zeros((3, 2, 2, 2)), e, e).shape == (0, 3)


def test_used_rows_is_numpys_unique_inverse():
    from texelbake.brdf.evaluate import _used_rows

    rng = np.random.default_rng(5)
    for m, n in ((1, 5), (7, 40), (300, 1000), (50, 0)):
        rows = rng.integers(0, m, n)
        used, local = _used_rows(rows, m)
        want_used, want_local = np.unique(rows, return_inverse=True)
        np.testing.assert_array_equal(used, want_used)
        np.testing.assert_array_equal(local, want_local)
