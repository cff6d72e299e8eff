"""Wire models of bake jobs (`/api/v1/jobs`): the job, its stages, its shards and its events.

Job states: queued (created; the plan task is on the `ingest` queue) -> running (planned; stages
are being worked off) -> succeeded | failed | cancelled. Stage and shard states: pending (waiting
for the stages it depends on) -> queued (sent to the broker) -> running -> done | failed |
cancelled.
"""

from __future__ import annotations

from datetime import datetime
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from schemas.settings import BakeSettings

JobState = Literal["queued", "running", "succeeded", "failed", "cancelled"]
UnitState = Literal["pending", "queued", "running", "done", "failed", "cancelled"]
TERMINAL_JOB_STATES: frozenset[str] = frozenset({"succeeded", "failed", "cancelled"})
#: a job's priority when the request names none (0..100)
DEFAULT_PRIORITY = 50


class JobCreate(BaseModel):
    """Request body of `POST /api/v1/jobs`."""

    model_config = ConfigDict(extra="forbid")

    asset_id: str = Field(min_length=1, max_length=64)
    settings: BakeSettings = Field(default_factory=BakeSettings)
    priority: int = Field(
        DEFAULT_PRIORITY, ge=0, le=100,
        description="0..100, higher first: the shard ledger sends a queue's ready shards to the "
        "workers in priority order (then oldest job first), within the tenant's running-shard "
        "limit. Not part of the bake: it does not change the result or its artifact keys.")


class ShardPublic(BaseModel):
    model_config = ConfigDict(from_attributes=True)

    shard: int
    state: UnitState
    attempts: int = Field(description="Times a worker started this shard (redeliveries included).")
    worker: str | None = Field(None, description="hostname:pid of the last worker that ran it.")
    seconds: float | None = Field(None, description="Wall time of the successful run.")
    artifact_key: str | None = None
    error: str | None = None


class StagePublic(BaseModel):
    name: str
    queue: str
    state: UnitState
    depends_on: list[str]
    n_shards: int
    n_done: int
    progress: float = Field(description="Fraction of shards done, 0..1.")
    started_at: datetime | None = None
    finished_at: datetime | None = None
    seconds: float | None = Field(None, description="Wall time from first start to last finish.")
    shards: list[ShardPublic] = Field(default_factory=list)


class SkippedStage(BaseModel):
    stage: str
    reason: str


class JobEstimate(BaseModel):
    """The cost model's prediction of a bake (`texelbake.estimate.costmodel.estimate`): from the
    settings (texel count, samples per texel, direction pairs) and the worker count, before
    the geometry exists (atlas fill assumed)."""

    seconds: float = Field(description="Predicted wall seconds of the whole bake.")
    workers: int = Field(description="Worker processes the prediction assumes.")
    cpm_seconds: float = Field(description="Predicted CPU seconds of the CPM fit, all levels.")
    eta: datetime | None = Field(
        None, description="started_at + seconds while the job runs; null before it starts.")
    machine_speed: dict[str, float] | None = Field(
        None, description="Seconds per kind of work (grid, blas, rays, python) on the API's "
        "machine against the machine the cost model was fitted on (> 1: slower); the "
        "estimate is scaled by them (`texelbake.estimate.machinespeed`).")


class JobPublic(BaseModel):
    id: str
    asset_id: str
    state: JobState
    priority: int = Field(DEFAULT_PRIORITY, description="0..100, higher first (`JobCreate`).")
    settings: BakeSettings
    progress: float = Field(description="Fraction of all planned shards done, 0..1.")
    stages: list[StagePublic] = Field(description="Planned stages in execution order.")
    skipped: list[SkippedStage] = Field(default_factory=list)
    error: str | None = None
    created_at: datetime
    started_at: datetime | None = None
    finished_at: datetime | None = None
    seconds: float | None = None
    previews: list[str] = Field(default_factory=list, description="Names under .../previews/.")
    estimate: JobEstimate | None = Field(None, description="Predicted time (the cost model's estimate).")
    outcome: Literal["completed", "completed with warnings"] | None = Field(
        None, description="A succeeded job's quality gate (texelbake.stages.quality): 'completed with "
        "warnings' when the bake missed a target, listed in `warnings`; null before success.")
    warnings: list[str] = Field(
        default_factory=list, description="Each missed quality target, naming the LOD or CPM "
        "level (the same list `texelbake bake` prints when it exits with status 3).")


class JobSummary(BaseModel):
    """A job in a listing (no per-shard detail)."""

    id: str
    asset_id: str
    state: JobState
    priority: int = Field(DEFAULT_PRIORITY, description="0..100, higher first.")
    progress: float
    error: str | None = None
    created_at: datetime
    finished_at: datetime | None = None


class JobsPublic(BaseModel):
    data: list[JobSummary]
    count: int


class JobEvent(BaseModel):
    """One server-sent event: `id: seq`, `event: kind`, `data: JobEvent JSON`."""

    seq: int
    job_id: str
    kind: str = Field(description="job | stage | shard")
    data: dict[str, Any]
    at: datetime
