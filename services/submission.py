"""Making jobs: the one path `POST /jobs` and `POST /batches` share.

The route checks its input (the asset is this tenant's, the settings validate) with
`own_asset`, then `create_jobs` writes every job (and the batch row, if any) in one
transaction and sends their plan messages; a broker outage is not the client's problem (the
sweeper sends them later).
"""

from __future__ import annotations

import uuid
from dataclasses import dataclass
from typing import Any

from fastapi import BackgroundTasks, Request, status
from fastapi.exceptions import RequestValidationError
from pydantic import ValidationError
from sqlalchemy.orm import Session

from farm import ledger
from farm.broker import broker_run_id, celery_sender
from farm.db import Asset, Batch, BatchItem
from schemas.common import ErrorCode
from schemas.settings import BakeSettings
from services.errors import ApiError
from services.routers.assets import ASSET_NOT_FOUND

#: where a request carries the settings of `POST /jobs` and the defaults of `POST /batches`
SETTINGS_LOC: tuple[str | int, ...] = ("body", "settings")


@dataclass(frozen=True)
class JobSpec:
    """One job to make: an asset of the tenant, validated settings (JSON), a priority;
    `loc` is where the request carried the settings (a 422 names it)."""

    asset_id: str
    settings_json: str
    priority: int
    loc: tuple[str | int, ...] = SETTINGS_LOC


@dataclass(frozen=True)
class BatchSpec:
    """The batch row the jobs belong to (item i is `JobSpec` i)."""

    id: str
    name: str | None
    settings_json: str
    priority: int
    loc: tuple[str | int, ...] = SETTINGS_LOC


def check_readable(specs: list[JobSpec | BatchSpec]) -> None:
    """Every spec's stored settings read back (`BakeSettings.model_validate_json`), else one
    422 naming each field at its `loc`: nothing is stored that a later read could not
    serve."""
    issues: list[dict[str, Any]] = []
    for spec in specs:
        try:
            BakeSettings.model_validate_json(spec.settings_json)
        except ValidationError as exc:
            issues += [{"loc": [*spec.loc, *e["loc"]], "msg": e["msg"], "type": e["type"]}
                       for e in exc.errors()]
    if issues:
        raise RequestValidationError(issues)


def own_asset(session: Session, tenant: str, asset_id: str, where: str = "") -> Asset:
    """The tenant's asset, else a 404 (anyone else's asset does not exist for this tenant);
    `where` names the request field in the message (`items[2].asset_id`)."""
    asset = session.get(Asset, asset_id)
    if asset is None or asset.tenant != tenant:
        detail = f"{where}: {ASSET_NOT_FOUND} ({asset_id!r})" if where else ASSET_NOT_FOUND
        raise ApiError(status.HTTP_404_NOT_FOUND, detail, ErrorCode.ASSET_NOT_FOUND)
    return asset


def create_jobs(
    request: Request, tenant: str, jobs: list[JobSpec], batch: BatchSpec | None = None,
    later: BackgroundTasks | None = None,
) -> list[str]:
    """Create one job per spec (and the batch holding them) in one write transaction, then
    send their plan messages: now, or after the response when `later` is given (a batch's
    thousand messages cost seconds; a job is `queued` either way, and an unsent plan is sent
    by the sweeper). Returns the job ids in order. The caller has validated every spec and
    holds no read session; settings that would not read back are a 422 (`check_readable`)."""
    check_readable([*jobs, *([batch] if batch is not None else [])])
    app = request.app
    ids = [uuid.uuid4().hex for _ in jobs]
    with app.state.writer.begin() as s:
        if batch is not None:
            s.add(Batch(id=batch.id, tenant=tenant, name=batch.name,
                        settings_json=batch.settings_json, priority=batch.priority,
                        n_items=len(jobs)))
            s.flush()
        sends = [
            ledger.add_job(s, job_id, tenant, spec.asset_id, spec.settings_json,
                           priority=spec.priority)
            for job_id, spec in zip(ids, jobs, strict=True)
        ]
        if batch is not None:
            s.add_all(BatchItem(batch_id=batch.id, position=i, job_id=job_id)
                      for i, job_id in enumerate(ids))
    if later is not None:
        later.add_task(send_plans, app, sends)
    else:
        send_plans(app, sends)
    return ids


def send_plans(app: Any, sends: list[ledger.Send]) -> None:
    """Send the jobs' plan messages (marking each sent). A broker outage is not the client's
    problem: the sweeper sends what is not marked."""
    try:
        ledger.dispatch(app.state.writer, sends, celery_sender(app.state.celery),
                        broker_run_id(app.state.settings.redis_url))
    except Exception:  # noqa: BLE001
        pass
