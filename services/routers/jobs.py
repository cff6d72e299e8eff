"""`/jobs`: create (plan on the ingest queue), list, read, events (SSE), cancel, resume (the
finished job's files: `services.routers.job_files`). A tenant sees only its own jobs: anyone else's is a 404."""

from __future__ import annotations

import asyncio
import json
from typing import Annotated

from fastapi import APIRouter, Query, Request, Response, status
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import StreamingResponse
from sqlalchemy import func, select
from sqlalchemy.orm import Session

from farm import ledger
from farm.broker import broker_run_id, celery_sender
from farm.db import Event, Job, Shard, Stage
from farm.resume import resume_job
from schemas.common import ErrorCode
from schemas.job import (
    TERMINAL_JOB_STATES,
    JobCreate,
    JobPublic,
    JobsPublic,
    JobState,
    JobSummary,
)
from services.deps import (
    CurrentTenant,
    LastEventId,
    LimitQ,
    SessionDep,
    SettingsDep,
    SkipQ,
    WriterDep,
)
from services.errors import ApiError, errors
from services.event_order import SettledMark, events_upto
from services.job_view import job_public, progress_percent
from services.routers.assets import ASSET_404
from services.status_cache import JobCache, VersionCache
from services.submission import JobSpec, create_jobs, own_asset

router = APIRouter(prefix="/jobs", tags=["jobs"])

JOB_NOT_FOUND = "job not found"
JOB_NOT_FINISHED = "job has not succeeded"
AssetIdQ = Annotated[str | None, Query(min_length=1, max_length=64)]

JOB_404 = (404, "`job_not_found`: no such job for this tenant.")
JOB_409 = (409, "`job_not_finished`: the job has not succeeded (yet).")
JOB_NOT_FAILED_409 = (409, "`job_not_failed`: only a failed job can be resumed.")
#: a binary body: generators give the caller the bytes
BINARY = {"type": "string", "format": "binary"}
#: the real media type first; `application/octet-stream` is the generic alias a client may ask
#: for (`Accept`) and the one generic generators know how to download
OCTET = "application/octet-stream"


def _own_job(session: Session, job_id: str, tenant: str) -> Job:
    job = session.get(Job, job_id)
    if job is None or job.tenant != tenant:
        raise ApiError(status.HTTP_404_NOT_FOUND, JOB_NOT_FOUND, ErrorCode.JOB_NOT_FOUND)
    return job


@router.post(
    "",
    response_model=JobPublic,
    status_code=status.HTTP_201_CREATED,
    operation_id="create_job",
    responses=errors(401, ASSET_404, 413, 422),
)
async def create_job(
    body: JobCreate,
    request: Request,
    session: SessionDep,
    tenant: CurrentTenant,
) -> JobPublic:
    """Create a bake job for one of this tenant's assets; its stages are planned by a worker."""
    # its Python work runs in the thread pool, a bounded number at once per process; the rest
    # wait on the event loop, holding no thread (`services.limits.CpuSlots`)
    async with request.app.state.cpu_slots:
        return await run_in_threadpool(_create_job, body, request, session, tenant)


def _create_job(body: JobCreate, request: Request, session: Session, tenant: str) -> JobPublic:
    asset = own_asset(session, tenant, body.asset_id)
    session.close()  # hold no read connection (nor, on SQLite, an old snapshot) from here on
    spec = JobSpec(asset.id, body.settings.model_dump_json(), body.priority)
    (job_id,) = create_jobs(request, tenant, [spec])
    return _read_public(request, job_id)


def _read_public(request: Request, job_id: str) -> JobPublic:
    """A job's status from a fresh read session: the response is built outside any write
    transaction (it used to hold SQLite's write lock while it was built)."""
    st = request.app.state.settings
    with request.app.state.reader() as s:
        return job_public(s, s.get(Job, job_id), st.artifact_root, st.estimate_workers)


@router.get("", response_model=JobsPublic, operation_id="list_jobs", responses=errors(401, 422))
def read_jobs(
    session: SessionDep,
    tenant: CurrentTenant,
    skip: SkipQ = 0,
    limit: LimitQ = 100,
    state: JobState | None = None,
    asset_id: AssetIdQ = None,
) -> JobsPublic:
    """This tenant's jobs, newest first; `state` and `asset_id` filter (`count` counts the
    filtered jobs)."""
    q = select(Job).where(Job.tenant == tenant)
    if state is not None:
        q = q.where(Job.state == state)
    if asset_id is not None:
        q = q.where(Job.asset_id == asset_id)
    count = session.scalar(select(func.count()).select_from(q.subquery())) or 0
    jobs = session.scalars(
        q.order_by(Job.created_at.desc(), Job.id).offset(skip).limit(limit)
    ).all()
    ids = [j.id for j in jobs]
    totals = (
        dict(
            session.execute(
                select(Stage.job_id, func.sum(Stage.n_shards))
                .where(Stage.job_id.in_(ids))
                .group_by(Stage.job_id)
            ).all()
        )
        if ids
        else {}
    )
    dones = (
        dict(
            session.execute(
                select(Shard.job_id, func.count())
                .where(Shard.job_id.in_(ids), Shard.state == "done")
                .group_by(Shard.job_id)
            ).all()
        )
        if ids
        else {}
    )
    data = [
        JobSummary(
            id=j.id,
            asset_id=j.asset_id,
            state=j.state,
            priority=j.priority,
            progress=progress_percent(int(dones.get(j.id, 0)), int(totals.get(j.id, 0) or 0)),
            error=j.error,
            created_at=j.created_at,
            finished_at=j.finished_at,
        )
        for j in jobs
    ]
    return JobsPublic(data=data, count=count)


@router.get(
    "/{job_id}",
    response_model=JobPublic,
    operation_id="read_job",
    responses=errors(401, JOB_404, 422),
)
async def read_job(job_id: str, request: Request, tenant: CurrentTenant) -> Response:
    """State, per-stage and per-shard progress, timings and errors of one job."""
    # a cached version (owner, state, newest event) answers a cache hit with no thread-pool hop;
    # a miss waits for its read on the loop's read threads (`services.status_cache`) and builds
    # the status in a worker thread
    st = request.app.state
    versions: VersionCache = st.version_cache
    row = versions.get(job_id)
    if row is None:
        row = await versions.load(st.loop_reads, job_id)
    if row is None or row[0] != tenant:
        raise ApiError(status.HTTP_404_NOT_FOUND, JOB_NOT_FOUND, ErrorCode.JOB_NOT_FOUND)
    cache: JobCache = st.job_cache
    body = await cache.build((job_id, int(row[2] or 0), str(row[1])),
                             lambda: _read_public(request, job_id).model_dump_json().encode())
    return Response(content=body, media_type="application/json")


def _events_after(reader, job_id: str, after: int, mark: SettledMark  # noqa: ANN001
                  ) -> tuple[list[Event], str | None, int, bool]:
    """(the job's events in (after, settled], its state, settled, held): the state read
    first, then the settled mark (`services.event_order`), then the events. Under READ
    COMMITTED each statement sees the commits before it, so a terminal state read here comes
    with every event its transaction wrote (read the other way round, a commit landing between
    the reads ends the stream before its last events); `held` says an event in flight may
    still come below the mark's next gap, so the stream does not end on a terminal state."""
    with reader() as s:
        state = s.scalar(select(Job.state).where(Job.id == job_id))
        rows, upto, held = events_upto(s, mark, select(Event).where(Event.job_id == job_id),
                                       after, 500)
    return rows, state, upto, held


@router.get(
    "/{job_id}/events",
    response_class=StreamingResponse,
    operation_id="read_job_events",
    responses={
        200: {
            "content": {"text/event-stream": {"schema": {"type": "string"}}},
            "description": "Server-sent events.",
        },
        **errors(401, JOB_404, 422),
    },
)
def read_job_events(
    job_id: str,
    request: Request,
    session: SessionDep,
    tenant: CurrentTenant,
    given: LastEventId,
) -> StreamingResponse:
    """Server-sent events of one job (`event: job|stage|shard`, `data: JSON`, `id: seq`); the
    stream ends after the job's terminal event, or after `sse_max_seconds` (reconnect with
    `Last-Event-ID` to resume; one that is not a sequence number, 0 to 2^63 - 1, is
    ignored)."""
    _own_job(session, job_id, tenant)
    after = given or 0
    reader = request.app.state.reader
    max_seconds = request.app.state.settings.sse_max_seconds

    async def stream():
        nonlocal after
        mark = SettledMark()
        idle = 0.0
        loop = asyncio.get_running_loop()
        t_end = loop.time() + max_seconds
        while True:
            rows, state, upto, held = await run_in_threadpool(_events_after, reader, job_id,
                                                              after, mark)
            for ev in rows:
                after = ev.seq
                payload = {
                    "seq": ev.seq,
                    "job_id": ev.job_id,
                    "kind": ev.kind,
                    "data": json.loads(ev.data_json),
                    "at": ev.at.isoformat(),
                }
                yield f"id: {ev.seq}\nevent: {ev.kind}\ndata: {json.dumps(payload)}\n\n"
            after = upto
            if rows:
                idle = 0.0
                continue
            if (state in TERMINAL_JOB_STATES or state is None) and not held:
                return
            if await request.is_disconnected() or loop.time() > t_end:
                return  # a client reconnects with Last-Event-ID
            await asyncio.sleep(0.25)
            idle += 0.25
            if idle >= 15.0:
                idle = 0.0
                yield ": keep-alive\n\n"

    return StreamingResponse(
        stream(), media_type="text/event-stream", headers={"Cache-Control": "no-cache"}
    )


def _require_done(job: Job) -> None:
    if job.state != "succeeded":
        raise ApiError(
            status.HTTP_409_CONFLICT,
            f"{JOB_NOT_FINISHED} (state {job.state})",
            ErrorCode.JOB_NOT_FINISHED,
        )


def _media_type(request: Request, native: str) -> str:
    """`native`, unless the client asks for `application/octet-stream` and not for it."""
    accept = request.headers.get("accept", "")
    return OCTET if OCTET in accept and native not in accept else native


@router.delete(
    "/{job_id}",
    response_model=JobPublic,
    status_code=status.HTTP_202_ACCEPTED,
    operation_id="cancel_job",
    responses=errors(401, JOB_404, 422),
)
def delete_job(
    job_id: str,
    request: Request,
    session: SessionDep,
    writer: WriterDep,
    tenant: CurrentTenant,
    settings: SettingsDep,
) -> JobPublic:
    """Cancel a job: queued shards are dropped, running ones revoked; its state is kept."""
    _own_job(session, job_id, tenant)
    task_ids = ledger.cancel_job(writer, job_id)
    request.app.state.version_cache.drop(job_id)
    if task_ids:
        try:
            # SIGKILL: a pool child deep in numpy/torch did not act on SIGTERM (measured)
            request.app.state.celery.control.revoke(task_ids, terminate=True, signal="SIGKILL")
        except Exception:  # noqa: BLE001 - broker down: workers skip cancelled shards anyway
            pass
    return _read_public(request, job_id)


@router.post(
    "/{job_id}/resume",
    response_model=JobPublic,
    status_code=status.HTTP_202_ACCEPTED,
    operation_id="resume_job",
    responses=errors(401, JOB_404, JOB_NOT_FAILED_409, 422),
)
def resume(job_id: str, request: Request, session: SessionDep, writer: WriterDep,
           tenant: CurrentTenant, settings: SettingsDep) -> JobPublic:
    """Resume a failed job once its cause is gone: its unfinished shards run again, done ones
    are kept (`farm.resume`)."""
    state = _own_job(session, job_id, tenant).state
    session.close()
    sends = resume_job(writer, job_id, ledger.policy_from(settings))
    if sends is None:
        raise ApiError(status.HTTP_409_CONFLICT, f"job is {state}, not failed",
                       ErrorCode.JOB_NOT_FAILED)
    request.app.state.version_cache.drop(job_id)
    try:  # a broker outage is not the client's problem: the sweeper sends them later
        ledger.dispatch(writer, sends, celery_sender(request.app.state.celery),
                        broker_run_id(settings.redis_url))
    except Exception:  # noqa: BLE001
        pass
    return _read_public(request, job_id)
