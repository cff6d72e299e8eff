"""The studio cases baked and checked against Blender (bpy 5.0.1, its own USD importer and
Cycles, as tests/dcc/test_blender_import.py): each small asset of tests.helpers.studio_assets
is baked with light CPM settings, its LOD1 exported, and Blender's render of LOD1 compared with
Blender's render of the original from one camera and sun.

- the kit (swatches under UVs in -37.8..37.8, no st input, no wrap modes): Blender tiles them,
  and so does the bake (read as "black", ingest gave black base colours:
  tests/asset/test_studio_assets.py);
- the car whose unselected variants name a file outside the asset and one missing from it:
  Blender and the bake both show the selected variant;
- the MaterialX reference: the reference is Blender's render of the same material written as
  a UsdPreviewSurface (the checker box), whatever Blender's importer makes of the `.mtlx`;
- the missing texture: Blender paints a missing image magenta, so the reference is the box
  with the texture's fallback colour as its constant (what a renderer shows);
- a normal map: the fallback's normal map carries the source's (baked from the samples'
  shading normals, which read it).

The bars are those of tests/dcc/test_blender_import.py (IoU >= 0.95, object-pixel mean
difference <= 0.10, 8-bit display values) and for the same reason: the camera frames the
object in a 160 px image, less than LOD1's switch size. Measured: kit 0.079, variants 0.089,
MaterialX 0.075, missing texture 0.090, IoU 1.0 each (Blender renders the `.mtlx` reference
itself black: 0.31 from the same material as UsdPreviewSurface).
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from tests.helpers.dcc import compare_renders, import_and_render, keep_artifacts, side_by_side
from tests.helpers.studio_assets import (
    fallback_colour_box,
    kit_asset,
    mtlx_asset,
    normal_mapped_box,
    textured_box,
    wheel_variants_asset,
)

pytestmark = [pytest.mark.dcc, pytest.mark.slow]

LIGHT = {"samples_per_texel": 8, "n_light_dirs": 8, "n_view_dirs": 8, "n_heldout": 16,
         "c_max": 8}
IOU_MIN = 0.95
MAD_MAX = 0.10


def _build(case: str, d: Path) -> tuple[Path, Path]:
    """(the asset to bake, the file whose Blender render is the reference)."""
    if case == "kit":
        src = kit_asset(d / "kit")
        return src, src
    if case == "variants":
        src, _ = wheel_variants_asset(d / "car")
        return src, src
    if case == "mtlx":
        return mtlx_asset(d / "rook"), textured_box(d / "same_as_preview")
    if case == "normalmap":
        src = normal_mapped_box(d / "bumps")
        return src, src
    # missing: the reference shows the fallback colour as the constant
    fallback = (0.2, 0.4, 0.6)
    return (textured_box(d / "missing", "./gone.png", fallback=(*fallback, 1.0)),
            fallback_colour_box(d / "ref", fallback))


@pytest.fixture(scope="module", params=["kit", "variants", "mtlx", "missing", "normalmap"])
def studio(request, tmp_path_factory):
    from schemas.settings import BakeSettings
    from texelbake.pipeline.run import bake
    from texelbake.usd.export import export_lod

    case = request.param
    d = tmp_path_factory.mktemp(f"studio_{case}")
    src, ref = _build(case, d)
    root = bake(src, d / "out", BakeSettings(**LIGHT), progress=False)
    report = json.loads((root.parent / "report.json").read_text())
    lod1 = export_lod(root, 1, d / "export" / "lod1.usdz")
    renders = d / "renders"
    files = {"reference": ref, "original": src, "lod1": lod1}
    if case == "normalmap":  # the box without its map: what a fallback without it shows
        files["flat"] = normal_mapped_box(d / "flat", with_map=False)
    got = import_and_render(files, renders, resolution=160, samples=32)
    side_by_side([Path(got["files"][k]["png"]) for k in ("reference", "original", "lod1")],
                 renders / "row.png")
    keep_artifacts(sorted(renders.glob("*.png")), f"dcc/studio_{case}")
    return {"case": case, "report": report, "got": got, "renders": renders}


def test_lod1_in_blender_matches_blenders_render_of_the_original(studio):
    files = studio["got"]["files"]
    assert files["lod1"]["import"] == ["FINISHED"]
    cmp = compare_renders(files["reference"]["png"], files["lod1"]["png"])
    assert cmp["iou"] >= IOU_MIN, cmp
    assert cmp["mad"] <= MAD_MAX, (cmp, f"renders in {studio['renders']}")


@pytest.mark.parametrize("studio", ["normalmap"], indirect=True)
def test_the_lod1_fallback_carries_the_sources_normal_map(studio):
    # the fallback's normal map is baked from the samples' shading normals, which read the
    # source's normal map: LOD1 shows its stripes (measured: MAD 0.0014 to the original, 0.066
    # to the box without its map)
    files = studio["got"]["files"]
    to_original = compare_renders(files["reference"]["png"], files["lod1"]["png"])
    flat = compare_renders(files["flat"]["png"], files["lod1"]["png"])
    assert to_original["mad"] < 0.5 * flat["mad"], (to_original, flat, studio["renders"])


def test_the_report_lists_what_was_not_read(studio):
    report = studio["report"]
    if studio["case"] == "variants":
        assert [p.split("'")[1] for p in report["unreachable_paths"]] == [
            "../../../wheels/wheelVariants.usda", "./parts/racing_wheels.usda"]
    else:
        assert report["unreachable_paths"] == []
    assert len(report["missing_paths"]) == (studio["case"] == "missing")
