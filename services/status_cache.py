"""What a status read needs without the database: the serialized status (`JobCache`), each
job's version (`VersionCache`), and the threads that do the event loop's reads (`LoopReads`).

The event loop never waits on the database. On PostgreSQL a read is a round trip to a server
process that shares the machine's cores: under load a version read on the loop stalled every
request the API was serving for 20-60 ms, once per job per `status_cache_seconds`
(benchmarks/load.py). Reads the loop needs run on `LoopReads`' own threads; the versions of the
jobs being polled are re-read in one query every half `status_cache_seconds` by a background
task, so a poller finds a fresh version instead of waiting for a read, and a request whose
version is not cached joins the read in flight for it, if any.
"""

from __future__ import annotations

import asyncio
import logging
import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from functools import partial
from typing import TypeVar

from fastapi.concurrency import run_in_threadpool
from sqlalchemy import func, select
from sqlalchemy.orm import sessionmaker

from farm.db import Event, Job, retry_disconnect

T = TypeVar("T")
log = logging.getLogger("texelbake.api")

#: a job's version: (tenant, state, newest event seq)
Version = tuple


class LoopReads:
    """Short reads the event loop needs (a token's tenant, job versions), each on one of
    `threads` threads of their own with sessions of `sessions` (the `inline` engine role, a
    pool as large as these threads): the loop awaits them and serves other requests meanwhile,
    and no other work of the process (the thread pool's routes, the sweeper) can hold the
    threads or the connections they read on."""

    def __init__(self, sessions: sessionmaker, threads: int = 2):
        self.sessions = sessions
        self._pool = ThreadPoolExecutor(threads, thread_name_prefix="loop-reads")

    async def run(self, fn: Callable[[sessionmaker], T]) -> T:
        """`fn(sessions)` on a read thread, once more on a dropped connection."""
        loop = asyncio.get_running_loop()
        return await loop.run_in_executor(self._pool, retry_disconnect, partial(fn, self.sessions))

    def close(self) -> None:
        self._pool.shutdown(wait=False)


#: job ids per version query (an IN list)
CHUNK = 500


def job_versions(sessions: sessionmaker, job_ids: list[str]) -> dict[str, Version]:
    """{job id: (tenant, state, newest event seq)} of the jobs that exist, one indexed
    statement per `CHUNK` ids."""
    newest = (select(func.max(Event.seq)).where(Event.job_id == Job.id)
              .correlate(Job).scalar_subquery())  # fmt: skip
    out: dict[str, Version] = {}
    with sessions() as s:
        for i in range(0, len(job_ids), CHUNK):
            rows = s.execute(select(Job.id, Job.tenant, Job.state, newest)
                             .where(Job.id.in_(job_ids[i:i + CHUNK])))  # fmt: skip
            out.update((r[0], tuple(r[1:])) for r in rows)
    return out


class JobCache:
    """Serialized `JobPublic` per (job id, last event seq, state): every ledger transition
    appends an event, so a new seq means a new status. Bounded; cleared when full."""

    def __init__(self, size: int = 2048):
        self.size = size
        self._d: dict[tuple[str, int, str], bytes] = {}
        self._pending: dict[tuple[str, int, str], asyncio.Future] = {}  # builds in flight

    def get(self, key: tuple[str, int, str]) -> bytes | None:
        return self._d.get(key)

    def put(self, key: tuple[str, int, str], body: bytes) -> None:
        if len(self._d) >= self.size:
            self._d.clear()
        self._d[key] = body

    async def build(self, key: tuple[str, int, str], fn: Callable[[], bytes]) -> bytes:
        """The cached body of `key`, else `fn()` in the thread pool, cached; requests that
        miss the same key meanwhile await that one build (when a polled job changed, its 25
        pollers each built the status at once: 25 threads taking turns at the GIL, while the
        event loop waited for its own turns)."""
        cached = self._d.get(key)
        if cached is not None:
            return cached
        fut = self._pending.get(key)
        if fut is None:
            fut = asyncio.ensure_future(run_in_threadpool(fn))
            self._pending[key] = fut
            try:
                body: bytes = await asyncio.shield(fut)
            finally:
                del self._pending[key]
            self.put(key, body)
            return body
        return await asyncio.shield(fut)


class VersionCache:
    """job id -> (tenant, state, newest event seq) for `ttl` seconds after its read: 50 clients
    polling one job share one database read per `ttl` (a status may be that much older than
    the ledger; this process's own cancel and resume drop the entry). `get` and `load` run on
    the event loop; `refresh` keeps the jobs asked for within `keep` seconds fresh; `drop` may
    be called from any thread."""

    def __init__(self, ttl: float, size: int = 4096, keep: float = 2.0):
        self.ttl, self.size, self.keep = ttl, size, keep
        self._d: dict[str, tuple[Version, float]] = {}
        self._asked: dict[str, float] = {}  # job id -> when a request last asked for it
        self._pending: dict[str, asyncio.Future] = {}  # job id -> the read in flight for it
        self._epoch = 0  # drops so far: a read that started before a drop stores nothing
        self._lock = threading.Lock()

    def get(self, job_id: str) -> Version | None:
        now = time.monotonic()
        if len(self._asked) >= self.size:
            self._asked.clear()
        self._asked[job_id] = now
        hit = self._d.get(job_id)
        if hit is None or hit[1] < now:
            return None
        return hit[0]

    def put(self, job_id: str, row: Version, epoch: int | None = None) -> None:
        """Cache `row`, unless `epoch` (the drops counted when its read started) is stale."""
        if self.ttl <= 0:
            return
        with self._lock:
            if epoch is not None and epoch != self._epoch:
                return
            if len(self._d) >= self.size:
                self._d.clear()
            self._d[job_id] = (row, time.monotonic() + self.ttl)

    def drop(self, job_id: str) -> None:
        with self._lock:
            self._epoch += 1
            self._d.pop(job_id, None)

    async def load(self, reads: LoopReads, job_id: str) -> Version | None:
        """The job's version from the database (None: no such job), cached; a read already
        in flight for it (a refresh, another request's) is joined, not repeated."""
        pending = self._pending.get(job_id)
        if pending is None:
            return (await self._read(reads, [job_id])).get(job_id)
        return (await asyncio.shield(pending)).get(job_id)

    async def _read(self, reads: LoopReads, job_ids: list[str]) -> dict[str, Version]:
        epoch = self._epoch
        fut = asyncio.ensure_future(reads.run(partial(job_versions, job_ids=job_ids)))
        for j in job_ids:
            self._pending[j] = fut
        try:
            rows = await asyncio.shield(fut)
        finally:
            for j in job_ids:
                if self._pending.get(j) is fut:
                    del self._pending[j]
        for j, row in rows.items():
            self.put(j, row, epoch)
        return rows

    async def refresh(self, reads: LoopReads) -> None:
        """Forever: every `ttl / 2` seconds, re-read in one query the versions of the jobs
        asked for within the last `keep` seconds, so their entries are renewed before they
        expire (a refresh every `ttl` left each entry expired for the length of a read, and the
        requests then waited for it). A failed read is logged; the requests' own reads report
        the database's errors."""
        if self.ttl <= 0:
            return
        period = self.ttl / 2
        while True:
            t0 = time.monotonic()
            asked = {j: t for j, t in self._asked.items() if t0 - t <= self.keep}
            self._asked = asked
            ids = [j for j in asked if j not in self._pending]
            if ids:
                try:
                    await self._read(reads, ids)
                except Exception as exc:  # noqa: BLE001 - keep refreshing; the next tick retries
                    log.debug("status version refresh failed: %r", exc)
            await asyncio.sleep(max(0.0, period - (time.monotonic() - t0)))
