"""Running a bake's stages: one shard (`run_shard`, the farm's tasks), or every stage in
this process (`bake`). Every shard is a pure function from files in the artifact store to files
in the artifact store (`texelbake.stages`); the plan and its tiles are `pipeline.plan`'s.
"""
from __future__ import annotations

import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from schemas.settings import BakeSettings
from texelbake import stages
from texelbake.errors import SettingsError, StageError
from texelbake.pipeline.estimate import bake_estimate
from texelbake.pipeline.plan import Plan, StagePlan, atlas_note, plan_bake, resolve_settings
from texelbake.pipeline.process import release_freed_memory, setup_bake_process

#: stage -> shard body (the render stage needs the exported folder: `bake` and the farm call
#: `stages.run_render` / `texelbake.render` directly)
_RUNNERS: dict[str, Callable[[stages.StageContext, int], str]] = {
    "ingest": stages.run_ingest,
    "geometry": stages.run_geometry,
    "cpm": stages.run_cpm_tile,
    "cpm_top": stages.run_cpm_top,
    "avis": stages.run_avis_tile,
    "avis_top": stages.run_avis_top,
    "btf": stages.run_btf,
    "srf": stages.run_srf_shard,
    "srf_top": stages.run_srf_top,
    "export": stages.run_export,
}


def run_shard(
    workdir: Path, asset_path: Path, settings: BakeSettings, stage: str, shard: int
) -> str:
    """Run one shard of one stage; idempotent. Returns the artifact key it wrote (or found)."""
    setup_bake_process()  # every process that runs shards: local pools, Celery workers
    settings = resolve_settings(asset_path, settings)
    plan = plan_bake(asset_path, settings)
    sp = plan.stage(stage)
    if not 0 <= shard < sp.n_shards:
        raise SettingsError(f"shard {shard} out of range for stage {stage!r} (0..{sp.n_shards - 1})")
    if stage not in _RUNNERS:
        raise StageError(f"stage {stage!r} is not run by shard (render previews from the export)")
    ctx = stages.StageContext.create(Path(workdir), Path(asset_path), settings)
    return _RUNNERS[stage](ctx, shard)


#: a run's facts (seconds, estimate, host, date: `stages.write_run`), beside the result
RUN_JSON = "run.json"


@dataclass
class BakeResult:
    root_layer: Path
    report: dict = field(default_factory=dict)


def finalize(workdir: Path, asset_path: Path, settings: BakeSettings, out_dir: Path, *,
             plan: Plan | None = None, run_path: Path | None = None,
             stage_seconds: dict[str, float] | None = None, **run_extra) -> Path:
    """The export stage's body: write the baked USD, maps and report.json into `out_dir`;
    with `run_path`, this run's facts there (`stages.write_run`: `stage_seconds`, the farm's
    timings per stage, and `run_extra`), outside the result."""
    setup_bake_process()
    settings = resolve_settings(asset_path, settings)
    ctx = stages.StageContext.create(Path(workdir), Path(asset_path), settings)
    plan = plan or plan_bake(asset_path, settings)
    root = stages.export_to(ctx, Path(out_dir), plan=plan)
    if run_path is not None:
        stages.write_run(run_path, Path(out_dir), stage_seconds or {}, **run_extra)
    return root


def default_workdir() -> Path:
    """Where local bakes keep their artifact store: $TEXELBAKE_WORKDIR, else
    $XDG_CACHE_HOME/texelbake (~/.cache/texelbake). Artifacts are named by the asset's content
    hash and the settings that made them, so bakes of different assets share it safely."""
    env = os.environ.get("TEXELBAKE_WORKDIR")
    if env:
        return Path(env)
    cache = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(cache) / "texelbake"


def _run_in_subprocess(workdir: str, asset_path: str, settings_json: str, stage: str,
                       shard: int) -> str:
    return run_shard(Path(workdir), Path(asset_path),
                     BakeSettings.model_validate_json(settings_json), stage, shard)


def bake(
    asset_path: Path,
    out_dir: Path,
    settings: BakeSettings | None = None,
    *,
    workdir: Path | None = None,
    progress: bool = True,
    jobs: int = 1,
    source: str = "reference",
) -> Path:
    """Run every planned stage and shard on this machine (no broker, no server) and write the
    baked USD to `out_dir`.

    Returns the root layer path. `workdir` holds the artifact store (default
    `default_workdir()`, outside out_dir: the output holds the result only).
    source : "reference" (the baked root references the source where it lies, by a relative
        path) or "copy" (copied into out_dir/source: a folder that travels alone).
    Besides the result, out_dir gets `run.json` (`RUN_JSON`): the seconds per stage, the cost
    model's estimate, host and date, which differ between runs; every other file is
    byte-identical on a rerun.
    jobs : processes for the sharded stages (cpm, avis); 1 runs everything in this process.
        The result does not depend on it (per-texel seeds, content-derived artifacts).
    """
    from tqdm import tqdm

    setup_bake_process()  # the in-process stages (ingest, geometry, export) and -j 1 shards
    settings = settings or BakeSettings()
    asset_path = Path(asset_path)
    out_dir = Path(out_dir)
    workdir = Path(workdir) if workdir is not None else default_workdir()
    if progress:
        print(atlas_note(asset_path, settings))
    settings = resolve_settings(asset_path, settings)
    plan = plan_bake(asset_path, settings)
    ctx = stages.StageContext.create(workdir, asset_path, settings)
    seconds: dict[str, float] = {}
    root: Path | None = None
    est: dict | None = None
    pool = None
    # the pool lives until the last stage that runs on it
    pooled = [i for i, sp in enumerate(plan.stages) if jobs > 1 and sp.n_shards > 1]
    try:
        for i, sp in enumerate(plan.stages):
            t0 = time.perf_counter()
            if sp.name == "export":
                root = stages.export_to(ctx, out_dir, plan=plan, source=source)
            elif sp.name in ("render", "deformed"):
                run = stages.run_render if sp.name == "render" else stages.run_deformed
                for p in run(ctx, 0, out_dir=out_dir):
                    if progress:
                        print(f"preview: {p}")
            elif i in pooled:
                if pool is None:  # one pool for every sharded stage (see _shard_pool)
                    release_freed_memory()  # this process waits while the pool works
                    pool = _shard_pool(jobs)
                _run_parallel(pool, workdir, asset_path, settings, sp, progress, est)
            else:
                bar = tqdm(range(sp.n_shards), desc=f"{sp.name:<9}", unit="shard",
                           disable=not progress, leave=True)
                if est is not None and sp.name in ("cpm", "avis"):
                    bar.set_postfix_str(f"model {est['stage_seconds'][sp.name]:.0f} s")
                for shard in bar:
                    _RUNNERS[sp.name](ctx, shard)
            seconds[sp.name] = time.perf_counter() - t0
            if sp.name == "geometry":
                est = bake_estimate(ctx, jobs, elapsed=sum(seconds.values()))
                if progress:
                    print(f"estimate: {est['seconds']:.0f} s on {est['workers']} worker(s) "
                          f"(cpm {est['stage_seconds']['cpm']:.0f} s, avis "
                          f"{est['stage_seconds']['avis']:.0f} s), ETA {est['eta']}; this "
                          "machine's seconds / the model's: " + ", ".join(
                              f"{k} {v:.2f}" for k, v in est["machine_speed"]["factors"].items()))
            if pool is not None and i == pooled[-1]:
                pool.shutdown()  # no sharded stage left: its processes' memory goes back now
                pool = None
    finally:
        if pool is not None:  # an error mid-bake: stop the shard processes too
            pool.shutdown(cancel_futures=True)
    if root is None:
        raise StageError("the plan has no export stage")
    # the run's facts beside report.json: the one file of out_dir that differs between runs
    stages.write_run(out_dir / RUN_JSON, out_dir, seconds, est, jobs=jobs)
    return root


def _shard_pool(jobs: int):
    """`jobs` processes for the sharded stages of one bake (spawn: no fork after Embree and
    BLAS have started threads). One pool serves every sharded stage: a new one per stage paid
    each process's imports (4.5 s of torch, open3d and pxr on a Xeon) and its
    first touch of its memory again."""
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor

    return ProcessPoolExecutor(max_workers=jobs, mp_context=mp.get_context("spawn"))


def _run_parallel(pool, workdir: Path, asset_path: Path, settings: BakeSettings, sp: StagePlan,
                  progress: bool, est: dict | None = None) -> None:
    """The shards of one stage on the processes of `pool` (`_shard_pool`)."""
    from concurrent.futures import as_completed

    from tqdm import tqdm

    futures = [
        pool.submit(_run_in_subprocess, str(workdir), str(asset_path),
                    settings.model_dump_json(), sp.name, shard)
        for shard in range(sp.n_shards)
    ]
    bar = tqdm(total=sp.n_shards, desc=f"{sp.name:<9}", unit="shard", disable=not progress)
    if est is not None and sp.name in ("cpm", "avis"):
        bar.set_postfix_str(f"model {est['stage_seconds'][sp.name]:.0f} s")
    for fut in as_completed(futures):
        fut.result()
        bar.update(1)
    bar.close()
