"""Native instances and point instancers are flattened into meshes (issue 11, item 4).
Expected points are computed here from the authored positions, orientations and scales with
the UsdGeom PointInstancer rule (scale, then orientation, then translation, then the
instancer's transform), not with pxr's instancer helpers."""

from __future__ import annotations

import numpy as np
from pxr import Gf, Sdf, Usd, UsdGeom, Vt

from tests.helpers.usd_stages import new_stage, triangle_mesh
from texelbake.asset import load_asset

TRI = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])


def _quat_matrix(w, x, y, z):
    """Column-vector rotation matrix of a unit quaternion (w, x, y, z)."""
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def test_point_instancer_is_flattened(tmp_path):
    stage = new_stage(tmp_path / "a.usda")
    inst = UsdGeom.PointInstancer.Define(stage, "/Root/Scatter")
    inst.AddTranslateOp().Set(Gf.Vec3d(0.0, 0.0, 5.0))
    protos = UsdGeom.Scope.Define(stage, "/Root/Scatter/Protos")
    a = UsdGeom.Xform.Define(stage, "/Root/Scatter/Protos/A")
    triangle_mesh(stage, "/Root/Scatter/Protos/A/Tri", TRI, [0, 1, 2])
    b = UsdGeom.Xform.Define(stage, "/Root/Scatter/Protos/B")
    b.AddTranslateOp().Set(Gf.Vec3d(0.0, 0.0, 1.0))  # the prototype root's own transform
    triangle_mesh(stage, "/Root/Scatter/Protos/B/Tri", TRI * 2.0, [0, 1, 2])
    del protos, a
    inst.CreatePrototypesRel().SetTargets([Sdf.Path("/Root/Scatter/Protos/A"),
                                           Sdf.Path("/Root/Scatter/Protos/B")])
    pos = np.array([[1.0, 0, 0], [0, 2.0, 0], [3.0, 3.0, 0], [9.0, 9.0, 9.0]])
    h = np.sqrt(0.5)
    quats = [(1.0, 0, 0, 0), (h, 0, 0, h), (1.0, 0, 0, 0), (1.0, 0, 0, 0)]  # 90° about z
    scales = np.array([[1.0, 1, 1], [2.0, 1, 1], [-1.0, 1, 1], [1.0, 1, 1]])  # one mirrored
    inst.CreateProtoIndicesAttr(Vt.IntArray([0, 0, 1, 0]))
    inst.CreatePositionsAttr(Vt.Vec3fArray.FromNumpy(pos.astype(np.float32)))
    inst.CreateOrientationsAttr(Vt.QuathArray([Gf.Quath(*q) for q in quats]))
    inst.CreateScalesAttr(Vt.Vec3fArray.FromNumpy(scales.astype(np.float32)))
    inst.CreateIdsAttr(Vt.Int64Array([10, 11, 12, 13]))
    inst.InvisId(13, Usd.TimeCode.Default())  # hidden: not baked
    stage.Save()
    asset = load_asset(tmp_path / "a.usda")

    def place(local, i, proto_offset):
        p = local * scales[i]  # scale, orient, translate, then the instancer's +5 z
        p = p @ _quat_matrix(*quats[i]).T + proto_offset
        return p + pos[i] + np.array([0.0, 0.0, 5.0])

    expected = [place(TRI, 0, 0.0), place(TRI, 1, 0.0), place(TRI * 2.0, 2, [0.0, 0.0, 1.0])]
    got = asset.points[asset.faces]  # (f, 3, 3)
    assert got.shape[0] == 3  # the hidden instance is not there
    for tri in expected:
        # the same triangle (any corner order: a mirrored copy is rewound); orientations are
        # half-precision quaternions (11-bit mantissa): 2e-3 absolute on unit-size triangles
        match = [np.allclose(np.sort(g, axis=0), np.sort(tri, axis=0), atol=2e-3) for g in got]
        assert any(match), tri
    # every triangle faces +z as authored, the mirrored copy included (winding reversed)
    cross = np.cross(got[:, 1] - got[:, 0], got[:, 2] - got[:, 0])
    assert (cross[:, 2] > 0).all()
    np.testing.assert_allclose(asset.corner_normals[..., 2], 1.0, atol=1e-6)
    assert all(p.startswith("/Root/Scatter[") for p in asset.mesh_paths)


def test_native_instances_each_count(tmp_path):
    stage = new_stage(tmp_path / "a.usda")
    proto = UsdGeom.Xform.Define(stage, "/Proto")
    triangle_mesh(stage, "/Proto/Tri", TRI, [0, 1, 2]).CreateSubdivisionSchemeAttr("none")
    stage.GetPrimAtPath("/Proto").SetSpecifier(Sdf.SpecifierClass)
    del proto
    for i, x in enumerate((0.0, 4.0)):
        copy = UsdGeom.Xform.Define(stage, f"/Root/Copy{i}")
        copy.AddTranslateOp().Set(Gf.Vec3d(x, 0.0, 0.0))
        copy.GetPrim().GetInherits().AddInherit("/Proto")
        copy.GetPrim().SetInstanceable(True)
    stage.Save()
    asset = load_asset(tmp_path / "a.usda")
    assert asset.faces.shape[0] == 2
    xs = sorted(float(asset.points[f].min(axis=0)[0]) for f in asset.faces)
    np.testing.assert_allclose(xs, [0.0, 4.0], atol=1e-6)
