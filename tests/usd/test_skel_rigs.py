"""The LOD meshes of a UsdSkel character stay bound to its skeleton for the common rigs (one
skeleton, several meshes, joint subsets, geomBindTransform, a rest pose that is not the bind
pose, an unskinned static prop), and fall back to time samples, saying so, where the rig cannot
be carried (dual-quaternion skinning, a prop that moves with no joint).

Everything about the result is read in a plain pxr process (no texelbake import): UsdSkel's own
skinning of the original meshes and of the LODs at several time codes. The bar per time t: every
LOD vertex, posed by UsdSkel, lies on the original's skinned surface within
  κ_t · e_rest + 1.05 · dev_t + 1e-5 · diag,
where e_rest is the LOD vertices' largest distance to the original at the rest time (its own
simplification error), and, computed here in numpy from the plain process's joint transforms
and weights (an independent implementation of the blend), dev_t is how far linear-blend
skinning carries a point of an original triangle, with the barycentric blend of its corners'
weights, from the skinned triangle (sampled on a 1/8 barycentric grid; the deviation is
quadratic in the position inside a triangle and vanishes at its corners, so the grid misses
under 2 % of its peak: the 1.05), and κ_t the largest stretch of that map (σ_max of A_t A_r⁻¹).
A LOD vertex is a point x of an original triangle plus an offset d along the normal, with the
weights at x (transferred: barycentric blend; here at most three joints, none dropped): posed,
it is Φ(x) + A_t A_r⁻¹ d. 1e-5 · diag is float32 points and transforms (~1e-7) through a few
products, with margin.
"""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import pytest

from tests.helpers.skel_rigs import (
    blend_deviation,
    original_surface,
    plain_pxr,
    surface_distance,
    write_rig,
)
from tests.helpers.usd_validation import stock_errors

TIMES = (0.0, 12.0, 24.0)

def _settings():
    from schemas.settings import BakeSettings

    return BakeSettings(atlas_resolution=16, samples_per_texel=8, n_light_dirs=8,
                        n_view_dirs=8, n_heldout=4, c_max=8, avis_resolution=4,
                        lod_mode="atlas")  # the atlas-sized chain: M1 and M2


def _bake(d: Path, **rig) -> Path:
    from texelbake.pipeline.run import bake

    src = write_rig(d / "rig.usda", **rig)
    with warnings.catch_warnings():  # the fallback's reason: asserted in report.json
        warnings.simplefilter("ignore")
        return bake(src, d / "baked", _settings(), progress=False)


@pytest.fixture(scope="module")
def baked_leg(tmp_path_factory) -> Path:
    return _bake(tmp_path_factory.mktemp("leg"))


@pytest.fixture(scope="module")
def baked_prop(tmp_path_factory) -> Path:
    return _bake(tmp_path_factory.mktemp("prop"), prop=True)


def _check_lods_on_surface(got: dict, *, skinned: bool) -> None:
    """The module docstring's bar, per LOD vertex, at every time (e_rest: that vertex's own
    distance at the rest time); the LODs moved far more than the bar."""
    lods = sorted(p for p in got["meshes"] if "/Baked/LOD" in p)
    assert len(lods) >= 2
    v0, f0 = original_surface(got, TIMES[0])
    diag = float(np.linalg.norm(v0.max(0) - v0.min(0)))
    e_rest = {p: surface_distance(np.array(got["meshes"][p]["t"][str(TIMES[0])]), v0, f0)
              for p in lods}
    for t in TIMES:
        dev, kappa = blend_deviation(got, t, TIMES[0]) if skinned else (0.0, 1.5)
        vt, ft = original_surface(got, t)
        for p in lods:
            bar = kappa * e_rest[p] + 1.05 * dev + 1e-5 * diag
            d_t = surface_distance(np.array(got["meshes"][p]["t"][str(t)]), vt, ft)
            worst = int(np.argmax(d_t - bar))
            assert d_t[worst] <= bar[worst], (p, t, d_t[worst], bar[worst], dev, kappa)
    lod1 = got["meshes"][lods[0]]["t"]
    moved = np.abs(np.array(lod1[str(TIMES[-1])]) - np.array(lod1[str(TIMES[0])])).max()
    assert moved > 0.3 * diag  # not a rest-pose comparison


def test_a_leg_whose_rest_pose_is_not_its_bind_pose_keeps_its_skeleton(baked_leg):
    """Two meshes, joint subsets, geomBindTransforms, restTransforms and a first frame that are
    not the bind pose, a translated SkelRoot: the LODs are bound to the source's skeleton, their
    points in bind space; UsdSkel poses them at the rest time exactly where the bake saw them
    (their p0) and on the skinned original at every other time."""
    from texelbake.usd.read import read_baked

    report = json.loads((baked_leg.parent / "report.json").read_text())
    assert report["lod_animation"] == "usdskel"
    assert not [w for w in report["warnings"] if "not transferred" in w]
    baked = read_baked(baked_leg)
    assert baked.skeleton.endswith("/Char/Skel")
    got = plain_pxr(baked_leg, TIMES)
    for i, m in enumerate(baked.meshes, start=1):
        assert not m.points_over_time.size
        path = next(p for p in got["meshes"] if p.endswith(f"/Baked/LOD{i}"))
        rest = np.array(got["meshes"][path]["t"][str(TIMES[0])])
        np.testing.assert_array_equal(np.array(got["p0"][path]), m.vertices)
        # posed at the rest time: the rest vertices (float32 bind-space points through a blend)
        np.testing.assert_allclose(rest, m.vertices, rtol=0, atol=1e-5)
        # the authored points are the bind pose, not the rest pose: the rig was not trivial
        assert np.abs(m.skin["points"] - m.vertices).max() > 0.1
    _check_lods_on_surface(got, skinned=True)


def test_the_renderer_deforms_the_leg_lods_as_usdskel_does(baked_leg):
    from texelbake.render.deformed import deform_scene
    from texelbake.render.deformed_report import warp_at_time
    from texelbake.render.scene import load_scene

    scene = load_scene(baked_leg)
    got = plain_pxr(baked_leg, TIMES)
    for t in TIMES:
        d = deform_scene(scene, warp_at_time(scene.asset, t))
        for i in range(1, len(scene.baked.meshes) + 1):
            usd = np.array(got["meshes"][next(p for p in got["meshes"]
                                              if p.endswith(f"/Baked/LOD{i}"))]["t"][str(t)])
            np.testing.assert_allclose(d.baked.meshes[i - 1].vertices[: usd.shape[0]], usd,
                                       rtol=0, atol=1e-5 * scene.diag)


def test_an_unskinned_static_prop_is_bound_to_a_static_joint(baked_prop):
    """A mesh under the SkelRoot with no binding: bound rigidly (weight 1) to the first joint
    that does not move, `Root`; its part of each LOD stays where it is."""
    from texelbake.usd.read import read_baked

    report = json.loads((baked_prop.parent / "report.json").read_text())
    assert report["lod_animation"] == "usdskel"
    got = plain_pxr(baked_prop, TIMES)
    _check_lods_on_surface(got, skinned=True)
    prop, leg = ([got["meshes"][p] for p in got["meshes"] if "/Baked/" not in p
                  and p.endswith("/Prop") == want] for want in (True, False))
    for i, m in enumerate(read_baked(baked_prop).meshes, start=1):
        # LOD vertices whose closest original triangle is the prop's
        d_prop = surface_distance(m.vertices, np.array(prop[0]["t"][str(TIMES[0])]),
                           np.array(prop[0]["faces"]))
        d_leg = np.min([surface_distance(m.vertices, np.array(x["t"][str(TIMES[0])]),
                                  np.array(x["faces"])) for x in leg], axis=0)
        near = d_prop < d_leg
        assert near.sum() >= (4 if i == 1 else 0)
        np.testing.assert_array_equal(m.skin["indices"][near, 0], 0)  # Root
        np.testing.assert_allclose(m.skin["weights"][near, 0], 1.0)
        path = next(p for p in got["meshes"] if p.endswith(f"/Baked/LOD{i}"))
        for t in TIMES:
            np.testing.assert_allclose(np.array(got["meshes"][path]["t"][str(t)])[near],
                                       m.vertices[near], rtol=0, atol=1e-5)


@pytest.mark.parametrize(("rig", "reason"), [
    ({"method": "dualQuaternion"}, "mesh /Root/Char/Upper uses dualQuaternion skinning"),
    ({"moving_prop": True}, "mesh /Root/Char/Prop is not skinned and moves with no joint")])
def test_a_rig_that_cannot_be_carried_gives_time_samples_and_says_why(tmp_path, rig, reason):
    """Dual-quaternion skinning is not a linear blend; a prop with its own animation follows no
    joint: the LODs carry time samples of the skinned points (each vertex follows its closest
    original triangle's affine map: on the skinned surface to κ e_rest, κ = 1.5 a bound on the
    normal offset's sqrt(area ratio) scaling for these near-rigid motions), and the report
    names the reason."""
    root = _bake(tmp_path, **rig)
    report = json.loads((root.parent / "report.json").read_text())
    assert report["lod_animation"] == "time_samples"
    assert [w for w in report["warnings"]
            if "UsdSkel skinning not transferred" in w and reason in w]
    got = plain_pxr(root, TIMES)
    assert not [p for p in got["meshes"] if "/Baked/LOD" in p and "weights" in got["meshes"][p]]
    _check_lods_on_surface(got, skinned=False)
    assert stock_errors(root) == {str(root): []}


def test_a_rest_pose_that_folds_a_blend_flat_is_not_carried(tmp_path):
    """The Knee bent 180° at the first frame: the ring weighted 50/50 Hip/Knee is collapsed
    onto the axis at the rest time, where no bind-space point can be recovered from it
    (`lbs.rest_inverse`); ingest says so and describes no skin."""
    from texelbake.asset import load_asset

    src = write_rig(tmp_path / "rig.usda", knee=180.0)
    with pytest.warns(Warning, match="near-singular"):
        asset = load_asset(str(src))
    assert asset.skin is None and asset.has_deformation
    assert load_asset(str(write_rig(tmp_path / "ok.usda", knee=150.0))).skin is not None


def test_a_lod_vertex_with_a_near_singular_rest_blend_gives_every_lod_time_samples(tmp_path):
    """The export's own check (`stages.export.lod_animation`): M_org's blends are all fine but
    a LOD vertex's is not (here the Knee's rest transform replaced by the Hip's turned 180°
    about z, so a LOD vertex weighted 50/50 Hip/Knee folds flat): no LOD is bound, each
    carries time samples, and the warning names the LOD and the count."""
    import dataclasses

    from texelbake.asset import load_asset
    from texelbake.stages.export import lod_animation
    from texelbake.usd.lodmesh import LodMesh

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        asset = load_asset(str(write_rig(tmp_path / "rig.usda")))
    rest = asset.skin.rest.copy()
    turn = np.diag([-1.0, -1.0, 1.0, 1.0])  # 180° about z
    rest[2] = rest[1] @ turn
    asset = dataclasses.replace(asset, skin=dataclasses.replace(asset.skin, rest=rest))
    knee = asset.points[np.argmin(np.abs(asset.skin.weights[:, 1] - 0.5)
                                  + np.abs(asset.skin.weights[:, 2] - 0.5))]
    far = asset.points[np.argmax(asset.skin.weights[:, 1])]  # all Hip
    meshes = [LodMesh(np.stack([knee, far, far + 1e-3]), np.array([[0, 1, 2]]),
                      np.zeros((1, 3, 2))) for _ in range(2)]
    skeleton, warned = lod_animation(asset, meshes)
    assert skeleton == ""
    assert warned == ["lod: UsdSkel skinning not transferred to the LOD meshes (LOD1: 1 "
                      "vertices' blended rest transform is near-singular); they carry time "
                      "samples of the skinned points instead"]
    for m in meshes:
        assert not m.skin
        np.testing.assert_array_equal(m.time_codes, asset.time_codes)
        assert m.points_over_time.shape == (len(asset.time_codes), 3, 3)


def test_skinned_rig_bakes_pass_stock_validation(baked_leg, baked_prop):
    assert stock_errors(baked_leg) == {str(baked_leg): []}
    assert stock_errors(baked_prop) == {str(baked_prop): []}


def test_a_skinned_rig_rebakes_byte_identical(baked_leg, tmp_path):
    again = _bake(tmp_path)
    for name in (baked_leg.name, baked_leg.name.replace("_baked.usda", "_payload.usdc")):
        assert (again.parent / name).read_bytes() == (baked_leg.parent / name).read_bytes()
