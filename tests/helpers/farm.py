"""A farm of real processes for the service tests (and benchmarks/chaos.py): redis-server on a
free port, Celery prefork workers and uvicorn (`farm.stack`), with the sweeper and the
heartbeats at their default speed; and what the tests read back from it (job status, result, ledger)."""

from __future__ import annotations

import os
import time
from contextlib import contextmanager
from pathlib import Path

import httpx
from sqlalchemy import select

from farm.db import Shard, session_factory
from farm.stack import OWN_REDIS, stack_down, stack_up

TOKEN = "farm-token-0123456789abcdef"
AUTH = {"Authorization": f"Bearer {TOKEN}"}


@contextmanager
def farm(workdir: Path, database_url: str | None = None, **kw):
    stack = stack_up(
        workdir,
        redis_url=OWN_REDIS,
        database_url=database_url,
        tokens=kw.pop("tokens", {TOKEN: "farm"}),
        workers=kw.pop("workers", {"prep": 1, "numeric": 1}),
        environment="test",
        extra_env={
            # the sweep period, heartbeat interval and lease are the defaults (0.5 s, 0.5 s,
            # 3 s): what a farm runs is what the tests run
            "TEXELBAKE_VISIBILITY_TIMEOUT": "120",
            **kw,
        },
    )
    try:
        yield stack
    finally:
        stack_down(workdir)


def db_url(stack) -> str:
    return stack.env.get("TEXELBAKE_DATABASE_URL") or (
        f"sqlite:///{Path(stack.env['TEXELBAKE_ARTIFACT_ROOT']) / 'texelbake.db'}"
    )


def ledger_rows(stack, job_id: str) -> list[Shard]:
    with session_factory(db_url(stack))() as s:
        return list(s.scalars(select(Shard).where(Shard.job_id == job_id)))


def wait_for(stack, job_id: str, pred, timeout: float = 240.0, every: float = 0.05) -> dict:
    deadline = time.monotonic() + timeout
    last = None
    while time.monotonic() < deadline:
        try:
            r = httpx.get(f"{stack.api_url}/api/v1/jobs/{job_id}", headers=AUTH, timeout=10)
            if r.status_code == 200:
                last = r.json()
                if pred(last):
                    return last
                if last["state"] in ("failed", "cancelled"):
                    raise AssertionError(f"job ended {last['state']}: {last['error']}")
        except httpx.TransportError:
            pass  # the API is restarting
        time.sleep(every)
    raise AssertionError(f"timed out; last status: {last}")


def download(stack, job_id: str, out: Path) -> Path:
    from texelbake_client.submit import safe_extract

    r = httpx.get(f"{stack.api_url}/api/v1/jobs/{job_id}/result", headers=AUTH, timeout=60)
    assert r.status_code == 200, r.text
    files = safe_extract(r.content, out)
    return next(p for p in files if p.name.endswith("_baked.usda"))


def child_pids(pid: int) -> set[int]:
    out = set()
    for d in os.listdir("/proc"):
        if d.isdigit():
            try:
                with open(f"/proc/{d}/stat") as f:
                    if int(f.read().rsplit(")", 1)[1].split()[1]) == pid:
                        out.add(int(d))
            except (OSError, IndexError, ValueError):
                pass
    return out
