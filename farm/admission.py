"""Admission: which ready shards the ledger sends to the broker, and when.

A stage that becomes ready makes its shards `queued` in the ledger; only *admitted* shards get
a task id and are sent (`farm.ledger.dispatch`). `Policy` says how: job priority, a backlog
per queue group, per-tenant limits (docs/service.md "Priorities and fair share"). Admission runs
inside the ledger's transactions, one at a time (`serialize`). `farm.ledger` re-exports its
names.
"""

from __future__ import annotations

import secrets
from dataclasses import dataclass
from datetime import datetime
from typing import Any

from sqlalchemy import func, select, text, update
from sqlalchemy.orm import Session

from farm.db import Job, Shard, utcnow
from schemas.queues import QUEUE_FAMILIES

RUN_SHARD_TASK = "workers.tasks.run_shard"


@dataclass(frozen=True)
class Send:
    """A message to put on the broker: `task(*args)` on `queue`, tracked by ledger row `row_id`."""

    task: str
    args: tuple[Any, ...]
    queue: str
    row_id: int | None  # shard row id; None for the plan task (tracked on the job row)
    job_id: str
    expect_task_id: str | None = None  # claim: send only if the row still has this task id
    task_id: str | None = None  # admitted by the ledger under this id (claimed in its txn)


@dataclass(frozen=True)
class Policy:
    """How the ledger admits ready (`queued`) shards to the broker.

    A ready shard waits in the ledger until it is admitted: then it gets its task id and is
    sent. Admission takes, per queue group (`groups`: the queues one kind of worker serves;
    a queue in no group is a group of its own), the ready shards of the highest job priority
    first (then the oldest job, then shard order; at equal priority the tenant with fewer
    shards in flight first), as long as
    - `queue_backlog`: fewer than this many admitted shards of the group wait unstarted in
      the broker (the broker's own order is FIFO, and a worker serving several queues takes
      from whichever has a message, so a short backlog per group is what makes priority
      count; a worker's start frees a slot and admits the next shard at once), and
    - `tenant_max_running`: the tenant has fewer than this many shards admitted or running
      (`tenant_limits` overrides it per tenant): one tenant's batch cannot take every worker.
    0 means no limit; `Policy()` admits every ready shard at once (no scheduling).
    """

    queue_backlog: int = 0
    tenant_max_running: int = 0
    tenant_limits: tuple[tuple[str, int], ...] = ()
    groups: tuple[tuple[str, tuple[str, ...]], ...] = ()

    def tenant_cap(self, tenant: str) -> int:
        return dict(self.tenant_limits).get(tenant, self.tenant_max_running)

    def group_of(self, queue: str) -> str:
        for name, queues in self.groups:
            if queue in queues:
                return name
        return queue


#: no scheduling: every ready shard is sent at once (tests of the transitions)
NO_LIMITS = Policy()


def policy_from(settings: Any) -> Policy:
    """The admission policy of the service settings (`farm.config.Settings`)."""

    groups = settings.queue_groups if settings.queue_groups is not None else QUEUE_FAMILIES
    return Policy(
        queue_backlog=int(settings.queue_backlog),
        tenant_max_running=int(settings.tenant_max_running_shards),
        tenant_limits=tuple(sorted((str(k), int(v)) for k, v in settings.tenant_shard_limits.items())),
        groups=tuple(sorted((str(k), tuple(v)) for k, v in groups.items())),
    )


def serialize(s: Session) -> None:
    """Admissions one at a time: PostgreSQL takes a transaction-scoped advisory lock first
    thing (before any row lock, so it cannot deadlock with the job-row locks); SQLite's
    writers are serialized by `BEGIN IMMEDIATE` already."""
    if s.get_bind().dialect.name == "postgresql":
        s.execute(text("SELECT pg_advisory_xact_lock(:k)"), {"k": ADMISSION_LOCK})


#: the advisory lock key of admissions (any constant shared by every process)
ADMISSION_LOCK = 0x7E6E1B


def rowcount(result: Any) -> int:
    return int(result.rowcount)


def new_task_id(send: Send) -> str:
    tail = secrets.token_hex(4)
    if send.row_id is None:
        return f"{send.job_id}.plan.{tail}"
    return f"{send.job_id}.{send.args[1]}.{send.args[2]}.{tail}"


_ADMITTED = (Shard.state == "queued") & Shard.task_id.is_not(None)
_HELD = (Shard.state == "running") | _ADMITTED


def admit(s: Session, policy: Policy, now: datetime | None = None) -> list[Send]:
    """Admit ready shards to the broker under `policy` (see `Policy`): each admitted row gets
    its task id in this transaction, and the caller sends the returned messages after the
    commit (`dispatch`). Callers hold the admission lock (`serialize`)."""
    now = now or utcnow()
    running = Job.state == "running"
    ready = (
        select(Shard.queue, Job.tenant, func.count())
        .select_from(Shard).join(Job, Job.id == Shard.job_id)
        .where(running, Shard.state == "queued", Shard.task_id.is_(None))
        .group_by(Shard.queue, Job.tenant)
    )
    pairs = s.execute(ready).all()
    if not pairs:
        return []
    held: dict[str, int] = dict(
        s.execute(  # type: ignore[arg-type]
            select(Job.tenant, func.count())
            .select_from(Shard).join(Job, Job.id == Shard.job_id)
            .where(running, _HELD)
            .group_by(Job.tenant)
        ).all()
    )
    backlog: dict[str, int] = dict(
        s.execute(  # type: ignore[arg-type]
            select(Shard.queue, func.count())
            .select_from(Shard).join(Job, Job.id == Shard.job_id)
            .where(running, _ADMITTED)
            .group_by(Shard.queue)
        ).all()
    )
    by_group: dict[str, dict[str, list[str]]] = {}  # group -> tenant -> its ready queues
    for q, tenant, _n in pairs:
        by_group.setdefault(policy.group_of(q), {}).setdefault(tenant, []).append(q)
    waiting: dict[str, int] = {}
    for q, n in backlog.items():
        waiting[policy.group_of(q)] = waiting.get(policy.group_of(q), 0) + int(n)
    inf = 1 << 30
    sends: list[Send] = []
    for g in sorted(by_group):
        free = (policy.queue_backlog - waiting.get(g, 0)) if policy.queue_backlog else inf
        if free <= 0:
            continue
        # each tenant's best ready shards of this group, best first (at most what could go)
        heads: dict[str, list] = {}
        for tenant, queues in by_group[g].items():
            cap = policy.tenant_cap(tenant)
            room = (cap - held.get(tenant, 0)) if cap else inf
            take = min(free, room)
            if take <= 0:
                continue
            heads[tenant] = list(reversed(s.execute(
                select(Shard.id, Shard.job_id, Shard.stage, Shard.shard, Shard.queue,
                       Job.priority, Job.created_at)
                .select_from(Shard).join(Job, Job.id == Shard.job_id)
                .where(running, Job.tenant == tenant, Shard.queue.in_(queues),
                       Shard.state == "queued", Shard.task_id.is_(None))
                .order_by(Job.priority.desc(), Job.created_at, Job.id, Shard.id)
                .limit(min(take, 10_000))
            ).all()))
        while free > 0:
            best = None
            for tenant, rows in heads.items():
                cap = policy.tenant_cap(tenant)
                if not rows or (cap and held.get(tenant, 0) >= cap):
                    continue
                rid, jid, _st, _k, _q, prio, created = rows[-1]
                key = (-int(prio), held.get(tenant, 0), created, jid, rid)
                if best is None or key < best[0]:
                    best = (key, tenant)
            if best is None:
                break
            tenant = best[1]
            rid, jid, st, k, q, _p, _c = heads[tenant].pop()
            send = Send(RUN_SHARD_TASK, (jid, st, k), q, rid, jid)
            tid = new_task_id(send)
            if not rowcount(s.execute(
                update(Shard)
                .where(Shard.id == rid, Shard.state == "queued", Shard.task_id.is_(None))
                .values(task_id=tid, sent=False, enqueued_at=now)
            )):
                continue
            sends.append(Send(RUN_SHARD_TASK, (jid, st, k), q, rid, jid, task_id=tid))
            held[tenant] = held.get(tenant, 0) + 1
            free -= 1
    return sends
