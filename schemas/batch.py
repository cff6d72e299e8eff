"""Wire models of batches (`/api/v1/batches`): many assets submitted at once, one job each.

A batch's items are jobs like any other (`/jobs/{id}`, `/jobs/{id}/result`); the batch adds
their common defaults, their order, and progress and a result archive over all of them.
Batch state, from its items' job states: `queued` (every item queued), `running` (some item
not finished), then, once every item is finished: `succeeded` (all succeeded), `failed` (some
item failed), else `cancelled`.
"""

from __future__ import annotations

from datetime import datetime
from typing import Any

from pydantic import BaseModel, ConfigDict, Field

from schemas.job import DEFAULT_PRIORITY, JobState
from schemas.settings import BakeSettings

#: the most items one request may carry
MAX_BATCH_ITEMS = 5000


class BatchItemCreate(BaseModel):
    """One item: an uploaded asset (`POST /assets`) and what differs from the batch."""

    model_config = ConfigDict(extra="forbid")

    asset_id: str = Field(min_length=1, max_length=64)
    settings: dict[str, Any] | None = Field(
        None, description="BakeSettings fields that override the batch's `settings` for this "
        "item (field by field; the merged settings are validated like `POST /jobs`).")
    priority: int | None = Field(
        None, ge=0, le=100, description="0..100; null: the batch's `priority`.")


class BatchCreate(BaseModel):
    """Request body of `POST /api/v1/batches`. Every item is checked before anything is
    created: one bad item is a 422 (settings) or 404 (asset) naming `items[i]` and the
    field, and no batch and no job is made."""

    model_config = ConfigDict(extra="forbid")

    name: str | None = Field(None, max_length=200)
    settings: BakeSettings = Field(
        default_factory=BakeSettings, description="Default settings of every item.")
    priority: int = Field(DEFAULT_PRIORITY, ge=0, le=100,
                          description="Default priority of every item (as `JobCreate`).")
    items: list[BatchItemCreate] = Field(min_length=1, max_length=MAX_BATCH_ITEMS)


class BatchCounts(BaseModel):
    """Items by their job's state."""

    total: int
    queued: int = 0
    running: int = 0
    succeeded: int = 0
    failed: int = 0
    cancelled: int = 0


class BatchItemPublic(BaseModel):
    index: int = Field(description="Position in the request's `items`.")
    asset_id: str
    asset_name: str = Field(description="The uploaded file's name.")
    job_id: str
    state: JobState
    priority: int
    progress: float = Field(description="The job's fraction of planned shards done, 0..1.")
    error: str | None = None


class BatchSummary(BaseModel):
    """A batch in a listing (no per-item detail)."""

    id: str
    name: str | None = None
    state: JobState
    priority: int
    counts: BatchCounts
    progress: float = Field(
        description="0..1: the mean over items of 1 for a finished item (succeeded, failed or "
        "cancelled), else the job's fraction of shards done.")
    created_at: datetime
    finished_at: datetime | None = Field(None, description="When its last item finished.")


class BatchPublic(BatchSummary):
    settings: BakeSettings = Field(description="The batch's default settings.")
    items: list[BatchItemPublic]


class BatchesPublic(BaseModel):
    data: list[BatchSummary]
    count: int
