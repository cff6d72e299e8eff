"""Deformed frames of a baked asset (seed 002 §4, `texelbake.render.deformed`): the rigid-motion
identity against the undeformed renderer, point lights (Eq. 11), a singular warp."""

from __future__ import annotations

import copy
import dataclasses
from pathlib import Path

import numpy as np
import pytest

from tests.helpers.render import bake_small_cylinder, psnr_object
from texelbake.deform.warps import AffineWarp, _rotation, parse_warp
from texelbake.errors import SettingsError, StageError
from texelbake.model import Light
from texelbake.render.deformed import deform_scene
from texelbake.render.frame import render_deformed, render_frame
from texelbake.render.scene import RenderScene, load_scene, lod_camera, resolve_camera
from texelbake.trace.camera import PinholeCamera


@pytest.fixture(scope="module")
def baked_cylinder(tmp_path_factory) -> Path:
    return bake_small_cylinder(tmp_path_factory.mktemp("cyl"))


def _with_point_light(scene: RenderScene) -> RenderScene:
    """The scene's lights plus a point light near the object (Eq. 11's attenuation)."""
    s = copy.copy(scene)
    lo, hi = scene.asset.bounds
    pos = 0.5 * (lo + hi) + np.array([2.5, 1.5, 3.0]) * (hi - lo)
    point = Light(path="/Lights/Point", kind="sphere", direction=np.zeros(3), position=pos,
                  radius=0.0, radiance_scale=np.full(3, 40.0))
    s.lights = tuple(scene.lights) + (point,)
    return s


def _moved(scene: RenderScene, q: np.ndarray, t: np.ndarray) -> RenderScene:
    """The scene's lights moved by x -> qᵀ (x − t) (the inverse motion)."""
    s = copy.copy(scene)
    s.lights = tuple(dataclasses.replace(li, direction=q.T @ li.direction,
                                         position=q.T @ (li.position - t))
                     for li in scene.lights)
    return s


def _near_lod_camera(scene: RenderScene, px: int) -> PinholeCamera:
    """The `lod` view's pixel footprint (a finest texel ~0.95 px) from 3 bounding-box
    diagonals away with a narrower field of view. The lod camera itself stands ~150
    diagonals away, where float32 eye-ray origins (Embree) carry ~1e-5 of the object's size
    of rounding, which moves some eye rays across M_i's chart seams between the moved and
    the unmoved frame; nearer, that rounding is 50x smaller."""
    cam = lod_camera(scene, px, px, texel_px=0.95)
    centre = scene.asset.bounds.mean(axis=0)
    far = float(np.linalg.norm(centre - cam.position))
    near = 3.0 * scene.diag
    return PinholeCamera(centre - near * cam.forward, cam.rotation,
                         cam.tan_half_x * far / near, px, px)


@pytest.mark.parametrize("camera", ["lod", 2.5])  # the maps; mostly the fallback to M_org
def test_rigid_motion_equals_the_inversely_moved_view(baked_cylinder, camera):
    scene = _with_point_light(load_scene(baked_cylinder))
    q = _rotation(np.array([0.3, 1.0, 0.2]), 0.7)
    t = np.array([0.3, -0.2, 0.5])
    moved = deform_scene(scene, AffineWarp(q, t))
    cam = (_near_lod_camera(scene, 96) if camera == "lod"
           else resolve_camera(scene, camera, 96, 96))
    inv_cam = PinholeCamera(q.T @ (cam.position - t), q.T @ cam.rotation, cam.tan_half_x,
                            96, 96)
    ref = render_frame(_moved(scene, q, t), "cpm", inv_cam, 4, seed=3)
    got = render_deformed(moved, "cpm", cam, 4, seed=3)
    assert ref.image.max() > 0.05 and (ref.coverage > 0).sum() >= 20
    assert psnr_object(got, ref) >= 60.0
    # the same with L from each texel's own frame (the texel as impostor point)
    assert psnr_object(render_deformed(moved, "cpm", cam, 4, seed=3, lookup="texel"),
                       ref) >= 60.0
    if camera == "lod":  # the maps are used: without L they are read with the moved
        assert got.extras["fallback_fraction"] < 0.1  # world's directions, not the same
        naive = render_deformed(moved, "cpm-naive", cam, 4, seed=3)
        assert psnr_object(naive, ref) < 40.0
    else:  # near: the fallback to the (moved) M_org
        assert got.extras["fallback_fraction"] > 0.5
    gt_ref = render_frame(_moved(scene, q, t), "gt", inv_cam, 4, seed=3)
    assert psnr_object(render_deformed(moved, "gt", cam, 4, seed=3), gt_ref) >= 60.0


def test_point_light_attenuation_follows_the_deformed_distance(baked_cylinder):
    # a uniform scale by s about the centre seen by a camera moved out by s: L = I, every
    # direction unchanged, the point light s times farther: radiance x 1/s² (Eq. 11)
    scene = load_scene(baked_cylinder)
    lo, hi = scene.asset.bounds
    c = 0.5 * (lo + hi)
    pos = c + np.array([2.5, 1.5, 3.0]) * (hi - lo)
    only_point = copy.copy(scene)
    only_point.lights = (Light(path="/Lights/Point", kind="sphere", direction=np.zeros(3),
                               position=pos, radius=0.0, radiance_scale=np.full(3, 40.0)),)
    s = 2.0
    scaled = deform_scene(only_point, AffineWarp(s * np.eye(3), c - s * c))
    scaled.lights = (dataclasses.replace(only_point.lights[0], position=c + s * (pos - c)),)
    cam = resolve_camera(scene, "lod", 64, 64)
    far = PinholeCamera(c + s * (cam.position - c), cam.rotation, cam.tan_half_x, 64, 64)
    ref = render_frame(only_point, "cpm", cam, 4, seed=1)
    got = render_deformed(scaled, "cpm", far, 4, seed=1)
    assert ref.image.max() > 0.01
    mask = (ref.coverage > 0) & (got.coverage > 0)
    np.testing.assert_allclose(got.image[mask] * s * s, ref.image[mask], rtol=1e-4,
                               atol=1e-6 * ref.image.max())


def test_singular_warp_renders_without_nan(baked_cylinder):
    scene = load_scene(baked_cylinder)
    flat = deform_scene(scene, parse_warp("stretch:x=0,y=1,z=1", scene.asset.bounds))
    cam = resolve_camera(scene, "lod", 32, 32)
    for mode in ("gt", "cpm", "cpm-naive", "normalmap"):
        res = render_deformed(flat, mode, cam, 1, seed=0)
        assert np.isfinite(res.image).all(), mode


def test_deformed_modes_and_errors(baked_cylinder):
    scene = load_scene(baked_cylinder)
    d = deform_scene(scene, parse_warp("twist:angle=90", scene.asset.bounds))
    cam = resolve_camera(scene, "lod", 32, 32)
    with pytest.raises(SettingsError, match="mode"):
        render_deformed(d, "toksvig", cam, 1)
    with pytest.raises(StageError, match="needs the BTF maps"):  # baked without settings.btf
        render_deformed(d, "btf", cam, 1)
    with pytest.raises(SettingsError, match="lookup"):
        render_deformed(d, "cpm", cam, 1, lookup="polar")
    with pytest.raises(SettingsError, match="deform_scene"):
        render_deformed(scene, "cpm", cam, 1)
    res = render_deformed(d, "equal-time", cam, 1, budget_seconds=0.0)
    assert res.extras["mean_spp"] == 1.0
    # twisting the rest scene moves the object's pixels: gt differs from the rest's gt
    rest = render_frame(scene, "gt", cam, 1)
    assert np.abs(render_deformed(d, "gt", cam, 1).image - rest.image).max() > 0.01


def test_warp_at_time_follows_the_time_samples():
    from tests.helpers.render import icosphere, model
    from texelbake.render.deformed_report import warp_at_time

    v, f = icosphere(1)
    rest = model(v, f)
    q = _rotation(np.array([0.0, 0.0, 1.0]), 0.5)
    frames = np.stack([v, v @ q.T + [1.0, 0.0, 0.0]])
    animated = dataclasses.replace(rest, time_codes=np.array([0.0, 10.0]),
                                   points_over_time=frames)
    w = warp_at_time(animated, 10.0)
    np.testing.assert_allclose(w.positions(v), frames[1], atol=1e-9)
    np.testing.assert_allclose(w.jacobian(v[:5]), np.broadcast_to(q, (5, 3, 3)), atol=1e-9)
    half = warp_at_time(animated, 5.0).positions(v)  # linear between the two samples
    np.testing.assert_allclose(half, 0.5 * (frames[0] + frames[1]), atol=1e-9)
    np.testing.assert_allclose(warp_at_time(animated, 99.0).positions(v), frames[1], atol=1e-9)
    # a single time sample: the asset does not deform
    single = dataclasses.replace(rest, time_codes=np.array([3.0]), points_over_time=v[None])
    np.testing.assert_array_equal(warp_at_time(single, 7.0).positions(v), v)
    with pytest.raises(SettingsError, match="time"):
        warp_at_time(animated, float("nan"))


def test_cli_render_with_a_warp(baked_cylinder, tmp_path, capsys):
    import json

    from texelbake.cli import main

    out = tmp_path / "tw"
    assert main(["render", str(baked_cylinder), "--warp", "bend:angle=60", "-o", str(out),
                 "--width", "32", "--height", "32", "--ref-spp", "4", "--camera", "lod"]) == 0
    rep = json.loads((out / "deformed_report.json").read_text())
    assert rep["warp"] == "bend:angle=60"
    assert set(rep["modes"]) == {"gt", "cpm", "cpm-naive", "normalmap"}
    assert all(np.isfinite(e["seconds"]) for e in rep["modes"].values())
    assert (out / "cpm.png").is_file() and (out / "reference.exr").is_file()
    assert "cpm-naive" in capsys.readouterr().out
    assert main(["render", str(baked_cylinder), "--warp", "twist:angel=3", "-o", str(out)]) == 2
    assert "field 'warp.angel'" in capsys.readouterr().err


def test_impostor_primvars_round_trip_through_the_payload(baked_cylinder):
    from pxr import Usd, UsdGeom

    from texelbake.deform import impostor as imp
    from texelbake.render.deformed import lod_impostor
    from texelbake.usd.lodmesh import IMPOSTOR_PRIMVARS
    from texelbake.usd.read import read_baked

    baked = read_baked(baked_cylinder)
    assert len(baked.meshes) >= 2
    for i, m in enumerate(baked.meshes):
        assert sorted(m.impostor) == sorted(IMPOSTOR_PRIMVARS)
        assert all(a.shape == (len(m.vertices), 3) for a in m.impostor.values())
        np.testing.assert_array_equal(m.impostor["p0"], m.vertices)  # both float32 on disk
        # what was written is the parameterization of the mesh read back, up to float32
        # storage and ties between quarter turns of equal angle (same minimal angle, u0 a
        # quarter turn of the recomputed one)
        again = imp.impostor_params(m.vertices, m.faces, m.corner_uvs)
        a_st = imp.rotation_angle(imp.rodrigues_to_matrix(m.impostor["r0"]))
        a_re = imp.rotation_angle(imp.rodrigues_to_matrix(again.r0))
        np.testing.assert_allclose(a_st, a_re, atol=1e-5)
        dot = np.abs(np.einsum("ij,ij->i", m.impostor["u0"], again.u0))
        assert (np.minimum(dot, np.abs(1.0 - dot)) < 1e-5).all()
        frames = imp.decode_frames(m.impostor["r0"], m.impostor["u0"], m.impostor["v0"])
        n0 = imp.vertex_normals(m.vertices, m.faces)
        live = np.linalg.norm(n0, axis=1) > 0
        np.testing.assert_allclose(frames[live, :, 2], n0[live], atol=1e-5)
        angle = np.degrees(imp.rotation_angle(imp.rodrigues_to_matrix(m.impostor["r0"])))
        assert angle.max() <= imp.MAX_ANGLE_DEG
        # the renderer takes the stored arrays
        scene = load_scene(baked_cylinder)
        np.testing.assert_array_equal(lod_impostor(scene, i).r0, m.impostor["r0"])
    # a plain pxr reader sees vertex-interpolated float3[] primvars on the LOD meshes
    stage = Usd.Stage.Open(str(baked_cylinder))
    lod1 = [p for p in stage.Traverse() if p.GetName() == "LOD1" and p.IsA(UsdGeom.Mesh)][0]
    pv = UsdGeom.PrimvarsAPI(lod1).GetPrimvar("texelbake:r0")
    assert pv and pv.GetInterpolation() == UsdGeom.Tokens.vertex
    assert str(pv.GetTypeName()) == "float3[]"


def test_refined_lods_follow_a_bend(baked_cylinder):
    # the small cylinder's M1 keeps no edge loop along its axis: deformed vertex by vertex it
    # stays a chord of the bent M_org; refined it follows it
    scene = load_scene(baked_cylinder)
    bend = parse_warp("bend:angle=90", scene.asset.bounds)
    chord = deform_scene(scene, bend, refine=0)
    refined = deform_scene(scene, bend)
    assert refined.lod_error[0] <= 1.5 * scene.lod_error[0]
    assert chord.lod_error[0] > 1.5 * refined.lod_error[0]
    assert len(refined.baked.meshes[0].faces) > len(scene.baked.meshes[0].faces)


def _normal_angles_deg(d) -> np.ndarray:
    """Per characteristic point of the finest level: the angle between the normal the
    per-point look-up shades with (Lᵀ n_rest: the rest shading normal carried to the deformed
    frame) and gt's shading normal at the point (the deformed M_org's corner normals,
    cof(J) n, interpolated at the point's rest triangle)."""
    from texelbake.deform.warps import bind_to_mesh
    from texelbake.render.deformed import _level_geometry

    rest = d.rest
    cp = rest.points(0)
    lpt = _level_geometry(d, 0)["lookup:point"]
    n_cpm = np.einsum("nji,nj->ni", lpt, cp["normal"])  # Lᵀ n
    prim, bary, _ = bind_to_mesh(cp["position"], rest.asset.points, rest.asset.faces)
    n_gt = np.einsum("nk,nkj->nj", bary, d.asset.corner_normals[prim])
    n_gt /= np.linalg.norm(n_gt, axis=1, keepdims=True)
    return np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", n_cpm, n_gt), -1.0, 1.0)))


def test_deformed_jacobians_are_the_field_of_gts_normals(baked_cylinder):
    # the characteristic points and the look-up read Ψ's Jacobian at M_org's vertices
    # interpolated on its triangles, the field gt's shading normals come from; M_org
    # triangles' constant affine maps (jacobian_field="triangle") turned each coarse flat
    # face as one piece while gt shades it curved, and a sharp highlight then held 2.6-3.8x
    # the reference's light (the 64² bolt twisted 90°, docs/deformation.md)
    scene = load_scene(baked_cylinder)
    twist = parse_warp("twist:angle=90", scene.asset.bounds)
    d = deform_scene(scene, twist)
    pts = scene.asset.points
    np.testing.assert_allclose(d.warp.jacobian(pts), twist.jacobian(pts), atol=1e-9)
    tri = deform_scene(scene, twist, jacobian_field="triangle")
    assert np.abs(tri.warp.jacobian(pts) - twist.jacobian(pts)).max() > 0.05
    a_vertex, a_tri = _normal_angles_deg(d), _normal_angles_deg(tri)
    assert np.median(a_vertex) < 0.5 * np.median(a_tri)
    with pytest.raises(SettingsError, match="jacobian_field"):
        deform_scene(scene, twist, jacobian_field="face")


def test_affine_view_lookup_sees_what_the_deformed_geometry_sees(baked_cylinder):
    # lookup="affine": under a linear Ψ (a 2:1 stretch with shear) the rest points that see
    # J⁻¹ ω (the texel's view direction) are exactly those whose deformed image sees ω on
    # the deformed M_org (rays map linearly), traced independently in both worlds; and the
    # area-weighted projected areas keep one ratio per texel (Nanson: dA* n* = cof(J) dA n),
    # which Eq. 12's division by a_vis cancels. The seed's rotation L disagrees on 3-9 % of
    # the points here (measured: 91-97 % agreement).
    from texelbake.render.deformed import _level_geometry
    from texelbake.tol import TOL

    scene = load_scene(baked_cylinder)
    a = np.array([[2.0, 0.3, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    c = scene.asset.bounds.mean(axis=0)
    d = deform_scene(scene, AffineWarp(a, c - a @ c))
    geo = _level_geometry(d, 0)
    cp = scene.points(0)
    offsets = scene.baked.levels[0]["texel_offsets"]
    tex = np.repeat(np.arange(offsets.shape[0] - 1), np.diff(offsets))
    ng, ng_d = cp["geom_normal"], geo["geom_normal"]
    g = TOL.grazing_cos

    def agreement(key: str, w: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
        wr = np.einsum("nij,j->ni", geo[key][tex], w)
        wr /= np.linalg.norm(wr, axis=1, keepdims=True)
        vis_r = np.einsum("ij,ij->i", ng, wr) > g
        i = np.flatnonzero(vis_r)
        vis_r[i] &= ~scene.org.occluded(cp["position"][i] + scene.ray_eps * ng[i], wr[i])
        vis_d = ng_d @ w > g
        i = np.flatnonzero(vis_d)
        vis_d[i] &= ~d.org.occluded(geo["position"][i] + d.ray_eps * ng_d[i],
                                    np.broadcast_to(w, (i.size, 3)))
        return float((vis_r == vis_d).mean()), wr, vis_d

    for w in ([0.3, 0.5, 0.8], [-0.7, 0.1, 0.7], [0.9, -0.2, 0.3]):
        w = np.asarray(w) / np.linalg.norm(w)
        same, wr, vis_d = agreement("view:affine", w)
        # all but grazing points (offsets eps·n at rest, eps·n* deformed; measured: 1 of
        # 2,460 in one direction)
        assert same >= 0.998 and vis_d.sum() > 300
        assert agreement("lookup:vertex", w)[0] < 0.99
        # projected areas: w* cos* / (w cos') is one number per texel
        area_d = np.linalg.norm(np.einsum("ij,nj->ni", np.linalg.inv(a).T, ng), axis=1)
        ratio = (area_d * (ng_d @ w)) / np.einsum("ij,ij->i", ng, wr)
        for t in np.unique(tex[vis_d])[:50]:
            r = ratio[(tex == t) & vis_d]
            np.testing.assert_allclose(r, r[0], rtol=1e-9)


def test_affine_view_lookup_under_rigid_motion_and_uniform_scale(baked_cylinder):
    # J a rotation times a scale: J⁻¹ ω is L ω, so "affine" renders what "point" renders
    scene = load_scene(baked_cylinder)
    q = _rotation(np.array([0.3, 1.0, 0.2]), 0.7)
    cam = _near_lod_camera(scene, 64)
    for warp in (AffineWarp(q, np.array([0.3, -0.2, 0.5])), AffineWarp(1.7 * q, np.zeros(3))):
        d = deform_scene(scene, warp)
        ref = render_deformed(d, "cpm", cam, 4, seed=2, lookup="point")
        got = render_deformed(d, "cpm", cam, 4, seed=2, lookup="affine")
        assert ref.image.max() > 0.05
        assert psnr_object(got, ref) >= 60.0
    # a squeezed warp (det J = 0): the vertex L, no NaN
    flat = deform_scene(scene, parse_warp("stretch:x=0,y=1,z=1", scene.asset.bounds))
    assert np.isfinite(render_deformed(flat, "cpm", cam, 1, lookup="affine").image).all()
