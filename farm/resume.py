"""Resuming a failed job: the ledger transition behind `POST /jobs/{id}/resume`.

A job fails when one shard fails for good (bad input, or a transient fault such as a full disk
that outlived the retry budget). Once the cause is gone, resuming puts every shard that is not
`done` back to `pending`, every unfinished stage back to `pending`, and the job back to
`running`; the stages whose dependencies are done become ready and are admitted as usual
(`ledger.promote_ready`, `admission.admit`). Done shards keep their rows and their artifacts
(content-keyed in the work folder), so only the unfinished work runs again and no shard is
counted done twice. A job that failed before it was planned goes back to `queued` with its plan
message unsent (sent here, or by the sweeper).
"""

from __future__ import annotations

from sqlalchemy import func, select, update
from sqlalchemy.orm import sessionmaker

from farm.admission import NO_LIMITS, Policy, Send, admit, serialize
from farm.db import Shard, Stage, utcnow
from farm.ledger.jobs import PLAN_JOB_TASK, lock_job, promote_ready, set_job_state
from schemas.queues import PLAN_QUEUE


def resume_job(sm: sessionmaker, job_id: str, policy: Policy = NO_LIMITS) -> list[Send] | None:
    """Re-queue the unfinished work of a failed job. Returns the messages to send (`dispatch`),
    or None when the job does not exist or is not `failed` (nothing changed)."""
    with sm.begin() as s:
        serialize(s)
        job = lock_job(s, job_id)
        if job is None or job.state != "failed":
            return None
        planned = s.scalar(select(func.count()).select_from(Stage).where(Stage.job_id == job_id))
        if not planned:
            set_job_state(s, job_id, "queued", ["failed"], error=None, finished_at=None,
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
        set_job_state(s, job_id, "running", ["failed"], error=None, finished_at=None)
        promote_ready(s, job_id)
        return admit(s, policy, utcnow())
