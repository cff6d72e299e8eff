"""The event loop never waits on the database (services/status_cache.py): a status read whose
version read is stuck in PostgreSQL leaves the API answering everything else, and pollers of
one job share one read (real PostgreSQL, the real app on TestClient's event loop)."""

from __future__ import annotations

import threading
import time

import pytest
import sqlalchemy
from fastapi.testclient import TestClient

from farm import ledger
from farm.config import Settings
from farm.db import Asset, session_factory
from services.main import create_app
from tests.helpers.service import fresh_postgres

pytestmark = [pytest.mark.service, pytest.mark.timeout(120)]

TOKEN = "token-status-cache-0123456789"


def _job(url: str) -> str:
    """One asset row and one queued job of tenant `t`; returns the job id."""
    writer = session_factory(url)
    with writer.begin() as s:
        s.add(Asset(id="a1", tenant="t", sha256="0" * 64, filename="a.usda", kind="usda",
                    root_layer="a.usda", size_bytes=1, n_files=1))
    ledger.create_job(writer, "j1", "t", "a1", "{}")
    return "j1"


def test_a_status_read_stuck_in_the_database_does_not_stall_the_api(tmp_path):
    """While `jobs` is locked (ACCESS EXCLUSIVE: every read of it waits), a status read waits
    for its version; the health check, which reads no job, answers meanwhile. With the version
    read on the event loop, the health check waited for the lock as well."""
    with fresh_postgres() as url:
        jid = _job(url)
        st = Settings(secret_key="x" * 16, redis_url="redis://127.0.0.1:1/0",
                      artifact_root=tmp_path, environment="test", database_url=url,
                      tokens={TOKEN: "t"}, status_cache_seconds=30)  # fmt: skip
        app = create_app(st, sweeper=False)
        locker = sqlalchemy.create_engine(url)
        lock = locker.connect()
        results: dict[str, object] = {}
        try:
            with TestClient(app) as c:
                auth = {"Authorization": f"Bearer {TOKEN}"}
                assert c.get("/api/v1/utils/health-check/").status_code == 200  # warm
                lock.exec_driver_sql("LOCK TABLE jobs IN ACCESS EXCLUSIVE MODE")

                def read(k: int) -> None:
                    results[f"status{k}"] = c.get(f"/api/v1/jobs/{jid}", headers=auth)

                def health() -> None:
                    t0 = time.monotonic()
                    results["health"] = c.get("/api/v1/utils/health-check/")
                    results["health_s"] = time.monotonic() - t0

                readers = [threading.Thread(target=read, args=(k,), daemon=True)
                           for k in range(3)]  # fmt: skip
                for t in readers:
                    t.start()
                deadline = time.monotonic() + 10
                while not app.state.version_cache._pending:  # the version read is in flight
                    assert time.monotonic() < deadline, "no version read started"
                    time.sleep(0.01)
                time.sleep(0.3)  # every reader has joined it (or would be blocked behind it)
                probe = threading.Thread(target=health, daemon=True)
                probe.start()
                probe.join(10)
                still_waiting = [t.is_alive() for t in readers]
                lock.rollback()  # release the table: the status reads complete
                probe.join(10)
                for t in readers:
                    t.join(20)
        finally:
            lock.close()
            locker.dispose()
        assert "health" in results, "the health check waited for a lock on a table it never reads"
        assert results["health"].status_code == 200  # type: ignore[attr-defined]
        assert results["health_s"] < 5  # type: ignore[operator]
        assert all(still_waiting), "a status read answered while its job's row was unreadable"
        bodies = [results[f"status{k}"] for k in range(3)]
        assert all(r.status_code == 200 for r in bodies)  # type: ignore[attr-defined]
        assert {r.json()["state"] for r in bodies} == {"queued"}  # type: ignore[attr-defined]
