"""Surface reflectance fields, item 6: the `srf` mode of `texelbake render` on a baked asset
(the field captured beside the bake, surfels of the enclosing M1), undeformed and under a
warp through L (`srf`) or without it (`srf-naive`)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from texelbake.cli import main
from texelbake.errors import StageError
from texelbake.render.frame import render_frame
from texelbake.render.scene import load_scene


@pytest.fixture(scope="module")
def baked_cylinder(tmp_path_factory) -> Path:
    from schemas.settings import BakeSettings
    from texelbake.pipeline.run import bake
    from texelbake.testscenes import write_scene

    d = tmp_path_factory.mktemp("cyl")
    src = write_scene("cylinder", d / "cylinder.usda", size="small")
    settings = BakeSettings(atlas_resolution=32, samples_per_texel=8, n_light_dirs=8,
                            n_view_dirs=8, n_heldout=4, c_max=8, avis_resolution=4)
    return bake(src, d / "baked", settings, progress=False)


def test_srf_mode_needs_a_capture_then_renders(baked_cylinder, capsys):
    scene = load_scene(baked_cylinder)
    cam = scene.default_camera(24, 24)
    with pytest.raises(StageError, match="srf-capture"):
        render_frame(scene, "srf", cam, 1)
    assert main(["srf-capture", str(baked_cylinder), "--cameras", "16", "--lights", "6",
                 "--size", "24", "--spp", "1"]) == 0
    assert "16 cameras x 6 lights" in capsys.readouterr().out
    res = render_frame(scene, "srf", cam, 1)
    assert res.mode == "srf" and res.image.shape == (24, 24, 3)
    assert res.coverage.sum() > 20 and res.image.max() > 0
    assert res.extras["block_reads"] <= 16 * 6
    hull = render_frame(scene, "srf", cam, 1, impostor="hull")  # the carved visual hull
    assert hull.coverage.sum() > 20 and np.isfinite(hull.image).all()


def test_cli_renders_srf_undeformed_and_under_a_warp(baked_cylinder, tmp_path, capsys):
    if not (baked_cylinder.parent / "srf" / "srf.json").is_file():
        main(["srf-capture", str(baked_cylinder), "--cameras", "16", "--lights", "6",
              "--size", "24", "--spp", "1"])
    out = tmp_path / "r"
    assert main(["render", str(baked_cylinder), "--modes", "gt,srf", "-o", str(out),
                 "--width", "24", "--height", "24", "--spp", "1", "--ref-spp", "4"]) == 0
    rep = json.loads((out / "render_report.json").read_text())
    assert "srf" in rep["modes"] and np.isfinite(rep["modes"]["srf"]["psnr_db_object"])
    out2 = tmp_path / "w"
    assert main(["render", str(baked_cylinder), "--warp", "bend:angle=60", "--modes",
                 "gt,srf,srf-naive", "-o", str(out2), "--width", "24", "--height", "24",
                 "--spp", "1", "--ref-spp", "4"]) == 0
    rep = json.loads((out2 / "deformed_report.json").read_text())
    assert {"srf", "srf-naive"} <= set(rep["modes"])
    assert "srf-naive" in capsys.readouterr().out
