"""`texelbake export BAKED --lod N -o FILE` (issue 22): one LOD as a self-contained file for
tools without variant support, checked in a process that never imports texelbake."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

CHECK = r"""
import json, sys
from pxr import Usd, UsdGeom, UsdShade, UsdValidation
st = Usd.Stage.Open(sys.argv[1])
meshes = [p for p in st.Traverse() if p.IsA(UsdGeom.Mesh)]
out = {"meshes": [m.GetPath().pathString for m in meshes],
       "points": [[list(map(float, v)) for v in UsdGeom.Mesh(m).GetPointsAttr().Get()]
                  for m in meshes],
       "files": [], "baked_scope": bool(st.GetPrimAtPath("/Cylinder/Baked"))}
for m in meshes:
    mat, _ = UsdShade.MaterialBindingAPI(m).ComputeBoundMaterial()
    out.setdefault("materials", []).append(mat.GetPath().pathString if mat else None)
    for p in Usd.PrimRange(mat.GetPrim()) if mat else []:
        sh = UsdShade.Shader(p)
        if sh and sh.GetIdAttr().Get() == "UsdUVTexture":
            f = sh.GetInput("file").Get()
            out["files"].append(bool(f.resolvedPath))
ctx = UsdValidation.ValidationContext(
    list(UsdValidation.ValidationRegistry().GetAllValidatorMetadata()), True)
out["errors"] = [e.GetName() for e in ctx.Validate(st)
                 if e.GetType() == UsdValidation.ValidationErrorType.Error]
print(json.dumps(out))
"""


def _inspect(path):
    r = subprocess.run([sys.executable, "-c", CHECK, str(path)], capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout.strip().splitlines()[-1])


@pytest.fixture(scope="module")
def baked(tmp_path_factory):
    from schemas.settings import BakeSettings
    from texelbake.pipeline.run import bake
    from texelbake.testscenes import write_scene

    d = tmp_path_factory.mktemp("lods")
    src = write_scene("cylinder", d / "cylinder.usda", "small")
    settings = BakeSettings(samples_per_texel=4, n_light_dirs=4, n_view_dirs=4, n_heldout=4,
                            c_max=4, lod_switch_px=(32.0, 8.0))  # two LODs (issue 22)
    return bake(src, d / "out", settings, progress=False)


@pytest.mark.parametrize("suffix", [".usdc", ".usdz"])
def test_one_lod_exports_self_contained_and_stock_valid(baked, tmp_path, suffix):
    from texelbake.usd.export import export_lod
    from texelbake.usd.read import read_baked

    lods = read_baked(baked).meshes
    for n in (1, 2):
        out = export_lod(baked, n, tmp_path / f"lod{n}{suffix}")
        got = _inspect(out)
        # only that LOD's mesh, with its points, bound to the preview material whose
        # textures resolve next to (or inside) the file; 0 errors from stock validation
        assert got["meshes"] == [f"/Cylinder/Baked/LOD{n}"]
        np.testing.assert_allclose(np.asarray(got["points"][0]), lods[n - 1].vertices,
                                   atol=1e-6)
        # each LOD has its own fallback (issue 21): diffuseColor, normal, roughness widened
        # for that LOD, occlusion
        assert got["materials"] == ["/Cylinder/Baked/Looks/BakedPreview" if n == 1 else
                                    f"/Cylinder/Baked/Looks/BakedPreview_LOD{n}"]
        assert got["files"] == [True, True, True, True]
        assert got["errors"] == []
    if suffix == ".usdc":
        (tmp_path / "lod1_maps" / "cylinder_basecolor.png").unlink()  # not self-contained now
        assert _inspect(tmp_path / "lod1.usdc")["files"] == [False, True, True, True]


def test_lod0_is_the_asset_as_authored(baked, tmp_path):
    from texelbake.usd.export import export_lod

    got = _inspect(export_lod(baked, 0, tmp_path / "lod0.usda"))
    assert got["meshes"] == ["/Cylinder/Geom/RidgedCylinder"] and not got["baked_scope"]
    # the source's texelbake shaders keep their definitions (copied beside the file)
    assert got["errors"] == []
    for suffix in (".usdz", ".usdc"):
        assert _inspect(export_lod(baked, 0, tmp_path / f"lod0{suffix}"))["errors"] == []


def test_baked_result_passes_stock_validation(baked):
    # the root (LOD0 selected), its payload with the CPM shader, and every LOD variant, in a
    # process that never imported texelbake (issue 11, item 5)
    got = _inspect(baked)
    assert got["errors"] == []
    assert (baked.parent / "texelbake_shaders.usda").is_file()


def test_bad_requests_name_the_field_and_write_nothing(baked, tmp_path):
    from texelbake.errors import AssetError, SettingsError
    from texelbake.usd.export import export_lod

    with pytest.raises(SettingsError, match="'lod'"):
        export_lod(baked, 3, tmp_path / "x.usdc")
    with pytest.raises(SettingsError, match="'output'"):
        export_lod(baked, 1, tmp_path / "x.obj")
    with pytest.raises(AssetError, match="LOD variant set"):
        export_lod(baked.parent.parent / "cylinder.usda", 1, tmp_path / "x.usdc")
    assert list(tmp_path.iterdir()) == []


def test_the_output_folder_holds_the_result_only(baked, tmp_path):
    # issue 22, item 4: root, payload, maps, report (and the shader definitions the layers
    # name); the artifact store lives elsewhere and the source is referenced where it lies
    from pxr import Usd

    entries = sorted(baked.parent.iterdir())
    assert all(p.is_file() for p in entries), entries  # no .work/, no source/
    names = [p.name for p in entries]
    maps = [n for n in names if n.startswith("cylinder_") and n.endswith((".png", ".exr"))]
    assert sorted(set(names) - set(maps)) == [
        "cylinder_baked.usda", "cylinder_payload.usdc", "report.json", "texelbake_shaders.usda"]
    assert "cylinder_albedo.png" in maps
    stage = Usd.Stage.Open(str(baked))
    refs = stage.GetRootLayer().GetPrimAtPath("/Cylinder").referenceList.prependedItems
    assert [r.assetPath for r in refs] == ["./../cylinder.usda"]


def test_packed_usdz_carries_the_source_and_passes_stock_validation(baked, tmp_path):
    import shutil

    from texelbake.usd.package import pack_usdz

    # a copy of the result beside a copy of its source, so the package is written there
    (tmp_path / "out").mkdir()
    for f in baked.parent.iterdir():
        shutil.copyfile(f, tmp_path / "out" / f.name)
    shutil.copyfile(baked.parent.parent / "cylinder.usda", tmp_path / "cylinder.usda")
    shutil.copyfile(baked.parent.parent / "texelbake_shaders.usda",
                    tmp_path / "texelbake_shaders.usda")
    packed = pack_usdz(tmp_path / "out" / baked.name)
    (tmp_path / "cylinder.usda").unlink()  # the package alone
    got = _inspect(packed)
    assert "/Cylinder/Geom/RidgedCylinder" in got["meshes"]  # LOD0, from the packed source
    assert got["errors"] == []
