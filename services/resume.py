"""Resuming a failed job: the ledger transition behind `POST /jobs/{id}/resume`.

A job fails when one shard fails for good (bad input, or a transient fault such as a full disk
that outlived the retry budget). Once the cause is gone, resuming puts every shard that is not
`done` back to `pending`, every unfinished stage back to `pending`, and the job back to
`running`; the stages whose dependencies are done become ready and are admitted as usual
(`ledger._promote_ready`, `ledger._admit`). Done shards keep their rows and their artifacts
(content-keyed in the work folder), so only the unfinished work runs again and no shard is
counted done twice. A job that failed before it was planned goes back to `queued` with its plan
message unsent (sent here, or by the sweeper).
"""

from __future__ import annotations

from sqlalchemy import func, select, update
from sqlalchemy.orm import sessionmaker

from services.db import Shard, Stage, utcnow
from services.ledger import (
    NO_LIMITS,
    PLAN_JOB_TASK,
    PLAN_QUEUE,
    Policy,
    Send,
    _admit,
    _lock_job,
    _promote_ready,
    _serialize,
    _set_job_state,
)


def resume_job(sm: sessionmaker, job_id: str, policy: Policy = NO_LIMITS) -> list[Send] | None:
    """Re-queue the unfinished work of a failed job. Returns the messages to send (`dispatch`),
    or None when the job does not exist or is not `failed` (nothing changed)."""
    with sm.begin() as s:
        _serialize(s)
        job = _lock_job(s, job_id)
        if job is None or job.state != "failed":
            return None
        planned = s.scalar(select(func.count()).select_from(Stage).where(Stage.job_id == job_id))
        if not planned:
            _set_job_state(s, job_id, "queued", ["failed"], error=None, finished_at=None,
                           plan_sent=False)
            return [Send(PLAN_JOB_TASK, (job_id,), PLAN_QUEUE, None, job_id)]
        s.execute(
            update(Shard)
            .where(Shard.job_id == job_id, Shard.state != "done")
            .values(state="pending", task_id=None, sent=False, lost=0, error=None, worker=None,
                    heartbeat_at=None, finished_at=None)
        )
        s.execute(
            update(Stage)
            .where(Stage.job_id == job_id, Stage.state != "done")
            .values(state="pending", finished_at=None)
        )
        _set_job_state(s, job_id, "running", ["failed"], error=None, finished_at=None)
        _promote_ready(s, job_id)
        return _admit(s, policy, utcnow())
