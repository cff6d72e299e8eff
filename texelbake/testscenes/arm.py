"""The `arm`: the ridged cylinder (seed 000 Fig. 1) as a skinned limb for seed 002 — more
rings along its axis (so that it can bend), a three-joint UsdSkel skeleton (Shoulder at the
base, Elbow and Wrist at a third and two thirds of its height) and an animation that bends
Elbow and Wrist by 45° each about −z, 0 → 90° in all over time codes 0 … 24 (the top ends up
pointing along +x). Points are weighted by height: one joint per segment, a linear blend over
`BLEND` either side of each inner joint (at most two influences per point).

`write_arm(path, size)` writes it (deterministic, atomic); `ingest` skins it with UsdSkel into
time-sampled points, which `texelbake render BAKED --time T` follows
(`render.deformed_report.warp_at_time`).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from pxr import Gf, Usd, UsdGeom, UsdShade, UsdSkel, Vt

from texelbake.errors import SettingsError
from texelbake.io.atomic import atomic_path
from texelbake.testscenes.author import _author_mesh, build_stage
from texelbake.testscenes.cylinder import build_cylinder
from texelbake.testscenes.params import CYLINDER, SCENE_PARAMS, SEEDS

JOINTS = ("Shoulder", "Shoulder/Elbow", "Shoulder/Elbow/Wrist")
#: rings along the axis per size (the cylinder scene has 4 / 11: too few to bend)
RINGS = {"small": 12, "full": 24}
#: half-width of the weight blend around the inner joints, in units of the height
BLEND = 0.1
TIME_CODES = (0.0, 6.0, 12.0, 18.0, 24.0)
#: total bend at the last time code (degrees), shared by Elbow and Wrist
BEND_DEG = 90.0


def joint_heights() -> np.ndarray:
    """y of the three joints: base, one third, two thirds of the height (3,)."""
    h = CYLINDER["height"]
    return -0.5 * h + h * np.array([0.0, 1.0 / 3.0, 2.0 / 3.0])


def joint_weights(y: np.ndarray) -> np.ndarray:
    """(n, 3) skin weights by height (module docstring); rows sum to 1."""
    h = CYLINDER["height"]
    jy = joint_heights()
    w = np.zeros((y.shape[0], 3))
    t1 = np.clip((y - (jy[1] - BLEND * h)) / (2 * BLEND * h), 0.0, 1.0)  # Shoulder -> Elbow
    t2 = np.clip((y - (jy[2] - BLEND * h)) / (2 * BLEND * h), 0.0, 1.0)  # Elbow -> Wrist
    w[:, 0] = 1.0 - t1
    w[:, 1] = t1 * (1.0 - t2)
    w[:, 2] = t2
    return w


def joint_angles(time: float) -> np.ndarray:
    """Bend of (Shoulder, Elbow, Wrist) about −z at `time` (radians), linear 0 → 24."""
    s = float(np.clip(time / TIME_CODES[-1], 0.0, 1.0))
    a = math.radians(0.5 * BEND_DEG) * s
    return np.array([0.0, a, a])


def skinning_transforms(time: float) -> np.ndarray:
    """Closed form of the skinning transforms (world at `time` · inverse bind), (3, 4, 4)
    float64, column-vector convention (`deform.lbs.SkinWarp`)."""
    jy = joint_heights()
    out = np.zeros((3, 4, 4))
    world = np.eye(4)
    for j, ang in enumerate(joint_angles(time)):
        local = np.eye(4)
        local[1, 3] = jy[j] - (jy[j - 1] if j else 0.0)
        c, s = math.cos(-ang), math.sin(-ang)
        local[:2, :2] = [[c, -s], [s, c]]
        world = world @ local
        bind_inv = np.eye(4)
        bind_inv[1, 3] = -jy[j]
        out[j] = world @ bind_inv
    return out


def _gf_local(j: int, ang: float) -> tuple[Gf.Vec3f, Gf.Quatf]:
    jy = joint_heights()
    t = Gf.Vec3f(0.0, float(jy[j] - (jy[j - 1] if j else 0.0)), 0.0)
    q = Gf.Rotation(Gf.Vec3d(0, 0, -1), math.degrees(ang)).GetQuat()
    return t, Gf.Quatf(float(q.GetReal()), Gf.Vec3f(*map(float, q.GetImaginary())))


def build_arm_stage(size: str = "small") -> tuple[Usd.Stage, dict[str, np.ndarray]]:
    """The arm as an in-memory stage plus its textures (as `scenes.build_stage`)."""
    if size not in RINGS:
        raise SettingsError(f"field 'size': expected one of {sorted(RINGS)}, got {size!r}")
    stage, textures = build_stage("cylinder", size)
    params = {"ridges": SCENE_PARAMS["cylinder"][size]["ridges"], "rings": RINGS[size]}
    spec = build_cylinder(params, np.random.default_rng(SEEDS["cylinder"]))
    mats = {m.name: UsdShade.Material(stage.GetPrimAtPath(f"/Cylinder/Looks/{m.name}"))
            for m in spec.materials}
    mesh_path = "/Cylinder/Geom/RidgedCylinder"
    _author_mesh(stage, mesh_path, spec.meshes[0], mats)
    UsdSkel.Root.Define(stage, "/Cylinder/Geom")
    skel = UsdSkel.Skeleton.Define(stage, "/Cylinder/Geom/Skel")
    skel.CreateJointsAttr(Vt.TokenArray(list(JOINTS)))
    jy = joint_heights()
    bind = [Gf.Matrix4d(1.0).SetTranslate(Gf.Vec3d(0.0, float(y), 0.0)) for y in jy]
    skel.CreateBindTransformsAttr(Vt.Matrix4dArray(bind))
    rest = [Gf.Matrix4d(1.0).SetTranslate(Gf.Vec3d(*map(float, _gf_local(j, 0.0)[0])))
            for j in range(3)]
    skel.CreateRestTransformsAttr(Vt.Matrix4dArray(rest))
    anim = UsdSkel.Animation.Define(stage, "/Cylinder/Geom/Skel/Anim")
    anim.CreateJointsAttr(Vt.TokenArray(list(JOINTS)))
    anim.CreateTranslationsAttr(Vt.Vec3fArray([_gf_local(j, 0.0)[0] for j in range(3)]))
    anim.CreateScalesAttr(Vt.Vec3hArray([Gf.Vec3h(1, 1, 1)] * 3))
    rot = anim.CreateRotationsAttr()
    rot.Set(Vt.QuatfArray([_gf_local(j, 0.0)[1] for j in range(3)]))  # default: straight
    for t in TIME_CODES:
        ang = joint_angles(t)
        rot.Set(Vt.QuatfArray([_gf_local(j, ang[j])[1] for j in range(3)]), Usd.TimeCode(t))
    UsdSkel.BindingAPI.Apply(skel.GetPrim()).CreateAnimationSourceRel().SetTargets(
        [anim.GetPath()])
    mesh = stage.GetPrimAtPath(mesh_path)
    api = UsdSkel.BindingAPI.Apply(mesh)
    api.CreateSkeletonRel().SetTargets([skel.GetPath()])
    pts = np.asarray(spec.meshes[0].points, dtype=np.float64)
    w = joint_weights(pts[:, 1])
    order = np.argsort(-w, axis=1, kind="stable")[:, :2]  # two influences per point
    wi = np.take_along_axis(w, order, axis=1)
    api.CreateJointIndicesPrimvar(False, 2).Set(Vt.IntArray(order.reshape(-1).tolist()))
    api.CreateJointWeightsPrimvar(False, 2).Set(Vt.FloatArray(wi.reshape(-1).tolist()))
    api.CreateGeomBindTransformAttr(Gf.Matrix4d(1.0))
    stage.SetStartTimeCode(TIME_CODES[0])
    stage.SetEndTimeCode(TIME_CODES[-1])
    stage.GetRootLayer().customLayerData = {
        "texelbake": {"scene": "arm", "size": size, "seed": SEEDS["cylinder"]}}
    lo = pts.min(axis=0) - [0.0, 0.0, 0.0]
    hi = pts.max(axis=0) + [CYLINDER["height"], 0.0, 0.0]  # the bent arm reaches along +x
    UsdGeom.ModelAPI(stage.GetPrimAtPath("/Cylinder")).SetExtentsHint(
        Vt.Vec3fArray([Gf.Vec3f(*map(float, lo)), Gf.Vec3f(*map(float, hi))]))
    return stage, textures


def write_arm(path: str | Path, size: str = "small") -> Path:
    """Write the arm to `path` (.usda/.usdc/.usd) with its textures beside it."""
    from texelbake.io.images import write_png
    from texelbake.usd.shaderdefs import write_definitions

    path = Path(path)
    if path.suffix not in (".usda", ".usdc", ".usd"):
        raise SettingsError(f"field 'path': {str(path)!r} must end in .usda, .usdc or .usd")
    stage, textures = build_arm_stage(size)
    path.parent.mkdir(parents=True, exist_ok=True)
    for name in sorted(textures):
        write_png(path.parent / name, textures[name])
    write_definitions(path.parent)  # the texelbake shaders' definitions, as write_scene
    with atomic_path(path) as tmp:
        if not stage.GetRootLayer().Export(str(tmp)):
            raise OSError(f"cannot write {path}")
    return path
