"""A bake's estimate while it runs: the cost model priced on this machine, under its load now,
with the share of each classed level's texels that the classes leave to the fit measured on a
seeded sample of its texels (`sampled_fitted_shares`).
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from texelbake import stages

#: texels classed per classed level to measure the share the fit gets (its standard error at
#: most 0.5 / sqrt(16) = 0.125; the bake's classes are the whole level's)
CLASS_SAMPLE = 16


def _other_runnable(samples: int = 5, interval: float = 0.05) -> float:
    """Runnable tasks of the other processes on the machine, now: the mean of a few readings
    of every task's state in /proc (`runnable_tasks`), this process's own threads left out.
    Not the 1-min load average: it lags by minutes, so the workers of a bake that just ended
    (or of this bake's earlier stages) still count there as load, and stretched the estimate
    of a bake on an idle machine by 1.5x. Not /proc/loadavg's running count either: it counts
    this process's own runnable threads (BLAS, Embree, the progress bar's), which are the bake,
    not load on it (measured: three re-estimates of one idle-machine bake read
    0.2-1.4 other tasks, 0.89-1.19 of the outcome)."""
    try:
        runs = []
        for i in range(samples):  # a few readings: one is a snapshot
            if i:
                time.sleep(interval)
            runs.append(len(runnable_tasks(exclude_pid=os.getpid())))
        return sum(runs) / len(runs)
    except OSError:  # no procfs: the 1-min average
        return max(os.getloadavg()[0] - 1.0, 0.0)


def runnable_tasks(exclude_pid: int | None = None, proc: Path = Path("/proc")
                   ) -> list[tuple[int, int]]:
    """(pid, tid) of every task (thread) in state R (running or waiting for a core) under
    `proc`, the threads of `exclude_pid` left out. A loop over the machine's few hundred tasks:
    procfs has no batched read. Raises OSError when `proc` cannot be listed; tasks that end
    while being read are skipped."""
    out = []
    for pdir in proc.iterdir():  # a loop over processes: one directory each
        if not pdir.name.isdigit() or int(pdir.name) == exclude_pid:
            continue
        try:
            tasks = list((pdir / "task").iterdir())
        except OSError:  # ended, or not ours to read
            continue
        for task in tasks:  # a loop over the process's threads
            try:
                stat = (task / "stat").read_bytes()
            except OSError:
                continue
            # "pid (comm) S ...": comm may hold spaces and parentheses, the state follows
            # the last ')'
            end = stat.rfind(b")")
            if stat[end + 2:end + 3] == b"R":
                out.append((int(pdir.name), int(task.name)))
    return out


@dataclass(frozen=True)
class SampledFit:
    """What the fit gets, measured on a seeded sample of texels (`sampled_fitted_shares`):
    shares per classed level, the fraction of its texels the classes leave to the fit;
    level0_ratio the candidates of a fitted finest texel over its dense samples (its groups,
    level0_candidates "clustered"), None where they are its samples or no sampled texel is
    fitted. points: per classed level, the mean points a texel the classes store holds (1
    where none of the sample is classed). lobe_tried: with lobe_class "validated", the
    fraction of level 0's sample the lobe class tries (its lobe texels count as stored in
    `shares` and `points`); None without it."""

    shares: list[float]
    level0_ratio: float | None
    points: list[float] = field(default_factory=list)
    lobe_tried: float | None = None


def sampled_fitted_shares(ctx: stages.StageContext) -> SampledFit | None:
    """Per classed level (texel_classes "by_need", the finest `classed_levels`), the fraction
    of a seeded sample of `CLASS_SAMPLE` occupied texels (all when fewer) that the classes
    (`texelbake.cpm.classify`) leave to the fit: what the cost model's fit terms are priced
    on; and at level 0 the fitted texels' candidates over their samples (`SampledFit`). None
    when the bake classes no texel. Costs the sample's classing rays (a few seconds at a 128^2
    atlas) and the ray caster's build."""
    from texelbake.cpm.dense import LevelPass, dense_of
    from texelbake.cpm.level import clusters_level0, texel_ids
    from texelbake.cpm.level_by_need import classes_bounded, fitted_groups, lobe_tried
    from texelbake.cpm.lobe_class import lobes_bounded

    s = ctx.settings
    if s.texel_classes != "by_need" or s.btf:
        return None
    src = ctx.fit_inputs()
    geo, n = src.geo, s.atlas_resolution
    rng = np.random.default_rng(s.seed)
    out: list[float] = []
    points: list[float] = []
    ratio = tried_share = None
    for level in range(min(s.classed_levels, ctx.n_levels)):  # a loop over a few levels
        occupied = np.unique(texel_ids(geo, n, level))
        if not occupied.size:
            out.append(1.0)
            points.append(1.0)
            continue
        texels = np.sort(rng.choice(occupied, min(CLASS_SAMPLE, occupied.size), replace=False))
        lp = LevelPass.of(src, level)
        dense, dseg = dense_of(lp, texels)
        cls = classes_bounded(lp, texels, dense, dseg)
        fit = ~(cls.exact | cls.grouped)
        counts = np.diff(cls.offsets)
        tried = lobe_tried(s, level, cls)
        if tried is not None:
            lob = lobes_bounded(lp, texels, dense, dseg, tried)
            tried_share = float(np.mean(tried))
            counts = np.where(lob.lobe, np.diff(lob.offsets), counts)
            fit &= ~lob.lobe
        out.append(float(np.mean(fit)))
        stored = counts[~fit]
        points.append(float(stored.mean()) if stored.size else 1.0)
        if level == 0 and clusters_level0(s) and fit.any():
            cands, seg = fitted_groups(lp, texels, dense, dseg, cls, np.flatnonzero(fit))
            ratio = len(cands.sample) / seg.size if seg.size else None
    return SampledFit(out, ratio, points, tried_share)


def avis_ray_samples(settings, counts: np.ndarray) -> float | None:
    """The samples that cast level 0's a_vis rays with avis_level0 "by_need": at most
    `strata_for(atlas side)` strata of each texel (one for a one-facet, one-pattern texel:
    an upper bound); None with "dense" (every sample)."""
    from texelbake.cpm.avis.by_need import strata_for

    if settings.avis_level0 != "by_need":
        return None
    k = strata_for(settings.atlas_resolution)
    return float(np.minimum(np.asarray(counts), k).sum())


def estimate_inputs(ctx: stages.StageContext) -> dict:
    """What `costmodel.estimate` prices a bake on once its samples are placed (keyword
    arguments): the samples per finest texel, the costly materials' share, and on a seeded
    sample of texels the classes' fitted shares, level-0 candidate ratio and stored points
    (`sampled_fitted_shares`), and level 0's a_vis ray samples."""
    from texelbake.estimate import costmodel

    s = ctx.settings
    geo = ctx.geometry()
    sampled = sampled_fitted_shares(ctx)
    counts = costmodel.sample_counts(geo, s.atlas_resolution)
    return {"sample_counts": counts,
            "ggx_fraction": costmodel.ggx_fraction_of(geo, ctx.asset().materials),
            "fitted": None if sampled is None else sampled.shares,
            "avis_ray_samples": avis_ray_samples(s, counts),
            "level0_ratio": None if sampled is None else sampled.level0_ratio,
            "classed_points": None if sampled is None else sampled.points,
            "lobe_tried": None if sampled is None else sampled.lobe_tried}


def bake_estimate(ctx: stages.StageContext, jobs: int, elapsed: float = 0.0) -> dict:
    """The cost model's prediction (`texelbake.estimate.costmodel`) from the placed samples: total
    seconds, the cpm and avis stages' wall seconds on `jobs` workers, and the ETA (UTC) of the
    bake given the `elapsed` seconds so far."""
    from datetime import UTC, datetime, timedelta

    from texelbake.estimate import costmodel, machinespeed

    cores = os.cpu_count() or 1
    speed = machinespeed.this_machine()  # before the load reading: ~1 s of this process's CPU
    other = _other_runnable()
    inputs = estimate_inputs(ctx)
    fitted = inputs["fitted"]
    e = costmodel.estimate(ctx.settings, jobs, load=other, cores=cores, speed=speed, **inputs)
    w = max(int(jobs), 1)
    # made after the geometry stage: its measured seconds (`elapsed`, with ingest) replace the
    # model's geometry term (the bolt's xatlas packing took 42 s where the model says 1)
    seconds = elapsed + max(e.seconds - e.geometry_seconds * e.stretch, 0.0)
    remaining = max(seconds - elapsed, 0.0)
    eta = datetime.now(UTC) + timedelta(seconds=remaining)
    return {"seconds": round(seconds, 1), "workers": w, "load": round(other, 2),
            "cores": cores,
            "stage_seconds": {"cpm": round(e.cpm_wall_seconds, 1),
                              "avis": round(e.avis_wall_seconds, 1),
                              "export": round(e.export_seconds * e.stretch, 1)},
            "per_level": e.per_level, "eta": eta.strftime("%H:%M:%S UTC"),
            "fitted_shares": None if fitted is None else [round(f, 3) for f in fitted],
            "machine_speed": e.speed}
