"""`/farm`: what the farm is doing (Flower-like): workers and their queues from Celery's own
inspection, queue lengths from the broker, running and queued shards from the shard ledger;
and the same snapshot as server-sent events (`/farm/events`). Another tenant's shards are
counted and shown without their job id."""

from __future__ import annotations

import asyncio
import json
import threading
import time

import redis
from fastapi import APIRouter, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import StreamingResponse
from sqlalchemy import func, select
from sqlalchemy.orm import sessionmaker

from farm.db import Job, Shard, utcnow
from schemas.farm import CurrentShard, FarmPublic, QueuePublic, WorkerPublic
from schemas.queues import QUEUES
from services.deps import CurrentTenant
from services.errors import errors

router = APIRouter(prefix="/farm", tags=["farm"])

#: seconds Celery's inspection waits for workers' replies
INSPECT_TIMEOUT = 1.0
#: seconds between two snapshots of the events stream
FARM_EVENT_INTERVAL = 2.0


def queue_lengths(redis_url: str) -> dict[str, int] | None:
    """Messages waiting per queue: the Redis list of the queue (kombu's Redis transport keeps
    one list per queue, named as the queue). None when the broker does not answer."""
    try:
        r = redis.Redis.from_url(redis_url, socket_timeout=1.0, socket_connect_timeout=1.0)
        try:
            pipe = r.pipeline()
            for q in QUEUES:
                pipe.llen(q)
            return dict(zip(QUEUES, (int(n) for n in pipe.execute()), strict=True))
        finally:
            r.close()
    except (redis.RedisError, OSError):
        return None


def inspect_workers(celery) -> list[WorkerPublic]:  # noqa: ANN001
    """Workers that answer Celery's inspection within `INSPECT_TIMEOUT`: the first broadcast
    waits the whole timeout (it cannot know how many workers there are), the next two return
    as soon as that many workers replied."""
    try:
        queues = celery.control.inspect(timeout=INSPECT_TIMEOUT).active_queues() or {}
        if not queues:
            return []
        insp = celery.control.inspect(timeout=INSPECT_TIMEOUT, limit=len(queues))
        active = insp.active() or {}
        stats = insp.stats() or {}
    except Exception:  # noqa: BLE001 - broker down: no workers can be seen
        return []
    out = []
    for name in sorted(queues):
        pool = (stats.get(name) or {}).get("pool") or {}
        conc = pool.get("max-concurrency")
        out.append(
            WorkerPublic(
                name=name,
                queues=sorted(q.get("name", "") for q in queues.get(name) or []),
                active=len(active.get(name) or []),
                concurrency=int(conc) if isinstance(conc, int) else None,
            )
        )
    return out


class WorkerCache:
    """The last inspection, kept `ttl` seconds: every farm view and stream of every tenant
    shares one broadcast per `ttl` (an inspection takes `INSPECT_TIMEOUT`)."""

    def __init__(self, ttl: float = FARM_EVENT_INTERVAL):
        self.ttl = ttl
        self._lock = threading.Lock()
        self._at = -float("inf")
        self._workers: list[WorkerPublic] = []

    def get(self, celery) -> list[WorkerPublic]:  # noqa: ANN001
        with self._lock:
            if time.monotonic() - self._at > self.ttl:
                self._workers = inspect_workers(celery)
                self._at = time.monotonic()
            return list(self._workers)


_workers = WorkerCache()


def farm_snapshot(reader: sessionmaker, celery, redis_url: str, tenant: str) -> FarmPublic:  # noqa: ANN001
    lengths = queue_lengths(redis_url)
    with reader() as s:
        counts = {
            (q, st): int(n)
            for q, st, n in s.execute(
                select(Shard.queue, Shard.state, func.count())
                .where(Shard.state.in_(("queued", "running")))
                .group_by(Shard.queue, Shard.state)
            ).all()
        }
        rows = s.execute(
            select(Shard, Job.tenant)
            .join(Job, Job.id == Shard.job_id)
            .where(Shard.state == "running")
            .order_by(Shard.started_at, Shard.id)
            .limit(500)
        ).all()
        current = [
            CurrentShard(
                job_id=sh.job_id if owner == tenant else None,
                stage=sh.stage,
                shard=sh.shard,
                queue=sh.queue,
                worker=sh.worker,
                started_at=sh.started_at,
                attempts=sh.attempts,
            )
            for sh, owner in rows
        ]
    queues = [
        QueuePublic(
            name=q,
            length=None if lengths is None else lengths[q],
            queued=counts.get((q, "queued"), 0),
            running=counts.get((q, "running"), 0),
        )
        for q in QUEUES
    ]
    return FarmPublic(
        broker=lengths is not None,
        workers=_workers.get(celery) if lengths is not None else [],
        queues=queues,
        current=current,
        at=utcnow(),
    )


@router.get("", response_model=FarmPublic, operation_id="read_farm", responses=errors(401, 422))
def read_farm(request: Request, tenant: CurrentTenant) -> FarmPublic:
    """Workers and their queues, queue lengths, and the shards running now."""
    st = request.app.state
    return farm_snapshot(st.reader, st.celery, st.settings.redis_url, tenant)


@router.get(
    "/events",
    response_class=StreamingResponse,
    operation_id="read_farm_events",
    responses={
        200: {
            "content": {"text/event-stream": {"schema": {"type": "string"}}},
            "description": "Server-sent events: `event: farm`, `data: FarmPublic JSON`.",
        },
        **errors(401, 422),
    },
)
def read_farm_events(request: Request, tenant: CurrentTenant) -> StreamingResponse:
    """The farm snapshot every 2 s as server-sent events; the stream ends after
    `sse_max_seconds` (a client reconnects)."""
    st = request.app.state
    max_seconds = st.settings.sse_max_seconds

    async def stream():
        loop = asyncio.get_running_loop()
        t_end = loop.time() + max_seconds
        seq = 0
        while True:
            snap = await run_in_threadpool(
                farm_snapshot, st.reader, st.celery, st.settings.redis_url, tenant
            )
            seq += 1
            yield f"id: {seq}\nevent: farm\ndata: {json.dumps(snap.model_dump(mode='json'))}\n\n"
            if await request.is_disconnected() or loop.time() > t_end:
                return
            await asyncio.sleep(FARM_EVENT_INTERVAL)

    return StreamingResponse(
        stream(), media_type="text/event-stream", headers={"Cache-Control": "no-cache"}
    )
