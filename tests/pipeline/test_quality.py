"""The quality gate (issue 22, item 2; texelbake.stages.quality): the report's pass/fail per LOD and
per CPM level, `texelbake bake`'s exit status 3 naming what missed, `--accept-below-target`."""

from __future__ import annotations

import json

import pytest

CHEAP = {"samples_per_texel": 4, "n_light_dirs": 4, "n_view_dirs": 4, "n_heldout": 8,
         "c_max": 4, "avis_resolution": 4}


@pytest.fixture(scope="module")
def cylinder(tmp_path_factory):
    from texelbake.testscenes import write_scene

    d = tmp_path_factory.mktemp("quality")
    return d, write_scene("cylinder", d / "cylinder.usda", "small")


def _bake(d, src, name, capsys, *extra, **gate):
    from texelbake.cli import main

    settings = d / f"{name}.json"
    settings.write_text(json.dumps({**CHEAP, **gate}))
    capsys.readouterr()
    # one artifact store for every run: the gate's targets change no stage output, so
    # later runs only re-export (stages.context.LAYOUT_ONLY)
    code = main(["bake", str(src), "-o", str(d / name), "-q", "-j", "1", "--settings",
                 str(settings), *extra])
    out = capsys.readouterr()
    report = json.loads((d / name / "report.json").read_text())
    return code, out.err, report


def test_a_bake_within_its_targets_exits_0_and_says_so(cylinder, capsys):
    d, src = cylinder
    code, err, report = _bake(d, src, "lax", capsys, gate_snr_median_db=-200.0,
                              gate_snr_p5_db=-200.0, gate_avis_rel_error=10.0)
    q = report["quality"]
    assert code == 0 and err == "" and q["passed"] and q["missed"] == []
    # a check per LOD (its Hausdorff bound) and three per CPM level with samples
    whats = [c["what"] for c in q["checks"]]
    n_lods = len(report["lods"]["levels"])
    assert [w for w in whats if w.startswith("LOD")] == [
        f"LOD{i} Hausdorff distance" for i in range(1, n_lods + 1)]
    gated = [lv["level"] for lv in report["levels"] if lv["texels_with_samples"]]
    assert len(whats) == n_lods + 3 * len(gated)
    for c in q["checks"]:
        assert c["passed"]


def test_a_missed_target_exits_3_naming_the_level(cylinder, capsys):
    from texelbake.stages.quality import QUALITY_EXIT

    d, src = cylinder
    code, err, report = _bake(d, src, "strict", capsys, gate_snr_median_db=199.0,
                              gate_snr_p5_db=-200.0, gate_avis_rel_error=10.0)
    assert code == QUALITY_EXIT == 3
    q = report["quality"]
    assert not q["passed"]
    # every gated level's median misses 199 dB, and only the median checks miss
    levels = [lv["level"] for lv in report["levels"] if lv["texels_with_samples"]]
    medians = {lv["level"]: lv["snr_heldout_db"]["p50"] for lv in report["levels"]}
    assert q["missed"] == [
        f"CPM level {lvl} held-out SNR median (dB) is {medians[lvl]:.4g}, target at least 199"
        for lvl in levels]
    for m in q["missed"]:
        assert f"quality target missed: {m}" in err


def test_accept_below_target_exits_0_but_still_reports(cylinder, capsys):
    d, src = cylinder
    code, err, report = _bake(d, src, "accepted", capsys, "--accept-below-target",
                              gate_snr_median_db=-200.0, gate_snr_p5_db=-200.0,
                              gate_avis_rel_error=1e-9)
    assert code == 0
    q = report["quality"]
    assert not q["passed"] and all("a_vis relative error" in m for m in q["missed"])
    assert "accepted (--accept-below-target)" in err


def test_a_lod_outside_its_bound_is_named(cylinder, capsys):
    # the gate reads the report: the same bake's LOD1 against a bound a tenth of its distance
    from schemas.settings import BakeSettings
    from texelbake.stages.quality import quality_gate

    d, src = cylinder
    _, _, report = _bake(d, src, "lod", capsys, gate_snr_median_db=-200.0,
                         gate_snr_p5_db=-200.0, gate_avis_rel_error=10.0)
    lod1 = report["lods"]["levels"][0]
    assert lod1["hausdorff"] > 0
    lod1["bound"] = lod1["hausdorff"] / 10
    q = quality_gate(report, BakeSettings(gate_snr_median_db=-200.0, gate_snr_p5_db=-200.0,
                                          gate_avis_rel_error=10.0))
    assert q["missed"] == [f"LOD1 Hausdorff distance is {lod1['hausdorff']:.4g}, target at "
                           f"most {lod1['bound']:.4g}"]
