"""A skinned character's LOD1 in Blender follows the rig (tests/helpers/skel_rigs.py: two meshes,
joint subsets, geomBindTransforms, a rest pose that is not the bind pose, a translated
SkelRoot): baked at a 16² atlas with a light CPM, LOD1 exported (.usdz), and the original and
LOD1 imported by Blender 5.0.1's USD importer (its skeleton as an armature, the meshes bound by
armature modifiers) and rendered by Cycles (tests/blender/import_render.py) at the rest frame
and at frame 18, where the knee is bent by 80° and the hip has turned and moved.

The bar is the LODs' (tests/dcc/test_blender_import.py says why): IoU >= 0.95 and an
object-pixel mean absolute difference <= 0.10, at both frames. Blender places a skinned mesh by
its parent prim and its geomBindTransform (not by the skeleton's transform, as UsdSkel does):
with the LODs' SkelRoot at the origin instead of where the skeleton stands, LOD1 rendered
shifted by the SkelRoot's offset (IoU 0.0 at the rest frame, 0.04 at frame 18).
"""

from __future__ import annotations

import warnings
from pathlib import Path

import pytest

from tests.helpers.dcc import compare_renders, import_and_render, keep_artifacts, side_by_side
from tests.helpers.skel_rigs import write_rig

pytestmark = [pytest.mark.dcc, pytest.mark.slow]  # Blender and Cycles: not for test-fast

SETTINGS = {"atlas_resolution": 16, "samples_per_texel": 8, "n_light_dirs": 8,
            "n_view_dirs": 8, "n_heldout": 16, "c_max": 8}
IOU_MIN, MAD_MAX = 0.95, 0.10
FRAMES = (0, 18)


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    from schemas.settings import BakeSettings
    from texelbake.pipeline.run import bake
    from texelbake.usd.export import export_lod

    d = tmp_path_factory.mktemp("skel_rig")
    src = write_rig(d / "rig.usda")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        root = bake(src, d / "out", BakeSettings(**SETTINGS), progress=False)
    lod1 = export_lod(root, 1, d / "lod1.usdz")
    files, frames = {}, {}
    for f in FRAMES:
        files[f"original_{f}"], files[f"lod1_{f}"] = src, lod1
        frames[f"original_{f}"] = frames[f"lod1_{f}"] = f
    renders = d / "renders"
    got = import_and_render(files, renders, resolution=160, samples=32, scene_frames=frames)
    pngs = {k: Path(v["png"]) for k, v in got["files"].items()}
    side_by_side([pngs[k] for k in sorted(pngs)], renders / "skel_rig.png")
    keep_artifacts(sorted(renders.glob("*.png")), "dcc/skel_rig")
    return {"pngs": pngs, "files": got["files"], "renders": renders}


@pytest.mark.parametrize("frame", FRAMES)
def test_lod1_in_blender_follows_the_rig(rendered, frame):
    made = rendered["files"][f"lod1_{frame}"]
    assert made["frame_current"] == frame
    c = compare_renders(rendered["pngs"][f"original_{frame}"], rendered["pngs"][f"lod1_{frame}"])
    assert c["iou"] >= IOU_MIN, (c, f"renders in {rendered['renders']}")
    assert c["mad"] <= MAD_MAX, (c, f"renders in {rendered['renders']}")


def test_the_rig_moved_between_the_frames(rendered):
    c = compare_renders(rendered["pngs"]["original_0"], rendered["pngs"][f"original_{FRAMES[1]}"])
    assert c["iou"] < 0.5  # the pose at frame 18 is not the rest pose
