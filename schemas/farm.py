"""Wire models of the farm view (`/api/v1/farm`): workers, queues, current shards."""

from __future__ import annotations

from datetime import datetime

from pydantic import BaseModel, Field


class WorkerPublic(BaseModel):
    name: str = Field(description="Celery node name, e.g. numeric@host.")
    queues: list[str]
    active: int = Field(description="Tasks the worker is running now (Celery inspection).")
    concurrency: int | None = Field(None, description="Pool processes, when reported.")


class QueuePublic(BaseModel):
    name: str
    length: int | None = Field(None, description="Messages waiting in the broker; None if down.")
    queued: int = Field(description="Shards the ledger has queued on it (all tenants).")
    running: int = Field(description="Shards the ledger has running on it (all tenants).")


class CurrentShard(BaseModel):
    """A running shard. Another tenant's shard is shown without its job id."""

    job_id: str | None = Field(None, description="None when the job is another tenant's.")
    stage: str
    shard: int
    queue: str
    worker: str | None = Field(None, description="hostname:pid of the worker running it.")
    started_at: datetime | None = None
    attempts: int


class FarmPublic(BaseModel):
    broker: bool = Field(description="The broker answered.")
    workers: list[WorkerPublic]
    queues: list[QueuePublic]
    current: list[CurrentShard]
    at: datetime
