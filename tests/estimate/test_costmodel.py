"""The cost model (issue 15): the O(log N) prediction before the geometry against the same
model on an explicit per-texel sample histogram, its scaling laws, and the bake's report and
the job API carrying it."""

from __future__ import annotations

import numpy as np
import pytest

from schemas.settings import BakeSettings
from texelbake.estimate import costmodel, farmsim


def test_uniform_prediction_equals_the_histogram_of_an_even_fill():
    """Second method: level_sizes pools an explicit (N, N) histogram of spt samples on every
    texel of a full atlas level by level; the O(log N) path assumes the same."""
    n, spt = 32, 64
    s = BakeSettings(atlas_resolution=n, samples_per_texel=spt)
    counts = np.full((n, n), spt)
    fill = costmodel.DEFAULT_FILL
    try:
        costmodel.DEFAULT_FILL = 1.0
        a = costmodel.estimate(s, 2)
    finally:
        costmodel.DEFAULT_FILL = fill
    b = costmodel.estimate(s, 2, counts)
    assert a.texels == b.texels == sum((n >> k) ** 2 for k in range(6))
    assert a.cpm_seconds == pytest.approx(b.cpm_seconds, rel=1e-9)
    for x, y in zip(a.per_level, b.per_level, strict=True):
        assert x["seconds"] == pytest.approx(y["seconds"], rel=1e-9)


def test_scaling_laws():
    s = BakeSettings(atlas_resolution=64)
    one, two = costmodel.estimate(s, 1), costmodel.estimate(s, 2)
    assert two.cpm_seconds == one.cpm_seconds
    assert two.seconds < one.seconds
    # a loaded machine: 10 other runnable processes on 2 cores stretch 2 workers 6x
    loaded = costmodel.estimate(s, 2, load=10.0, cores=2)
    assert loaded.stretch == pytest.approx(6.0) and loaded.seconds == pytest.approx(6 * two.seconds)
    assert costmodel.estimate(s, 2, load=0.0, cores=2).seconds == pytest.approx(two.seconds)
    # four times the direction pairs: R, Grams scale with d, the held-out truth does not
    s4 = BakeSettings(atlas_resolution=64, n_light_dirs=128, n_view_dirs=128)
    r = costmodel.estimate(s4, 1).cpm_seconds / one.cpm_seconds
    assert 2.5 < r < 4.0
    # GGX materials cost more than Lambert / Phong
    assert costmodel.estimate(s, 1, ggx_fraction=1.0).cpm_seconds > \
        costmodel.estimate(s, 1, ggx_fraction=0.0).cpm_seconds
    # a 4096^2 atlas is predicted without an N x N array (fast) and scales ~N^2
    big = costmodel.estimate(BakeSettings(atlas_resolution=4096), 2)
    small = costmodel.estimate(BakeSettings(atlas_resolution=2048), 2)
    assert 3.0 < big.cpm_seconds / small.cpm_seconds < 5.0


def test_sample_counts_histogram():
    geo = {"sample_row": np.array([0, 0, 1, 3]), "sample_col": np.array([0, 0, 2, 3])}
    c = costmodel.sample_counts(geo, 4)
    assert c.shape == (4, 4) and c[0, 0] == 2 and c[1, 2] == 1 and c[3, 3] == 1 and c.sum() == 4


def test_job_status_carries_the_core_estimate():
    """The job API's estimate is the core function's (thin): same seconds, ETA = start +
    seconds once the job started, none before."""
    from datetime import UTC, datetime, timedelta
    from types import SimpleNamespace

    from services.job_view import job_estimate
    from texelbake.estimate import machinespeed

    s = BakeSettings(atlas_resolution=64)
    core = costmodel.estimate(s, 3, speed=machinespeed.this_machine())
    queued = job_estimate(SimpleNamespace(started_at=None, settings_json=s.model_dump_json()), s, 3)
    assert queued.seconds == pytest.approx(core.seconds, abs=0.05) and queued.eta is None
    assert queued.workers == 3 and queued.machine_speed == core.speed["factors"]
    t0 = datetime(2026, 11, 25, 9, 0, tzinfo=UTC)
    running = job_estimate(SimpleNamespace(started_at=t0, settings_json=s.model_dump_json()), s, 3)
    assert running.eta == t0 + timedelta(seconds=core.seconds)


def test_farm_simulation_against_closed_forms():
    """Second method: with no transfers the simulation is list scheduling of equal shards,
    ceil(S / n) rounds; with one worker and a store, every byte and second adds up; a slow store
    makes many workers wait on it (time -> total bytes / bandwidth)."""
    S = 37
    dur = np.full(S, 2.0)
    zero = np.zeros(S)
    for n in (1, 2, 4, 8, 64):
        r = farmsim.simulate_farm(dur, zero, zero, n, bandwidth=1.0)
        assert r.seconds == pytest.approx(np.ceil(S / n) * 2.0)
    r = farmsim.simulate_farm(dur, np.full(S, 10.0), np.full(S, 5.0), 1, bandwidth=5.0,
                                overhead=0.5, startup_bytes=50.0, serial_seconds=3.0,
                                serial_read_bytes=20.0)
    assert r.seconds == pytest.approx(S * (2.0 + 0.5 + 3.0) + 50.0 / 5.0 + 3.0 + 4.0)
    slow = farmsim.simulate_farm(dur, np.full(S, 100.0), zero, 32, bandwidth=10.0)
    assert slow.seconds == pytest.approx(S * 10.0 + 2.0)
    # oversubscribed: 4 workers on 2 cores stretch every shard 2x
    over = farmsim.simulate_farm(dur, zero, zero, 4, bandwidth=1.0, cores=2)
    assert over.seconds == pytest.approx(np.ceil(S / 4) * 4.0)


def test_atlas_trade_prices_the_resolution_lod1_asks_for():
    """The report's CPM atlas trade (issue 22): the same cost model at both resolutions, so a
    4x larger atlas side costs more (about 16x the texels), an equal one the same."""
    from texelbake.estimate.costmodel import atlas_trade, estimate

    s = BakeSettings(atlas_resolution=16)
    lod = {"atlas_mesh": {"atlas_resolution_for_lod1": 64, "cpm_max_px": 40.0}}
    t = atlas_trade(s, lod)
    assert t["resolution"] == 16 and t["for_lod1"] == 64 and t["max_px"] == 40.0
    assert t["estimated_seconds"] == estimate(s).seconds
    assert t["estimated_seconds_for_lod1"] == estimate(
        BakeSettings(atlas_resolution=64)).seconds
    # every term but the process start-up (7 s) scales with the texels, 16x here
    assert t["estimated_seconds_for_lod1"] - 7.0 > 8 * (t["estimated_seconds"] - 7.0)
    assert t["cost_ratio"] == t["estimated_seconds_for_lod1"] / t["estimated_seconds"]
    assert t["projected_seconds_for_lod1"] is None
    projected = atlas_trade(s, lod, measured_seconds=50.0)["projected_seconds_for_lod1"]
    assert projected == pytest.approx(50.0 * t["cost_ratio"])
    same = atlas_trade(s, {"atlas_mesh": {"atlas_resolution_for_lod1": 16}})
    assert same["estimated_seconds_for_lod1"] == same["estimated_seconds"]
    assert atlas_trade(s, {})["estimated_seconds_for_lod1"] is None


def test_levels_above_a_tile_are_one_serial_shard():
    """The levels coarser than a shard's tile run as one shard (`run_cpm_top`) on one worker,
    except their dense samples' sums (a_vis and the held-out truth, the held term), which the
    tile shards make: more workers divide the tiles' levels and those sums only. By hand from
    the per-level prediction: on the uniform prediction every level holds all N^2 spt samples
    (each measured in full: heldout_samples 0)."""
    s = BakeSettings(atlas_resolution=64, shard_texels=8, heldout_samples=0)
    one, two = costmodel.estimate(s, 1, cores=2), costmodel.estimate(s, 2, cores=2)
    top = sum(lv["seconds"] for lv in two.per_level if lv["level"] >= 4)  # 8 = 0b1000: L0-3 tile
    c = costmodel.Coefficients()
    held = (1.0 + (c.held_ggx - 1.0) * 0.5) * c.held * 64 ** 2 * s.samples_per_texel \
        * s.n_heldout * 3  # levels 4, 5, 6
    assert two.cpm_serial_seconds == pytest.approx(top - held, rel=1e-9)
    assert 0 < held < top
    # one worker -> two: the tiles' levels, the top levels' sums and a_vis halve, the serial
    # levels do not; one process term either way (one pool serves every sharded stage)
    saved = (two.cpm_seconds - two.cpm_serial_seconds + two.avis_seconds) / 2.0
    assert one.seconds - two.seconds == pytest.approx(saved, rel=1e-9)


def test_the_load_reading_counts_other_processes_not_this_ones_threads(tmp_path):
    """The estimate's load is other processes' runnable tasks: a busy child process is counted
    (a CPU-bound loop is in state R whether it runs or waits for a core), this process's own
    busy threads are not; a fake procfs pins the parsing (a comm with spaces and parentheses)."""
    import os
    import subprocess
    import sys
    import threading

    from texelbake.pipeline.estimate import _other_runnable, runnable_tasks

    stop = threading.Event()

    def busy() -> None:
        while not stop.is_set():
            pass

    spin = threading.Thread(target=busy, daemon=True)
    child = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        spin.start()
        # the child counts once it runs its loop
        for _ in range(100):  # a bounded wait for the child's first reading
            seen = runnable_tasks(exclude_pid=os.getpid())
            if any(pid == child.pid for pid, _ in seen):
                break
        assert any(pid == child.pid for pid, _ in seen)
        assert not any(pid == os.getpid() for pid, _ in seen)
        assert any(pid == os.getpid() for pid, _ in runnable_tasks())  # the spinning thread
        assert _other_runnable(samples=3, interval=0.01) >= 1.0
    finally:
        stop.set()
        child.kill()
        child.wait()
    for pid, tid, state in ((10, 10, "R"), (10, 11, "S"), (12, 12, "R"), (13, 13, "D")):
        d = tmp_path / str(pid) / "task" / str(tid)
        d.mkdir(parents=True)
        (d / "stat").write_text(f"{tid} (a (b) c) {state} 1 2 3\n")
    (tmp_path / "self").mkdir()
    assert sorted(runnable_tasks(proc=tmp_path)) == [(10, 10), (12, 12)]
    assert runnable_tasks(exclude_pid=12, proc=tmp_path) == [(10, 10)]


def test_machine_speed_scales_each_term_by_its_kind_of_work():
    """`estimate(speed=...)` multiplies each coefficient by its kind of work's factor: with
    one coefficient nonzero at a time the estimate's part grows by exactly that factor (by
    hand); every seconds field of `Coefficients` has a kind of work (a new one must too)."""
    from dataclasses import fields, replace

    from texelbake.estimate.costmodel import Coefficients
    from texelbake.estimate.machinespeed import PART_OF, MachineSpeed

    ratios = {"brdf_ggx", "held_ggx", "btf_cell", "widened"}
    assert {f.name for f in fields(Coefficients)} == set(PART_OF) | ratios
    factors = {"grid": 2.0, "blas": 3.0, "rays": 5.0, "python": 7.0}
    speed = MachineSpeed(factors=factors, seconds=dict.fromkeys(factors, 1.0))
    zero = Coefficients(**{f.name: (1.0 if f.name in ratios else 0.0)
                           for f in fields(Coefficients)})
    s = BakeSettings(atlas_resolution=32, avis_coarse="dense")  # every term priced
    for name, part in PART_OF.items():
        one = replace(zero, **{name: getattr(Coefficients(), name) or 1e-9})
        base = costmodel.estimate(s, 1, coef=one, ggx_fraction=0.0, lobe_tried=0.5)
        fast = costmodel.estimate(s, 1, coef=one, ggx_fraction=0.0, speed=speed,
                                  lobe_tried=0.5)
        assert base.seconds > 0, name
        # a mix of kinds (R's entries: the BRDF grid, rays and per-call work) by its weights
        want = (sum(w * factors[p] for p, w in part.items()) if isinstance(part, dict)
                else factors[part])
        assert fast.seconds == pytest.approx(want * base.seconds, rel=1e-12), name
        assert fast.speed == speed.to_dict() and base.speed is None
    # R's mix: its weights are shares (they add up to 1), so a machine of one speed in every
    # kind of work scales R by that speed; by hand at these factors
    from texelbake.estimate.machinespeed import R_MIX

    assert sum(R_MIX.values()) == pytest.approx(1.0, rel=1e-12)
    assert speed.factor("r_entry") == pytest.approx(
        (1.60 * 2.0 + 1.04 * 5.0 + 2.28 * 7.0) / 4.92, rel=1e-12)
    # the ratio fields are not seconds: the GGX share of R is priced the same on any machine
    c = Coefficients().scaled(speed)
    assert (c.brdf_ggx, c.held_ggx) == (Coefficients().brdf_ggx, Coefficients().held_ggx)


def test_machine_speed_measurement(monkeypatch):
    """The reference workload's factors are its seconds here over the reference seconds;
    a factor outside FACTOR_RANGE (a broken timing) is clamped and flagged; the environment
    switch returns the reference machine without timing anything."""
    from texelbake.estimate import machinespeed

    m = machinespeed.measure(repeats=1)
    lo, hi = machinespeed.FACTOR_RANGE
    for k, f in m.factors.items():
        assert m.seconds[k] > 0 and np.isfinite(f)
        assert f == pytest.approx(np.clip(m.seconds[k] / machinespeed.REFERENCE[k], lo, hi))
    monkeypatch.setattr(machinespeed, "REFERENCE", dict.fromkeys(machinespeed.REFERENCE, 1e-09))
    slow = machinespeed.measure(repeats=1)
    assert slow.clamped and all(f == hi for f in slow.factors.values())
    monkeypatch.setenv("TEXELBAKE_MACHINE_SPEED", "1")
    ref = machinespeed.measure()
    assert ref is machinespeed.REFERENCE_SPEED and set(ref.factors.values()) == {1.0}


def test_the_cell_table_is_priced_at_level_0():
    """btf_table "cell" adds (1 + draws) BRDF grids over level 0's (sample, pair) entries, at
    btf_cell x r_entry each (by hand from the uniform sizes); "point" and btf off add nothing."""
    c = costmodel.Coefficients()
    point = BakeSettings(atlas_resolution=32, btf=True)
    off = BakeSettings(atlas_resolution=32, texel_classes="points",  # a BTF bake classes none
                       point_lobe=point.point_lobe)
    cell = BakeSettings(atlas_resolution=32, btf=True, btf_table="cell", btf_cell_draws=6)
    m, _, mult = costmodel._uniform_sizes(32, point.samples_per_texel, point.c_max)[0]
    d = point.n_light_dirs * point.n_view_dirs
    brdf = 1.0 + (c.brdf_ggx - 1.0) * 0.5
    extra = mult * 7 * c.btf_cell * brdf * c.r_entry * float((m * d).sum())
    extra *= c.widened if cell.point_lobe == "widened" else 1.0  # the fit's factor (default)
    e_point, e_cell = (costmodel.estimate(s, 2) for s in (point, cell))
    assert costmodel.estimate(off, 2).cpm_seconds == e_point.cpm_seconds
    assert e_cell.cpm_seconds - e_point.cpm_seconds == pytest.approx(extra, rel=1e-9)
    assert e_cell.per_level[1] == e_point.per_level[1]


def test_widened_lobes_price_the_fit_at_its_measured_ratio():
    """point_lobe "widened" multiplies every level's fit seconds by `widened` and nothing
    else (by hand against the narrow estimate)."""
    c = costmodel.Coefficients()
    narrow = BakeSettings(atlas_resolution=32, point_lobe="narrow")
    wide = BakeSettings(atlas_resolution=32, point_lobe="widened")
    e_n, e_w = (costmodel.estimate(s, 2) for s in (narrow, wide))
    for a, b in zip(e_n.per_level, e_w.per_level, strict=True):
        assert b["seconds"] == pytest.approx(c.widened * a["seconds"], rel=1e-12)
    assert e_w.cpm_seconds == pytest.approx(c.widened * e_n.cpm_seconds, rel=1e-9)
    assert e_w.avis_seconds == e_n.avis_seconds


def _only(**nonzero):
    """Coefficients with every seconds field 0 but `nonzero` (the ratio fields 1)."""
    from dataclasses import fields

    ratios = {"brdf_ggx", "held_ggx", "btf_cell", "widened"}
    return costmodel.Coefficients(**{f.name: nonzero.get(f.name, 1.0 if f.name in ratios
                                                         else 0.0)
                                     for f in fields(costmodel.Coefficients)})


def test_classed_levels_price_the_classing_and_the_fitted_share():
    """By hand on an even 8^2 atlas of 10 samples a texel: each classed level costs `classify`
    x its samples x (N_i + N_o), every level; the fit's terms (here R alone) are paid by the
    `fitted` share of a classed level's texels, in full above the classed levels and without a
    measured share; texel_classes "points" classes nothing."""
    n, spt = 8, 10
    s = BakeSettings(atlas_resolution=n, shard_texels=8, samples_per_texel=spt,
                     classed_levels=2, c_max=64)
    counts = np.full((n, n), spt)
    d = s.n_light_dirs * s.n_view_dirs
    cls = costmodel.estimate(s, 1, counts, coef=_only(classify=1e-6), ggx_fraction=0.0)
    for lv in cls.per_level:
        want = 1e-6 * (s.n_light_dirs + s.n_view_dirs) * n * n * spt if lv["level"] < 2 else 0
        assert lv["seconds"] == pytest.approx(want, rel=1e-12), lv
    sizes = costmodel.level_sizes(counts, s.c_max)
    r = costmodel.estimate(s, 1, counts, coef=_only(r_entry=1e-6), ggx_fraction=0.0,
                           fitted=[0.25, 0.5])
    full = costmodel.estimate(s, 1, counts, coef=_only(r_entry=1e-6), ggx_fraction=0.0)
    for lv, lf, (m, _) in zip(r.per_level, full.per_level, sizes, strict=True):
        whole = 1e-6 * d * m.sum()
        assert lf["seconds"] == pytest.approx(whole, rel=1e-12)
        share = (0.25, 0.5, 1.0, 1.0)[lv["level"]]
        assert lv["seconds"] == pytest.approx(share * whole, rel=1e-12), lv
    points = s.model_copy(update={"texel_classes": "points"})
    assert costmodel.estimate(points, 1, counts, coef=_only(classify=1e-6)).seconds == 0.0


def test_level_0_groups_price_its_fit_on_the_groups():
    """By hand on an even 8^2 atlas of 10 samples a texel: with `level0_ratio` r, level 0's R
    term is paid on r m candidates (r d m) and its Gram term on (r m)^2 d; the other levels and
    the held-out truth (on the samples) are unchanged; no ratio prices every sample."""
    n, spt = 8, 10
    s = BakeSettings(atlas_resolution=n, shard_texels=8, samples_per_texel=spt, c_max=64)
    counts = np.full((n, n), spt)
    for coef in (_only(r_entry=1e-6), _only(gram=1e-9), _only(held=1e-7)):
        base = costmodel.estimate(s, 1, counts, coef=coef, ggx_fraction=0.0)
        grp = costmodel.estimate(s, 1, counts, coef=coef, ggx_fraction=0.0, level0_ratio=0.25)
        power = 1 if coef.r_entry else 2 if coef.gram else 0
        for lv, lb in zip(grp.per_level, base.per_level, strict=True):
            want = lb["seconds"] * (0.25 ** power if lv["level"] == 0 else 1.0)
            assert lv["seconds"] == pytest.approx(want, rel=1e-12), (coef, lv)


def test_the_held_out_truth_is_priced_on_its_samples():
    """The held-out term counts the measured texels (`heldout_texels` of a level's occupied
    ones) and at most `heldout_samples` samples of each: on an even 16^2 atlas of 64 samples a
    texel, level 0 measures 8 of 256 texels over all 64 samples, level 3 all 4 texels over
    1,000 of their 4,096."""
    n, spt = 16, 64
    s = BakeSettings(atlas_resolution=n, samples_per_texel=spt, heldout_texels=8,
                     heldout_samples=1000)
    counts = np.full((n, n), spt)
    e = costmodel.estimate(s, 1, counts, coef=_only(held=1e-6), ggx_fraction=0.0)
    n_h = int(round(np.sqrt(s.n_heldout))) ** 2
    per = {lv["level"]: lv["seconds"] for lv in e.per_level}
    assert per[0] == pytest.approx(1e-6 * n_h * 8 * 64, rel=1e-12)
    assert per[3] == pytest.approx(1e-6 * n_h * 4 * 1000, rel=1e-12)
    assert per[4] == pytest.approx(1e-6 * n_h * 1000, rel=1e-12)


def test_a_vis_rays_are_priced_on_the_samples_that_cast_them():
    """avis_level0 "by_need" casts level 0's cube from a few strata per texel: the a_vis
    stage's ray term scales with the samples given (`avis_ray_samples`), its maps term (per
    occupied finest texel) does not; the pipeline counts at most `strata_for(side)` per
    texel (16 up to 128², 8 at 512²)."""
    from texelbake.pipeline.estimate import avis_ray_samples

    n, spt = 8, 40
    s = BakeSettings(atlas_resolution=n, samples_per_texel=spt, avis_level0="by_need")
    counts = np.full((n, n), spt)
    k = avis_ray_samples(s, counts)
    assert k == 16 * n * n and avis_ray_samples(s.model_copy(
        update={"avis_level0": "dense"}), counts) is None
    rays = costmodel.estimate(s, 1, counts, coef=_only(avis=1e-6), avis_ray_samples=k)
    every = costmodel.estimate(s, 1, counts, coef=_only(avis=1e-6))
    assert rays.avis_seconds == pytest.approx(every.avis_seconds * 16 / spt, rel=1e-12)
    maps = costmodel.estimate(s, 1, counts, coef=_only(avis_fixed=1e-6), avis_ray_samples=k)
    assert maps.avis_seconds == pytest.approx(1e-6 * n * n, rel=1e-12)
    fine = s.model_copy(update={"atlas_resolution": 512})
    assert avis_ray_samples(fine, counts) == 8 * n * n


def test_a_coarse_fit_prices_its_a_vis_rays_on_the_capped_samples():
    """avis_coarse "dense": a coarse level's fit casts a_vis from every ceil(n / cap)-th of a
    texel's n samples (`avis_cast`, by hand), so on an even 16^2 atlas of 64 samples a texel
    with avis_fit_samples=1000 level 1 (64 texels of 256) casts from all, level 2 (16 of
    1,024) from 16 x 512, level 3 (4 of 4,096) from 4 x 820 and level 4 (one of 16,384) from
    964; 0 casts from every one."""
    np.testing.assert_array_equal(costmodel.avis_cast(np.array([100, 16384, 16385, 40000]),
                                                      16384), [100, 16384, 8193, 13334])
    np.testing.assert_array_equal(costmodel.avis_cast(np.array([5, 40000]), 0), [5, 40000])
    n, spt = 16, 64
    s = BakeSettings(atlas_resolution=n, samples_per_texel=spt, avis_coarse="dense",
                     texel_classes="points", point_lobe="narrow", avis_fit_samples=1000)
    counts = np.full((n, n), spt)
    per = {lv["level"]: lv["seconds"] for lv in costmodel.estimate(
        s, 1, counts, coef=_only(fit_avis=1e-6), ggx_fraction=0.0).per_level}
    every = {lv["level"]: lv["seconds"] for lv in costmodel.estimate(
        s.model_copy(update={"avis_fit_samples": 0}), 1, counts, coef=_only(fit_avis=1e-6),
        ggx_fraction=0.0).per_level}
    nv = s.n_view_dirs
    assert per[0] == every[0] == 0.0
    for lv, cast in ((1, 64 * 256), (2, 16 * 512), (3, 4 * 820), (4, 964)):
        assert per[lv] == pytest.approx(1e-6 * nv * cast, rel=1e-12), lv
        assert every[lv] == pytest.approx(1e-6 * nv * n * n * spt, rel=1e-12), lv


def test_atlas_trade_prices_the_classes_by_texel_size():
    """The LOD1 projection with this bake's classed shares: this atlas priced at them, the
    larger atlas's classed levels at the share of this bake's level of the same texel size, a
    smaller texel at this bake's finest share (an upper bound); by hand against `estimate`.
    Without shares every texel is priced as fitted, so the shares can only lower both."""
    s = BakeSettings(atlas_resolution=16)
    lods = {"atlas_mesh": {"atlas_resolution_for_lod1": 64, "cpm_max_px": 10.0}}
    shares = [0.5, 0.7, 0.9]
    t = costmodel.atlas_trade(s, lods, fitted=shares)
    big = s.model_copy(update={"atlas_resolution": 64})
    # 64^2 level L has the texel size of 16^2 level L - 2: levels 0-2 are smaller than 16^2's
    # finest
    assert t["estimated_seconds"] == costmodel.estimate(s, fitted=shares).seconds
    assert t["estimated_seconds_for_lod1"] == costmodel.estimate(big, fitted=[0.5] * 3).seconds
    assert t["fitted_shares"] == shares
    plain = costmodel.atlas_trade(s, lods)
    assert plain["fitted_shares"] is None
    assert t["estimated_seconds_for_lod1"] < plain["estimated_seconds_for_lod1"]
    assert t["estimated_seconds"] < plain["estimated_seconds"]
    # twice the side: 32^2 level 1 is 16^2 level 0, level 2 is level 1
    half = costmodel.atlas_trade(s, {"atlas_mesh": {"atlas_resolution_for_lod1": 32}},
                                 fitted=shares)
    assert half["estimated_seconds_for_lod1"] == costmodel.estimate(
        s.model_copy(update={"atlas_resolution": 32}), fitted=[0.5, 0.5, 0.7]).seconds


@pytest.mark.parametrize("update", [
    {"avis_coarse": "dense", "point_lobe": "widened"},
    {"btf": True, "btf_table": "cell", "point_lobe": "narrow"},
])
def test_a_levels_terms_are_each_coefficients_share_of_its_seconds(update):
    """Each level's `terms` (what calibrate_costmodel.py --terms fits a factor to) add up to
    its seconds, and each term is the level's seconds with that coefficient alone (every other
    seconds field 0; btf_cell, a ratio to r_entry, with r_entry's value set and its own R
    subtracted), on an uneven atlas with sampled fitted shares below 1."""
    n = 16
    counts = np.random.default_rng(3).integers(0, 90, (n, n))
    s = BakeSettings(atlas_resolution=n, **update)
    kw = {"ggx_fraction": 0.3, "fitted": [0.5, 0.7, 0.9], "level0_ratio": 0.6,
          "lobe_tried": 0.4 if update.get("avis_coarse") else None}
    c = costmodel.Coefficients()
    ratios = {"brdf_ggx": c.brdf_ggx, "held_ggx": c.held_ggx, "widened": c.widened}
    full = costmodel.estimate(s, 1, counts, coef=c, **kw).per_level
    used = set()
    for name in costmodel.TERMS:
        if name == "btf_cell":
            both = costmodel.estimate(s, 1, counts, coef=_only(
                r_entry=c.r_entry, btf_cell=c.btf_cell, **ratios), **kw)
            alone = costmodel.estimate(s, 1, counts, coef=_only(r_entry=c.r_entry, btf_cell=0.0,
                                                                **ratios), **kw)
            only = [a["seconds"] - b["seconds"] for a, b in zip(both.per_level,
                                                                alone.per_level, strict=True)]
        else:
            only = [lv["seconds"] for lv in costmodel.estimate(
                s, 1, counts, coef=_only(**{name: getattr(c, name)}, btf_cell=0.0, **ratios),
                **kw).per_level]
        for lv, want in zip(full, only, strict=True):
            assert lv["terms"][name] == pytest.approx(want, rel=1e-9, abs=1e-12), (name, lv)
            used |= {name} if lv["terms"][name] > 0 else set()
    for lv in full:
        assert sum(lv["terms"].values()) == pytest.approx(lv["seconds"], rel=1e-12)
    # the two settings exercise every term but eigh (0 in the coefficients)
    assert used >= ({"held", "r_entry", "gram", "texel", "classify", "fit_avis", "lobe"}
                    if update.get("avis_coarse") else {"r_entry", "btf_cell"})


def test_a_coarse_texels_candidates_are_its_childrens_points_fitted_and_classed():
    """By hand on an even 4^2 atlas of 10 samples a texel: a level-1 texel's candidates are its
    4 children's points, each min(10, c) with c = C_LEVEL[0] = 27 for a fitted child; with a
    fitted share of 1/4 at level 0 and 2 points per classed texel, c = 27 / 4 + 3 / 4 x 2 =
    8.25 (33 candidates); level 2 (not classed) takes C_LEVEL[1] of its children either way."""
    counts = np.full((4, 4), 10)
    plain = costmodel.level_sizes(counts, 64)
    mixed = costmodel.level_sizes(counts, 64, fitted=[0.25], classed_points=[2.0])
    np.testing.assert_allclose(plain[1][0], np.full(4, 40.0))
    np.testing.assert_allclose(mixed[1][0], np.full(4, 33.0))
    np.testing.assert_allclose(plain[2][0], [4 * 27.0])
    np.testing.assert_allclose(mixed[2][0], [4 * 27.0])
    for a, b in zip(plain, mixed, strict=True):  # the dense samples do not change
        np.testing.assert_array_equal(a[1], b[1])
    # a classed texel never stores more than a fitted one's C_LEVEL
    big = costmodel.level_sizes(counts, 64, fitted=[0.0], classed_points=[99.0])
    np.testing.assert_allclose(big[1][0], np.full(4, 40.0))


def test_the_exports_tables_are_priced_per_texel_and_its_filtered_maps_per_sample():
    """By hand on an 8^2 atlas with samples on half its texels: the a_vis tables' term is
    `export` x (faces / 32)^2 per occupied finest texel, whatever their samples; the filtered
    maps' `filtered` per dense sample, whatever the faces."""
    n = 8
    counts = np.zeros((n, n), int)
    counts[:, : n // 2] = 30
    for res in (16, 32):
        s = BakeSettings(atlas_resolution=n, avis_resolution=res)
        tables = costmodel.estimate(s, 1, counts, coef=_only(export=1e-3)).export_seconds
        assert tables == pytest.approx(1e-3 * (res / 32) ** 2 * (n * n // 2), rel=1e-12)
        four = costmodel.estimate(s, 1, 4 * counts, coef=_only(export=1e-3)).export_seconds
        assert four == pytest.approx(tables, rel=1e-12)
        maps = costmodel.estimate(s, 1, counts, coef=_only(filtered=1e-6)).export_seconds
        assert maps == pytest.approx(1e-6 * 30 * (n * n // 2), rel=1e-12)


def test_the_lobe_class_tries_are_priced_per_sample_of_a_tried_finest_texel():
    """By hand on an 8^2 atlas of 20 samples on half its texels: trying level 0's lobe class
    costs `lobe` x the tried share x level 0's dense samples, at level 0 only (x `widened`,
    the point lobe's factor every term of a level carries); no share tried, no term."""
    n = 8
    counts = np.zeros((n, n), int)
    counts[:, : n // 2] = 20
    s = BakeSettings(atlas_resolution=n)
    c = costmodel.Coefficients()
    levels = costmodel.estimate(s, 1, counts, coef=c, lobe_tried=0.25).per_level
    assert levels[0]["terms"]["lobe"] == pytest.approx(
        c.lobe * 0.25 * 32 * 20 * (c.widened if s.point_lobe == "widened" else 1.0), rel=1e-12)
    assert all(lv["terms"]["lobe"] == 0.0 for lv in levels[1:])
    for tried in (None, 0.0):
        none = costmodel.estimate(s, 1, counts, coef=c, lobe_tried=tried).per_level
        assert none[0]["terms"]["lobe"] == 0.0


def test_a_fitted_finest_texel_holds_fewer_points_on_a_larger_atlas():
    """By hand: up to 32^2 a fitted finest texel holds C_LEVEL[0] points; above, C_LEVEL[0] x
    (n / 32)^C0_SLOPE (512^2: 27 x 16^-0.29 = 12.1); a 64^2 atlas of 100 samples a texel gives
    level 1 four children of that many, and level 2 C_LEVEL[1] of each of its children as
    before; the samples do not change."""
    assert costmodel.finest_points(16) == costmodel.C_LEVEL[0]
    assert costmodel.finest_points(32) == costmodel.C_LEVEL[0]
    assert costmodel.finest_points(512) == pytest.approx(27.0 * 16.0 ** -0.29, rel=1e-12)
    assert costmodel.finest_points(512) == pytest.approx(12.08, abs=0.01)
    sizes = costmodel.level_sizes(np.full((64, 64), 100), 64)
    c0 = 27.0 * 2.0 ** -0.29
    np.testing.assert_allclose(sizes[1][0], np.full(32 * 32, 4 * c0))
    np.testing.assert_allclose(sizes[2][0], np.full(16 * 16, 4 * costmodel.C_LEVEL[1]))
    np.testing.assert_allclose(sizes[1][1], np.full(32 * 32, 400.0))
    # the O(log n) estimate before the geometry prices the same points
    uniform = costmodel._uniform_sizes(64, 100, 64)
    assert uniform[1][0][0] == pytest.approx(min(uniform[0][0][0], c0) * 4, rel=1e-12)
