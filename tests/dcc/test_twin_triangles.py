"""Blender's reference in benchmarks/fallback.py is the original without coplanar overlapping
twin triangles (`tests.helpers.dcc.without_twin_triangles`). BoxAnimated.usdz, converted from
glTF, writes every quad (0, 1, 2, 3) as the triangles (0, 1, 2), (1, 2, 3), (2, 3, 0), of which
the second overlaps the other two; Cycles excludes only the triangle a ray leaves, so a shadow
ray from one stops on its twin at distance ~0 and the overlap renders black (BoxAnimated's LOD1
then scored 13.8 dB against it and 22.4 against the original without its twins; texelbake,
which sees the same surface either way, 22.9).

A cube written that way: the twins are found and removed, which leaves the two-triangle cube,
and that renders as the cube written with two triangles a quad.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from tests.helpers.dcc import (
    compare_renders,
    import_and_render,
    keep_artifacts,
    side_by_side,
    without_twin_triangles,
)

pytestmark = [pytest.mark.dcc, pytest.mark.slow]  # Blender and Cycles: not for test-fast

#: a cube's faces, corners counter-clockwise seen from outside, and their outward normals
FACES = (((0, 1, 3, 2), (-1, 0, 0)), ((4, 6, 7, 5), (1, 0, 0)), ((0, 4, 5, 1), (0, -1, 0)),
         ((2, 3, 7, 6), (0, 1, 0)), ((0, 2, 6, 4), (0, 0, -1)), ((1, 5, 7, 3), (0, 0, 1)))
CORNERS = np.array([[x, y, z] for x in (-1.0, 1.0) for y in (-1.0, 1.0) for z in (-1.0, 1.0)])


def _cube(path: Path, triangles: tuple[tuple[int, int, int], ...]) -> Path:
    """A cube of 24 points (four a face), each face's quad (0, 1, 2, 3) written as `triangles`
    of those corners, the face's normal on each corner (faceVarying), `st` the quad corner's
    (faceVarying, indexed), a GeomSubset of the +z face's triangles; one grey
    UsdPreviewSurface."""
    from pxr import Gf, Sdf, Usd, UsdGeom, UsdShade, Vt

    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    root = UsdGeom.Xform.Define(stage, "/Cube")
    stage.SetDefaultPrim(root.GetPrim())
    pts, nrm, idx, st_idx, top = [], [], [], [], []
    for quad, n in FACES:
        base = len(pts)
        pts += [CORNERS[i] for i in quad]
        if n == (0, 0, 1):
            top += range(len(idx) // 3, len(idx) // 3 + len(triangles))
        nrm += [n] * 3 * len(triangles)
        idx += [base + i for t in triangles for i in t]
        st_idx += [i for t in triangles for i in t]
    mesh = UsdGeom.Mesh.Define(stage, "/Cube/Geom")
    mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(np.asarray(pts, dtype=np.float32)))
    mesh.CreateNormalsAttr(Vt.Vec3fArray.FromNumpy(np.asarray(nrm, dtype=np.float32)))
    mesh.SetNormalsInterpolation(UsdGeom.Tokens.faceVarying)
    st = UsdGeom.PrimvarsAPI(mesh).CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray,
                                                 UsdGeom.Tokens.faceVarying)
    st.Set(Vt.Vec2fArray([(0.0, 0.0), (1.0, 0.0), (1.0, 1.0), (0.0, 1.0)]))
    st.SetIndices(Vt.IntArray(st_idx))
    UsdGeom.Subset.CreateGeomSubset(mesh, "top", UsdGeom.Tokens.face, Vt.IntArray(top))
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray([3] * (len(idx) // 3)))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray(idx))
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    mesh.CreateExtentAttr([Gf.Vec3f(-1.0), Gf.Vec3f(1.0)])
    mat = UsdShade.Material.Define(stage, "/Cube/Looks/Grey")
    surf = UsdShade.Shader.Define(stage, "/Cube/Looks/Grey/PreviewSurface")
    surf.CreateIdAttr("UsdPreviewSurface")
    surf.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(0.5, 0.6, 0.8))
    surf.CreateInput("roughness", Sdf.ValueTypeNames.Float).Set(1.0)
    mat.CreateSurfaceOutput().ConnectToSource(surf.CreateOutput("surface",
                                                                Sdf.ValueTypeNames.Token))
    UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim()).Bind(mat)
    stage.Save()
    return path


@pytest.fixture(scope="module")
def cubes(tmp_path_factory):
    d = tmp_path_factory.mktemp("dcc_twins")
    twins = _cube(d / "twins.usda", ((0, 1, 2), (1, 2, 3), (2, 3, 0)))
    clean = _cube(d / "clean.usda", ((0, 1, 2), (2, 3, 0)))
    repaired, removed = without_twin_triangles(twins, d / "repaired.usda")
    return {"twins": twins, "clean": clean, "repaired": repaired, "removed": removed, "dir": d}


def test_the_twins_are_found_and_the_cover_kept(cubes):
    from pxr import Usd, UsdGeom

    assert cubes["removed"] == 6 and cubes["repaired"] != cubes["twins"]

    def faces(path):
        stage = Usd.Stage.Open(str(path))
        mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/Cube/Geom"))
        st = UsdGeom.PrimvarsAPI(mesh).GetPrimvar("st")
        return {"faces": list(mesh.GetFaceVertexIndicesAttr().Get()),
                "normals": np.asarray(mesh.GetNormalsAttr().Get()).tolist(),
                "st": np.asarray(st.ComputeFlattened()).tolist(),
                "top": list(UsdGeom.Subset.GetAllGeomSubsets(mesh)[0].GetIndicesAttr().Get())}

    # topology, corner normals, the indexed st and the subset: the cube written cleanly
    assert faces(cubes["repaired"]) == faces(cubes["clean"])
    # a mesh without twins is handed back as it is
    assert without_twin_triangles(cubes["clean"], cubes["dir"] / "again.usda") == (
        cubes["clean"], 0)


def test_without_its_twins_it_renders_as_the_clean_cube(cubes):
    renders = cubes["dir"] / "renders"
    got = import_and_render({k: cubes[k] for k in ("clean", "repaired", "twins")}, renders,
                            resolution=64, samples=16)
    pngs = {k: Path(f["png"]) for k, f in got["files"].items()}
    side_by_side([pngs[k] for k in ("clean", "repaired", "twins")], renders / "row.png")
    keep_artifacts(sorted(renders.glob("*.png")), "dcc/twin_triangles")
    same = compare_renders(pngs["clean"], pngs["repaired"])
    assert same["iou"] == 1.0 and same["mad"] < 1e-3, same
    # and the twins are why: Cycles renders the cube written with them otherwise (measured
    # object MAD 0.26: the overlaps black)
    assert compare_renders(pngs["clean"], pngs["twins"])["mad"] > 0.05
