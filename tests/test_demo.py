"""`texelbake demo` (what `make demo` runs): bakes generated scenes in one process and writes
the previews of every mode next to each bake (issue 4), btf included (issue 5)."""

from __future__ import annotations

import json

import numpy as np


def test_demo_writes_previews_of_every_mode_next_to_the_bake(tmp_path, capsys):
    from texelbake.cli import main
    from texelbake.imageio import read_image

    out = tmp_path / "demo"
    # the demo's own settings, made smaller for CI; the scenes are the small ones as in
    # `make demo`
    rc = main(["demo", "--out", str(out), "--scenes", "cylinder",
               "--set", "atlas_resolution=16", "--set", "samples_per_texel=4",
               "--set", "n_light_dirs=8", "--set", "n_view_dirs=8", "--set", "n_heldout=4",
               "--set", "c_max=8"])
    assert rc == 0
    bake_dir = out / "cylinder"
    assert list(bake_dir.glob("*_baked.usda"))
    prev = bake_dir / "previews"
    report = json.loads((prev / "render_report.json").read_text())
    modes = {"gt", "cpm", "normalmap", "equal-time", "btf"}
    for view, prefix in ((report, ""), (report["far"], "far_")):
        assert set(view["modes"]) == modes
        for m in modes:
            img = read_image(prev / f"{prefix}{m}.exr")
            # every mode draws the object: lit pixels, finite values, none negative
            assert np.isfinite(img).all() and img.min() >= 0.0 and img.max() > 0.01, m
            assert (prev / f"{prefix}{m}.png").is_file()
            assert isinstance(view["modes"][m]["psnr_db"], float)
    for f in ("cp_density_atlas.png", "cp_density_model.png", "speed_error.png",
              "mip_levels.png", "far_mip_levels.png"):
        assert (prev / f).is_file(), f
    assert "previews:" in capsys.readouterr().out
