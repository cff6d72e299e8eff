"""A bake with the lobe class (BakeSettings.lobe_class="validated", `texelbake.cpm.lobe_class`)
end to end on the shared Teapot, a smooth-shaded glossy asset: the report counts lobe texels
with their held-out SNR, the payload carries their lobe variances and passes stock
validation, and the cpm mode reads them back and shades the object. Nothing is tuned to the
asset: the checks are what any bake with lobes must pass."""

from __future__ import annotations

import json

import numpy as np
import pytest

from tests.helpers.usd_validation import stock_errors
from tests.pipeline.test_real_assets import _asset


@pytest.fixture(scope="module")
def baked_lobes(tmp_path_factory):
    from schemas.settings import BakeSettings
    from texelbake.pipeline.run import bake

    src = _asset("teapot")
    out = tmp_path_factory.mktemp("lobes")
    settings = BakeSettings(atlas_resolution=64, shard_texels=16, samples_per_texel=16,
                            n_light_dirs=16, n_view_dirs=16, n_heldout=64, c_max=8,
                            n_trials=2, avis_resolution=16, mesh_levels=1,
                            lobe_class="validated")
    return bake(src, out / "baked", settings, progress=False)


def test_the_report_counts_lobes_and_their_held_out_snr(baked_lobes):
    report = json.loads((baked_lobes.parent / "report.json").read_text())
    level0 = report["levels"][0]["classes"]
    assert level0["lobe"]["texels"] > 0
    assert 1.0 <= level0["lobe"]["points_mean"] <= 16.0
    # kept at eps_db on their own validation pairs; the held-out pairs are another sample
    assert level0["lobe"]["snr_heldout_db"]["p50"] >= 20.0


def test_the_payload_carries_the_lobes_and_cpm_shades_them(baked_lobes):
    from texelbake.render.report import render
    from texelbake.render.scene import load_scene

    assert stock_errors(baked_lobes) == {str(baked_lobes): []}
    pts = load_scene(baked_lobes).points(0)
    assert pts["var"] is not None and np.any(pts["var"] > 0)
    gt = render(baked_lobes, "gt", width=48, height=48, spp=4, camera="lod").image
    cpm = render(baked_lobes, "cpm", width=48, height=48, spp=4, camera="lod").image
    lit = gt.sum(axis=2) > 0
    assert np.isfinite(cpm).all() and lit.mean() > 0.01
    assert (cpm.sum(axis=2)[lit] > 0).mean() > 0.9
