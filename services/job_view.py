"""A job as the API shows it: its public record with per-stage progress, timings, estimate
and quality."""

from __future__ import annotations

import json
import logging
from collections import defaultdict
from functools import lru_cache
from pathlib import Path

from pydantic import ValidationError
from sqlalchemy import select
from sqlalchemy.orm import Session

from farm import storage
from farm.db import Job, Shard, Stage
from schemas.job import (
    JobEstimate,
    JobPublic,
    ShardPublic,
    SkippedStage,
    StagePublic,
)
from schemas.settings import BakeSettings
from texelbake.estimate import costmodel

log = logging.getLogger("texelbake.api")


def _seconds(a, b) -> float | None:  # noqa: ANN001
    return (b - a).total_seconds() if a is not None and b is not None else None


def stored_settings(settings_json: str, row: str) -> BakeSettings:
    """The settings a job or batch row stores. A row stored before its settings were checked
    to read back (`services.submission.check_readable`) may not validate: its unreadable
    fields show their defaults (logged with `row`), so reading the row never fails."""
    try:
        return BakeSettings.model_validate_json(settings_json)
    except ValidationError as exc:
        log.warning("unreadable settings of %s: %s", row,
                    "; ".join(f"{'.'.join(map(str, e['loc']))}: {e['msg']}" for e in exc.errors()))
    try:
        data = json.loads(settings_json)
    except ValueError:
        return BakeSettings()
    if not isinstance(data, dict):
        return BakeSettings()
    fields = {k: v for k, v in data.items() if k in BakeSettings.model_fields}
    while True:
        try:
            return BakeSettings.model_validate(fields)
        except ValidationError as exc:
            bad = {e["loc"][0] for e in exc.errors() if e["loc"] and e["loc"][0] in fields}
        if not bad:  # the fields disagree with each other
            return BakeSettings()
        for name in bad:
            del fields[name]


def progress_percent(done: int, total: int) -> float:
    return done / total if total else 0.0


@lru_cache(maxsize=1024)
def _estimate(settings_json: str, workers: int) -> costmodel.Estimate:
    """The cost model per (settings, workers): computed once, not on every status read. Priced
    on this API process's machine (`machinespeed.this_machine()`, measured once per process):
    the workers are assumed to run on machines like it."""
    from texelbake.estimate import machinespeed

    return costmodel.estimate(BakeSettings.model_validate_json(settings_json), workers,
                              speed=machinespeed.this_machine())


def job_estimate(job: Job, settings: BakeSettings, workers: int) -> JobEstimate:
    """The core cost model's prediction for a job (thin: `texelbake.estimate.costmodel.estimate`)."""
    from datetime import timedelta

    e = _estimate(settings.model_dump_json(), workers)
    eta = job.started_at + timedelta(seconds=e.seconds) if job.started_at is not None else None
    return JobEstimate(seconds=round(e.seconds, 1), workers=e.workers,
                       cpm_seconds=round(e.cpm_seconds, 1), eta=eta,
                       machine_speed=e.speed["factors"] if e.speed else None)


def job_public(session: Session, job: Job, root: Path, workers: int = 2) -> JobPublic:
    stages = session.scalars(
        select(Stage).where(Stage.job_id == job.id).order_by(Stage.position)
    ).all()
    shards = session.scalars(
        select(Shard).where(Shard.job_id == job.id).order_by(Shard.stage, Shard.shard)
    ).all()
    by_stage: dict[str, list[Shard]] = defaultdict(list)
    for sh in shards:
        by_stage[sh.stage].append(sh)
    out_stages = []
    for st in stages:
        rows = by_stage.get(st.name, [])
        done = sum(r.state == "done" for r in rows)
        starts = [r.started_at for r in rows if r.started_at is not None]
        ends = [r.finished_at for r in rows if r.finished_at is not None]
        first = min(starts) if starts else None
        last = max(ends) if ends and st.state == "done" else None
        out_stages.append(
            StagePublic(
                name=st.name,
                queue=st.queue,
                state=st.state,
                depends_on=json.loads(st.depends_on_json),
                n_shards=st.n_shards,
                n_done=done,
                progress=progress_percent(done, st.n_shards),
                started_at=first,
                finished_at=last,
                seconds=_seconds(first, last),
                shards=[ShardPublic.model_validate(r) for r in rows],
            )
        )
    total = sum(s.n_shards for s in stages)
    done = sum(s.n_done for s in out_stages)
    previews_dir = storage.job_out(root, job.id) / "previews"
    previews = (
        sorted(p.name for p in previews_dir.iterdir() if p.is_file() and not p.name.startswith("."))
        if previews_dir.is_dir()
        else []
    )
    settings = stored_settings(job.settings_json, f"job {job.id}")
    outcome, warnings = _quality(storage.job_out(root, job.id), job.state)
    return JobPublic(
        id=job.id,
        asset_id=job.asset_id,
        state=job.state,
        priority=job.priority,
        settings=settings,
        progress=progress_percent(done, total),
        stages=out_stages,
        skipped=[SkippedStage(stage=a, reason=b) for a, b in json.loads(job.skipped_json or "[]")],
        error=job.error,
        created_at=job.created_at,
        started_at=job.started_at,
        finished_at=job.finished_at,
        seconds=_seconds(job.created_at, job.finished_at),
        previews=previews,
        estimate=job_estimate(job, settings, workers),
        outcome=outcome,
        warnings=warnings,
    )


def _quality(out: Path, state: str) -> tuple[str | None, list[str]]:
    """A succeeded job's quality gate from its report.json (texelbake.stages.quality)."""
    report = out / "report.json"
    if state != "succeeded" or not report.is_file():
        return None, []
    missed = list(json.loads(report.read_text()).get("quality", {}).get("missed", []))
    return ("completed with warnings" if missed else "completed"), missed
