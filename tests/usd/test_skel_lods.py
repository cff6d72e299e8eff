"""The LOD meshes of a baked animated asset follow M_org in any USD tool (issue 12, deliverable
2): a skinned asset's LODs are bound to its UsdSkel skeleton with weights transferred from
M_org, an asset with time-sampled points gets time samples on its LODs. Checked in a plain pxr
process (no texelbake import): UsdSkel's own skinning of each LOD (UsdSkel.Cache, skinning
query) and the LODs' time samples against the renderer's deformed M_i, and stock
UsdValidation of the result."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.helpers.skel_rigs import run_plain_pxr
from tests.helpers.usd_validation import stock_errors
from texelbake.render.deformed import deform_scene
from texelbake.render.deformed_report import warp_at_time
from texelbake.render.scene import load_scene

#: stock pxr only: every LOD mesh of the baked stage at time t, in world space — skinned by
#: UsdSkel where it is bound (skinned points are in skeleton space: times the skeleton's
#: local-to-world), else its points at t. Fails if texelbake was imported.
PLAIN_PXR = r"""
import json, sys
import numpy as np
from pxr import Usd, UsdGeom, UsdSkel
stage = Usd.Stage.Open(sys.argv[1])
out = {"skinned": {}, "points": {}}
for t in map(float, sys.argv[2:]):
    xc = UsdGeom.XformCache(t)
    for prim in stage.Traverse():
        if prim.IsA(UsdSkel.Root):
            cache = UsdSkel.Cache()
            root = UsdSkel.Root(prim)
            cache.Populate(root, Usd.PrimDefaultPredicate)
            for binding in cache.ComputeSkelBindings(root, Usd.PrimDefaultPredicate):
                skel = cache.GetSkelQuery(binding.GetSkeleton())
                xf = skel.ComputeSkinningTransforms(t)
                w = np.array(xc.GetLocalToWorldTransform(skel.GetPrim()))
                for sq in binding.GetSkinningTargets():
                    pts = UsdGeom.Mesh(sq.GetPrim()).GetPointsAttr().Get(t)
                    assert sq.ComputeSkinnedPoints(xf, pts, t)
                    a = np.array(pts, dtype=np.float64)
                    out["skinned"].setdefault(str(sq.GetPrim().GetPath()), {})[str(t)] = (
                        a @ w[:3, :3] + w[3, :3]).tolist()
        if prim.IsA(UsdGeom.Mesh) and "Baked/LOD" in str(prim.GetPath()):
            pts = np.array(UsdGeom.Mesh(prim).GetPointsAttr().Get(t), dtype=np.float64)
            w = np.array(xc.GetLocalToWorldTransform(prim))
            out["points"].setdefault(str(prim.GetPath()), {})[str(t)] = (
                pts @ w[:3, :3] + w[3, :3]).tolist()
# with payloads unloaded (a viewer's first look): the proxy, and the root's extentsHint
light = Usd.Stage.Open(sys.argv[1], Usd.Stage.LoadNone)
out["proxy"] = {}
for prim in light.Traverse():
    if prim.IsA(UsdGeom.Mesh) and prim.GetName() == "Proxy":
        for t in map(float, sys.argv[2:]):
            pts = np.array(UsdGeom.Mesh(prim).GetPointsAttr().Get(t), dtype=np.float64)
            w = np.array(UsdGeom.XformCache(t).GetLocalToWorldTransform(prim))
            out["proxy"][str(t)] = (pts @ w[:3, :3] + w[3, :3]).tolist()
hint = UsdGeom.ModelAPI(light.GetDefaultPrim()).GetExtentsHint()
out["extents_hint"] = [list(hint[0]), list(hint[1])]
assert not [m for m in sys.modules if m.split(".")[0] in ("texelbake", "schemas")]
print(json.dumps(out))
"""

TIMES = (0.0, 12.0, 24.0)


def plain_pxr(root: Path, times: tuple[float, ...]) -> dict:
    return run_plain_pxr(PLAIN_PXR, root, times)


def _settings():
    from schemas.settings import BakeSettings

    return BakeSettings(atlas_resolution=16, samples_per_texel=8, n_light_dirs=8,
                        n_view_dirs=8, n_heldout=4, c_max=8, avis_resolution=4,
                        lod_mode="atlas")  # the atlas-sized chain: M1 and M2


@pytest.fixture(scope="module")
def baked_arm(tmp_path_factory) -> Path:
    from texelbake.pipeline.run import bake
    from texelbake.testscenes.arm import write_arm

    d = tmp_path_factory.mktemp("arm")
    with pytest.warns(Warning, match="skinned by UsdSkel"):
        src = write_arm(d / "arm.usda")
        return bake(src, d / "baked", _settings(), progress=False)


@pytest.fixture(scope="module")
def baked_pointcache(tmp_path_factory) -> Path:
    """The small cylinder whose mesh points are time-sampled (a twist growing 0 -> 90°), no
    skeleton: the LODs must carry time samples."""
    from pxr import Gf, Usd, UsdGeom, Vt

    from texelbake.deform.warps import parse_warp
    from texelbake.pipeline.run import bake
    from texelbake.testscenes import write_scene

    d = tmp_path_factory.mktemp("pc")
    src = write_scene("cylinder", d / "cyl.usda", size="small")
    stage = Usd.Stage.Open(str(src))
    mesh = next(UsdGeom.Mesh(p) for p in stage.Traverse() if p.IsA(UsdGeom.Mesh))
    rest = np.array(mesh.GetPointsAttr().Get(), dtype=np.float64)
    assert UsdGeom.Xformable(mesh.GetPrim()).ComputeLocalToWorldTransform(0) == Gf.Matrix4d(1)
    bounds = np.stack([rest.min(0), rest.max(0)])
    for t in TIMES:
        pts = parse_warp(f"twist:angle={90.0 * t / 24.0}", bounds).positions(rest)
        mesh.GetPointsAttr().Set(Vt.Vec3fArray.FromNumpy(pts.astype(np.float32)), t)
    stage.GetRootLayer().Save()
    return bake(src, d / "baked", _settings(), progress=False)


def _check_follows(root: Path, got: dict[str, dict[str, list]]) -> int:
    """Each LOD as the plain process saw it against the renderer's deformed M_i (its first n
    vertices: the renderer refines the LODs by appending vertices); returns how many LODs."""
    scene = load_scene(root)
    n_lod = len(scene.baked.meshes)
    got = {k: v for k, v in got.items() if "/Baked/LOD" in k}  # not the source's own mesh
    assert sorted(k.rsplit("/", 1)[-1] for k in got) == [f"LOD{i}" for i in
                                                         range(1, n_lod + 1)]
    moved = 0.0
    for t in TIMES:
        d = deform_scene(scene, warp_at_time(scene.asset, t))
        for i, m in enumerate(scene.baked.meshes, start=1):
            usd = np.array(got[next(k for k in got if k.endswith(f"/LOD{i}"))][str(t)])
            ours = d.baked.meshes[i - 1].vertices[: usd.shape[0]]
            assert usd.shape == m.vertices.shape
            # the bar; float32 points and weights in USD carry ~1e-7 of the arm's size
            np.testing.assert_allclose(ours, usd, rtol=0, atol=1e-5)
            moved = max(moved, float(np.abs(usd - m.vertices).max()))
    assert moved > 0.3 * scene.diag  # bent 90° / twisted: not a rest-pose comparison
    return n_lod


def test_skinned_lods_animate_in_plain_usdskel_as_the_renderer_deforms_them(baked_arm):
    from texelbake.usd.read import read_baked

    baked = read_baked(baked_arm)
    assert baked.skeleton == "/Cylinder/Geom/Skel"
    assert len(baked.meshes) >= 2
    for m in baked.meshes:  # bounded influences, renormalised
        assert m.skin["indices"].shape[1] == 3  # min(MAX_INFLUENCES, 3 joints)
        np.testing.assert_allclose(m.skin["weights"].sum(axis=1), 1.0, atol=1e-6)
        assert not m.points_over_time.size  # skinned, not time-sampled
    report = json.loads((baked_arm.parent / "report.json").read_text())
    assert report["lod_animation"] == "usdskel"
    got = plain_pxr(baked_arm, TIMES)
    assert _check_follows(baked_arm, got["skinned"]) == len(baked.meshes)


def _check_proxy_follows(got: dict, lods: dict[str, dict[str, list]], diag: float) -> None:
    """The proxy, read with payloads unloaded, at every time code is the coarsest LOD as the
    loaded stage poses it; the extentsHint holds it at every time (identity root transform)."""
    last = max(lods, key=lambda k: int(k.rsplit("LOD", 1)[1]))
    lo, hi = (np.array(x) for x in got["extents_hint"])
    rest = np.array(got["proxy"]["0.0"])
    for t in map(str, TIMES):
        proxy = np.array(got["proxy"][t])
        np.testing.assert_allclose(proxy, np.array(lods[last][t]), rtol=0, atol=1e-5)
        assert np.all(proxy >= lo - 1e-5) and np.all(proxy <= hi + 1e-5), t
    assert np.abs(proxy - rest).max() > 0.3 * diag  # it moved with the animation


def test_the_proxy_moves_with_a_skinned_asset(baked_arm):
    """Issue 12: the proxy (outside the payload, so it cannot be bound to the skeleton inside)
    carries the coarsest LOD's UsdSkel pose at every time code of the animation."""
    got = plain_pxr(baked_arm, TIMES)
    lods = {k: v for k, v in got["skinned"].items() if "/Baked/LOD" in k}
    _check_proxy_follows(got, lods, load_scene(baked_arm).diag)


def test_the_proxy_moves_with_time_sampled_points(baked_pointcache):
    got = plain_pxr(baked_pointcache, TIMES)
    _check_proxy_follows(got, got["points"], load_scene(baked_pointcache).diag)


@pytest.mark.parametrize("suffix", [".usda", ".usdz"])
def test_an_exported_skinned_lod_stays_bound(baked_arm, tmp_path, suffix):
    """`texelbake export --lod 1`: the one-LOD file keeps the skeleton, its animation and the
    binding, so a plain UsdSkel process poses LOD1 exactly as in the baked root; stock valid."""
    from texelbake.usd.export import export_lod

    out = export_lod(baked_arm, 1, tmp_path / f"lod1{suffix}")
    root = plain_pxr(baked_arm, TIMES)["skinned"]
    got = plain_pxr(out, TIMES)["skinned"]
    lod1 = next(k for k in root if k.endswith("/Baked/LOD1"))
    assert lod1 in got and not any(k.endswith("/Baked/LOD2") for k in got)
    for t in map(str, TIMES):
        np.testing.assert_array_equal(np.array(got[lod1][t]), np.array(root[lod1][t]))
    assert np.abs(np.array(got[lod1]["24.0"]) - np.array(got[lod1]["0.0"])).max() > 0.1
    assert stock_errors(out) == {str(out): []}


def test_lod_weights_are_m_orgs_blended_at_the_closest_point(baked_arm):
    """Independent of `transfer_weights`: the arm's weights are a piecewise-linear function
    of height (scenes.arm.joint_weights), so the barycentric blend at a vertex's closest
    point on M_org is that function of the closest point's height wherever the triangle lies
    inside one linear piece; brute-force closest points over every triangle."""
    from texelbake.testscenes.arm import BLEND, joint_heights, joint_weights
    from texelbake.usd.read import read_baked

    scene = load_scene(baked_arm)
    a = scene.asset
    m = read_baked(baked_arm).meshes[0]
    p = m.vertices
    tri = a.points[a.faces]  # (f, 3, 3)
    # closest point on each triangle by dense sampling of its barycentric plane (brute force)
    g = np.linspace(0, 1, 41)
    b1, b2 = np.meshgrid(g, g, indexing="ij")
    keep = (b1 + b2) <= 1
    bary = np.stack([1 - b1[keep] - b2[keep], b1[keep], b2[keep]], 1)  # (s, 3)
    samples = np.einsum("sk,fkc->fsc", bary, tri).reshape(-1, 3)
    best = np.empty(len(p), dtype=np.int64)
    for s in range(0, len(p), 64):  # chunks of vertices, each a whole-array distance
        dist = ((p[s:s + 64, None, :] - samples[None]) ** 2).sum(-1)
        best[s:s + 64] = dist.argmin(1)
    y = samples[best, 1]
    h = float(a.points[:, 1].max() - a.points[:, 1].min())
    jy = joint_heights()
    # away from the blend zones' ends (where a triangle may straddle a kink of the function)
    edges = np.concatenate([jy[1:] - BLEND * h, jy[1:] + BLEND * h])
    step = h / 12.0  # arm rings (small): a triangle spans one ring
    far = (np.abs(y[:, None] - edges[None]).min(1) > step)
    assert far.sum() > 0.5 * len(p)
    dense = np.zeros((len(p), 3))
    np.add.at(dense, (np.repeat(np.arange(len(p)), 3), m.skin["indices"].reshape(-1)),
              m.skin["weights"].reshape(-1))
    # the sampled closest point is within 1/40 of a triangle's edge of the true one
    np.testing.assert_allclose(dense[far], joint_weights(y)[far], atol=0.05)


def test_skinned_bake_passes_stock_validation(baked_arm):
    errors = stock_errors(baked_arm)
    assert errors == {str(baked_arm): []}


def test_time_sampled_lods_follow_m_org_in_plain_pxr(baked_pointcache):
    from texelbake.usd.read import read_baked

    baked = read_baked(baked_pointcache)
    assert baked.skeleton == ""
    for m in baked.meshes:
        np.testing.assert_array_equal(m.time_codes, TIMES)
        assert not m.skin
    report = json.loads((baked_pointcache.parent / "report.json").read_text())
    assert report["lod_animation"] == "time_samples"
    got = plain_pxr(baked_pointcache, TIMES)
    assert _check_follows(baked_pointcache, got["points"]) == len(baked.meshes)
    assert stock_errors(baked_pointcache) == {str(baked_pointcache): []}


def test_skinning_that_is_not_one_blend_falls_back_to_time_samples(tmp_path):
    """A vertex with no joint influence: UsdSkel would collapse a LOD vertex bound with zero
    weights to the skeleton's origin, so ingest describes no skin and says why; the points
    are still skinned into time samples (the LODs then carry those)."""
    from pxr import Usd, Vt

    from texelbake.asset import load_asset
    from texelbake.testscenes.arm import write_arm

    path = write_arm(tmp_path / "arm.usda")
    stage = Usd.Stage.Open(str(path))
    mesh = stage.GetPrimAtPath("/Cylinder/Geom/RidgedCylinder")
    attr = mesh.GetAttribute("primvars:skel:jointWeights")
    w = np.array(attr.Get(), dtype=np.float32)
    w[:2] = 0.0  # vertex 0: two influences, both 0
    attr.Set(Vt.FloatArray.FromNumpy(w))
    stage.GetRootLayer().Save()
    with pytest.warns(Warning, match="no joint influence"):
        asset = load_asset(str(tmp_path / "arm.usda"))
    assert asset.skin is None
    assert asset.has_deformation


# --------------------------------------------------------------------------- animated previews


def test_animated_preview_of_the_arm_and_its_error_plot(baked_arm, tmp_path):
    import OpenImageIO as oiio

    from texelbake.render.deformed_anim import render_animation

    runs = []
    for k in range(2):  # reruns: images byte-identical (the JSON's seconds are timings)
        out = tmp_path / f"run{k}"
        path = render_animation(baked_arm, out, frames=3, spp=1, ref_spp=4)
        runs.append({p.name: p.read_bytes() for p in sorted(out.iterdir())
                     if p.suffix != ".json"})
    assert runs[0] == runs[1]
    assert sorted(runs[0]) == ["animation.gif", "error_per_frame.png"]
    rep = json.loads(path.read_text())
    assert rep["tiles"] == ["reference", "cpm", "cpm-naive", "normalmap"]
    assert [f["time"] for f in rep["frames"]] == [0.0, 12.0, 24.0]
    for f in rep["frames"]:
        assert f["object_pixels"] > 0
        assert all(np.isfinite(f["modes"][m]["psnr_db_object"]) for m in rep["tiles"][1:])
    inp = oiio.ImageInput.open(str(path.parent / "animation.gif"))
    spec = inp.spec()
    n = 0
    while inp.seek_subimage(n, 0):
        n += 1
    inp.close()
    assert n == 3
    z, w = rep["zoom"], rep["width"]
    assert (spec.width, spec.height) == (4 * z * w + 3 * 2, z * rep["height"])


def test_warp_sweep_runs_from_identity_to_the_spec():
    from texelbake.deform.warps import parse_warp
    from texelbake.errors import SettingsError
    from texelbake.render.deformed_anim import sweep_spec

    rng = np.random.default_rng(3)
    pts = rng.random((50, 3))
    bounds = np.stack([pts.min(0), pts.max(0)])
    for spec in ("bend:angle=90", "twist:angle=90,axis=x", "stretch:x=1,y=2,z=1",
                 "rigid:angle=40,axis=x,tx=0.5", "sine:amplitude=0.2", "scale:s=3"):
        zero = parse_warp(sweep_spec(spec, 0.0), bounds).positions(pts)
        full = parse_warp(sweep_spec(spec, 1.0), bounds).positions(pts)
        np.testing.assert_allclose(zero, pts, atol=1e-12)
        np.testing.assert_allclose(full, parse_warp(spec, bounds).positions(pts), atol=1e-12)
    half = parse_warp(sweep_spec("twist:angle=90", 0.5), bounds)
    np.testing.assert_allclose(half.positions(pts),
                               parse_warp("twist:angle=45", bounds).positions(pts), atol=1e-12)
    with pytest.raises(SettingsError, match="amount"):
        sweep_spec("bend:angle=90", 1.5)


def test_write_animation_frames_and_errors(tmp_path):
    import OpenImageIO as oiio

    from texelbake.errors import ShapeError
    from texelbake.io.images import write_animation

    frames = [np.full((6, 5, 3), k / 3.0) for k in range(4)]
    p = write_animation(tmp_path / "a.gif", frames, fps=4.0)
    inp = oiio.ImageInput.open(str(p))
    got = []
    k = 0
    while inp.seek_subimage(k, 0):
        got.append(inp.read_image("uint8")[0, 0, :3])
        k += 1
    inp.close()
    assert k == 4
    # flat frames: the palette holds the exact sRGB-encoded grey
    from texelbake.io.images import to_uint8

    assert [int(g[0]) for g in got] == [int(to_uint8(np.full(3, j / 3.0))[0]) for j in range(4)]
    with pytest.raises(ShapeError, match="gif"):
        write_animation(tmp_path / "a.png", frames)
    with pytest.raises(ShapeError, match="size"):
        write_animation(tmp_path / "b.gif", [frames[0], np.zeros((3, 3, 3))])


def test_refined_lods_follow_the_bent_m_org(baked_arm):
    # the renderer refines the skinned LODs before deforming them; the added vertices take
    # weights transferred from M_org, as the payload's own vertices did, so that each refined
    # vertex moves as the M_org triangle it lies on (`MeshWarp`: the time samples). The mean
    # of an edge's ends' weights (the construction before 2026-11-27, rebuilt here) put them
    # up to 10 % of the diagonal off the bent M_org (the 64² arm bent 90°: 0.38 of 3.8):
    # linear blending of averaged weights is not the skinning of the surface between two
    # vertices whose weights differ. Here: M1's largest departure 0.27 against 0.58.
    from texelbake.deform.lbs import SkinWarp
    from texelbake.deform.refine import refine_levels, subdivide
    from texelbake.deform.skinbind import dense_weights
    from texelbake.render.deformed import _refined_lods

    scene = load_scene(baked_arm)
    warp = warp_at_time(scene.asset, 24.0)
    d = deform_scene(scene, warp)
    n_joints = len(scene.asset.skin.joints)
    (v, f, _), = _refined_lods(scene, 16.0, n_joints)[0][:1]
    follow = d.warp.positions(v)  # each refined vertex carried by its M_org triangle
    got = float(np.linalg.norm(d.baked.meshes[0].vertices - follow, axis=1).max())
    m1 = scene.baked.meshes[0]
    va, fa, ca = m1.vertices, m1.faces, m1.corner_uvs
    wa = dense_weights(m1.skin["indices"], m1.skin["weights"], n_joints)
    for _ in range(refine_levels(va, fa, scene.diag / 16.0)):
        va, fa, ca, (wa,), _ = subdivide(va, fa, ca, (wa,))
    np.testing.assert_allclose(va, v)
    averaged = SkinWarp(np.asarray(warp.transforms), va, fa, wa,
                        rest_transforms=warp.rest_transforms).positions(va)
    old = float(np.linalg.norm(averaged - follow, axis=1).max())
    assert got < 0.6 * old, (got, old)


def test_an_asset_warning_is_shown_once_and_kept_in_the_report(tmp_path):
    """The asset's warnings (here: the skinned arm's authored rest-pose normals, replaced) are
    shown once by the ingest stage, not again by each shard process that reads the asset,
    and listed in report.json; `texelbake`'s terminal shows them as "warning: <message>"."""
    import warnings

    from texelbake.pipeline.run import bake
    from texelbake.stages.context import _load_asset_cached
    from texelbake.testscenes.arm import write_arm

    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        src = write_arm(tmp_path / "arm.usda")
        # a fresh artifact store: with the arm's ingest stored already (the same file's bytes
        # baked by another test), its warnings are in the report, not shown again
        root = bake(src, tmp_path / "baked", _settings(), progress=False, jobs=2,
                    workdir=tmp_path / "work")
        _load_asset_cached.cache_clear()  # what a shard process does: read the asset again
        _load_asset_cached(str(src), "digest")
    shown = [str(w.message) for w in seen if "skinned by UsdSkel" in str(w.message)]
    assert len(shown) == 1
    report = json.loads((root.parent / "report.json").read_text())
    assert [w for w in report["warnings"] if "skinned by UsdSkel" in w] == [f"asset: {shown[0]}"]
    code = ("import warnings\nfrom texelbake.cli import _show_asset_warnings_plainly\n"
            "from texelbake.asset.values import AssetWarning\n_show_asset_warnings_plainly()\n"
            "warnings.warn('mesh /A: something', AssetWarning)\n")
    err = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stderr
    assert err == "warning: mesh /A: something\n"
