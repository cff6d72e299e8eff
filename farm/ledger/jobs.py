"""The shard ledger's job transitions: create, plan, promote ready stages, fail, cancel.

Every transition is one transaction whose `UPDATE ... WHERE state = <expected>` decides who wins
(`farm.ledger`). The helpers that take the caller's session (`lock_job`, `set_job_state`,
`promote_ready`, `add_event`) are the building blocks the shard transitions, the sweeper and
resuming (`farm.resume`) share.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterable
from typing import Any

from sqlalchemy import func, select, update
from sqlalchemy.orm import Session, sessionmaker

from farm.admission import NO_LIMITS, Policy, Send, admit, rowcount, serialize
from farm.db import Event, Job, Shard, Stage, utcnow
from schemas.job import DEFAULT_PRIORITY, TERMINAL_JOB_STATES
from schemas.queues import PLAN_QUEUE

PLAN_JOB_TASK = "workers.tasks.plan_job"

# a sender: (task name, args, queue, task id) -> None; raises when the broker is unreachable
Sender = Callable[[str, tuple, str, str], None]


def add_event(s: Session, job_id: str, kind: str, data: dict[str, Any]) -> None:
    s.add(Event(job_id=job_id, kind=kind, data_json=json.dumps(data, sort_keys=True)))

def lock_job(s: Session, job_id: str) -> Job | None:
    """The job row, locked until the transaction ends (PostgreSQL `FOR UPDATE`; SQLite's
    writers are already serialized by `BEGIN IMMEDIATE`)."""
    return s.scalar(select(Job).where(Job.id == job_id).with_for_update())

def set_job_state(s: Session, job_id: str, new: str, expect: Iterable[str], **extra) -> bool:
    now = utcnow()
    values: dict[str, Any] = {"state": new, **extra}
    if new in TERMINAL_JOB_STATES:
        values["finished_at"] = now
    n = rowcount(s.execute(
        update(Job).where(Job.id == job_id, Job.state.in_(list(expect))).values(**values)
    ))
    if n:
        ev = {"state": new}
        if "error" in extra:
            ev["error"] = extra["error"]
        add_event(s, job_id, "job", ev)
    return bool(n)

def create_job(
    sm: sessionmaker,
    job_id: str,
    tenant: str,
    asset_id: str,
    settings_json: str,
    priority: int = DEFAULT_PRIORITY,
) -> Send:
    with sm.begin() as s:
        return add_job(s, job_id, tenant, asset_id, settings_json, priority)


def add_job(s: Session, job_id: str, tenant: str, asset_id: str, settings_json: str,
            priority: int = DEFAULT_PRIORITY) -> Send:
    """`create_job` inside the caller's transaction (a batch adds all its jobs in one)."""
    s.add(Job(id=job_id, tenant=tenant, asset_id=asset_id, settings_json=settings_json,
              priority=int(priority)))
    s.flush()
    add_event(s, job_id, "job", {"state": "queued"})
    return Send(PLAN_JOB_TASK, (job_id,), PLAN_QUEUE, None, job_id)


def record_plan(
    sm: sessionmaker,
    job_id: str,
    stages: list[tuple[str, str, int, tuple[str, ...]]],
    skipped: list[tuple[str, str]],
    policy: Policy = NO_LIMITS,
) -> list[Send]:
    """Insert the planned stages and their shard rows (once), start the job, queue ready stages.

    stages : [(name, queue, n_shards, depends_on)] in execution order.
    Returns the shards admitted now (of any job: `Policy`).
    """
    with sm.begin() as s:
        serialize(s)
        job = lock_job(s, job_id)
        if job is None or job.state != "queued":
            return []
        exists = s.scalar(select(func.count()).select_from(Stage).where(Stage.job_id == job_id))
        if not exists:
            for pos, (name, queue, n_shards, deps) in enumerate(stages):
                s.add(
                    Stage(
                        job_id=job_id,
                        name=name,
                        position=pos,
                        queue=queue,
                        depends_on_json=json.dumps(list(deps)),
                        n_shards=int(n_shards),
                    )
                )
                for k in range(int(n_shards)):
                    s.add(Shard(job_id=job_id, stage=name, shard=k, queue=queue))
            s.flush()
        set_job_state(
            s, job_id, "running", ["queued"], started_at=utcnow(), skipped_json=json.dumps(skipped)
        )
        promote_ready(s, job_id)
        return admit(s, policy)

def promote_ready(s: Session, job_id: str) -> int:
    """Make every pending stage whose dependencies are all done ready (conditional per
    stage): its shards become `queued`, to be admitted to the broker by `admit`."""
    stages = s.scalars(select(Stage).where(Stage.job_id == job_id).order_by(Stage.position)).all()
    done = {st.name for st in stages if st.state == "done"}
    n = 0
    for st in stages:
        if st.state != "pending" or not set(json.loads(st.depends_on_json)) <= done:
            continue
        won = rowcount(s.execute(
            update(Stage)
            .where(Stage.id == st.id, Stage.state == "pending")
            .values(state="queued", started_at=utcnow())
        ))
        if not won:
            continue
        n += rowcount(s.execute(
            update(Shard)
            .where(Shard.job_id == job_id, Shard.stage == st.name, Shard.state == "pending")
            .values(state="queued", sent=False, task_id=None)
        ))
        add_event(s, job_id, "stage", {"stage": st.name, "state": "queued"})
    return n

def fail_job(sm: sessionmaker, job_id: str, error: str) -> None:
    with sm.begin() as s:
        set_job_state(s, job_id, "failed", ["queued", "running"], error=error)

def cancel_job(sm: sessionmaker, job_id: str) -> list[str]:
    """Cancel a job that is not finished; returns the task ids to revoke. State rows are kept."""
    return cancel_jobs(sm, [job_id])


def cancel_jobs(sm: sessionmaker, job_ids: list[str]) -> list[str]:
    """`cancel_job` of many jobs (a batch's) in one transaction."""
    with sm.begin() as s:
        live = [j for j in job_ids if set_job_state(s, j, "cancelled", ["queued", "running"])]
        if not live:
            return []
        ids = [t for t in s.scalars(select(Shard.task_id).where(
            Shard.job_id.in_(live), Shard.state.in_(["queued", "running"]))) if t]
        for model in (Shard, Stage):
            s.execute(
                update(model)
                .where(model.job_id.in_(live), model.state.in_(["pending", "queued", "running"]))
                .values(state="cancelled")
            )
        return ids

def stage_seconds(sm: sessionmaker, job_id: str) -> dict[str, float]:
    """Wall time per finished stage of a job: first shard start to last shard finish."""
    with sm() as s:
        rows = s.execute(
            select(Shard.stage, func.min(Shard.started_at), func.max(Shard.finished_at))
            .where(Shard.job_id == job_id, Shard.state == "done")
            .group_by(Shard.stage)
        ).all()
    return {
        st: round((b - a).total_seconds(), 4)
        for st, a, b in rows
        if a is not None and b is not None
    }
