"""Per-tenant limits and priorities on real processes (issue 16, item 2): redis-server, two
Celery worker processes serving every queue, uvicorn, SQLite.

A tenant limited to one running shard, with two jobs on a farm of two workers, never has two
shards running at once (without the limit the two workers run its cpm shards side by side);
the jobs still complete with the in-process bake's result. The queue discipline itself
(priority order, the single job that is not starved) is measured by benchmarks/fairshare.py.
"""

from __future__ import annotations

import httpx
import pytest
from sqlalchemy import select

from farm.db import Job, Shard, session_factory
from farm.stack import OWN_REDIS, stack_down, stack_up
from schemas.queues import QUEUES
from tests.helpers.farm import AUTH, TOKEN, download, wait_for
from tests.helpers.service import CHEAP_SETTINGS, assert_same_bake
from texelbake_client.submit import package

pytestmark = [pytest.mark.service, pytest.mark.timeout(400)]


def test_tenant_limit_serializes_a_tenants_shards(cylinder, reference, tmp_path):
    db = f"sqlite:///{tmp_path / 'fair.db'}"
    stack = stack_up(
        tmp_path / "stack", redis_url=OWN_REDIS, database_url=db,
        tokens={TOKEN: "farm"}, environment="test", workers={"all": 2},
        queues={"all": QUEUES},
        extra_env={"TEXELBAKE_TENANT_MAX_RUNNING_SHARDS": "1", "TEXELBAKE_QUEUE_BACKLOG": "1",
                   "TEXELBAKE_SWEEP_INTERVAL": "1"},
    )
    try:
        with httpx.Client(base_url=stack.api_url + "/api/v1", headers=AUTH, timeout=60) as c:
            aid = c.post("/assets", files={"file": package(cylinder)}).json()["id"]
            ids = []
            for prio in (40, 60):
                r = c.post("/jobs", json={"asset_id": aid, "settings": CHEAP_SETTINGS,
                                          "priority": prio})
                assert r.status_code == 201, r.text
                assert r.json()["priority"] == prio
                ids.append(r.json()["id"])
        for job_id in ids:
            wait_for(stack, job_id, lambda j: j["state"] == "succeeded", timeout=360)
        with session_factory(db)() as s:
            rows = list(s.scalars(select(Shard).where(Shard.job_id.in_(ids))))
            assert {j.priority for j in s.scalars(select(Job).where(Job.id.in_(ids)))} == {40, 60}
        spans = sorted((r.started_at, r.finished_at) for r in rows)
        assert all(r.state == "done" and r.completions == 1 for r in rows)
        overlaps = [(a, b) for a, b in zip(spans, spans[1:], strict=False) if b[0] < a[1]]
        assert not overlaps, overlaps
        assert_same_bake(reference, download(stack, ids[1], tmp_path / "out"))
    finally:
        stack_down(tmp_path / "stack")


def test_priority_is_not_a_bake_setting():
    """Two jobs that differ only in priority share their artifacts: `priority` is a job field,
    outside `BakeSettings` and its digest."""
    from schemas.job import JobCreate

    a = JobCreate(asset_id="a", settings=CHEAP_SETTINGS, priority=0)
    b = JobCreate(asset_id="a", settings=CHEAP_SETTINGS, priority=100)
    assert a.settings.digest() == b.settings.digest()
    with pytest.raises(ValueError):
        JobCreate(asset_id="a", priority=101)
