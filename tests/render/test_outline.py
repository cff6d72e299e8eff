"""cpm's outline is M_org's both ways (issue 11): an eye ray that misses the enclosing M_i
but meets M_org — an open surface's edge under M_i's rim — is shaded from M_org."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from pxr import Gf, Sdf, Usd, UsdGeom, UsdLux, UsdShade


def _write_field(path: Path, n: int = 24, amp: float = 0.04) -> Path:
    """An open bumpy height field z = amp sin(9x) cos(7y) over the unit square, Lambertian,
    one distant light."""
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    root = UsdGeom.Xform.Define(stage, "/Root")
    stage.SetDefaultPrim(root.GetPrim())
    xs = np.linspace(-0.5, 0.5, n + 1)
    x, y = np.meshgrid(xs, xs, indexing="xy")
    pts = np.stack([x, y, amp * np.sin(9 * x) * np.cos(7 * y)], -1).reshape(-1, 3)
    a = (np.arange(n)[:, None] * (n + 1) + np.arange(n)[None, :]).reshape(-1)
    quads = np.stack([a, a + 1, a + n + 2, a + n + 1], axis=1).reshape(-1)
    mesh = UsdGeom.Mesh.Define(stage, "/Root/Field")
    mesh.CreatePointsAttr([Gf.Vec3f(*map(float, p)) for p in pts])
    mesh.CreateFaceVertexCountsAttr([4] * (n * n))
    mesh.CreateFaceVertexIndicesAttr([int(i) for i in quads])
    mesh.CreateSubdivisionSchemeAttr("none")
    mat = UsdShade.Material.Define(stage, "/Root/Looks/L")
    sh = UsdShade.Shader.Define(stage, "/Root/Looks/L/S")
    sh.CreateIdAttr("texelbake:lambert")
    sh.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(0.6, 0.5, 0.4))
    mat.CreateSurfaceOutput("texelbake").ConnectToSource(
        sh.CreateOutput("surface", Sdf.ValueTypeNames.Token))
    UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim()).Bind(mat)
    light = UsdLux.DistantLight.Define(stage, "/Root/Sun")
    light.CreateIntensityAttr(3.0)
    light.CreateNormalizeAttr(True)  # UsdLux: the intensity is the irradiance
    UsdGeom.Xformable(light).AddRotateXYZOp().Set(Gf.Vec3f(20, 10, 0))
    stage.GetRootLayer().Save()
    return path


@pytest.fixture(scope="module")
def baked_field(tmp_path_factory):
    from schemas.settings import BakeSettings
    from texelbake.pipeline.run import bake

    d = tmp_path_factory.mktemp("field")
    settings = BakeSettings(atlas_resolution=16, shard_texels=16, samples_per_texel=8,
                            n_light_dirs=8, n_view_dirs=8, n_heldout=8, c_max=8,
                            avis_resolution=8)
    return bake(_write_field(d / "field.usda"), d / "baked", settings, progress=False)


@pytest.mark.parametrize("eye, target, fov", [
    ((1.6, 0.0, 0.25), (0.5, 0.0, 0.0), 8.0),  # magnified, grazing, at the open edge
    ((4.0, 3.0, 3.0), (0.0, 0.0, 0.0), 20.0),  # the whole field, oblique
])
def test_cpm_covers_every_pixel_gt_covers(baked_field, eye, target, fov):
    from texelbake.render.frame import render_frame
    from texelbake.render.scene import load_scene
    from texelbake.trace import camera as cam_mod

    scene = load_scene(baked_field)
    # M1 encloses the open field: its rim lies beyond M_org's edge (what loses the rays)
    m1 = scene.baked.meshes[0].vertices
    assert m1[:, 2].max() > scene.asset.points[:, 2].max()
    cam = cam_mod.look_at(eye, target, 96, 96, fov_deg=fov)
    gt = render_frame(scene, "gt", cam, 4, 0)
    cpm = render_frame(scene, "cpm", cam, 4, 0)
    # the same eye rays (same seed): every ray that meets M_org is shaded by cpm too
    # (before: 473 of 6,720 object pixels lost at the grazing view, 14 of 1,170 oblique)
    np.testing.assert_array_equal(cpm.coverage, gt.coverage)
    lit = gt.image.max(axis=2) > 0
    assert np.all(cpm.image.max(axis=2)[lit] > 0)
