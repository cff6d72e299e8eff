"""The one settings class of the service, read from the environment (prefix `TEXELBAKE_`).

Shared by the API and the Celery workers. The secret and the broker URL are required; the
placeholder secret `changethis` is refused outside `environment=development`.
"""

from __future__ import annotations

from datetime import timedelta
from functools import lru_cache
from pathlib import Path
from typing import Literal

from pydantic import Field, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

PLACEHOLDER_SECRET = "changethis"
API_V1 = "/api/v1"


class Settings(BaseSettings):
    model_config = SettingsConfigDict(env_prefix="TEXELBAKE_", env_file=None, extra="ignore")

    environment: Literal["development", "test", "production"] = "development"
    secret_key: str = Field(min_length=8, description="HMAC key for stored token digests.")
    redis_url: str = Field(description="Celery broker, e.g. redis://127.0.0.1:6379/0")
    database_url: str | None = Field(
        None, description="SQLAlchemy URL; default SQLite at <artifact_root>/texelbake.db"
    )
    artifact_root: Path = Field(Path("texelbake-data"), description="Shared by every worker.")
    tokens: dict[str, str] = Field(
        default_factory=dict, description="Bootstrap bearer tokens: token -> tenant (JSON)."
    )
    # uploads
    max_upload_bytes: int = Field(256 << 20, ge=1)
    max_unpacked_bytes: int = Field(1 << 30, ge=1, description="Zip/usdz: total unpacked cap.")
    max_zip_ratio: float = Field(100.0, gt=1.0, description="Zip/usdz: unpacked/packed cap.")
    max_zip_members: int = Field(4096, ge=1)
    validate_timeout: float = Field(120.0, gt=0, description="Seconds for the pxr check.")
    check_memory_bytes: int = Field(
        2 << 30, ge=64 << 20, description="Address space one upload check (unpacking and pxr) "
        "may map beyond the warm checker's own; past it the check fails, not the machine.")
    validate_concurrency: int | None = Field(
        None, ge=1, description="Upload checks (pxr child processes) at once per API process; "
        "more wait their turn. Default: the CPU count.")
    # farm
    visibility_timeout: int = Field(
        3600, ge=5, description="Redis redelivery of unacked messages; above the longest shard."
    )
    max_attempts: int = Field(3, ge=1, description="Redelivery cap: starts of one shard.")
    max_retries: int = Field(4, ge=0, description="Retries of a transient fault per delivery.")
    retry_backoff_max: int = Field(60, ge=1)
    sse_max_seconds: float = Field(
        300.0, gt=0, description="An events stream closes after this long; clients reconnect."
    )
    heartbeat_interval: float = Field(
        0.5, gt=0, description="Seconds between a running shard's heartbeats (from a thread "
        "of the process that runs it)."
    )
    heartbeat_timeout: float = Field(
        3.0, gt=0, description="A running shard's lease: silent this long, it is re-queued "
        "(worker gone). At least 4 heartbeat intervals; the longest gap between beats of a "
        "busy worker on a loaded machine is logged per shard (docs/decisions.md).")
    shard_time_limit: float | None = Field(
        None, gt=0, description="A shard running longer than this is presumed stuck (a "
        "heartbeat proves its process lives, not that it progresses): it stops beating, "
        "records why, and Celery kills its pool child `shard_kill_grace` s later; the sweeper "
        "re-queues it, up to max_attempts. With the grace it must stay below "
        "visibility_timeout. Default: half the visibility_timeout (30 min).")
    shard_kill_grace: float | None = Field(
        None, gt=0, description="Seconds between a shard's time limit and Celery's hard kill "
        "of its pool child (the time to record why); below heartbeat_timeout. Default: 10 s "
        "or half the heartbeat_timeout if that is less.")
    sweep_interval: float = Field(0.5, gt=0, description="Seconds between ledger sweeps (API).")
    # scheduling: the shard ledger admits ready shards to the broker
    queue_backlog: int = Field(
        2, ge=0, description="Admitted shards per queue group waiting unstarted in the broker; the "
        "rest wait in the ledger, which admits by job priority (Redis queues are FIFO). "
        "0: no limit (every ready shard is sent at once and priority has no effect).")
    queue_groups: dict[str, list[str]] | None = Field(
        None, description="Queues served by the same workers, sharing one backlog and one "
        "priority order (JSON: group -> queues); default the worker families "
        "(prep: ingest, geometry, export; numeric: cpm, avis, btf; render: render).")
    tenant_max_running_shards: int = Field(
        0, ge=0, description="Shards one tenant may have admitted or running at once, over "
        "all queues; 0: no limit. Below the farm's worker count, another tenant's job always "
        "finds a worker.")
    tenant_shard_limits: dict[str, int] = Field(
        default_factory=dict, description="Per-tenant overrides of tenant_max_running_shards "
        "(JSON: tenant -> limit; 0: no limit).")
    status_cache_seconds: float = Field(
        0.05, ge=0, description="Seconds a job's status version (state, newest event), once "
        "read from the database, answers status reads in an API process (the versions of "
        "polled jobs are re-read in the background twice as often); 0: read on every request.")
    status_fast_path: bool = Field(
        True, description="Answer a status read whose token, job version and body are cached "
        "before the framework (services/fastpath.py); false: always through the route.")
    cpu_route_concurrency: int = Field(
        2, ge=0, description="POST /jobs requests (Python CPU work in the thread pool) served "
        "at once per API process, the rest wait on the event loop without a thread; 0: no "
        "limit.")
    estimate_workers: int = Field(
        2, ge=1, description="Worker processes the cost model assumes for a job's estimate."
    )
    web_dist: Path | None = Field(
        None, description="The dashboard's built bundle served at /; default <repo>/web/dist."
    )

    @model_validator(mode="after")
    def _refuse_placeholder(self) -> Settings:
        if self.secret_key == PLACEHOLDER_SECRET and self.environment != "development":
            raise ValueError(
                f"TEXELBAKE_SECRET_KEY is the placeholder {PLACEHOLDER_SECRET!r}; "
                f"set a real secret for environment={self.environment!r}"
            )
        return self

    @property
    def db_url(self) -> str:
        if self.database_url:
            return self.database_url
        return f"sqlite:///{(self.artifact_root / 'texelbake.db').resolve()}"

    @model_validator(mode="after")
    def _time_limit(self) -> Settings:
        if self.shard_time_limit is None:
            self.shard_time_limit = self.visibility_timeout / 2
        if self.shard_kill_grace is None:
            self.shard_kill_grace = min(10.0, self.heartbeat_timeout / 2)
        if self.shard_time_limit + self.shard_kill_grace >= self.visibility_timeout:
            raise ValueError(
                f"shard_time_limit + shard_kill_grace ({self.shard_time_limit} + "
                f"{self.shard_kill_grace} s) must stay below visibility_timeout "
                f"({self.visibility_timeout} s): Redis would deliver a running shard again"
            )
        if self.shard_kill_grace >= self.heartbeat_timeout:
            raise ValueError(
                f"shard_kill_grace ({self.shard_kill_grace} s) must stay below "
                f"heartbeat_timeout ({self.heartbeat_timeout} s): the sweeper would re-queue a "
                f"shard past its time limit before Celery killed it"
            )
        return self

    @property
    def task_hard_time_limit(self) -> float:
        """Celery's hard limit on one task: the shard time limit and its grace."""
        return self.shard_time_limit + self.shard_kill_grace

    @property
    def lease(self) -> timedelta:
        """A running shard's lease (`heartbeat_timeout`) as the ledger takes it."""
        return timedelta(seconds=self.heartbeat_timeout)

    @model_validator(mode="after")
    def _heartbeats(self) -> Settings:
        # four beats may be late or lost (a loaded machine, a busy database) before a live
        # worker's shard is taken for lost
        if self.heartbeat_timeout < 4 * self.heartbeat_interval:
            raise ValueError(
                f"heartbeat_timeout ({self.heartbeat_timeout}) must be at least four times "
                f"heartbeat_interval ({self.heartbeat_interval})"
            )
        return self


@lru_cache
def get_settings() -> Settings:
    return Settings()  # type: ignore[call-arg]
