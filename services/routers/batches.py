"""`/batches`: create many jobs at once (one per item), list, read progress, cancel, and the
finished batch as one archive. A tenant sees only its own batches: anyone else's is a 404.
Items are ordinary jobs made by the same path as `POST /jobs` (`services.submission`)."""

from __future__ import annotations

import hashlib
import json
import re
import uuid
from datetime import datetime
from pathlib import Path
from typing import Any

from fastapi import BackgroundTasks, Request, status
from fastapi.exceptions import RequestValidationError
from fastapi.responses import FileResponse
from fastapi.routing import APIRouter
from pydantic import ValidationError
from sqlalchemy import func, select
from sqlalchemy.orm import Session

from farm import ledger, storage
from farm.db import Asset, Batch, BatchItem, Job, Shard, Stage
from schemas.batch import (
    BatchCounts,
    BatchCreate,
    BatchesPublic,
    BatchItemPublic,
    BatchPublic,
    BatchSummary,
)
from schemas.common import ErrorCode
from schemas.job import TERMINAL_JOB_STATES
from schemas.settings import BakeSettings
from services.deps import CurrentTenant, LimitQ, SessionDep, SettingsDep, SkipQ
from services.errors import ApiError, errors
from services.job_view import stored_settings
from services.routers.jobs import BINARY, OCTET, _media_type
from services.submission import BatchSpec, JobSpec, create_jobs, own_asset
from texelbake.io.archive import folder_members, write_zip

router = APIRouter(prefix="/batches", tags=["batches"])

BATCH_NOT_FOUND = "batch not found"
BATCH_NOT_FINISHED = "batch has not finished"
BATCH_404 = (404, "`batch_not_found`: no such batch for this tenant.")
BATCH_409 = (409, "`batch_not_finished`: some item is still queued or running.")
ITEM_404 = (404, "`asset_not_found`: an item's asset is not this tenant's; `detail` names "
            "`items[i].asset_id`. Nothing was created.")
_UNSAFE = re.compile(r"[^A-Za-z0-9._-]+")


def _own_batch(session: Session, batch_id: str, tenant: str) -> Batch:
    batch = session.get(Batch, batch_id)
    if batch is None or batch.tenant != tenant:
        raise ApiError(status.HTTP_404_NOT_FOUND, BATCH_NOT_FOUND, ErrorCode.BATCH_NOT_FOUND)
    return batch


def _item_rows(session: Session, batch_ids: list[str]) -> list[Any]:
    """(batch_id, position, job id, asset id, asset filename, state, priority, error,
    finished_at) of every item of the batches, in batch and item order."""
    if not batch_ids:
        return []
    return list(session.execute(
        select(BatchItem.batch_id, BatchItem.position, Job.id, Job.asset_id, Asset.filename,
               Job.state, Job.priority, Job.error, Job.finished_at)
        .join(Job, Job.id == BatchItem.job_id)
        .join(Asset, Asset.id == Job.asset_id)
        .where(BatchItem.batch_id.in_(batch_ids))
        .order_by(BatchItem.batch_id, BatchItem.position)
    ).all())


def _shard_progress(session: Session, job_ids: list[str]) -> dict[str, float]:
    """Fraction of planned shards done per job (0 for a job not planned yet)."""
    if not job_ids:
        return {}
    totals = dict(session.execute(
        select(Stage.job_id, func.sum(Stage.n_shards))
        .where(Stage.job_id.in_(job_ids)).group_by(Stage.job_id)).all())
    dones = dict(session.execute(
        select(Shard.job_id, func.count())
        .where(Shard.job_id.in_(job_ids), Shard.state == "done").group_by(Shard.job_id)).all())
    return {j: (int(dones.get(j, 0)) / int(totals[j]) if totals.get(j) else 0.0)
            for j in job_ids}


def batch_state(states: list[str]) -> str:
    """A batch's state from its items' job states (`schemas.batch`)."""
    if all(s == "queued" for s in states):
        return "queued"
    if any(s not in TERMINAL_JOB_STATES for s in states):
        return "running"
    if all(s == "succeeded" for s in states):
        return "succeeded"
    return "failed" if "failed" in states else "cancelled"


def _summary(b: Batch, counts: dict[str, int], open_progress: float,
             last_finished: datetime | None) -> dict[str, Any]:
    """`BatchSummary` fields from item counts by state, the summed shard progress of the
    unfinished items, and the newest finish of a finished item."""
    total = sum(counts.values())
    state = batch_state([st for st, n in counts.items() if n])
    finished = sum(n for st, n in counts.items() if st in TERMINAL_JOB_STATES)
    return {
        "id": b.id, "name": b.name, "state": state, "priority": b.priority,
        "counts": BatchCounts(total=total, **counts),
        "progress": (finished + open_progress) / total if total else 0.0,
        "created_at": b.created_at,
        "finished_at": last_finished if state in TERMINAL_JOB_STATES else None,
    }


def _with_items(session: Session, batch: Batch) -> tuple[dict[str, Any], list[BatchItemPublic]]:
    """One batch's `BatchSummary` fields and its items."""
    rows = _item_rows(session, [batch.id])
    progress = _shard_progress(
        session, [r.id for r in rows if r.state not in TERMINAL_JOB_STATES])
    items = [BatchItemPublic(
        index=r.position, asset_id=r.asset_id, asset_name=r.filename, job_id=r.id,
        state=r.state, priority=r.priority, error=r.error,
        progress=1.0 if r.state == "succeeded" else progress.get(r.id, 0.0)) for r in rows]
    counts: dict[str, int] = {}
    for r in rows:
        counts[r.state] = counts.get(r.state, 0) + 1
    ends = [r.finished_at for r in rows
            if r.state in TERMINAL_JOB_STATES and r.finished_at is not None]
    return _summary(batch, counts, sum(progress.values()), max(ends, default=None)), items


def _summaries(session: Session, batches: list[Batch]) -> list[BatchSummary]:
    """Many batches' summaries from aggregates (no per-item rows but the unfinished)."""
    ids = [b.id for b in batches]
    if not ids:
        return []
    joined = select(BatchItem.batch_id).join(Job, Job.id == BatchItem.job_id).where(
        BatchItem.batch_id.in_(ids))
    counts: dict[str, dict[str, int]] = {i: {} for i in ids}
    ends: dict[str, list[datetime]] = {i: [] for i in ids}
    for bid, st, n, end in session.execute(
            joined.add_columns(Job.state, func.count(), func.max(Job.finished_at))
            .group_by(BatchItem.batch_id, Job.state)):
        counts[bid][st] = int(n)
        if st in TERMINAL_JOB_STATES and end is not None:
            ends[bid].append(end)
    open_jobs = session.execute(joined.add_columns(Job.id).where(
        Job.state.not_in(list(TERMINAL_JOB_STATES)))).all()
    progress = _shard_progress(session, [j for _, j in open_jobs])
    open_sum: dict[str, float] = dict.fromkeys(ids, 0.0)
    for bid, j in open_jobs:
        open_sum[bid] += progress[j]
    return [BatchSummary(**_summary(b, counts[b.id], open_sum[b.id], max(ends[b.id], default=None)))
            for b in batches]


def batch_public(session: Session, batch: Batch) -> BatchPublic:
    fields, items = _with_items(session, batch)
    return BatchPublic(**fields, settings=stored_settings(batch.settings_json, f"batch {batch.id}"),
                       items=items)


def _read_public(request: Request, batch_id: str) -> BatchPublic:
    with request.app.state.reader() as s:
        return batch_public(s, s.get(Batch, batch_id))


def _item_specs(body: BatchCreate) -> list[JobSpec]:
    """Each item's settings (the batch's, overridden field by field by the item's) and
    priority; every item's problems in one 422, located at `items[i].settings.<field>`."""
    defaults = body.settings.model_dump()
    specs, issues = [], []
    for i, item in enumerate(body.items):
        try:
            merged = BakeSettings.model_validate({**defaults, **(item.settings or {})})
        except ValidationError as exc:
            issues += [{"loc": ["body", "items", i, "settings", *e["loc"]], "msg": e["msg"],
                        "type": e["type"]} for e in exc.errors()]
            continue
        priority = body.priority if item.priority is None else item.priority
        specs.append(JobSpec(item.asset_id, merged.model_dump_json(), priority,
                             ("body", "items", i, "settings")))
    if issues:
        raise RequestValidationError(issues)
    return specs


@router.post(
    "",
    response_model=BatchPublic,
    status_code=status.HTTP_201_CREATED,
    operation_id="create_batch",
    responses=errors(401, ITEM_404, 413, 422),
)
def create_batch(
    body: BatchCreate, request: Request, session: SessionDep, tenant: CurrentTenant,
    later: BackgroundTasks,
) -> BatchPublic:
    """Create a batch: one job per item, all or nothing (every item is checked first)."""
    specs = _item_specs(body)
    for i, spec in enumerate(specs):
        own_asset(session, tenant, spec.asset_id, where=f"items[{i}].asset_id")
    session.close()  # hold no read connection (nor, on SQLite, an old snapshot) from here on
    batch = BatchSpec(uuid.uuid4().hex, body.name, body.settings.model_dump_json(),
                      body.priority)
    create_jobs(request, tenant, specs, batch, later)  # plan messages sent after the response
    return _read_public(request, batch.id)


@router.get("", response_model=BatchesPublic, operation_id="list_batches",
            responses=errors(401, 422))
def read_batches(
    session: SessionDep, tenant: CurrentTenant, skip: SkipQ = 0, limit: LimitQ = 100
) -> BatchesPublic:
    """This tenant's batches, newest first, with their item counts and progress."""
    q = select(Batch).where(Batch.tenant == tenant)
    count = session.scalar(select(func.count()).select_from(q.subquery())) or 0
    batches = list(session.scalars(
        q.order_by(Batch.created_at.desc(), Batch.id).offset(skip).limit(limit)))
    return BatchesPublic(data=_summaries(session, batches), count=count)


@router.get("/{batch_id}", response_model=BatchPublic, operation_id="read_batch",
            responses=errors(401, BATCH_404, 422))
def read_batch(batch_id: str, session: SessionDep, tenant: CurrentTenant) -> BatchPublic:
    """A batch's progress: item counts by state, overall fraction, each item's job."""
    return batch_public(session, _own_batch(session, batch_id, tenant))


@router.delete(
    "/{batch_id}",
    response_model=BatchPublic,
    status_code=status.HTTP_202_ACCEPTED,
    operation_id="cancel_batch",
    responses=errors(401, BATCH_404, 422),
)
def delete_batch(
    batch_id: str, request: Request, session: SessionDep, tenant: CurrentTenant
) -> BatchPublic:
    """Cancel every unfinished item's job (as `DELETE /jobs/{id}`); finished items stay."""
    _own_batch(session, batch_id, tenant)
    open_jobs = [r.id for r in _item_rows(session, [batch_id])
                 if r.state not in TERMINAL_JOB_STATES]
    session.close()
    task_ids = ledger.cancel_jobs(request.app.state.writer, open_jobs)
    for job_id in open_jobs:
        request.app.state.version_cache.drop(job_id)
    if task_ids:
        try:  # SIGKILL, as DELETE /jobs/{id}: a pool child deep in numpy ignores SIGTERM
            request.app.state.celery.control.revoke(task_ids, terminate=True, signal="SIGKILL")
        except Exception:  # noqa: BLE001 - broker down: workers skip cancelled shards anyway
            pass
    return _read_public(request, batch_id)


def item_folder(index: int, n_items: int, filename: str) -> str:
    """`007_cylinder`: the item's index (zero-padded, so folders sort in item order) and its
    asset's file name without the suffix, reduced to [A-Za-z0-9._-]."""
    stem = _UNSAFE.sub("_", filename.rsplit(".", 1)[0]).strip("._") or "asset"
    return f"{index:0{max(3, len(str(n_items - 1)))}d}_{stem}"


def build_batch_zip(root: Path, batch: BatchPublic) -> Path:
    """The finished batch as one deterministic zip: a folder per succeeded item holding its
    result bundle (the files of `/jobs/{id}/result`), and `batch.json` listing every item's
    state, error and folder. Built once per content of `batch.json` (named by its digest: a
    job that changes state later, e.g. resumed, gets a new archive, never a stale one)."""
    n = len(batch.items)
    manifest = [{"index": it.index, "asset_id": it.asset_id, "asset_name": it.asset_name,
                 "job_id": it.job_id, "state": it.state, "error": it.error,
                 "folder": item_folder(it.index, n, it.asset_name)
                 if it.state == "succeeded" else None} for it in batch.items]
    doc = {"batch": batch.id, "name": batch.name, "state": batch.state,
           "counts": batch.counts.model_dump(), "items": manifest}
    data = (json.dumps(doc, indent=2, sort_keys=True) + "\n").encode()
    dest = storage.batch_dir(root, batch.id) / f"result-{hashlib.sha256(data).hexdigest()[:16]}.zip"
    if dest.is_file():
        return dest
    members: list[tuple[str, Path | bytes]] = [("batch.json", data)]
    for m in manifest:
        if m["folder"] is not None:
            members += folder_members(storage.job_out(root, m["job_id"]), m["folder"] + "/")
    return write_zip(dest, members)


@router.get(
    "/{batch_id}/result",
    response_class=FileResponse,
    operation_id="read_batch_result",
    responses={
        200: {
            "content": {"application/zip": {"schema": BINARY}, OCTET: {"schema": BINARY}},
            "description": "The finished batch (a zip): `batch.json` and a folder per "
            "succeeded item.",
        },
        **errors(401, BATCH_404, BATCH_409, 422),
    },
)
def read_batch_result(
    batch_id: str, request: Request, session: SessionDep, tenant: CurrentTenant,
    settings: SettingsDep,
) -> FileResponse:
    """Every item's result in one zip, once every item has finished (409 before)."""
    batch = batch_public(session, _own_batch(session, batch_id, tenant))
    if batch.state not in TERMINAL_JOB_STATES:
        finished = batch.counts.succeeded + batch.counts.failed + batch.counts.cancelled
        raise ApiError(
            status.HTTP_409_CONFLICT,
            f"{BATCH_NOT_FINISHED} ({finished} of {batch.counts.total} items finished)",
            ErrorCode.BATCH_NOT_FINISHED,
        )
    dest = build_batch_zip(settings.artifact_root, batch)
    return FileResponse(dest, media_type=_media_type(request, "application/zip"),
                        filename=f"batch-{batch_id}.zip")
