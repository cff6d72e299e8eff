"""The database under load (issue 16, item 5), the parts a unit test can pin down: a busy
database is a 503 with Retry-After whose body never carries the driver's text, and a database
made before job priorities is upgraded in place. The load itself is benchmarks/load.py."""

from __future__ import annotations

import sqlite3

from fastapi.testclient import TestClient
from sqlalchemy import select
from sqlalchemy.exc import OperationalError

from farm.config import Settings
from farm.db import Job, session_factory
from services.main import create_app


def test_busy_database_is_503_with_retry_after(tmp_path):
    st = Settings(secret_key="x" * 16, redis_url="redis://127.0.0.1:1/0",
                  artifact_root=tmp_path, environment="test")
    app = create_app(st, sweeper=False)

    @app.get("/locked", tags=["test"])
    def locked() -> None:
        raise OperationalError("BEGIN IMMEDIATE", {}, sqlite3.OperationalError("database is locked"))

    # ahead of the dashboard's catch-all mount at / (present where web/dist is built)
    app.router.routes.insert(0, app.router.routes.pop())
    with TestClient(app, raise_server_exceptions=False) as c:
        r = c.get("/locked")
    assert r.status_code == 503
    assert r.headers["retry-after"] == "1"
    assert r.json()["code"] == "service_unavailable"
    assert "locked" not in r.text and "BEGIN" not in r.text


def test_old_database_gets_the_priority_column(tmp_path):
    path = tmp_path / "old.db"
    con = sqlite3.connect(path)
    con.executescript(
        "CREATE TABLE jobs (id VARCHAR(64) PRIMARY KEY, tenant VARCHAR(128), asset_id VARCHAR(64),"
        " settings_json TEXT, state VARCHAR(16), error TEXT, skipped_json TEXT, plan_sent BOOLEAN,"
        " broker_run_id VARCHAR(64), created_at DATETIME, started_at DATETIME,"
        " finished_at DATETIME);"
        "INSERT INTO jobs (id, tenant, asset_id, settings_json, state, skipped_json, plan_sent)"
        " VALUES ('j', 't', 'a', '{}', 'queued', '[]', 0);"
    )
    con.commit()
    con.close()
    sm = session_factory(f"sqlite:///{path}")
    with sm() as s:
        assert s.scalar(select(Job.priority).where(Job.id == "j")) == 50
    idx = sqlite3.connect(path).execute(
        "SELECT name FROM sqlite_master WHERE type = 'index' AND name = 'ix_event_job_seq'"
    ).fetchall()
    assert idx == [("ix_event_job_seq",)]
