"""The srf farm stage (issue 14, item 6): a capture sharded by camera in the artifact store,
finished by srf_top, exported beside the baked USD where the srf mode finds it."""

from __future__ import annotations

import json

import numpy as np
import pytest

from schemas.settings import BakeSettings
from texelbake.errors import SettingsError
from texelbake.pipeline.plan import plan_bake
from texelbake.pipeline.run import bake, run_shard
from texelbake.render.frame import render_frame
from texelbake.render.scene import load_scene
from texelbake.srf.capture import capture
from texelbake.srf.store import open_store
from texelbake.testscenes import write_scene

SRF = {"srf": True, "srf_cameras": 5, "srf_lights": 2, "srf_size": 12, "srf_spp": 1,
       "srf_shard_cameras": 2}
SMALL = {"atlas_resolution": 32, "samples_per_texel": 8, "n_light_dirs": 8, "n_view_dirs": 8,
         "n_heldout": 4, "c_max": 8, "avis_resolution": 4}


def test_plan_shards_the_capture_by_camera(tmp_path):
    src = write_scene("cylinder", tmp_path / "c.usda", size="small")
    plan = plan_bake(src, BakeSettings(**SMALL, **SRF))
    assert plan.stage("srf").n_shards == 3 and plan.stage("srf").queue == "render"
    assert plan.stage("srf_top").depends_on == ("srf",)
    assert "srf_top" in plan.stage("export").depends_on
    assert "srf" in {s for s, _ in plan_bake(src, BakeSettings(**SMALL)).skipped}
    with pytest.raises(SettingsError, match="shard 3"):
        run_shard(tmp_path / "w", src, BakeSettings(**SMALL, **SRF), "srf", 3)


def test_sharded_capture_equals_the_one_process_capture_and_renders(tmp_path):
    src = write_scene("cylinder", tmp_path / "c.usda", size="small")
    settings = BakeSettings(**SMALL, **SRF)
    root = bake(src, tmp_path / "baked", settings, progress=False)
    store = open_store(root.parent / "srf")
    assert (store.n_cameras, store.n_lights, store.width) == (5, 2, 12)
    assert json.loads((root.parent / "report.json").read_text())["srf"]["cameras"] == 5
    # the shards' blocks are exactly those of one capture of the same rig
    scene = load_scene(root)
    ref = capture(scene.asset, tmp_path / "one", cameras=store.cameras,
                  light_dirs=store.light_dirs, spp=1, seed=settings.seed)
    for c in range(5):
        for j in range(2):
            assert (store.block_path(c, j).read_bytes() == ref.block_path(c, j).read_bytes())
    # a rerun of a shard is harmless ("already there" is success)
    run_shard(tmp_path / "baked" / ".work", src, settings, "srf", 1)
    res = render_frame(scene, "srf", scene.default_camera(16, 16), 1)
    assert res.coverage.sum() > 10 and np.isfinite(res.image).all()
