"""The USD LOD schema on a baked root (texelbake.usd.lodschema), read back by a stock pxr in a
process that never imported texelbake: LODRootAPI on `Baked` with its items in index order, a
screen-size heuristic whose thresholds select, at each LOD's switch distance, the LOD the `LOD`
variant set names; the baked root and every `--lod` export open silently with 0 errors."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys

import numpy as np
import pytest

from tests.helpers.usd_validation import stock_errors

#: stock pxr only: the schema as a LOD-aware renderer reads it, and the variant set beside it
READ_SCHEMA = r"""
import json, math, sys
from pxr import Gf, Usd, UsdLod
stage = Usd.Stage.Open(sys.argv[1])
root = stage.GetDefaultPrim()
baked = root.GetChild("Baked")
api = UsdLod.RootAPI(baked)
heur = UsdLod.ScreenSizeHeuristic(stage.GetPrimAtPath(api.GetLodHeuristicsRel().GetTargets()[0]))
lo, hi = [Gf.Vec3d(v) for v in heur.GetExtentAttr().Get()]
diag = (hi - lo).GetLength()
center = (lo + hi) / 2
out = {"applied": baked.HasAPI(UsdLod.RootAPI), "children": baked.GetAllChildrenNames(),
       "thresholds": list(heur.GetThresholdsAttr().Get()),
       "domain": heur.GetLodDomainAttr().Get(), "default_index": {}, "picked": {}}
vset = root.GetVariantSets().GetVariantSet("LOD")
for name in vset.GetVariantNames():
    vset.SetVariantSelection(name)
    out["default_index"][name] = api.GetLodDefaultIndexAttr().Get()
vset.SetVariantSelection("LOD0")
# a camera with a 40 degree vertical field of view on a 1920 x 1080 viewport, placed where the
# bounding-box diagonal covers `px` pixels (small-angle: px = diag / (2 d tan 20deg) * 1080)
for px in json.loads(sys.argv[2]):
    d = diag * 1080.0 / (2.0 * px * math.tan(math.radians(20.0)))
    f = Gf.Frustum()
    f.SetPerspective(40.0, 1920.0 / 1080.0, 0.01 * d, 100.0 * d)
    f.SetPosition(center + Gf.Vec3d(0.0, 0.0, d))
    out["picked"][str(px)] = heur.ComputeLOD(f, Gf.Matrix4d(1.0))
print(json.dumps(out))
"""


@pytest.fixture(scope="module")
def baked(tmp_path_factory):
    from schemas.settings import BakeSettings
    from texelbake.pipeline.run import bake
    from texelbake.testscenes import write_scene

    d = tmp_path_factory.mktemp("lodschema")
    src = write_scene("cylinder", d / "cylinder.usda", "small")
    settings = BakeSettings(samples_per_texel=4, n_light_dirs=4, n_view_dirs=4, n_heldout=4,
                            c_max=4, lod_switch_px=(32.0, 8.0))  # two LODs, a cheap bake
    return bake(src, d / "out", settings, progress=False)


def _read(path, sizes):
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PXR_", "PYTHONPATH"))}
    r = subprocess.run([sys.executable, "-c", READ_SCHEMA, str(path), json.dumps(sizes)],
                       capture_output=True, text=True, timeout=120, env=env, cwd="/")
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout.strip().splitlines()[-1]), r.stderr


def test_the_lod_schema_agrees_with_the_variant_set(baked):
    # switch sizes 32 and 8 px: above 32 the original, 8..32 LOD1, below 8 LOD2. Probed at
    # 1.25x and 0.8x each switch size, clear of the small-angle and sphere-projection
    # approximations (both under 0.1 % at these distances, the object covering < 3 % of the
    # frame height)
    sizes = [40.0, 25.6, 10.0, 6.4, 2.0]
    got, printed = _read(baked, sizes)
    assert printed == ""
    assert got["applied"] and got["domain"] == "imaging"
    assert got["children"][:3] == ["LOD0", "LOD1", "LOD2"]  # items in index order
    # thresholds: the area fraction of a 1920 x 1080 viewport a sphere of diameter px covers
    want = [math.pi * (p / 2) ** 2 / (1920 * 1080) for p in (32.0, 8.0)]
    np.testing.assert_allclose(got["thresholds"], want, rtol=1e-6)
    assert [round(got["picked"][str(p)]) for p in sizes] == [0, 1, 1, 2, 2]
    # a client that reads neither shows the item the variant selection shows
    assert got["default_index"] == {"LOD0": 0, "LOD1": 1, "LOD2": 2}


def test_baked_root_and_every_export_open_silently_with_no_errors(baked, tmp_path):
    from texelbake.usd.export import export_lod

    outs = [export_lod(baked, n, tmp_path / f"lod{n}{suffix}")
            for n in (0, 1, 2) for suffix in (".usda", ".usdz")]
    # stock_errors also asserts that nothing was printed on open, traversal, material
    # resolution and validation
    assert stock_errors(baked, *outs) == {str(p): [] for p in (baked, *outs)}
    # one LOD is the whole export: the schema that selects among LODs is not carried
    from pxr import Usd, UsdLod

    for n in (1, 2):
        stage = Usd.Stage.Open(str(tmp_path / f"lod{n}.usda"))
        assert not any(p.HasAPI(UsdLod.RootAPI) or p.IsA(UsdLod.Heuristic)
                       for p in stage.Traverse())
        assert not stage.GetPrimAtPath("/Cylinder/Baked/LOD0")


def test_switch_sizes_continue_the_last_ratio():
    from texelbake.errors import SettingsError
    from texelbake.usd.lodschema import switch_sizes

    assert switch_sizes((256.0, 64.0), 2) == [256.0, 64.0]
    assert switch_sizes((256.0, 64.0), 1) == [256.0]
    assert switch_sizes((256.0, 128.0), 3) == [256.0, 128.0, 64.0]
    assert switch_sizes((100.0,), 2) == [100.0, 25.0]
    with pytest.raises(SettingsError, match="'lod_switch_px'"):
        switch_sizes((0.0,), 1)


def test_the_normal_map_validator_sees_every_lods_normal_texture(baked):
    # the stock run above is not vacuous for usdShadeValidators:NormalMapTextureValidator:
    # every LOD's UsdPreviewSurface reads its normal from an 8-bit UsdUVTexture, the case that
    # validator checks (raw colour space, scale (2, 2, 2, 1), bias (-1, -1, -1, 0))
    from pxr import Usd, UsdGeom, UsdShade

    stage = Usd.Stage.Open(str(baked))
    seen = 0
    for prim in stage.Traverse():
        if not prim.GetPath().HasPrefix("/Cylinder/Baked") or not prim.IsA(UsdShade.Shader) \
                or UsdShade.Shader(prim).GetShaderId() != "UsdPreviewSurface":
            continue
        src = UsdShade.Shader(prim).GetInput("normal").GetConnectedSources()[0][0].source
        tex = UsdShade.Shader(src.GetPrim())
        assert tex.GetShaderId() == "UsdUVTexture"
        assert tex.GetInput("file").Get().path.endswith(".png")
        seen += 1
    assert seen == len([p for p in stage.Traverse() if p.IsA(UsdGeom.Mesh)
                        and p.GetPath().HasPrefix("/Cylinder/Baked")])
