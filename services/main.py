"""The FastAPI application: `uvicorn services.main:app` (settings from the environment).

The API never imports torch or pxr: it enqueues tasks by name, and uploads are checked with
pxr in a child process (`services.validate`). A background thread sweeps the shard ledger
(`farm.ledger.sweep`): it re-sends work lost with a Redis restart or a dead worker.
"""

from __future__ import annotations

import asyncio
import logging
import threading
import time
from contextlib import asynccontextmanager
from datetime import timedelta
from pathlib import Path

from celery import Celery
from fastapi import FastAPI, status
from fastapi.routing import APIRoute
from fastapi.staticfiles import StaticFiles

from farm import ledger
from farm.broker import broker_run_id, celery_sender
from farm.celeryconfig import celery_config
from farm.config import API_V1, Settings, get_settings
from farm.db import session_factory
from schemas.common import ErrorCode
from services import errors
from services.auth import ensure_tokens
from services.deps import TokenCache
from services.errors import ApiError
from services.fastpath import StatusFastPath
from services.limits import AuthFirst, BodyLimit, CpuSlots, ServerTiming
from services.routers import assets, batches, events, farm, job_files, jobs, utils, viewer
from services.status_cache import JobCache, LoopReads, VersionCache
from texelbake.estimate import machinespeed

log = logging.getLogger("texelbake.api")


def custom_generate_unique_id(route: APIRoute) -> str:
    """Names of generated body models (`Body_<tag>-<handler>`). Operation ids are given on each
    route (`operation_id=`), so a handler's rename does not rename a generated client's
    function; `tests/services/test_api_contract.py` checks that every route has one."""
    return f"{route.tags[0]}-{route.name}"


def sweep_once(app: FastAPI, grace: float = 0.0) -> int:
    """One sweep (`farm.ledger.sweep`); `grace` seconds lengthen the lease (`_sweeper`)."""
    st: Settings = app.state.settings
    run_id = broker_run_id(st.redis_url)
    if run_id is None:
        return 0
    sends = ledger.sweep(app.state.writer, run_id, st.lease + timedelta(seconds=grace),
                         policy=ledger.policy_from(st), max_attempts=st.max_attempts)
    if not sends:
        return 0
    return ledger.dispatch(app.state.writer, sends, celery_sender(app.state.celery), run_id)


def _sweeper(app: FastAPI, stop: threading.Event) -> None:
    """Sweep every `sweep_interval` s. After sweeps that failed (the database or Redis was
    out: the workers' heartbeats could not be written either), the next one lengthens the
    lease by the outage, so live shards are not taken for lost for the database's silence."""
    interval = app.state.settings.sweep_interval
    last_ok = time.monotonic()
    while not stop.wait(interval):
        try:
            n = sweep_once(app, grace=max(0.0, time.monotonic() - last_ok - 2 * interval))
            last_ok = time.monotonic()
            if n:
                log.info("sweeper re-sent %d messages", n)
        except Exception as exc:  # noqa: BLE001 - keep sweeping; the next tick retries
            log.warning("sweep failed: %r", exc)


#: the dashboard's built bundle (`web/`, built by `make setup`: npm ci && npm run build)
WEB_DIST = Path(__file__).resolve().parents[1] / "web" / "dist"
DASHBOARD_NOT_BUILT = "the dashboard is not built: run `make setup` (npm ci && npm run build in web/)"


def mount_dashboard(app: FastAPI, dist: Path) -> None:
    """Serve the dashboard at `/` (same origin as `/api/v1`), mounted after the API routes so
    they match first. Without a build, `/` answers a 503 naming the missing build."""
    if (dist / "index.html").is_file():
        app.mount("/", StaticFiles(directory=dist, html=True), name="dashboard")
        return

    @app.get("/", include_in_schema=False, tags=["dashboard"], operation_id="dashboard")
    def dashboard_not_built() -> None:
        raise ApiError(
            status.HTTP_503_SERVICE_UNAVAILABLE,
            f"{DASHBOARD_NOT_BUILT} ({dist} has no index.html)",
            ErrorCode.SERVICE_UNAVAILABLE,
        )


def create_app(settings: Settings | None = None, *, sweeper: bool = True) -> FastAPI:
    settings = settings or get_settings()
    settings.artifact_root.mkdir(parents=True, exist_ok=True)

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        ensure_tokens(app.state.writer, settings.secret_key, settings.tokens)
        stop = threading.Event()
        thread = None
        if sweeper:
            thread = threading.Thread(target=_sweeper, args=(app, stop), daemon=True)
            thread.start()
        # the cost model's machine speed (~1 s of CPU, `texelbake.estimate.machinespeed`) measured now,
        # so no job's first status read pays it
        threading.Thread(target=machinespeed.this_machine, daemon=True,
                         name="machine-speed").start()
        # the versions of the jobs being polled, re-read off the loop (services/status_cache.py)
        refresh = asyncio.create_task(app.state.version_cache.refresh(app.state.loop_reads))
        yield
        refresh.cancel()
        stop.set()
        if thread is not None:
            thread.join(timeout=5)
        app.state.loop_reads.close()

    app = FastAPI(
        title="texelbake",
        version="0.1.0",
        openapi_url=f"{API_V1}/openapi.json",
        generate_unique_id_function=custom_generate_unique_id,
        lifespan=lifespan,
    )
    app.state.settings = settings
    app.state.writer = session_factory(settings.db_url)
    app.state.reader = session_factory(settings.db_url, readonly=True)
    # the event loop's reads, on threads and connections of their own
    app.state.loop_reads = LoopReads(session_factory(settings.db_url, role="inline"))
    app.state.token_cache = TokenCache()
    app.state.job_cache = JobCache()
    app.state.version_cache = VersionCache(settings.status_cache_seconds)
    app.state.cpu_slots = CpuSlots(settings.cpu_route_concurrency)
    celery = Celery("texelbake")
    celery.conf.update(celery_config(settings))
    app.state.celery = celery
    for r in (utils.router, assets.router, jobs.router, job_files.router, batches.router,
              viewer.router, events.router, farm.router):
        app.include_router(r, prefix=API_V1)
    mount_dashboard(app, settings.web_dist or WEB_DIST)
    errors.install(app)
    app.add_middleware(BodyLimit, max_bytes=settings.max_upload_bytes)
    app.add_middleware(AuthFirst, state=app.state)  # a 401 before a body is read or limited
    if settings.status_fast_path:
        app.add_middleware(StatusFastPath, state=app.state)  # cached status reads
    app.add_middleware(ServerTiming)  # outermost: times the whole app
    return app


def __getattr__(name: str):
    """`services.main:app` is built on first access, so importing this module needs no env."""
    if name == "app":
        globals()["app"] = create_app()
        return globals()["app"]
    raise AttributeError(name)
