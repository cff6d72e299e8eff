"""Small UsdSkel rigs for the LOD-binding tests (tests/usd/test_skel_rigs.py), authored with pxr
only: a leg of two tube meshes on one skeleton, built the way exporters write characters; and
how a baked skinned asset is read back by a plain pxr process (`plain_pxr`) and measured
against its original (`surface_distance`, `blend_deviation`; benchmarks/skel_rigs.py too).

- Skeleton `Root/Hip/Knee/Ankle` (bind pose: joints at y = 0, 0, 1, 2 in skeleton space, no
  rotation); `restTransforms` with the Knee bent 20° (not the bind pose); an animation over
  time codes 0..24 that bends Knee and Ankle and swings and moves the Hip, whose first frame is
  not the bind pose either. `Root` is never animated (a static joint).
- `Lower` (y 0 .. 1.2) and `Upper` (y 1.2 .. 2.6): tubes whose points are authored in their own
  frame with a non-identity `geomBindTransform`, each with a joint subset (`skel:joints`):
  Lower [Hip, Knee], Upper [Knee, Ankle], weights blending linearly over ±0.2 around the knee
  (y = 1) and the ankle (y = 2), two influences per point.
- The SkelRoot `Char` is translated, so the skeleton's world transform is not the identity.
- Every mesh is bound to one grey UsdPreviewSurface (what Blender renders too).
- options: `prop` adds `Prop`, a box beside the leg under the SkelRoot with no binding (static);
  `moving_prop` gives it an xform animation no joint follows; `method` sets
  `skel:skinningMethod` on Upper (e.g. "dualQuaternion"); `knee` is the Knee's bend at the
  first frame (180: the knee's 50/50 ring is folded flat at the rest time).
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import open3d as o3d
from pxr import Gf, Sdf, Usd, UsdGeom, UsdShade, UsdSkel, Vt

JOINTS = ("Root", "Root/Hip", "Root/Hip/Knee", "Root/Hip/Knee/Ankle")
BIND_Y = (0.0, 0.0, 1.0, 2.0)
TIME_CODES = (0.0, 6.0, 12.0, 18.0, 24.0)
BLEND = 0.2
#: geomBindTransforms (row convention: skeleton-space point = authored point · G)
BIND_LOWER = Gf.Matrix4d(1.0).SetRotate(Gf.Rotation(Gf.Vec3d(1, 0, 0), 90.0)) * \
    Gf.Matrix4d(1.0).SetTranslate(Gf.Vec3d(0.3, -0.5, 0.2))
BIND_UPPER = Gf.Matrix4d(1.0).SetRotate(Gf.Rotation(Gf.Vec3d(0, 1, 1), -35.0)) * \
    Gf.Matrix4d(1.0).SetTranslate(Gf.Vec3d(-0.4, 0.1, 0.6))
CHAR_OFFSET = (0.7, 0.0, -0.3)


def tube(y0: float, y1: float, rings: int, segs: int = 16, radius: float = 0.25
         ) -> tuple[np.ndarray, list[list[int]]]:
    """A closed tube along +y with slightly ridged walls, capped by a triangle fan at each end:
    points (n, 3), polygons (quads and the caps' triangles)."""
    ys = np.linspace(y0, y1, rings + 1)
    a = 2 * np.pi * np.arange(segs) / segs
    r = radius * (1.0 + 0.08 * np.cos(4 * a))  # ridges: QEM keeps some rings
    pts = np.array([[ri * math.cos(ai), y, ri * math.sin(ai)] for y in ys
                    for ai, ri in zip(a, r, strict=True)] + [[0.0, y0, 0.0], [0.0, y1, 0.0]])
    quads = [[k * segs + i, (k + 1) * segs + i, (k + 1) * segs + (i + 1) % segs,
              k * segs + (i + 1) % segs] for k in range(rings) for i in range(segs)]  # outward
    lo, hi, top = len(pts) - 2, len(pts) - 1, rings * segs
    quads += [[lo, i, (i + 1) % segs] for i in range(segs)]  # facing -y
    quads += [[hi, top + (i + 1) % segs, top + i] for i in range(segs)]  # facing +y
    return pts, quads


def _topology(mesh: UsdGeom.Mesh, polys: list[list[int]]) -> None:
    mesh.CreateFaceVertexCountsAttr([len(p) for p in polys])
    mesh.CreateFaceVertexIndicesAttr([int(i) for p in polys for i in p])
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)


def leg_weights(y: np.ndarray) -> np.ndarray:
    """(n, 4) weights over JOINTS by height: Hip below the knee's blend, Knee between, Ankle
    above the ankle's blend; linear over ±BLEND around y = 1 and y = 2."""
    t1 = np.clip((y - (1.0 - BLEND)) / (2 * BLEND), 0.0, 1.0)
    t2 = np.clip((y - (2.0 - BLEND)) / (2 * BLEND), 0.0, 1.0)
    w = np.zeros((y.shape[0], 4))
    w[:, 1] = 1.0 - t1
    w[:, 2] = t1 * (1.0 - t2)
    w[:, 3] = t2
    return w


def _quat(axis, deg: float) -> Gf.Quatf:
    q = Gf.Rotation(Gf.Vec3d(*axis), deg).GetQuat()
    return Gf.Quatf(float(q.GetReal()), Gf.Vec3f(*map(float, q.GetImaginary())))


def _pose(s: float, knee: float = 30.0) -> tuple[list, list]:
    """Local (translations, rotations) of JOINTS at animation phase s in [0, 1] (the Knee bent
    `knee` degrees at s = 0)."""
    trans = [Gf.Vec3f(0, 0, 0), Gf.Vec3f(0.5 * s, 0.0, 0.2 * s), Gf.Vec3f(0, 1, 0),
             Gf.Vec3f(0, 1, 0)]
    rots = [_quat((0, 1, 0), 0.0), _quat((0, 1, 0), 10.0 + 50.0 * s),
            _quat((0, 0, 1), knee + 70.0 * s), _quat((1, 0, 0), -15.0 - 45.0 * s)]
    return trans, rots


def _mesh(stage: Usd.Stage, path: str, pts_skel: np.ndarray, polys: list[list[int]],
          bind: Gf.Matrix4d, joints: list[str], method: str | None) -> None:
    inv = np.array(bind.GetInverse(), dtype=np.float64)
    local = pts_skel @ inv[:3, :3] + inv[3, :3]  # authored so that local · G = skeleton space
    mesh = UsdGeom.Mesh.Define(stage, path)
    mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(local.astype(np.float32)))
    _topology(mesh, polys)
    api = UsdSkel.BindingAPI.Apply(mesh.GetPrim())
    api.CreateSkeletonRel().SetTargets([Sdf.Path("/Root/Char/Skel")])
    api.CreateJointsAttr(Vt.TokenArray(joints))
    w = leg_weights(pts_skel[:, 1])[:, [JOINTS.index(j) for j in joints]]  # subset order
    order = np.argsort(-w, axis=1, kind="stable")[:, :2]
    api.CreateJointIndicesPrimvar(False, 2).Set(Vt.IntArray(order.reshape(-1).tolist()))
    api.CreateJointWeightsPrimvar(False, 2).Set(
        Vt.FloatArray(np.take_along_axis(w, order, axis=1).reshape(-1).tolist()))
    api.CreateGeomBindTransformAttr(bind)
    if method is not None:
        api.CreateSkinningMethodAttr(method)
    _bind_grey(stage, mesh.GetPrim())


def _bind_grey(stage: Usd.Stage, prim: Usd.Prim) -> None:
    mat = UsdShade.Material.Define(stage, "/Root/Looks/Grey")
    shader = UsdShade.Shader.Define(stage, "/Root/Looks/Grey/Surface")
    shader.CreateIdAttr("UsdPreviewSurface")
    shader.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).Set((0.5, 0.5, 0.5))
    shader.CreateInput("roughness", Sdf.ValueTypeNames.Float).Set(0.5)
    mat.CreateSurfaceOutput().ConnectToSource(shader.ConnectableAPI(), "surface")
    UsdShade.MaterialBindingAPI.Apply(prim).Bind(mat)


def write_rig(path: Path, *, prop: bool = False, moving_prop: bool = False,
              method: str | None = None, knee: float = 30.0) -> Path:
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    root = UsdGeom.Xform.Define(stage, "/Root")
    stage.SetDefaultPrim(root.GetPrim())
    char = UsdSkel.Root.Define(stage, "/Root/Char")
    char.AddTranslateOp().Set(Gf.Vec3d(*CHAR_OFFSET))
    skel = UsdSkel.Skeleton.Define(stage, "/Root/Char/Skel")
    skel.CreateJointsAttr(Vt.TokenArray(list(JOINTS)))
    skel.CreateBindTransformsAttr(Vt.Matrix4dArray(
        [Gf.Matrix4d(1.0).SetTranslate(Gf.Vec3d(0, y, 0)) for y in BIND_Y]))
    rest = [Gf.Matrix4d(1.0), Gf.Matrix4d(1.0),
            Gf.Matrix4d(1.0).SetRotate(Gf.Rotation(Gf.Vec3d(0, 0, 1), 20.0))
            * Gf.Matrix4d(1.0).SetTranslate(Gf.Vec3d(0, 1, 0)),
            Gf.Matrix4d(1.0).SetTranslate(Gf.Vec3d(0, 1, 0))]
    skel.CreateRestTransformsAttr(Vt.Matrix4dArray(rest))
    anim = UsdSkel.Animation.Define(stage, "/Root/Char/Skel/Anim")
    anim.CreateJointsAttr(Vt.TokenArray(list(JOINTS)))
    anim.CreateScalesAttr(Vt.Vec3hArray([Gf.Vec3h(1, 1, 1)] * len(JOINTS)))
    tr, rot = anim.CreateTranslationsAttr(), anim.CreateRotationsAttr()
    for t in TIME_CODES:
        trans, rots = _pose(t / TIME_CODES[-1], knee)
        tr.Set(Vt.Vec3fArray(trans), Usd.TimeCode(t))
        rot.Set(Vt.QuatfArray(rots), Usd.TimeCode(t))
    UsdSkel.BindingAPI.Apply(skel.GetPrim()).CreateAnimationSourceRel().SetTargets(
        [anim.GetPath()])
    lower, lq = tube(0.0, 1.2, rings=12)
    upper, uq = tube(1.2, 2.6, rings=14, radius=0.22)
    _mesh(stage, "/Root/Char/Lower", lower, lq, BIND_LOWER, [JOINTS[1], JOINTS[2]], None)
    _mesh(stage, "/Root/Char/Upper", upper, uq, BIND_UPPER, [JOINTS[2], JOINTS[3]], method)
    if prop or moving_prop:
        pts, polys = tube(0.0, 0.6, rings=3, segs=8, radius=0.2)
        box = UsdGeom.Mesh.Define(stage, "/Root/Char/Prop")
        box.CreatePointsAttr(Vt.Vec3fArray.FromNumpy((pts + [1.0, 0.0, 0.0]).astype(np.float32)))
        _topology(box, polys)
        _bind_grey(stage, box.GetPrim())
        if moving_prop:
            op = box.AddTranslateOp()
            for t in TIME_CODES:
                op.Set(Gf.Vec3d(0.0, 0.02 * t, 0.0), Usd.TimeCode(t))
    stage.SetStartTimeCode(TIME_CODES[0])
    stage.SetEndTimeCode(TIME_CODES[-1])
    stage.GetRootLayer().Save()
    return path


# ------------------------------------------------------------ reading a baked rig back

#: stock pxr: every mesh of the baked stage at each time (world space; skinned by UsdSkel where
#: bound), its triangles, the LODs' p0, and per skeleton its joints' bind -> world transforms at
#: each time and each skinned mesh's dense weights (the skeleton's joint order).
PLAIN_PXR = r"""
import json, sys
import numpy as np
from pxr import Usd, UsdGeom, UsdSkel
stage = Usd.Stage.Open(sys.argv[1])
times = list(map(float, sys.argv[2:]))
out = {"meshes": {}, "p0": {}, "skel": {}}
cache = UsdSkel.Cache()
bound = {}
for prim in stage.Traverse():
    if prim.IsA(UsdSkel.Root):
        root = UsdSkel.Root(prim)
        cache.Populate(root, Usd.PrimDefaultPredicate)
        for binding in cache.ComputeSkelBindings(root, Usd.PrimDefaultPredicate):
            skel = cache.GetSkelQuery(binding.GetSkeleton())
            for sq in binding.GetSkinningTargets():
                bound[str(sq.GetPrim().GetPath())] = (sq, skel)
for prim in stage.Traverse():
    if not prim.IsA(UsdGeom.Mesh) or prim.GetName() == "Proxy":
        continue
    path = str(prim.GetPath())
    mesh = UsdGeom.Mesh(prim)
    counts = np.array(mesh.GetFaceVertexCountsAttr().Get())
    idx = np.array(mesh.GetFaceVertexIndicesAttr().Get())
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    tris = [[idx[s], idx[s + k], idx[s + k + 1]] for s, c in zip(starts, counts)
            for k in range(1, c - 1)]
    entry = {"faces": np.array(tris).tolist(), "t": {}}
    for t in times:
        pts = mesh.GetPointsAttr().Get(t)
        if path in bound:
            sq, skel = bound[path]
            assert sq.ComputeSkinnedPoints(skel.ComputeSkinningTransforms(t), pts, t)
            w = np.array(UsdGeom.XformCache(t).GetLocalToWorldTransform(skel.GetPrim()))
        else:
            w = np.array(UsdGeom.XformCache(t).GetLocalToWorldTransform(prim))
        a = np.array(pts, dtype=np.float64)
        entry["t"][str(t)] = (a @ w[:3, :3] + w[3, :3]).tolist()
    if path in bound:
        sq, skel = bound[path]
        key = str(skel.GetPrim().GetPath())
        if key not in out["skel"]:
            out["skel"][key] = {"joints": [str(j) for j in skel.GetJointOrder()], "t": {
                str(t): [(np.array(m) @ np.array(UsdGeom.XformCache(t)
                          .GetLocalToWorldTransform(skel.GetPrim()))).tolist()
                         for m in skel.ComputeSkinningTransforms(t)] for t in times}}
        n = len(mesh.GetPointsAttr().Get())
        ji, jw = sq.ComputeVaryingJointInfluences(n, times[0])
        ji = np.array(ji).reshape(n, -1)
        order = sq.GetJointOrder()
        names = list(order) if order is not None else list(skel.GetJointOrder())
        joints = [str(j) for j in skel.GetJointOrder()]
        ji = np.array([joints.index(str(j)) for j in names])[ji]
        dense = np.zeros((n, len(joints)))
        np.add.at(dense, (np.repeat(np.arange(n), ji.shape[1]), ji.ravel()),
                  np.array(jw).ravel())
        entry["weights"] = (dense / dense.sum(1, keepdims=True)).tolist()
    pv = UsdGeom.PrimvarsAPI(prim).GetPrimvar("texelbake:p0")
    if pv:
        out["p0"][path] = np.array(pv.Get(), dtype=np.float64).tolist()
    out["meshes"][path] = entry
assert not [m for m in sys.modules if m.split(".")[0] in ("texelbake", "schemas")]
print(json.dumps(out))
"""


def run_plain_pxr(script: str, root: Path, times: tuple[float, ...]) -> dict:
    """The JSON a read-back `script` prints last, run on `root` at `times` by a Python that
    never imports texelbake (no PYTHONPATH, no PXR_ overrides, another working folder)."""
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PXR_", "PYTHONPATH"))}
    r = subprocess.run([sys.executable, "-c", script, str(root), *map(str, times)],
                       capture_output=True, text=True, timeout=300, env=env, cwd="/")
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout.strip().splitlines()[-1])


def plain_pxr(root: Path, times: tuple[float, ...]) -> dict:
    """`PLAIN_PXR` on the baked root at `times` (the first: the rest time)."""
    return run_plain_pxr(PLAIN_PXR, root, times)


def original_surface(got: dict, t: float) -> tuple[np.ndarray, np.ndarray]:
    """The source's meshes at t, one triangle soup: points (n, 3), triangles (f, 3)."""
    pts, tris, off = [], [], 0
    for path in sorted(got["meshes"]):
        if "/Baked/" in path:
            continue
        m = got["meshes"][path]
        p = np.array(m["t"][str(t)])
        pts.append(p)
        tris.append(np.array(m["faces"]) + off)
        off += len(p)
    return np.concatenate(pts), np.concatenate(tris)


def surface_distance(points: np.ndarray, verts: np.ndarray, tris: np.ndarray
                     ) -> np.ndarray:
    """Unsigned distance of points (n, 3) to the triangle soup (verts, tris): (n,) float32."""
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(verts.astype(np.float32)),
                        o3d.core.Tensor(tris.astype(np.uint32)))
    return scene.compute_distance(o3d.core.Tensor(points.astype(np.float32))).numpy()


def blend_deviation(got: dict, t: float, rest_time: float) -> tuple[float, float]:
    """(dev_t, κ_t) of tests/usd/test_skel_rigs.py's docstring over every skinned original
    triangle (weights: the barycentric blend of its corners', as LOD weights are transferred);
    unskinned meshes (bound rigidly, one joint) move rigidly: no deviation, no stretch."""
    (skel,) = got["skel"].values()
    rest = np.transpose(np.array(skel["t"][str(rest_time)]), (0, 2, 1))  # (j, 4, 4) column
    now = np.transpose(np.array(skel["t"][str(t)]), (0, 2, 1))
    g = np.linspace(0.0, 1.0, 9)
    b1, b2 = np.meshgrid(g, g, indexing="ij")
    keep = (b1 + b2) <= 1.0 + 1e-12
    bary = np.stack([1.0 - b1[keep] - b2[keep], b1[keep], b2[keep]], axis=1)  # (s, 3)
    surf_v, surf_f = original_surface(got, t)
    dev, kappa = 0.0, 1.0
    for path, m in got["meshes"].items():
        if "weights" not in m or "/Baked/" in path:
            continue
        f = np.array(m["faces"])
        w = np.array(m["weights"])[f]  # (f, 3, j)
        ws = np.einsum("sk,fkj->fsj", bary, w).reshape(-1, w.shape[2])
        x = np.einsum("sk,fkc->fsc", bary, np.array(m["t"][str(rest_time)])[f]).reshape(-1, 3)
        m_r = np.einsum("nj,jab->nab", ws, rest[:, :3, :])
        m_t = np.einsum("nj,jab->nab", ws, now[:, :3, :])
        a = np.einsum("nab,nbc->nac", m_t[:, :, :3], np.linalg.inv(m_r[:, :, :3]))
        moved = np.einsum("nab,nb->na", a, x - m_r[:, :, 3]) + m_t[:, :, 3]
        dev = max(dev, float(surface_distance(moved, surf_v, surf_f).max()))
        kappa = max(kappa, float(np.linalg.norm(a, ord=2, axis=(1, 2)).max()))
    return dev, kappa
