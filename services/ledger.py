"""The shard ledger: job, stage and shard state transitions, as conditional updates.

Used by the API (create, cancel, sweep) and by the workers (start, finish, fail). Every
transition is one transaction whose `UPDATE ... WHERE state = <expected>` decides who wins, so
two workers finishing the last two shards of a stage at once promote the next stage exactly
once, a redelivered shard that is already done is skipped, and a shard is counted done once.

Sending to the broker happens *after* the commit: a shard is first marked `queued` with
`sent = False`, then sent, then marked `sent = True` with the broker's run id. A send that fails
(broker down) or a broker that restarted (its run id changed: queued messages are gone) leaves
rows the sweeper re-sends. A running shard whose lease expired (worker killed, message lost) is
re-queued by the sweeper too (a running shard sends heartbeats; one silent for
`heartbeat_timeout` has lost its worker). Re-running a shard is harmless: stage outputs are idempotent.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from datetime import datetime, timedelta
from typing import Any

from sqlalchemy import func, select, update
from sqlalchemy.orm import Session, sessionmaker

from schemas.job import DEFAULT_PRIORITY, TERMINAL_JOB_STATES
from services.admission import (  # noqa: F401  (re-exported: the ledger's names since issue 16)
    ADMISSION_LOCK,
    NO_LIMITS,
    RUN_SHARD_TASK,
    Policy,
    Send,
    new_task_id,
    policy_from,
)
from services.admission import admit as _admit
from services.admission import rowcount as _rowcount
from services.admission import serialize as _serialize
from services.db import Event, Job, Shard, Stage, utcnow

PLAN_JOB_TASK = "workers.tasks.plan_job"
PLAN_QUEUE = "ingest"


# a sender: (task name, args, queue, task id) -> None; raises when the broker is unreachable
Sender = Callable[[str, tuple, str, str], None]


def add_event(s: Session, job_id: str, kind: str, data: dict[str, Any]) -> None:
    s.add(Event(job_id=job_id, kind=kind, data_json=json.dumps(data, sort_keys=True)))


def _lock_job(s: Session, job_id: str) -> Job | None:
    """The job row, locked until the transaction ends (PostgreSQL `FOR UPDATE`; SQLite's
    writers are already serialized by `BEGIN IMMEDIATE`)."""
    return s.scalar(select(Job).where(Job.id == job_id).with_for_update())


def _set_job_state(s: Session, job_id: str, new: str, expect: Iterable[str], **extra) -> bool:
    now = utcnow()
    values: dict[str, Any] = {"state": new, **extra}
    if new in TERMINAL_JOB_STATES:
        values["finished_at"] = now
    n = _rowcount(s.execute(
        update(Job).where(Job.id == job_id, Job.state.in_(list(expect))).values(**values)
    ))
    if n:
        ev = {"state": new}
        if "error" in extra:
            ev["error"] = extra["error"]
        add_event(s, job_id, "job", ev)
    return bool(n)


# ---------------------------------------------------------------- create / plan


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
        _serialize(s)
        job = _lock_job(s, job_id)
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
        _set_job_state(
            s, job_id, "running", ["queued"], started_at=utcnow(), skipped_json=json.dumps(skipped)
        )
        _promote_ready(s, job_id)
        return _admit(s, policy)


def _promote_ready(s: Session, job_id: str) -> int:
    """Make every pending stage whose dependencies are all done ready (conditional per
    stage): its shards become `queued`, to be admitted to the broker by `_admit`."""
    stages = s.scalars(select(Stage).where(Stage.job_id == job_id).order_by(Stage.position)).all()
    done = {st.name for st in stages if st.state == "done"}
    n = 0
    for st in stages:
        if st.state != "pending" or not set(json.loads(st.depends_on_json)) <= done:
            continue
        won = _rowcount(s.execute(
            update(Stage)
            .where(Stage.id == st.id, Stage.state == "pending")
            .values(state="queued", started_at=utcnow())
        ))
        if not won:
            continue
        n += _rowcount(s.execute(
            update(Shard)
            .where(Shard.job_id == job_id, Shard.stage == st.name, Shard.state == "pending")
            .values(state="queued", sent=False, task_id=None)
        ))
        add_event(s, job_id, "stage", {"stage": st.name, "state": "queued"})
    return n


# ---------------------------------------------------------------- admission

#: shards a tenant holds: admitted (sent or being sent, not started) or running
# ---------------------------------------------------------------- sending


def dispatch(sm: sessionmaker, sends: list[Send], sender: Sender, run_id: str | None) -> int:
    """Send each message, then mark its row sent (only if it is still queued). Returns the count
    sent; stops at the first broker failure, and gives the rows not sent back to admission
    (the sweeper admits them again)."""
    n = 0
    for i, send in enumerate(sends):
        task_id = send.task_id or new_task_id(send)
        if send.row_id is not None and send.task_id is None:
            with sm.begin() as s:  # record the id first so a cancel can revoke it
                ok = _rowcount(s.execute(
                    update(Shard)
                    .where(
                        Shard.id == send.row_id,
                        Shard.state == "queued",
                        Shard.task_id.is_not_distinct_from(send.expect_task_id),
                    )
                    .values(task_id=task_id)
                ))
            if not ok:
                continue
        try:
            sender(send.task, send.args, send.queue, task_id)
        except Exception:
            _unadmit(sm, [x.row_id for x in sends[i:] if x.row_id is not None])
            raise
        with sm.begin() as s:
            if send.row_id is None:
                s.execute(
                    update(Job)
                    .where(Job.id == send.job_id)
                    .values(plan_sent=True, broker_run_id=run_id)
                )
            else:
                s.execute(
                    update(Shard)
                    .where(Shard.id == send.row_id, Shard.state == "queued")
                    .values(sent=True, broker_run_id=run_id, enqueued_at=utcnow())
                )
        n += 1
    return n


def _unadmit(sm: sessionmaker, row_ids: list[int]) -> None:
    """Rows whose message could not be sent go back to the ready set (best effort: if the
    database is down too, the sweeper re-sends them after the lease)."""
    if not row_ids:
        return
    try:
        with sm.begin() as s:
            s.execute(
                update(Shard)
                .where(Shard.id.in_(row_ids), Shard.state == "queued")
                .values(task_id=None, sent=False)
            )
    except Exception:  # noqa: BLE001
        pass


# ---------------------------------------------------------------- worker side


@dataclass(frozen=True)
class StartResult:
    action: str  # "run" | "done" | "inactive" | "exceeded"
    attempts: int = 0
    sends: tuple[Send, ...] = ()  # admitted now that this shard left the broker's backlog


def _shard_is(job_id: str, stage: str, shard: int) -> tuple:
    """The WHERE conditions naming one shard of a job."""
    return (Shard.job_id == job_id, Shard.stage == stage, Shard.shard == shard)


def start_shard(
    sm: sessionmaker,
    job_id: str,
    stage: str,
    shard: int,
    worker: str,
    max_attempts: int,
    policy: Policy = NO_LIMITS,
) -> StartResult:
    """Claim a shard for this delivery. Counts the attempt; past `max_attempts` the shard and the
    job fail (the redelivery cap for a shard that kills its worker). A started shard frees a
    slot of its queue's backlog: the shards admitted in its place come back in `sends`."""
    with sm.begin() as s:
        _serialize(s)
        job = s.get(Job, job_id)
        row = s.scalar(
            select(Shard).where(*_shard_is(job_id, stage, shard))
        )
        if job is None or row is None:
            return StartResult("inactive")
        if row.state == "done":
            return StartResult("done", row.attempts)
        if job.state != "running" or row.state not in ("queued", "running"):
            return StartResult("inactive", row.attempts)
        attempts = row.attempts + 1
        # state "running" here means the previous delivery never finished: its worker died
        lost = row.lost + (1 if row.state == "running" else 0)
        if lost >= max_attempts:
            msg = (
                f"shard {stage}/{shard} was lost {lost} times with its worker "
                f"(max_attempts={max_attempts}); not redelivering it again"
                + (f"; last: {row.error}" if row.error else "")
            )
            _fail(s, job_id, stage, shard, msg)
            return StartResult("exceeded", row.attempts)
        now = utcnow()
        s.execute(
            update(Shard)
            .where(Shard.id == row.id)
            .values(
                state="running",
                attempts=attempts,
                lost=lost,
                started_at=now,
                heartbeat_at=now,
                worker=worker,
                error=None,
            )
        )
        s.execute(
            update(Stage)
            .where(Stage.job_id == job_id, Stage.name == stage, Stage.state == "queued")
            .values(state="running")
        )
        add_event(
            s,
            job_id,
            "shard",
            {
                "stage": stage,
                "shard": shard,
                "state": "running",
                "attempts": attempts,
                "worker": worker,
            },
        )
        return StartResult("run", attempts, tuple(_admit(s, policy, now)))


def finish_shard(
    sm: sessionmaker,
    job_id: str,
    stage: str,
    shard: int,
    artifact_key: str,
    seconds: float,
    policy: Policy = NO_LIMITS,
) -> list[Send]:
    """Mark a shard done (once); if it was the stage's last, finish the stage (once) and make
    the stages that were waiting for it ready; if every stage is done, the job succeeds.
    Returns the shards admitted now (`Policy`: this shard's slot is free)."""
    with sm.begin() as s:
        _serialize(s)
        # serialize the finishes of one job: under READ COMMITTED two transactions finishing
        # the last two shards would each count the other's shard as not done, and nobody would
        # promote the next stage (test_concurrent_last_shards_promote_once caught this)
        if _lock_job(s, job_id) is None:
            return []
        won = _rowcount(s.execute(
            update(Shard)
            .where(
                *_shard_is(job_id, stage, shard),
                Shard.state.in_(["queued", "running"]),
            )
            .values(
                state="done",
                completions=Shard.completions + 1,
                finished_at=utcnow(),
                seconds=float(seconds),
                artifact_key=str(artifact_key),
                error=None,
            )
        ))
        if not won:
            return []
        add_event(
            s,
            job_id,
            "shard",
            {"stage": stage, "shard": shard, "state": "done", "seconds": round(float(seconds), 4)},
        )
        _after_finish(s, job_id, stage)
        return _admit(s, policy)


def _after_finish(s: Session, job_id: str, stage: str) -> None:
    """A shard of `stage` is done: finish the stage if it was the last (once), then the job
    or the stages that waited for it."""
    left = s.scalar(
        select(func.count())
        .select_from(Shard)
        .where(Shard.job_id == job_id, Shard.stage == stage, Shard.state != "done")
    )
    if left:
        return
    stage_won = _rowcount(s.execute(
        update(Stage)
        .where(
            Stage.job_id == job_id, Stage.name == stage, Stage.state.in_(["queued", "running"])
        )
        .values(state="done", finished_at=utcnow())
    ))
    if not stage_won:
        return
    add_event(s, job_id, "stage", {"stage": stage, "state": "done"})
    not_done = s.scalar(
        select(func.count())
        .select_from(Stage)
        .where(Stage.job_id == job_id, Stage.state != "done")
    )
    if not not_done:
        _set_job_state(s, job_id, "succeeded", ["running"])
        return
    job = s.get(Job, job_id)
    if job is not None and job.state == "running":
        _promote_ready(s, job_id)


def _fail(s: Session, job_id: str, stage: str, shard: int, error: str) -> None:
    s.execute(
        update(Shard)
        .where(
            *_shard_is(job_id, stage, shard),
            Shard.state != "done",
        )
        .values(state="failed", error=error, finished_at=utcnow())
    )
    s.execute(
        update(Stage)
        .where(Stage.job_id == job_id, Stage.name == stage, Stage.state != "done")
        .values(state="failed", finished_at=utcnow())
    )
    add_event(
        s, job_id, "shard", {"stage": stage, "shard": shard, "state": "failed", "error": error}
    )
    _set_job_state(s, job_id, "failed", ["queued", "running"], error=f"{stage}/{shard}: {error}")


def fail_shard(sm: sessionmaker, job_id: str, stage: str, shard: int, error: str) -> None:
    """Terminal failure of a shard (bad input, or retries exhausted): the job fails with it."""
    with sm.begin() as s:
        _fail(s, job_id, stage, shard, error)


def fail_job(sm: sessionmaker, job_id: str, error: str) -> None:
    with sm.begin() as s:
        _set_job_state(s, job_id, "failed", ["queued", "running"], error=error)


def heartbeat(sm: sessionmaker, job_id: str, stage: str, shard: int, worker: str) -> bool:
    """A running shard is alive (its worker still holds it). False when it no longer holds it."""
    with sm.begin() as s:
        return bool(_rowcount(
            s.execute(
                update(Shard)
                .where(
                    *_shard_is(job_id, stage, shard),
                    Shard.state == "running",
                    Shard.worker == worker,
                )
                .values(heartbeat_at=utcnow())
            )
        ))


def note_time_limit(sm: sessionmaker, job_id: str, stage: str, shard: int, worker: str,
                    limit: float) -> bool:
    """A running shard passed its time limit: record why on its row (the sweeper's re-queue and
    the final failure name it) and in the events. False when this worker no longer holds it."""
    error = f"exceeded the shard time limit of {limit:g} s on {worker} (presumed stuck)"
    with sm.begin() as s:
        ok = bool(_rowcount(s.execute(
            update(Shard)
            .where(*_shard_is(job_id, stage, shard), Shard.state == "running",
                   Shard.worker == worker)
            .values(error=error)
        )))
        if ok:
            add_event(s, job_id, "shard", {"stage": stage, "shard": shard, "state": "running",
                                           "error": error})
        return ok


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


def release_shard(sm: sessionmaker, job_id: str, stage: str, shard: int, error: str) -> None:
    """A transient fault: the shard goes back to `queued` (sent) while Celery retries it."""
    with sm.begin() as s:
        if _rowcount(s.execute(
            update(Shard)
            .where(
                *_shard_is(job_id, stage, shard),
                Shard.state == "running",
            )
            .values(state="queued", error=error)
        )):
            add_event(
                s,
                job_id,
                "shard",
                {"stage": stage, "shard": shard, "state": "queued", "error": error},
            )


# ---------------------------------------------------------------- API side


def cancel_job(sm: sessionmaker, job_id: str) -> list[str]:
    """Cancel a job that is not finished; returns the task ids to revoke. State rows are kept."""
    return cancel_jobs(sm, [job_id])


def cancel_jobs(sm: sessionmaker, job_ids: list[str]) -> list[str]:
    """`cancel_job` of many jobs (a batch's) in one transaction."""
    with sm.begin() as s:
        live = [j for j in job_ids if _set_job_state(s, j, "cancelled", ["queued", "running"])]
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


def sweep(
    sm: sessionmaker,
    run_id: str | None,
    lease: timedelta,
    now: datetime | None = None,
    policy: Policy = NO_LIMITS,
    max_attempts: int | None = None,
) -> list[Send]:
    """What to (re)send: unplanned jobs whose plan message was never sent or was lost with a
    broker restart; admitted shards whose message was lost with a broker restart, or whose
    sender died before sending (admitted longer than `lease` ago, never sent); running shards
    whose last heartbeat is older than `lease` (their worker died with them, or they passed
    their time limit and stopped beating) go back to the ready set, each counted as lost: the
    `max_attempts`-th loss fails the shard and its job, naming the last recorded error; then the
    ready shards `policy` admits now (slots freed by failed or cancelled jobs, by re-queued
    shards)."""
    now = now or utcnow()
    sends: list[Send] = []
    with sm.begin() as s:
        _serialize(s)
        for job_id, sent, rid in s.execute(
            select(Job.id, Job.plan_sent, Job.broker_run_id).where(Job.state == "queued")
        ):
            if not sent or rid != run_id:
                sends.append(Send(PLAN_JOB_TASK, (job_id,), PLAN_QUEUE, None, job_id))
        active = select(Job.id).where(Job.state == "running")
        expired = s.execute(
            select(Shard.id, Shard.job_id, Shard.stage, Shard.shard, Shard.lost, Shard.error)
            .where(
                Shard.job_id.in_(active),
                Shard.state == "running",
                func.coalesce(Shard.heartbeat_at, Shard.started_at) < now - lease,
            )
        ).all()
        for rid, j, st, k, lost, err in expired:
            lost += 1
            reason = err or "lease expired"
            if max_attempts is not None and lost >= max_attempts:
                _fail(s, j, st, k, f"shard {st}/{k} was lost {lost} times "
                                   f"(max_attempts={max_attempts}); last: {reason}")
                continue
            if _rowcount(s.execute(
                update(Shard)
                .where(Shard.id == rid, Shard.state == "running")
                .values(state="queued", sent=False, task_id=None, lost=lost)
            )):
                add_event(
                    s,
                    j,
                    "shard",
                    {"stage": st, "shard": k, "state": "queued", "reason": reason},
                )
        rows = s.execute(
            select(Shard.id, Shard.job_id, Shard.stage, Shard.shard, Shard.queue, Shard.task_id)
            .where(
                Shard.job_id.in_(active),
                Shard.state == "queued",
                Shard.task_id.is_not(None),
                (Shard.sent.is_(True) & Shard.broker_run_id.is_distinct_from(run_id))
                | (Shard.sent.is_(False) & (Shard.enqueued_at < now - lease)),
            )
            .order_by(Shard.id)
        ).all()
        sends += [
            Send(RUN_SHARD_TASK, (j, st, k), q, rid, j, tid) for rid, j, st, k, q, tid in rows
        ]
        sends += _admit(s, policy, now)
    return sends
