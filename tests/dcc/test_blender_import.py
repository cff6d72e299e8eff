"""A real DCC opens what we write (issue 22, item 5): Blender 5.0.1 (`bpy`, in its own
virtualenv, scripts/dcc-venv.sh) imports the baked root and `texelbake export --lod N` files
(.usdc and .usdz) with its own USD importer at its defaults, and renders them beside the
original from one camera and sun (tests/blender/import_render.py, run in a subprocess).

Assets: the Teapot as shipped (Y-up, metres, a payload and a variant set on its root; two
LODs at the default switch sizes) and the generated cylinder (Y-up, centimetres: Blender
scales it to metres; one LOD). Light CPM settings keep the bakes short; the LOD chain, the
fallback material and its textures do not depend on them (they follow the geometry fields).

The renders are PNGs in the test's tmp folder (`<asset>/*.png`, `<asset>/row.png` side by
side: original, root, LOD1, LOD2); with TEXELBAKE_TEST_ARTIFACTS=DIR they are also copied to
DIR/dcc/<asset>/.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

from tests.helpers.dcc import compare_renders, import_and_render, keep_artifacts, side_by_side

pytestmark = [pytest.mark.dcc, pytest.mark.slow]  # Blender and Cycles: not for test-fast

ASSETS = Path(__file__).resolve().parents[3] / "shared" / "assets"
LIGHT = {"samples_per_texel": 8, "n_light_dirs": 8, "n_view_dirs": 8, "n_heldout": 16,
         "c_max": 8}

# The bar of issue 22's acceptance, and why it is the right one at this view. The camera fits
# the original's bounding box in a 160 px frame, so the bounding-box diagonal covers ~150 px:
# less than LOD1's 256 px switch size, where LOD1 deviates at most lod_error_px = 1 px from
# M_org. The silhouettes may thus differ by a band of at most ~1 px along the outline; for
# these compact objects (~100 px across, outline ~350 px, area ~8000 px) that band is ~4 % of
# the area, so IoU >= 0.95 is what the 1 px bound allows and a wrong LOD shape, orientation or
# unit scale (IoU 0.61 for the Teapot's old 16-triangle LOD1) fails it. The colour bar, a mean
# absolute difference of 0.10 over the object's pixels (8-bit sRGB as displayed, in [0, 1]),
# is the issue's; a fallback material without the source's colour or roughness (the old grey
# 0.6-rough one: 0.26-0.30) fails it, and so did the cylinder's LOD1 with 16² fallback textures
# (0.16: its stripes smeared) and without shading normals (0.10: Blender shaded it smooth).
# The Cycles noise floor is 0: the renderer is deterministic (fixed seed, no adaptive
# sampling), asserted on the root below.
IOU_MIN = 0.95
MAD_MAX = 0.10


def _asset_file(name: str) -> Path:
    path = ASSETS / "Teapot" / "Teapot.usd"
    if not path.is_file():
        if os.environ.get("CI") == "true":
            pytest.fail(f"{path} is missing (shared/ must sit beside the clone)")
        pytest.skip(f"{path} is not here")
    return path


def _bake(name: str, d: Path) -> tuple[Path, Path]:
    from schemas.settings import BakeSettings
    from texelbake.pipeline.run import bake
    from texelbake.testscenes import write_scene

    src = _asset_file(name) if name == "teapot" else write_scene(name, d / f"{name}.usda",
                                                                   "small")
    return src, bake(src, d / "out", BakeSettings(**LIGHT), progress=False)


def _source_bounds_in_blender(src: Path) -> np.ndarray:
    """The source's world bounds (pxr, the bake's time), as Blender's importer places them:
    Y-up stages are turned Z-up ((x, y, z) -> (x, -z, y)) and stage units scaled to metres."""
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.Open(str(src), Usd.Stage.LoadAll)
    cache = UsdGeom.BBoxCache(Usd.TimeCode.EarliestTime(),
                              [UsdGeom.Tokens.default_, UsdGeom.Tokens.render])
    box = cache.ComputeWorldBound(stage.GetPseudoRoot()).ComputeAlignedRange()
    lo, hi = np.array(box.GetMin()), np.array(box.GetMax())
    if UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.y:
        lo, hi = np.array([lo[0], -hi[2], lo[1]]), np.array([hi[0], -lo[2], hi[1]])
    return np.stack([lo, hi]) * UsdGeom.GetStageMetersPerUnit(stage)


def _org_bounds_in_blender(src: Path) -> np.ndarray:
    """The bounds of M_org (`load_asset`: subdivision surfaces refined) placed as Blender's
    importer places the source (Y-up turned Z-up, units scaled to metres)."""
    from pxr import Usd, UsdGeom

    from texelbake.asset import load_asset

    pts = load_asset(src).points
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    stage = Usd.Stage.Open(str(src))
    if UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.y:
        lo, hi = np.array([lo[0], -hi[2], lo[1]]), np.array([hi[0], -lo[2], hi[1]])
    return np.stack([lo, hi]) * UsdGeom.GetStageMetersPerUnit(stage)


@pytest.fixture(scope="module", params=["teapot", "cylinder"])
def dcc(request, tmp_path_factory):
    """Bake, export every LOD as .usdc and .usdz, import and render everything in Blender."""
    from pxr import UsdGeom

    from texelbake.usd.export import export_lod

    name = request.param
    d = tmp_path_factory.mktemp(f"dcc_{name}")
    src, root = _bake(name, d)
    report = json.loads((root.parent / "report.json").read_text())
    n_lods = len(report["lods"]["levels"])
    files = {"original": src, "root": root}
    for n in range(1, n_lods + 1):
        for suffix in (".usdc", ".usdz"):
            files[f"lod{n}{suffix[1:]}"] = export_lod(root, n, d / "export" / f"lod{n}{suffix}")
    # the original as Blender smooths a subdivision surface when asked (its Subdivision
    # Surface modifier, render level 2 on the limit surface; the Teapot is catmullClark)
    files["original_subdiv"] = src
    renders = d / "renders"
    got = import_and_render(files, renders, resolution=160, samples=32,
                            options={"original_subdiv": {"import_subdivision": True}})
    rows = [Path(got["files"][k]["png"]) for k in ["original", "root"]
            + [f"lod{n}usdz" for n in range(1, n_lods + 1)]]
    side_by_side(rows, renders / "row.png")
    keep_artifacts(sorted(renders.glob("*.png")), f"dcc/{name}")
    from pxr import Usd
    mpu = UsdGeom.GetStageMetersPerUnit(Usd.Stage.Open(str(src)))
    return {"name": name, "src": src, "root": root, "report": report, "n_lods": n_lods,
            "got": got, "mpu": mpu, "renders": renders}


def test_the_root_imports_as_the_original(dcc):
    # the default LOD selection is LOD0, the asset as authored: no stacked LODs, no proxy
    orig, root = dcc["got"]["files"]["original"], dcc["got"]["files"]["root"]
    assert root["import"] == ["FINISHED"]
    assert [(m["name"], m["triangles"], m["materials"]) for m in root["meshes"]] == [
        (m["name"], m["triangles"], m["materials"]) for m in orig["meshes"]]
    np.testing.assert_allclose(root["bounds"], orig["bounds"], atol=1e-9)
    # and the importer put the original where pxr says it is (orientation and units)
    np.testing.assert_allclose(orig["bounds"], _source_bounds_in_blender(dcc["src"]),
                               atol=1e-6 * dcc["mpu"])


@pytest.mark.parametrize("suffix", ["usdc", "usdz"])
def test_each_lod_export_imports_with_its_mesh_material_and_textures(dcc, suffix):
    from texelbake.io.images import read_pixels

    # M_org as the bake reads it (the Teapot's limit surface, not the cage Blender's default
    # import shows), where Blender's importer places it
    orig = _org_bounds_in_blender(dcc["src"])
    for n, lod in enumerate(dcc["report"]["lods"]["levels"], start=1):
        f = dcc["got"]["files"][f"lod{n}{suffix}"]
        assert f["import"] == ["FINISHED"]
        # one mesh, the LOD's, with the report's triangles, bound to its fallback material
        assert [(m["name"], m["triangles"]) for m in f["meshes"]] == [
            (f"LOD{n}", lod["triangles"])]
        mat = "BakedPreview" if n == 1 else f"BakedPreview_LOD{n}"
        assert f["meshes"][0]["materials"] == [mat] and list(f["materials"]) == [mat]
        # its bounds within the LOD's stated deviation of the original's (Hausdorff <= bound)
        bound = lod["bound"] * dcc["mpu"]
        assert np.abs(np.asarray(f["bounds"]) - orig).max() <= bound * (1 + 1e-4), (n, bound)
        # the textures load: base colour, roughness and normal (Blender's importer reads no
        # occlusion input), each with pixels of the size the file on disk has
        images = f["materials"][mat]
        names = sorted(i["image"] for i in images)
        stem = dcc["root"].name.removesuffix("_baked.usda")
        # the fallback's own normal map when its page is finer than the atlas (issue 22),
        # each LOD after LOD1 its own (in its own MikkTSpace frames)
        own = dcc["report"]["fallback_resolution"] > dcc["report"]["settings"][
            "atlas_resolution"]
        normal = (f"{stem}_normal.png" if not own else f"{stem}_fallback_normal.png"
                  if n == 1 else f"{stem}_fallback_normal_lod{n}.png")
        assert names == sorted([f"{stem}_basecolor.png", normal,
                                f"{stem}_roughness_lod{n}.png"])
        for img in images:
            on_disk = read_pixels(dcc["root"].parent / img["image"])[0]
            assert img["has_pixels"] and img["size"] == [on_disk.shape[1], on_disk.shape[0]]
            assert img["packed"] == (suffix == "usdz")


def test_renders_of_the_lods_match_the_original(dcc):
    files = dcc["got"]["files"]
    ref = files["original"]["png"]
    # deterministic renderer, same meshes: the root renders exactly as the original
    same = compare_renders(ref, files["root"]["png"])
    assert same["mad"] == 0.0 and same["iou"] == 1.0
    lod1 = compare_renders(ref, files["lod1usdz"]["png"])
    # .usdc and .usdz of one LOD are one scene to Blender (textures beside vs packed)
    assert compare_renders(files["lod1usdc"]["png"], files["lod1usdz"]["png"])["mad"] == 0.0
    assert lod1["iou"] >= IOU_MIN, lod1
    assert lod1["mad"] <= MAD_MAX, (lod1, f"renders in {dcc['renders']}")


def test_teapot_lod1_matches_the_original_as_blender_smooths_it(dcc):
    # the Teapot bakes from its limit surface: its LOD1 against the original rendered with
    # Blender's subdivision (measured 0.0141; baked as its cage 0.0191, benchmarks/
    # subdivision.py); the bar is the acceptance's 0.02
    if dcc["name"] != "teapot":
        pytest.skip("the cylinder is not a subdivision surface")
    files = dcc["got"]["files"]
    c = compare_renders(files["original_subdiv"]["png"], files["lod1usdz"]["png"])
    assert c["iou"] >= IOU_MIN and c["mad"] <= 0.02, (c, f"renders in {dcc['renders']}")
