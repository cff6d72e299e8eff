"""Which stages an asset needs, and running them.

A bake is a plan of stages; some are sharded by texel tile. Every shard is a pure function from
files in the artifact store to files in the artifact store (`texelbake.stages`), so the same code
runs in one process (`bake`) or as Celery tasks (`run_shard`, called by `workers.tasks`).

Tiles: the finest CPM level has N x N texels (N = settings.atlas_resolution); a shard owns an
S x S tile (S = settings.shard_texels) and every coarser level's texels inside it (levels
0..log2 S). Levels coarser than a tile (log2 S + 1 .. log2 N) are one `*_top` shard.
"""

from __future__ import annotations

import functools
import os
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from schemas.queues import STAGE_QUEUES
from schemas.settings import BakeSettings
from texelbake import stages
from texelbake.errors import AssetError, SettingsError, StageError
from texelbake.process import setup_bake_process
from texelbake.stages.srf import n_srf_shards


@dataclass(frozen=True)
class StagePlan:
    name: str
    queue: str
    n_shards: int
    depends_on: tuple[str, ...] = ()


@dataclass(frozen=True)
class Plan:
    stages: tuple[StagePlan, ...]
    skipped: tuple[tuple[str, str], ...] = ()

    def stage(self, name: str) -> StagePlan:
        for s in self.stages:
            if s.name == name:
                return s
        raise StageError(f"stage {name!r} is not in this plan ({[s.name for s in self.stages]})")


def n_tiles(settings: BakeSettings) -> int:
    side = settings.atlas_resolution // settings.shard_texels
    return side * side


def plan_bake(asset_path: Path, settings: BakeSettings) -> Plan:
    """The stages this asset and these settings need, in execution order, with what is skipped."""
    tiles = n_tiles(settings)
    has_top = settings.shard_texels < settings.atlas_resolution
    plan = [
        StagePlan("ingest", STAGE_QUEUES["ingest"], 1),
        StagePlan("geometry", STAGE_QUEUES["geometry"], 1, ("ingest",)),
        StagePlan("cpm", STAGE_QUEUES["cpm"], tiles, ("geometry",)),
    ]
    skipped: list[tuple[str, str]] = []
    if has_top:
        plan.append(StagePlan("cpm_top", STAGE_QUEUES["cpm_top"], 1, ("cpm",)))
    plan.append(StagePlan("avis", STAGE_QUEUES["avis"], tiles, ("geometry",)))
    if has_top:
        plan.append(StagePlan("avis_top", STAGE_QUEUES["avis_top"], 1, ("avis",)))
    cpm_deps = ("cpm_top",) if has_top else ("cpm",)
    avis_deps = ("avis_top",) if has_top else ("avis",)
    if settings.btf:
        plan.append(StagePlan("btf", STAGE_QUEUES["btf"], 1, cpm_deps))
    else:
        skipped.append(("btf", "no real-time target requested (settings.btf is false)"))
    if settings.srf:  # seed 002 §3: captured with gt, sharded by camera (render workers)
        plan.append(StagePlan("srf", STAGE_QUEUES["srf"], n_srf_shards(settings), ("ingest",)))
        plan.append(StagePlan("srf_top", STAGE_QUEUES["srf_top"], 1, ("srf",)))
    export_deps = (cpm_deps + avis_deps + (("btf",) if settings.btf else ())
                   + (("srf_top",) if settings.srf else ()))
    plan.append(StagePlan("export", STAGE_QUEUES["export"], 1, export_deps))
    if settings.previews:
        plan.append(StagePlan("render", STAGE_QUEUES["render"], 1, ("export",)))
        # seed 002 §4: an animated preview of deformed frames, only when there is motion
        if settings.warp or asset_deforms(asset_path):
            plan.append(StagePlan("deformed", STAGE_QUEUES["deformed"], 1, ("export",)))
        else:
            skipped.append(("deformed", "the asset has no animation (at most one time sample) "
                                        "and no warp was asked (settings.warp)"))
    else:
        skipped.append(("render", "previews not requested (settings.previews is false)"))
        skipped.append(("deformed", "previews not requested (settings.previews is false)"))
    if not settings.srf:
        skipped.append(
            ("srf", "no reflectance field requested (settings.srf is false; the impostor "
                    "parameterization is on every LOD mesh for deformed frames)")
        )
    return Plan(tuple(plan), tuple(skipped))


def asset_deforms(asset_path: Path) -> bool:
    """Whether the asset's points move over its time samples (`AssetModel.has_deformation`,
    the ingest's own reading), read once per file version and process: the plan is made
    again by every shard."""
    path = Path(asset_path)
    try:
        st = path.stat()
    except OSError as exc:
        raise AssetError(f"the asset cannot be read ({exc.strerror})", path=str(path)) from None
    return _deforms(str(path.resolve()), st.st_mtime_ns, st.st_size)


@functools.lru_cache(maxsize=16)
def _deforms(path: str, mtime_ns: int, size: int) -> bool:
    from texelbake.scene.load import load_asset

    with warnings.catch_warnings():  # the ingest stage reports the asset's warnings
        warnings.simplefilter("ignore")
        return load_asset(path).has_deformation


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
    plan = plan_bake(asset_path, settings)
    sp = plan.stage(stage)
    if not 0 <= shard < sp.n_shards:
        raise SettingsError(f"shard {shard} out of range for stage {stage!r} (0..{sp.n_shards - 1})")
    if stage not in _RUNNERS:
        raise StageError(f"stage {stage!r} is not run by shard (render previews from the export)")
    ctx = stages.StageContext.create(Path(workdir), Path(asset_path), settings)
    return _RUNNERS[stage](ctx, shard)


@dataclass
class BakeResult:
    root_layer: Path
    report: dict = field(default_factory=dict)


def finalize(workdir: Path, asset_path: Path, settings: BakeSettings, out_dir: Path, *,
             stage_seconds: dict[str, float] | None = None, plan: Plan | None = None) -> Path:
    """The export stage's body: write the baked USD, maps and report.json into `out_dir`
    (`stage_seconds`: the farm's timings per stage, for the report)."""
    setup_bake_process()
    ctx = stages.StageContext.create(Path(workdir), Path(asset_path), settings)
    plan = plan or plan_bake(asset_path, settings)
    root = stages.export_to(ctx, Path(out_dir), stage_seconds=stage_seconds, plan=plan)
    if stage_seconds:
        stages.update_report_seconds(Path(out_dir), stage_seconds)
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
    `default_workdir()`, outside out_dir: the output holds the result only, issue 22).
    source : "reference" (the baked root references the source where it lies, by a relative
        path) or "copy" (copied into out_dir/source: a folder that travels alone).
    jobs : processes for the sharded stages (cpm, avis); 1 runs everything in this process.
        The result does not depend on it (per-texel seeds, content-derived artifacts).
    """
    from tqdm import tqdm

    setup_bake_process()  # the in-process stages (ingest, geometry, export) and -j 1 shards
    settings = settings or BakeSettings()
    asset_path = Path(asset_path)
    out_dir = Path(out_dir)
    workdir = Path(workdir) if workdir is not None else default_workdir()
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
    stages.update_report_seconds(out_dir, seconds, est)
    return root


def _other_runnable(samples: int = 5, interval: float = 0.05) -> float:
    """Runnable tasks of the other processes on the machine, now: the mean of a few readings
    of every task's state in /proc (`runnable_tasks`), this process's own threads left out.
    Not the 1-min load average: it lags by minutes, so the workers of a bake that just ended
    (or of this bake's earlier stages) still count there as load, and stretched the estimate
    of a bake on an idle machine by 1.5x. Not /proc/loadavg's running count either: it counts
    this process's own runnable threads (BLAS, Embree, the progress bar's), which are the bake,
    not load on it (measured 2026-11-27: three re-estimates of one idle-machine bake read
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


def bake_estimate(ctx: stages.StageContext, jobs: int, elapsed: float = 0.0) -> dict:
    """The cost model's prediction (`texelbake.costmodel`) from the placed samples: total
    seconds, the cpm and avis stages' wall seconds on `jobs` workers, and the ETA (UTC) of the
    bake given the `elapsed` seconds so far."""
    from datetime import UTC, datetime, timedelta

    from texelbake import costmodel, machinespeed

    s = ctx.settings
    geo = ctx.geometry()
    cores = os.cpu_count() or 1
    speed = machinespeed.this_machine()  # before the load reading: ~1 s of this process's CPU
    other = _other_runnable()
    e = costmodel.estimate(s, jobs, costmodel.sample_counts(geo, s.atlas_resolution),
                           ggx_fraction=costmodel.ggx_fraction_of(geo, ctx.asset().materials),
                           load=other, cores=cores, speed=speed)
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
            "machine_speed": e.speed}


def _shard_pool(jobs: int):
    """`jobs` processes for the sharded stages of one bake (spawn: no fork after Embree and
    BLAS have started threads). One pool serves every sharded stage: a new one per stage paid
    each process's imports (4.5 s of torch, open3d and pxr on the 2026-11-28 Xeon) and its
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
