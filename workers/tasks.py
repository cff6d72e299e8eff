"""Thin tasks over `texelbake.pipeline`: load by id, call one core function, record the result.

Tasks carry ids only (job id, stage name, shard index); arrays live in the artifact store.
Bad input (`texelbake.errors.TexelbakeError`) fails the job at once; transient faults (I/O,
database or broker hiccups) are retried with exponential backoff and jitter, a bounded number of
times, then fail the job with the reason. Redelivery after a lost worker is Celery's
(`acks_late` + `reject_on_worker_lost`), capped in the ledger (`Settings.max_attempts`).
"""

from __future__ import annotations

import os
import random
import socket
import threading
import time
import traceback
from collections.abc import Callable
from pathlib import Path

import kombu.exceptions
import redis
import sqlalchemy.exc
from celery.utils.log import get_task_logger

from farm import ledger, storage
from farm.broker import broker_run_id, celery_sender
from farm.config import get_settings
from farm.db import Asset, Job, session_factory
from schemas.settings import BakeSettings
from texelbake.errors import TexelbakeError
from texelbake.io.atomic import control_words
from workers.celery_app import app

log = get_task_logger(__name__)

#: faults worth a retry: the same call can succeed a moment later
TRANSIENT = (
    OSError,
    sqlalchemy.exc.OperationalError,
    redis.RedisError,
    kombu.exceptions.OperationalError,
    TimeoutError,
)


def _sm():
    return session_factory(get_settings().db_url)


def _worker_name() -> str:
    return f"{socket.gethostname()}:{os.getpid()}"


def _dispatch(sends: list[ledger.Send]) -> None:
    """Send what became ready; a broker outage leaves the rows unsent for the API's sweeper."""
    if not sends:
        return
    st = get_settings()
    try:
        ledger.dispatch(_sm(), sends, celery_sender(app), broker_run_id(st.redis_url))
    except TRANSIENT as exc:
        log.warning("could not send %d messages (the sweeper will): %r", len(sends), exc)


def _heartbeats(
    sm, job_id: str, stage: str, shard: int, stop: threading.Event, interval: float,
    limit: float = float("inf"),
) -> None:  # noqa: ANN001
    """While a shard runs: tell the ledger every `interval` s that this worker still holds it,
    for at most `limit` s. A heartbeat proves the process lives, not that it progresses (the
    chaos suite found a pool child hung in native code, beating for ever): past the limit it
    records why and stops beating, so the lease expires; Celery's hard time limit
    (`task_time_limit`, the limit plus `shard_kill_grace`) kills the pool child. When the shard
    ends it logs the longest gap between two recorded beats: what the lease
    (`Settings.heartbeat_timeout`) must exceed with room on a loaded machine."""
    me = _worker_name()
    deadline = time.monotonic() + limit
    last = time.monotonic()
    worst = 0.0
    while not stop.wait(max(0.0, min(interval, deadline - time.monotonic()))):
        if time.monotonic() >= deadline:
            log.error("shard %s/%s/%s passed its time limit of %g s; no more heartbeats",
                      job_id, stage, shard, limit)
            try:
                ledger.note_time_limit(sm, job_id, stage, shard, me, limit)
            except TRANSIENT as exc:
                log.warning("could not record the time limit of %s/%s/%s: %r",
                            job_id, stage, shard, exc)
            return
        try:
            ledger.heartbeat(sm, job_id, stage, shard, me)
        except TRANSIENT as exc:  # a missed beat is not fatal; a silent worker is re-queued
            log.warning("heartbeat of %s/%s/%s failed: %r", job_id, stage, shard, exc)
            continue
        now = time.monotonic()
        worst, last = max(worst, now - last), now
    log.info("shard %s/%s/%s: longest heartbeat gap %.3f s (interval %g s)", job_id, stage,
             shard, max(worst, time.monotonic() - last), interval)


#: the hang failpoint (chaos suite and tests): a control file naming a stage ("*": any),
#: optionally followed by "once" (the file is removed as the hang starts, so the redelivery runs)
HANG_FAILPOINT_ENV = "TEXELBAKE_FAILPOINT_HANG"


def _hang_failpoint(stage: str) -> None:
    words = control_words(HANG_FAILPOINT_ENV)
    if not words or words[0] not in (stage, "*"):
        return
    if "once" in words[1:]:
        try:
            Path(os.environ[HANG_FAILPOINT_ENV]).unlink()
        except FileNotFoundError:
            return  # another shard took the one hang
    log.error("failpoint %s: stage %s hangs", HANG_FAILPOINT_ENV, stage)
    while True:  # until the time limit's kill
        time.sleep(3600)


def _pxr_input_error(exc: BaseException, job_id: str) -> str | None:
    """The job error for a pxr error raised reading the asset (a truncated or corrupted crate
    layer the upload check let through): bad input naming the root layer, or None for any
    other exception."""
    if not type(exc).__module__.startswith("pxr"):
        return None
    reason = " ".join(storage.public_text(str(exc), get_settings().artifact_root).split())
    try:
        layer = load_job(job_id)[1].root_layer
    except TexelbakeError:
        layer = "the asset"
    return f"pxr cannot read {layer} or a layer it uses: {reason.strip(chr(39))}"


def _public(text: str) -> str:
    """A job's or shard's error as its client reads it: no server path (`storage.public_text`)."""
    return storage.public_text(text, get_settings().artifact_root)


def _backoff(retries: int) -> float:
    st = get_settings()
    base = min(float(st.retry_backoff_max), 2.0**retries)
    return base * (0.5 + random.random() / 2)  # jitter: 50..100 % of the exponential step


def load_job(job_id: str) -> tuple[Job, Asset, BakeSettings, Path]:
    """The job row, its asset row, its settings and the asset's root layer path."""
    with _sm()() as s:
        job = s.get(Job, job_id)
        if job is None:
            raise TexelbakeError(f"job {job_id} is not in the database")
        asset = s.get(Asset, job.asset_id)
        if asset is None:
            raise TexelbakeError(f"asset {job.asset_id} of job {job_id} is not in the database")
    settings = BakeSettings.model_validate_json(job.settings_json)
    root = get_settings().artifact_root
    return job, asset, settings, storage.asset_bundle(root, asset.sha256) / asset.root_layer


@app.task(name="workers.tasks.plan_job", bind=True, max_retries=None)
def plan_job(self, job_id: str) -> None:
    """Decide the stages of a job (`texelbake.pipeline.plan.plan_bake`) and queue the first ones."""
    from texelbake.pipeline.plan import plan_bake

    try:
        _job, _asset, settings, asset_path = load_job(job_id)
        plan = plan_bake(asset_path, settings)
        stages = [(sp.name, sp.queue, sp.n_shards, tuple(sp.depends_on)) for sp in plan.stages]
        sends = ledger.record_plan(_sm(), job_id, stages, [list(x) for x in plan.skipped],
                                   ledger.policy_from(get_settings()))
        _dispatch(sends)
    except TexelbakeError as exc:
        ledger.fail_job(_sm(), job_id, _public(f"plan: {exc}"))
    except TRANSIENT as exc:
        st = get_settings()
        if self.request.retries >= st.max_retries:
            ledger.fail_job(_sm(), job_id, _public(f"plan: transient fault persisted: {exc!r}"))
            return
        raise self.retry(exc=exc, countdown=_backoff(self.request.retries)) from exc
    except Exception as exc:  # a bug: the job fails with the reason instead of hanging
        if (why := _pxr_input_error(exc, job_id)) is not None:
            ledger.fail_job(_sm(), job_id, f"plan: {why}")
            return
        ledger.fail_job(_sm(), job_id, _public(f"plan: {type(exc).__name__}: {exc}"))
        raise


def execute_shard(job_id: str, stage: str, shard: int) -> str:
    """The body of one shard: the core stage function for (stage, shard). Returns its key."""
    from texelbake.pipeline.plan import plan_bake
    from texelbake.pipeline.run import finalize, run_shard

    _hang_failpoint(stage)
    job, asset, settings, asset_path = load_job(job_id)
    root = get_settings().artifact_root
    workdir = storage.work_dir(root, asset.sha256, settings.digest())
    out_dir = storage.job_out(root, job_id)
    if stage == "export":
        baked = finalize(
            workdir, asset_path, settings, out_dir, plan=plan_bake(asset_path, settings),
            # the farm's own timings, outside the result (they differ between runs)
            run_path=storage.job_run(root, job_id),
            stage_seconds=ledger.stage_seconds(_sm(), job_id), job_id=job_id,
            worker=_worker_name(),
        )
        return str(Path(baked).relative_to(out_dir))
    if stage in ("render", "deformed"):
        return _previews(stage, workdir, asset_path, settings, out_dir)
    return run_shard(workdir, asset_path, settings, stage, shard)


def _previews(
    stage: str, workdir: Path, asset_path: Path, settings: BakeSettings, out_dir: Path
) -> str:
    """Previews of the finished job rendered from the written USD: the stills (`render`) or
    the deformed frames (`deformed`); returns the written files' names."""
    from texelbake import stages

    ctx = stages.StageContext.create(workdir, asset_path, settings)
    run = stages.run_render if stage == "render" else stages.run_deformed
    written = run(ctx, 0, out_dir=out_dir)
    return ",".join(sorted(Path(p).name for p in written))


@app.task(name="workers.tasks.run_shard", bind=True, max_retries=None)
def run_shard(self, job_id: str, stage: str, shard: int) -> str:
    """Claim the shard in the ledger, run it, record it, queue what became ready."""

    def retry(exc: Exception, countdown: float) -> Exception:
        return self.retry(exc=exc, countdown=countdown)

    return shard_body(job_id, stage, int(shard), retries=self.request.retries, retry=retry)


def shard_body(
    job_id: str,
    stage: str,
    shard: int,
    *,
    retries: int,
    retry: Callable[[Exception, float], Exception],
) -> str:
    """The task body as a plain function. Returns the outcome: "done", "failed" or
    "skipped:<why>"; for a transient fault it raises what `retry(exc, countdown)` returns
    (Celery's `Retry`) until `max_retries`, then fails the shard and the job."""
    st = get_settings()
    sm = _sm()
    try:
        start = ledger.start_shard(sm, job_id, stage, shard, _worker_name(), st.max_attempts,
                                   ledger.policy_from(st), lease=st.lease)
    except TRANSIENT as exc:
        raise retry(exc, _backoff(retries)) from exc
    _dispatch(list(start.sends))  # shards admitted in this one's place in the broker
    if start.action != "run":
        log.info("shard %s/%s/%s not run: %s", job_id, stage, shard, start.action)
        return f"skipped:{start.action}"
    t0 = time.perf_counter()
    stop = threading.Event()
    beat = threading.Thread(
        target=_heartbeats,
        args=(sm, job_id, stage, shard, stop, st.heartbeat_interval, st.shard_time_limit),
        daemon=True,
    )
    beat.start()
    try:
        key = execute_shard(job_id, stage, shard)
    except TexelbakeError as exc:  # bad input: no retry
        ledger.fail_shard(sm, job_id, stage, shard, _public(f"{type(exc).__name__}: {exc}"))
        return "failed"
    except TRANSIENT as exc:
        if retries >= st.max_retries:
            ledger.fail_shard(
                sm,
                job_id,
                stage,
                shard,
                _public(f"transient fault persisted after "
                        f"{st.max_retries} retries: {type(exc).__name__}: {exc}"),
            )
            return "failed"
        ledger.release_shard(sm, job_id, stage, shard, _public(f"retrying: {exc!r}"))
        raise retry(exc, _backoff(retries)) from exc
    except Exception as exc:  # a bug, not bad input: fail loudly with the traceback's tail
        if (why := _pxr_input_error(exc, job_id)) is not None:
            ledger.fail_shard(sm, job_id, stage, shard, why)
            return "failed"
        tail = traceback.format_exc(limit=3)
        ledger.fail_shard(sm, job_id, stage, shard,
                          _public(f"{type(exc).__name__}: {exc}\n{tail}"))
        raise
    finally:
        stop.set()
        beat.join(timeout=10)
    seconds = time.perf_counter() - t0
    for i in range(st.max_retries + 1):  # recording the result must not lose the shard
        try:
            sends = ledger.finish_shard(sm, job_id, stage, shard, key, seconds,
                                        ledger.policy_from(st))
            break
        except sqlalchemy.exc.OperationalError:
            if i == st.max_retries:
                raise
            time.sleep(_backoff(i))
    _dispatch(sends)
    return "done"
