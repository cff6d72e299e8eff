"""`/events`: the server-sent events of all of this tenant's jobs on one stream (the job list
follows every job with one connection: a browser holds at most six per host, so a stream per
job would starve the page's other requests)."""

from __future__ import annotations

import asyncio
import json

from fastapi import APIRouter, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import StreamingResponse
from sqlalchemy import func, select
from sqlalchemy.orm import sessionmaker

from farm.db import Event, Job
from services.deps import CurrentTenant, LastEventId
from services.errors import errors
from services.event_order import SCAN, SettledMark, events_upto

router = APIRouter(prefix="/events", tags=["events"])

#: most events sent per read of the database
BATCH = 500


def tenant_events_after(reader: sessionmaker, tenant: str, after: int, mark: SettledMark
                        ) -> tuple[list[Event], int]:
    """(this tenant's events in (after, settled], settled): `event_order` says why a stream
    never reads past the settled mark."""
    with reader() as s:
        rows, upto, _ = events_upto(
            s, mark, select(Event).join(Job, Job.id == Event.job_id).where(Job.tenant == tenant),
            after, BATCH)
    return rows, upto


def start_seq(reader: sessionmaker, mark: SettledMark) -> int:
    """Where a new stream starts: the settled mark over the newest SCAN sequence values (an
    event still in flight below the newest committed one is sent when it commits)."""
    with reader() as s:
        top = int(s.scalar(select(func.max(Event.seq))) or 0)
        return mark.read(s, max(top - SCAN, 0))[0]


@router.get(
    "",
    response_class=StreamingResponse,
    operation_id="read_events",
    responses={
        200: {
            "content": {"text/event-stream": {"schema": {"type": "string"}}},
            "description": "Server-sent events of this tenant's jobs.",
        },
        **errors(401, 422),
    },
)
def read_events(request: Request, tenant: CurrentTenant, given: LastEventId) -> StreamingResponse:
    """Events of all of this tenant's jobs (`event: job|stage|shard`, `data: JobEvent JSON`,
    `id: seq`), from now on, or after `Last-Event-ID` when given. The stream opens with
    `event: ready` (its `id` the sequence number it starts after): a client that read the
    job list before has missed nothing once it re-reads the list on `ready`. It ends after
    `sse_max_seconds` (reconnect with `Last-Event-ID`). A `Last-Event-ID` that is not a
    sequence number (0 to 2^63 - 1) is ignored."""
    reader = request.app.state.reader
    max_seconds = request.app.state.settings.sse_max_seconds

    async def stream():
        mark = SettledMark()
        after = given if given is not None else await run_in_threadpool(start_seq, reader, mark)
        yield f"id: {after}\nevent: ready\ndata: {json.dumps({'after': after})}\n\n"
        loop = asyncio.get_running_loop()
        t_end = loop.time() + max_seconds
        idle = 0.0
        while True:
            rows, upto = await run_in_threadpool(tenant_events_after, reader, tenant, after,
                                                 mark)
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
            if await request.is_disconnected() or loop.time() > t_end:
                return
            await asyncio.sleep(0.25)
            idle += 0.25
            if idle >= 15.0:
                idle = 0.0
                yield ": keep-alive\n\n"

    return StreamingResponse(
        stream(), media_type="text/event-stream", headers={"Cache-Control": "no-cache"}
    )
