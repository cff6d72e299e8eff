"""The shard ledger's worker side: claim a shard, finish it, fail it, beat its heartbeat.

A started shard frees a slot of its queue's backlog and a finished one may make the next stages
ready: both return the shards admitted in their place (`farm.admission`), for the caller to send
after the commit (`farm.ledger.sweep.dispatch`).
"""

from __future__ import annotations

import socket
from dataclasses import dataclass
from datetime import timedelta

from sqlalchemy import func, select, update
from sqlalchemy.orm import Session, sessionmaker

from farm.admission import NO_LIMITS, Policy, Send, admit, rowcount, serialize
from farm.db import Job, Shard, Stage, utcnow
from farm.ledger.jobs import add_event, lock_job, promote_ready, set_job_state
from texelbake.io.spool import pid_alive


def holder_alive(worker: str | None) -> bool | None:
    """Whether the process named by a shard's `worker` ("host:pid", `workers.tasks`) lives:
    True or False for a process of this host (a zombie is dead: `pid_alive`), None for another
    host's (only its heartbeats tell). Worker names are unique per host and pid namespace."""
    if not worker or ":" not in worker:
        return None
    host, _, pid = worker.rpartition(":")
    if host != socket.gethostname() or not pid.isdigit():
        return None
    return pid_alive(int(pid))


@dataclass(frozen=True)
class StartResult:
    action: str  # "run" | "done" | "inactive" | "exceeded" | "held"
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
    lease: timedelta | None = None,
) -> StartResult:
    """Claim a shard for this delivery. Counts the attempt; past `max_attempts` the shard and the
    job fail (the redelivery cap for a shard that kills its worker). A started shard frees a
    slot of its queue's backlog: the shards admitted in its place come back in `sends`.

    A shard still `running` under another worker is taken over only when that worker is gone:
    a dead process of this host (a killed pool child whose message Celery redelivered: at
    once), or a holder whose last heartbeat is older than `lease`. Otherwise ("held") this
    delivery does nothing: the holder runs it, and if it dies the sweeper re-queues the shard
    when its lease expires. So a shard never runs twice at once (short of a live holder silent
    for a whole lease)."""
    with sm.begin() as s:
        serialize(s)
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
        if row.state == "running" and row.worker != worker:
            alive = holder_alive(row.worker)
            beat = row.heartbeat_at or row.started_at
            fresh = lease is not None and beat is not None and beat >= utcnow() - lease
            if alive or (alive is None and fresh):
                return StartResult("held", row.attempts)
        attempts = row.attempts + 1
        # state "running" here means the previous delivery never finished: its worker died
        lost = row.lost + (1 if row.state == "running" else 0)
        if lost >= max_attempts:
            msg = (
                f"shard {stage}/{shard} was lost {lost} times with its worker "
                f"(max_attempts={max_attempts}); not redelivering it again"
                + (f"; last: {row.error}" if row.error else "")
            )
            mark_failed(s, job_id, stage, shard, msg)
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
        return StartResult("run", attempts, tuple(admit(s, policy, now)))


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
        serialize(s)
        # serialize the finishes of one job: under READ COMMITTED two transactions finishing
        # the last two shards would each count the other's shard as not done, and nobody would
        # promote the next stage (test_concurrent_last_shards_promote_once caught this)
        if lock_job(s, job_id) is None:
            return []
        won = rowcount(s.execute(
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
        return admit(s, policy)


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
    stage_won = rowcount(s.execute(
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
        set_job_state(s, job_id, "succeeded", ["running"])
        return
    job = s.get(Job, job_id)
    if job is not None and job.state == "running":
        promote_ready(s, job_id)


def mark_failed(s: Session, job_id: str, stage: str, shard: int, error: str) -> None:
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
    set_job_state(s, job_id, "failed", ["queued", "running"], error=f"{stage}/{shard}: {error}")


def fail_shard(sm: sessionmaker, job_id: str, stage: str, shard: int, error: str) -> None:
    """Terminal failure of a shard (bad input, or retries exhausted): the job fails with it."""
    with sm.begin() as s:
        mark_failed(s, job_id, stage, shard, error)

def heartbeat(sm: sessionmaker, job_id: str, stage: str, shard: int, worker: str) -> bool:
    """A running shard is alive (its worker still holds it). False when it no longer holds it."""
    with sm.begin() as s:
        return bool(rowcount(
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
        ok = bool(rowcount(s.execute(
            update(Shard)
            .where(*_shard_is(job_id, stage, shard), Shard.state == "running",
                   Shard.worker == worker)
            .values(error=error)
        )))
        if ok:
            add_event(s, job_id, "shard", {"stage": stage, "shard": shard, "state": "running",
                                           "error": error})
        return ok

def release_shard(sm: sessionmaker, job_id: str, stage: str, shard: int, error: str) -> None:
    """A transient fault: the shard goes back to `queued` (sent) while Celery retries it."""
    with sm.begin() as s:
        if rowcount(s.execute(
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
