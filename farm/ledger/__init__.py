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
`heartbeat_timeout`, its lease, has lost its worker); a delivery of a shard still held by a live
worker does not run it (`start_shard`: "held"). Re-running a shard is harmless: stage outputs are idempotent.
"""

from farm.admission import (
    ADMISSION_LOCK,
    NO_LIMITS,
    RUN_SHARD_TASK,
    Policy,
    Send,
    new_task_id,
    policy_from,
)
from farm.ledger.jobs import (
    PLAN_JOB_TASK,
    PLAN_QUEUE,
    Sender,
    add_event,
    add_job,
    cancel_job,
    cancel_jobs,
    create_job,
    fail_job,
    lock_job,
    promote_ready,
    record_plan,
    set_job_state,
    stage_seconds,
)
from farm.ledger.shards import (
    StartResult,
    fail_shard,
    finish_shard,
    heartbeat,
    holder_alive,
    mark_failed,
    note_time_limit,
    release_shard,
    start_shard,
)
from farm.ledger.sweep import dispatch, sweep

__all__ = [
    "ADMISSION_LOCK", "NO_LIMITS", "PLAN_JOB_TASK", "PLAN_QUEUE", "RUN_SHARD_TASK", "Policy",
    "Send", "Sender", "StartResult", "add_event", "add_job", "cancel_job", "cancel_jobs",
    "create_job", "dispatch", "fail_job", "fail_shard", "finish_shard", "heartbeat",
    "holder_alive", "lock_job", "mark_failed", "new_task_id", "note_time_limit", "policy_from",
    "promote_ready", "record_plan", "release_shard", "set_job_state", "stage_seconds",
    "start_shard", "sweep",
]
