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


def write_dome_lit(folder: Path) -> Path:
    """A box on a floor lit only by a DomeLight whose lat-long PNG (32 x 64) is a dim blue
    sky with a bright warm patch above +X."""
    stage = _stage(folder / "dome.usda")
    _floor(stage)
    c = np.array([[x, y, z] for x in (-0.3, 0.3) for y in (0.0, 0.6) for z in (-0.3, 0.3)])
    quads = [[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]]
    box = _mesh(stage, "/Root/Box", c, [4] * 6, np.asarray(quads).ravel())
    _bind(box, preview_material(stage, "/Root/Looks/Box", diffuse=(0.7, 0.3, 0.2)))
    sky = np.zeros((32, 64, 3), dtype=np.uint8)
    sky[..., 0], sky[..., 1], sky[..., 2] = 60, 80, 120
    sky[6:10, 14:20] = 255  # latitude ~55 degrees, longitude ~+90 degrees: above +X
    write_png(folder / "sky.png", sky)
    dome = UsdLux.DomeLight.Define(stage, "/Root/Sky")
    dome.CreateTextureFileAttr(Sdf.AssetPath("./sky.png"))
    dome.CreateTextureFormatAttr(UsdLux.Tokens.latlong)
    dome.CreateIntensityAttr(1.0)
    dome.CreateColorAttr(Gf.Vec3f(1.0, 1.0, 1.0))
    stage.GetRootLayer().Save()
    return folder / "dome.usda"


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
