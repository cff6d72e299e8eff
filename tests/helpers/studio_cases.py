"""Small assets as studios ship them, built by the tests: a cut-out card, a dome-lit object and a
subdivision surface. Each is a folder with one root layer (Y-up, metres) and its textures,
authored with pxr and plain UsdPreviewSurface materials, so that Blender's importer reads them
as texelbake does."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from pxr import Gf, Sdf, Usd, UsdGeom, UsdLux, UsdShade, Vt

from tests.helpers.usd_stages import new_stage, preview_material, write_png


def _stage(path: Path) -> Usd.Stage:
    path.parent.mkdir(parents=True, exist_ok=True)
    return new_stage(path)


def _mesh(stage, path: str, points, counts, indices, st=None, scheme: str | None = "none"):
    mesh = UsdGeom.Mesh.Define(stage, path)
    mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(np.asarray(points, dtype=np.float32)))
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray([int(c) for c in counts]))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray([int(i) for i in indices]))
    if scheme is not None:
        mesh.CreateSubdivisionSchemeAttr(scheme)
    if st is not None:
        UsdGeom.PrimvarsAPI(mesh).CreatePrimvar(
            "st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.faceVarying
        ).Set(Vt.Vec2fArray.FromNumpy(np.asarray(st, dtype=np.float32)))
    return mesh


def _bind(prim, mat) -> None:
    UsdShade.MaterialBindingAPI.Apply(prim.GetPrim()).Bind(mat)


def _floor(stage, colour=(0.55, 0.55, 0.5)) -> None:
    pts = [(-1.0, 0.0, -1.0), (-1.0, 0.0, 1.0), (1.0, 0.0, 1.0), (1.0, 0.0, -1.0)]
    floor = _mesh(stage, "/Root/Floor", pts, [4], [0, 1, 2, 3])
    _bind(floor, preview_material(stage, "/Root/Looks/Floor", diffuse=colour))


def write_cutout_card(folder: Path) -> Path:
    """A floor and an upright card (1.2 x 1.2) whose opacity is the alpha of a 64 x 64 PNG: a
    disc of radius 0.4 (in uv) opaque, the rest cut (opacityThreshold 0.5)."""
    stage = _stage(folder / "card.usda")
    _floor(stage)
    yy, xx = np.mgrid[0:64, 0:64]
    r = np.hypot((xx + 0.5) / 64 - 0.5, (yy + 0.5) / 64 - 0.5)
    px = np.zeros((64, 64, 4), dtype=np.uint8)
    px[..., 0], px[..., 1], px[..., 2] = 60, 160, 70
    px[..., 3] = np.where(r < 0.4, 255, 0)
    write_png(folder / "leaf.png", px)
    pts = [(-0.6, 0.05, 0.0), (0.6, 0.05, 0.0), (0.6, 1.25, 0.0), (-0.6, 1.25, 0.0)]
    card = _mesh(stage, "/Root/Card", pts, [4], [0, 1, 2, 3],
                 st=[(0, 0), (1, 0), (1, 1), (0, 1)])
    card.CreateDoubleSidedAttr(True)
    mat = preview_material(stage, "/Root/Looks/Leaf", diffuse=(0.2, 0.6, 0.25),
                           texture="./leaf.png", output="a", connect_to="opacity")
    UsdShade.Shader(stage.GetPrimAtPath("/Root/Looks/Leaf/Surface")).CreateInput(
        "opacityThreshold", Sdf.ValueTypeNames.Float).Set(0.5)
    _bind(card, mat)
    stage.GetRootLayer().Save()
    return folder / "card.usda"


def write_dome_lit(folder: Path, sky: str = "patch", camera: bool = False,
                   turn_deg: float = 0.0, flat: bool = False) -> Path:
    """A box on a floor lit only by a DomeLight. `sky`: "patch", a lat-long PNG (32 x 64) of
    a dim blue sky with a bright warm patch above +X; "band", a dim blue sky with a broad
    bright warm band (longitude +45…+135 degrees, latitude +10…+60) on the +X side, so the
    box's +X face is lit and its shadow falls toward -X (a mirrored or turned dome shows);
    "constant", no texture, the light's colour alone. With `camera`, a UsdGeom.Camera
    /Root/Camera (24 mm, 20.955 mm aperture) looks at the box from +X+Z, above; `turn_deg`
    turns the dome about +Y (a rotateY op on the light); with `flat` the box carries its
    faces' normals (faceVarying), else none (renderers smooth it)."""
    stage = _stage(folder / "dome.usda")
    _floor(stage)
    c = np.array([[x, y, z] for x in (-0.3, 0.3) for y in (0.0, 0.6) for z in (-0.3, 0.3)])
    quads = [[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]]
    box = _mesh(stage, "/Root/Box", c, [4] * 6, np.asarray(quads).ravel())
    if flat:
        q = c[np.asarray(quads)]  # (6, 4, 3)
        n = np.cross(q[:, 1] - q[:, 0], q[:, 2] - q[:, 0])
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        box.CreateNormalsAttr(Vt.Vec3fArray.FromNumpy(np.repeat(n, 4, axis=0).astype(np.float32)))
        box.SetNormalsInterpolation(UsdGeom.Tokens.faceVarying)
    _bind(box, preview_material(stage, "/Root/Looks/Box", diffuse=(0.7, 0.3, 0.2)))
    dome = UsdLux.DomeLight.Define(stage, "/Root/Sky")
    if turn_deg:
        dome.AddRotateYOp().Set(float(turn_deg))
    if sky in ("patch", "band"):
        px = np.zeros((32, 64, 3), dtype=np.uint8)
        px[..., 0], px[..., 1], px[..., 2] = (60, 80, 120) if sky == "patch" else (20, 26, 40)
        if sky == "patch":
            px[6:10, 14:20] = 255  # latitude ~55 degrees, longitude ~+90 degrees: above +X
        else:  # rows 5..13: latitude +61…+11; columns 8..23: longitude +135…+45 (+X is col 16)
            px[5:14, 8:24] = (255, 230, 180)
        write_png(folder / "sky.png", px)
        dome.CreateTextureFileAttr(Sdf.AssetPath("./sky.png"))
        dome.CreateTextureFormatAttr(UsdLux.Tokens.latlong)
        dome.CreateIntensityAttr(1.0 if sky == "patch" else 2.0)
        dome.CreateColorAttr(Gf.Vec3f(1.0, 1.0, 1.0))
    elif sky == "constant":
        dome.CreateIntensityAttr(0.5)
        dome.CreateColorAttr(Gf.Vec3f(0.6, 0.7, 0.9))
    else:
        raise ValueError(f"sky must be 'patch', 'band' or 'constant', got {sky!r}")
    if camera:
        _look_at_camera(stage, "/Root/Camera", eye=(2.0, 1.9, 2.6), target=(0.0, 0.2, 0.0))
    stage.GetRootLayer().Save()
    return folder / "dome.usda"


def look_at_matrix(eye, target) -> Gf.Matrix4d:
    """The transform that puts a prim at `eye` with its -Z toward `target` (+Y up), as a
    camera looks and a distant light shines."""
    eye_v, target_v = np.asarray(eye, dtype=np.float64), np.asarray(target, dtype=np.float64)
    z = (eye_v - target_v) / np.linalg.norm(eye_v - target_v)
    x = np.cross([0.0, 1.0, 0.0], z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    m = np.eye(4)
    m[0, :3], m[1, :3], m[2, :3], m[3, :3] = x, y, z, eye_v  # USD: row vectors
    return Gf.Matrix4d(*m.ravel().tolist())


def _look_at_camera(stage, path: str, eye, target) -> UsdGeom.Camera:
    """A UsdGeom.Camera at `eye` looking at `target` (+Y up), 24 mm lens, 20.955 mm aperture."""
    cam = UsdGeom.Camera.Define(stage, path)
    cam.AddTransformOp().Set(look_at_matrix(eye, target))
    cam.CreateFocalLengthAttr(24.0)
    cam.CreateHorizontalApertureAttr(20.955)
    cam.CreateVerticalApertureAttr(20.955)
    cam.CreateClippingRangeAttr(Gf.Vec2f(0.1, 100.0))
    return cam


def write_subdivision_cube(folder: Path) -> Path:
    """A 6-quad catmullClark cube cage (edge 0.8): its limit surface is a rounded blob."""
    stage = _stage(folder / "subdiv.usda")
    c = np.array([[x, y, z] for x in (-0.4, 0.4) for y in (0.0, 0.8) for z in (-0.4, 0.4)])
    quads = [[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]]
    blob = _mesh(stage, "/Root/Blob", c, [4] * 6, np.asarray(quads).ravel(),
                 scheme="catmullClark")
    _bind(blob, preview_material(stage, "/Root/Looks/Blob", diffuse=(0.3, 0.45, 0.7)))
    stage.GetRootLayer().Save()
    return folder / "subdiv.usda"


def with_camera_and_sun(src: Path, out: Path, *, view=(1.0, 0.75, 1.4),
                        sun=(0.5, 1.0, 0.7), irradiance: float = 3.0) -> Path:
    """A root layer at `out` that sublayers `src` and adds a camera framing its bounds from
    direction `view` and a normalized DistantLight of `irradiance` shining from direction `sun`
    (both under `src`'s default prim), so that texelbake and Blender, each keeping the file's
    camera and lights, render the same view of the same asset."""
    import os

    src_stage = Usd.Stage.Open(str(src))
    box = UsdGeom.BBoxCache(Usd.TimeCode.EarliestTime(), [UsdGeom.Tokens.default_]
                            ).ComputeWorldBound(src_stage.GetPseudoRoot()).ComputeAlignedRange()
    lo, hi = np.array(box.GetMin()), np.array(box.GetMax())
    root = src_stage.GetDefaultPrim().GetPath()
    del src_stage
    centre, radius = 0.5 * (lo + hi), 0.5 * float(np.linalg.norm(hi - lo))
    stage = _stage(out)
    stage.GetRootLayer().subLayerPaths.append(os.path.relpath(src, out.parent))
    stage.GetRootLayer().defaultPrim = root.name
    view_v = np.asarray(view, dtype=np.float64) / np.linalg.norm(view)
    # 24 mm over 20.955 mm: a 47 degree field; the bounding sphere fills ~60 % of it
    _look_at_camera(stage, str(root.AppendChild("GtCamera")), eye=centre + 3.2 * radius * view_v,
                    target=centre)
    light = UsdLux.DistantLight.Define(stage, root.AppendChild("GtSun"))
    light.AddTransformOp().Set(look_at_matrix(centre + np.asarray(sun, dtype=np.float64),
                                              centre))
    light.CreateIntensityAttr(float(irradiance))
    light.CreateNormalizeAttr(True)
    light.CreateAngleAttr(0.53)
    stage.GetRootLayer().Save()
    return out
