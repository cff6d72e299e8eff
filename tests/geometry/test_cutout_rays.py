"""Rays through cut-outs (RayCaster(cutout=...), texelbake.brdf.opacity.Cutout): a card whose
opacity texture is 0 on its left half and 1 on its right, above an opaque floor. Expected hits
are the planes' analytic distances."""

from __future__ import annotations

import numpy as np
import pytest

from texelbake.brdf.opacity import can_cut, cutout_of
from texelbake.errors import ShapeError
from texelbake.geometry.raycast import MAX_CUTOUT_ROUNDS, RayCaster
from texelbake.model import Material, Texture

F32_ATOL = 1e-5  # Embree's float32 hits at unit scale (tests/geometry/test_raycast.py)


def _quad(z: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """[-1, 1]^2 at height z facing +z; corner uvs (2, 3, 2) = (x + 1) / 2, (y + 1) / 2."""
    v = np.array([[-1.0, -1.0, z], [1.0, -1.0, z], [1.0, 1.0, z], [-1.0, 1.0, z]])
    f = np.array([[0, 1, 2], [0, 2, 3]])
    return v, f, (v[f][..., :2] + 1.0) / 2.0


def _half_alpha() -> Texture:
    # 2 x 2 texels: columns (s < 0.5, s > 0.5) = (0, 1); nearest-texel halves after bilinear
    # filtering at x < -0.5 and x > 0.5 (the band between is blended)
    px = np.array([[[0.0], [1.0]], [[0.0], [1.0]]], dtype=np.float32)
    return Texture(path="alpha.png", pixels=px, wrap_s="clamp", wrap_t="clamp")


def _scene(n_cards: int = 1, threshold: float = 0.5, constant: float | None = None):
    """n_cards cut-out cards at z = 1, 2, ... above an opaque floor at z = 0."""
    parts = [_quad(0.0)] + [_quad(float(k)) for k in range(1, n_cards + 1)]
    v = np.concatenate([p[0] for p in parts])
    f = np.concatenate([p[1] + 4 * i for i, p in enumerate(parts)])
    uv = np.concatenate([p[2] for p in parts])
    card = Material("/Card", "preview", {"opacity": 1.0 if constant is None else constant,
                                         "opacityThreshold": threshold},
                    {} if constant is not None else {"opacity": _half_alpha()})
    floor = Material("/Floor", "preview", {})
    face_mat = np.array([0, 0] + [1] * (2 * n_cards), dtype=np.int32)
    return v, f, cutout_of((floor, card), face_mat, uv)


def test_eye_and_shadow_rays_pass_the_cut_half_only():
    v, f, cut = _scene()
    assert cut is not None and cut.faces.tolist() == [False, False, True, True]
    caster = RayCaster(v, f, cutout=cut)
    x = np.array([-0.9, -0.7, 0.7, 0.9])
    o = np.column_stack([x, np.zeros(4), np.full(4, 3.0)])
    d = np.tile([0.0, 0.0, -1.0], (4, 1))
    hits = caster.cast(o, d)
    # cut half: through the card (z = 1) to the floor (z = 0): t = 3; opaque half: t = 2
    np.testing.assert_allclose(hits.t, [3, 3, 2, 2], atol=F32_ATOL)
    assert (hits.prim[:2] < 2).all() and (hits.prim[2:] >= 2).all()
    np.testing.assert_allclose(hits.normal, np.tile([0, 0, 1.0], (4, 1)), atol=F32_ATOL)
    # occlusion up to z = 0.5 (tmax 2.5): only the opaque half; unbounded: all (the floor)
    np.testing.assert_array_equal(caster.occluded(o, d, tmax=2.5), [False, False, True, True])
    assert caster.occluded(o, d).all()
    # shadow rays from the floor up toward a light: blocked by the opaque half only
    up = np.column_stack([x, np.zeros(4), np.full(4, 1e-4)])
    np.testing.assert_array_equal(caster.occluded(up, -d), [False, False, True, True])
    np.testing.assert_array_equal(caster.occluded_pairs(up, -d[:1], np.arange(4),
                                                        np.zeros(4, dtype=np.int64)),
                                  [False, False, True, True])
    # the same rays without a cut-out test see the card everywhere
    plain = RayCaster(v, f)
    np.testing.assert_allclose(plain.cast(o, d).t, 2.0, atol=F32_ATOL)
    assert plain.occluded(up, -d).all()


def test_stacked_cut_layers_and_the_round_limit():
    # constant opacity 0.2 under threshold 0.5: every card is cut everywhere
    v, f, cut = _scene(n_cards=3, constant=0.2)
    o, d = np.array([[0.3, 0.1, 10.0]]), np.array([[0.0, 0.0, -1.0]])
    np.testing.assert_allclose(RayCaster(v, f, cutout=cut).cast(o, d).t, [10.0], atol=F32_ATOL)
    # more cut layers than rounds: the ray is taken to pass them all and misses the floor
    v, f, cut = _scene(n_cards=MAX_CUTOUT_ROUNDS + 1, constant=0.2)
    o = np.array([[0.3, 0.1, MAX_CUTOUT_ROUNDS + 5.0]])
    hits = RayCaster(v, f, cutout=cut).cast(o, d)
    assert hits.prim.tolist() == [-1] and np.isinf(hits.t).all()


def test_what_can_cut_and_bad_input():
    # threshold 0: opacity is not read (opaque); a constant at or above the threshold: opaque
    assert not can_cut(Material("/A", "preview", {"opacity": 0.0, "opacityThreshold": 0.0}))
    assert not can_cut(Material("/A", "preview", {"opacity": 0.5, "opacityThreshold": 0.5}))
    assert can_cut(Material("/A", "preview", {"opacity": 0.4, "opacityThreshold": 0.5}))
    assert not can_cut(Material("/A", "lambert", {"opacity": 0.0, "opacityThreshold": 0.5}))
    v, f, _ = _scene()
    assert cutout_of((Material("/F", "preview", {}),), np.zeros(2, np.int32),
                     np.zeros((2, 3, 2))) is None
    _, _, cut = _scene()
    with pytest.raises(ShapeError, match="cutout.faces"):
        RayCaster(v[:4], f[:1], cutout=cut)
    with pytest.raises(ShapeError, match="bary"):
        cut.cut(np.array([2]), np.zeros((1, 3)))
