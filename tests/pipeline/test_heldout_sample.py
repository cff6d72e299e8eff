"""The held-out SNR measured on a seeded sample of texels (BakeSettings.heldout_texels): on a
scene baked both ways, the sampled texels' SNRs are the full measurement's, each level's
sampled median interval covers the full population's median, and the gate reads the
interval."""

from __future__ import annotations

import json

import numpy as np
import pytest

from schemas.settings import BakeSettings
from texelbake.pipeline.run import bake
from texelbake.stages.quality import quality_gate
from texelbake.testscenes import write_scene
from texelbake.usd.read import read_baked

CHEAP = {"atlas_resolution": 32, "shard_texels": 16, "samples_per_texel": 8,
         "n_light_dirs": 8, "n_view_dirs": 8, "n_heldout": 16, "c_max": 8, "n_trials": 2,
         "mesh_levels": 1, "avis_resolution": 8}
SAMPLE = 60


@pytest.fixture(scope="module")
def both(tmp_path_factory):
    d = tmp_path_factory.mktemp("heldout")
    src = write_scene("cylinder", d / "cylinder.usda", "small")
    out = {}
    for name, want in (("full", 0), ("sample", SAMPLE)):  # one store: only cpm differs
        root = bake(src, d / name, BakeSettings(**CHEAP, heldout_texels=want), progress=False,
                    workdir=d / "store")
        out[name] = (read_baked(root), json.loads((root.parent / "report.json").read_text()))
    return out


def test_sampled_texels_and_median_interval(both):
    full, full_rep = both["full"]
    samp, samp_rep = both["sample"]
    sampled_levels = 0
    for lv, (lf, ls) in enumerate(zip(full.levels, samp.levels, strict=True)):
        f, s = lf["texel_snr_heldout"], ls["texel_snr_heldout"]
        valid = lf["texel_valid"]
        np.testing.assert_array_equal(valid, ls["texel_valid"])  # the fit does not change
        meas = valid & np.isfinite(s)
        assert np.all(np.isfinite(f[valid]))
        assert meas.sum() == min(SAMPLE, valid.sum()) or meas.sum() <= SAMPLE
        # the sampled texels' SNRs are the full measurement's (only the sums' batching
        # differs: float64 round-off, far below 1e-3 dB)
        np.testing.assert_allclose(s[meas], f[meas], atol=1e-3)
        held = samp_rep["levels"][lv]["snr_heldout_db"]
        pop = full_rep["levels"][lv]["snr_heldout_db"]
        if meas.sum() < valid.sum():
            sampled_levels += 1
            lo, hi = held["p50_ci"]
            assert lo <= pop["p50"] <= hi, (lv, lo, pop["p50"], hi)
            assert lo < hi
        else:  # every texel measured: the interval is the value
            assert held["p50_ci"] == [held["p50"], held["p50"]]
    assert sampled_levels >= 1  # the sample bit somewhere (level 0: several hundred texels)


def test_gate_reads_the_interval(both):
    _, rep = both["sample"]
    lv = next(lv for lv in rep["levels"]
              if lv["snr_heldout_db"].get("p50_ci", [0, 0])[0]
              < lv["snr_heldout_db"].get("p50_ci", [0, 0])[1])
    held = lv["snr_heldout_db"]
    lo, hi = held["p50_ci"]
    rep1 = {"levels": [lv]}
    between = BakeSettings(**CHEAP, gate_snr_median_db=(held["p50"] + hi) / 2 if hi > held["p50"]
                           else hi, gate_snr_p5_db=-200.0, gate_avis_rel_error=10.0)
    # a target above the point estimate but within the interval: not established as missed
    g = quality_gate(rep1, between)
    med = next(c for c in g["checks"] if "median" in c["what"])
    assert med["passed"] and med["judged_on"] == "ci_high" and med["ci"] == [lo, hi]
    above = BakeSettings(**CHEAP, gate_snr_median_db=min(hi + 1.0, 200.0),
                         gate_snr_p5_db=-200.0, gate_avis_rel_error=10.0)
    assert not quality_gate(rep1, above)["passed"]
