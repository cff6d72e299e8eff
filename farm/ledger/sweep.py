"""The shard ledger's sending: messages go to the broker after their transaction commits
(`dispatch`), and the sweeper finds what to send again (`sweep`).
"""

from __future__ import annotations

from datetime import datetime, timedelta

from sqlalchemy import func, select, update
from sqlalchemy.orm import sessionmaker

from farm.admission import (
    NO_LIMITS,
    RUN_SHARD_TASK,
    Policy,
    Send,
    admit,
    new_task_id,
    rowcount,
    serialize,
)
from farm.db import Job, Shard, relaxed_commit, utcnow
from farm.ledger.jobs import PLAN_JOB_TASK, Sender, add_event
from farm.ledger.shards import mark_failed
from schemas.queues import PLAN_QUEUE


def dispatch(sm: sessionmaker, sends: list[Send], sender: Sender, run_id: str | None) -> int:
    """Send each message, then mark its row sent (only if it is still queued). Returns the count
    sent; stops at the first broker failure, and gives the rows not sent back to admission
    (the sweeper admits them again)."""
    n = 0
    for i, send in enumerate(sends):
        task_id = send.task_id or new_task_id(send)
        if send.row_id is not None and send.task_id is None:
            with sm.begin() as s:  # record the id first so a cancel can revoke it
                ok = rowcount(s.execute(
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
            relaxed_commit(s)  # a mark lost with a crash only makes the sweeper send it again
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
        serialize(s)
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
                mark_failed(s, j, st, k, f"shard {st}/{k} was lost {lost} times "
                                   f"(max_attempts={max_attempts}); last: {reason}")
                continue
            if rowcount(s.execute(
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
        sends += admit(s, policy, now)
    return sends
