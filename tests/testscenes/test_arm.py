"""The skinned `arm` scene (seed 002): UsdSkel's skinning as read by ingest against an
independent linear-blend skinning in closed form, and the deformed frame it drives."""

from __future__ import annotations

import math

import numpy as np
import pytest

from texelbake.deform.lbs import SkinWarp
from texelbake.deform.warps import triangle_jacobians
from texelbake.errors import SettingsError
from texelbake.render.deformed_report import warp_at_time
from texelbake.testscenes.arm import (
    TIME_CODES,
    joint_heights,
    joint_weights,
    skinning_transforms,
    write_arm,
)


@pytest.fixture(scope="module")
def arm(tmp_path_factory):
    from texelbake.asset import load_asset

    path = write_arm(tmp_path_factory.mktemp("arm") / "arm.usda")
    with pytest.warns(Warning, match="skinned by UsdSkel"):
        return path, load_asset(str(path))


def test_usdskel_points_match_closed_form_skinning(arm):
    _, asset = arm
    np.testing.assert_array_equal(asset.time_codes, TIME_CODES)
    w = joint_weights(asset.points[:, 1])
    for k, t in enumerate(asset.time_codes):
        lbs = SkinWarp(skinning_transforms(t), asset.points, asset.faces, w)
        # float32 points in USD: ~3e-7 at this size
        np.testing.assert_allclose(lbs.positions(asset.points), asset.points_over_time[k],
                                   atol=1e-5)
    # the top cap's centre follows the Wrist alone: the arm bent 90° in closed form
    top = int(np.argmax(asset.points[:, 1] - 1e-3 * np.linalg.norm(asset.points[:, [0, 2]],
                                                                    axis=1)))
    jy = joint_heights()
    seg = jy[2] - jy[1]
    s45 = math.sqrt(0.5)
    tip = np.array([seg * s45 + (1.0 - jy[2]), jy[1] + seg * s45, 0.0])
    np.testing.assert_allclose(asset.points_over_time[-1][top], tip, atol=1e-5)


def test_lbs_jacobian_is_the_joint_rotation_on_rigid_segments(arm):
    _, asset = arm
    t = TIME_CODES[-1]
    w = joint_weights(asset.points[:, 1])
    lbs = SkinWarp(skinning_transforms(t), asset.points, asset.faces, w)
    jac = lbs.jacobian(asset.points)
    per_tri, ok = triangle_jacobians(asset.points, asset.points_over_time[-1], asset.faces)
    rigid = (w[asset.faces].max(axis=2) == 1.0).all(axis=1) & ok  # one joint per triangle
    rigid &= (w[asset.faces].argmax(axis=2) == w[asset.faces[:, 0]].argmax(axis=1)[:, None]
              ).all(axis=1)
    assert rigid.sum() > 50
    # Σ w_j A_j at the corners equals the time samples' per-triangle affine Jacobian
    np.testing.assert_allclose(per_tri[rigid], jac[asset.faces[rigid, 0]], atol=1e-5)
    # and warp_at_time reproduces the asset's own animation
    np.testing.assert_allclose(warp_at_time(asset, 24.0).positions(asset.points),
                               asset.points_over_time[-1], atol=1e-9)


def test_arm_ships_the_shader_definitions_beside_it(arm):
    from texelbake.usd.shaderdefs import DEFINITIONS_FILE

    path, _ = arm  # a stock pxr resolves the arm's texelbake shaders through this file
    assert (path.parent / DEFINITIONS_FILE).is_file()


def test_arm_errors(tmp_path):
    with pytest.raises(SettingsError, match="size"):
        write_arm(tmp_path / "a.usda", "huge")
    with pytest.raises(SettingsError, match="path"):
        write_arm(tmp_path / "a.obj")
