"""Assets as studios ship them, in Blender (tests/helpers/studio_cases.py): a cut-out card, a
dome-lit box and a subdivision surface, each baked at a 16² atlas with a light CPM, its LOD1
exported (.usdz) and rendered by Blender 5.0.1's importer and Cycles beside the original
(tests/blender/import_render.py: one camera and sun, 160 px, 32 samples, deterministic).

The bar is the LODs' (tests/dcc/test_blender_import.py says why): IoU >= 0.95 and an
object-pixel mean absolute difference <= 0.10. The subdivision surface's original is imported
with `import_subdivision` on (Blender's Subdivision Surface modifier, render level 2, limit
surface: how Blender smooths it; at its defaults the importer shows the cage). The harness
replaces the files' lights with its own sun, so the dome-lit case checks the bake of an asset
whose only light is a dome (texelbake's dome lighting itself is checked against closed forms in
tests/asset/test_dome.py, and against Cycles rendering the dome in tests/dcc/test_dome_light.py). The cut-out's LOD1 carries the bake's opacity map (the uncut
fraction of each texel) with threshold 0.5: without it the card renders as an opaque quad
(IoU 0.87).
"""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.helpers.dcc import compare_renders, import_and_render, keep_artifacts, side_by_side
from tests.helpers.studio_cases import write_cutout_card, write_dome_lit, write_subdivision_cube

pytestmark = [pytest.mark.dcc, pytest.mark.slow]  # Blender and Cycles: not for test-fast

SETTINGS = {"atlas_resolution": 16, "samples_per_texel": 8, "n_light_dirs": 8,
            "n_view_dirs": 8, "n_heldout": 16, "c_max": 8}
IOU_MIN, MAD_MAX = 0.95, 0.10
CASES = {"cutout": write_cutout_card, "dome": write_dome_lit, "subdivision": write_subdivision_cube}


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    """Every case baked and exported, then all originals and LOD1s rendered in one Blender
    run (one process start)."""
    from schemas.settings import BakeSettings
    from texelbake.pipeline.run import bake
    from texelbake.usd.export import export_lod

    d = tmp_path_factory.mktemp("studio_cases")
    files, options, roots = {}, {}, {}
    for name, write in CASES.items():
        src = write(d / name)
        root = bake(src, d / name / "out", BakeSettings(**SETTINGS), progress=False)
        roots[name] = root
        files[f"{name}_original"] = src
        files[f"{name}_lod1"] = export_lod(root, 1, d / name / "lod1.usdz")
    options["subdivision_original"] = {"import_subdivision": True}
    renders = d / "renders"
    got = import_and_render(files, renders, resolution=160, samples=32, options=options)
    pngs = {k: Path(v["png"]) for k, v in got["files"].items()}
    for name in CASES:
        side_by_side([pngs[f"{name}_original"], pngs[f"{name}_lod1"]], renders / f"{name}.png")
    keep_artifacts(sorted(renders.glob("*.png")), "dcc/studio_cases")
    return {"pngs": pngs, "roots": roots, "renders": renders}


@pytest.mark.parametrize("name", sorted(CASES))
def test_lod1_in_blender_matches_the_original(rendered, name):
    c = compare_renders(rendered["pngs"][f"{name}_original"], rendered["pngs"][f"{name}_lod1"])
    assert c["iou"] >= IOU_MIN, (c, f"renders in {rendered['renders']}")
    assert c["mad"] <= MAD_MAX, (c, f"renders in {rendered['renders']}")


def test_the_cutout_lod_carries_an_opacity_map(rendered):
    from pxr import Usd, UsdShade

    stage = Usd.Stage.Open(str(rendered["roots"]["cutout"]))
    surf = UsdShade.Shader(stage.GetPrimAtPath("/Root/Baked/Looks/BakedPreview/PreviewSurface"))
    assert surf, [str(p.GetPath()) for p in stage.Traverse()][:40]
    assert surf.GetInput("opacityThreshold").Get() == pytest.approx(0.5)
    assert surf.GetInput("opacity").HasConnectedSource()
