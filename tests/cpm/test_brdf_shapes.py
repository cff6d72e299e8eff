"""The product-grid BRDF kernels evaluate a lobe's shape once per distinct shape
(`texelbake.cpm.brdf_product.shape_blocks`): samples with equal local directions and shape
inputs (one flat facet of a texel) share it whatever their colours, and every value equals the
BRDF evaluated entry by entry (`level.brdf_grid`, `brdf.evaluate`), bit for bit."""

from __future__ import annotations

import numpy as np
import pytest

from schemas.settings import BakeSettings
from texelbake.cpm import brdf_product as bp
from texelbake.cpm.level import FitInputs, brdf_grid
from texelbake.model import Material, Texture


def _ramp() -> Texture:
    """A 4 x 4 colour texture varying along both axes."""
    s = np.linspace(0.1, 0.9, 4, dtype=np.float32)
    px = np.stack(np.broadcast_arrays(s[None, :], s[:, None], (s[None, :] + s[:, None]) / 2),
                  axis=-1).astype(np.float32)
    return Texture("ramp.png", np.ascontiguousarray(px), source_color_space="raw")


def _case(n_facets: int, per_facet: int, material: Material, seed: int = 0):
    """Samples on `n_facets` flat facets of `per_facet` samples each (one normal, one texel's
    directions per facet; distinct uv, so distinct colours), and every entry live."""
    rng = np.random.default_rng(seed)
    nrm = rng.normal(size=(n_facets, 3)) + [0.0, 0.0, 3.0]
    nrm /= np.linalg.norm(nrm, axis=1)[:, None]
    p = n_facets * per_facet
    geo = {"sample_nrm": np.repeat(nrm, per_facet, axis=0),
           "sample_mat": np.zeros(p, np.int64),
           "sample_uv": rng.random((p, 2))}
    A, B = 6, 5

    def dirs(k: int) -> np.ndarray:
        d = rng.normal(size=(n_facets, k, 3)) + [0.0, 0.0, 1.5]
        return np.repeat(d / np.linalg.norm(d, axis=2)[..., None], per_facet, axis=0)

    wi, wo = dirs(A), dirs(B)
    live = np.ones((A, B, p), bool)
    src = FitInputs(BakeSettings(), geo, None, [material])
    return src, np.arange(p), wi, wo, live


MATERIALS = {
    "metal": Material("/m/metal", "preview", {"metallic": 1.0, "roughness": 0.3},
                      {"diffuseColor": _ramp()}),
    "clearcoat": Material("/m/coat", "preview", {"roughness": 0.5, "clearcoat": 0.7,
                                                 "clearcoatRoughness": 0.1},
                          {"diffuseColor": _ramp()}),
    "phong": Material("/m/phong", "phong", {"specularColor": (0.3, 0.3, 0.3),
                                            "exponent": 20.0}, {"diffuseColor": _ramp()}),
}


@pytest.mark.parametrize("name", sorted(MATERIALS))
def test_facets_share_their_shape_and_equal_the_brdf_entry_by_entry(name, monkeypatch):
    """Five facets of 24 samples of a textured material: five shapes are evaluated (counted
    at the shape kernel) for 120 samples, and the grid equals the BRDF evaluated entry by
    entry; so does the same case with every sample a facet of its own (no sharing)."""
    shapes = {"preview": "preview_shape", "phong": "phong_shape"}[MATERIALS[name].model]
    inner = getattr(bp, shapes)
    rows: list[int] = []

    def counted(*a, **k):
        rows.append(len(a[1]))  # wi (n, A, 3): the shapes this call evaluates
        return inner(*a, **k)

    monkeypatch.setattr(bp, shapes, counted)
    for n_facets, per_facet in ((5, 24), (120, 1)):
        rows.clear()
        src, smp, wi, wo, live = _case(n_facets, per_facet, MATERIALS[name])
        got = bp.brdf_product(src.geo, src.materials, smp, wi, wo, live)  # (3, p, A, B)
        ref = brdf_grid(src, smp, wi, wo, live)  # (A, B, p, 3)
        np.testing.assert_array_equal(got.transpose(2, 3, 1, 0), ref)
        assert sum(rows) == n_facets
        assert np.ptp(got, axis=1).max() > 0  # the colours differ between a facet's samples


def test_equal_directions_with_other_shape_inputs_are_other_shapes():
    """A roughness texture: samples of one facet whose roughness differs are other shapes
    (the roughness is a shape input), and the grid still equals the BRDF entry by entry."""
    rough = Material("/m/rough", "preview", {"diffuseColor": (0.4, 0.4, 0.4)},
                     {"roughness": Texture("r.png", _ramp().pixels[..., :1].copy(),
                                           source_color_space="raw")})
    src, smp, wi, wo, live = _case(3, 16, rough)
    n_s = len(smp)
    prm = bp.preview_surface_params(
        bp.material_inputs(rough, bp.PREVIEW_BRDF_INPUTS, src.geo["sample_uv"], None), n_s)
    frames = bp.tangent_frames(src.geo["sample_nrm"])
    wi_loc, wo_loc = bp.grid_to_local(frames, wi), bp.grid_to_local(frames, wo)
    blocks = list(bp.shape_blocks(wi_loc, wo_loc, np.arange(n_s),
                                  [prm[k] for k in bp.PREVIEW_SHAPE_INPUTS]))
    n_shapes = sum(len(reps) for _, reps in blocks)
    assert n_shapes == len(np.unique(np.c_[np.repeat(np.arange(3), 16), prm["alpha"]], axis=0))
    assert n_shapes > 3
    got = bp.brdf_product(src.geo, src.materials, smp, wi, wo, live)
    np.testing.assert_array_equal(got.transpose(2, 3, 1, 0), brdf_grid(src, smp, wi, wo, live))
