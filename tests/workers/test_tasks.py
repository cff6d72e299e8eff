"""The task body as a function (`workers.tasks.shard_body`): bad input fails the job at once
without a retry; a transient fault is retried with bounded, jittered backoff, then fails the
job with the reason; a finished shard is skipped on redelivery. The real worker and broker are
exercised in test_service_farm.py."""

from __future__ import annotations

import pytest
from sqlalchemy import select

from farm import ledger, storage
from farm.config import get_settings
from farm.db import Asset, Job, Shard, session_factory

PLAN = [("ingest", "ingest", 1, ()), ("geometry", "geometry", 1, ("ingest",))]


class Retry(Exception):
    def __init__(self, exc, countdown):
        super().__init__(f"retry in {countdown:.2f}s: {exc!r}")
        self.exc, self.countdown = exc, countdown


@pytest.fixture
def env(tmp_path, monkeypatch):
    monkeypatch.setenv("TEXELBAKE_SECRET_KEY", "0123456789abcdef")
    monkeypatch.setenv("TEXELBAKE_REDIS_URL", "redis://127.0.0.1:1/0")  # nothing to send here
    monkeypatch.setenv("TEXELBAKE_ARTIFACT_ROOT", str(tmp_path / "root"))
    monkeypatch.setenv("TEXELBAKE_MAX_RETRIES", "2")
    get_settings.cache_clear()
    st = get_settings()
    sm = session_factory(st.db_url)
    yield st, sm
    get_settings.cache_clear()


def make_job(st, sm, layer_text: str) -> str:
    sha = "f" * 64
    bundle = storage.asset_bundle(st.artifact_root, sha)
    bundle.mkdir(parents=True)
    (bundle / "a.usda").write_text(layer_text)
    with sm.begin() as s:
        s.add(
            Asset(
                id="a1",
                tenant="t",
                sha256=sha,
                filename="a.usda",
                kind="usda",
                root_layer="a.usda",
                size_bytes=1,
                n_files=1,
            )
        )
    ledger.create_job(sm, "j1", "t", "a1", "{}")
    ledger.record_plan(sm, "j1", PLAN, [])
    return "j1"


def no_retry(exc, countdown):
    raise AssertionError(f"bad input must not be retried ({exc!r})")


def test_bad_input_fails_without_retry(env):
    from workers.tasks import shard_body

    st, sm = env
    job = make_job(st, sm, "#usda 1.0\n(\n def def def")
    assert shard_body(job, "ingest", 0, retries=0, retry=no_retry) == "failed"
    with sm() as s:
        j = s.get(Job, job)
        assert j.state == "failed"
        assert "AssetError" in j.error and "a.usda" in j.error
        assert s.scalar(select(Shard.attempts).where(Shard.stage == "ingest")) == 1


def test_transient_fault_retries_with_backoff_then_fails(env, monkeypatch):
    import workers.tasks as tasks

    st, sm = env
    job = make_job(st, sm, "#usda 1.0\n")

    def flaky(*_a):
        raise OSError("NFS hiccup")

    monkeypatch.setattr(tasks, "execute_shard", flaky)  # fault injection
    for attempt in range(st.max_retries):
        with pytest.raises(Retry) as info:
            tasks.shard_body(job, "ingest", 0, retries=attempt, retry=Retry)
        # exponential backoff with 50-100 % jitter, capped by retry_backoff_max
        step = min(float(st.retry_backoff_max), 2.0**attempt)
        assert 0.5 * step <= info.value.countdown <= step
        with sm() as s:
            row = s.scalar(select(Shard).where(Shard.stage == "ingest"))
            assert row.state == "queued" and "NFS hiccup" in row.error  # released for the retry
    assert tasks.shard_body(job, "ingest", 0, retries=st.max_retries, retry=Retry) == "failed"
    with sm() as s:
        j = s.get(Job, job)
        assert j.state == "failed" and "transient fault persisted" in j.error


def test_done_shard_is_skipped_on_redelivery(env):
    from workers.tasks import shard_body

    st, sm = env
    job = make_job(st, sm, "#usda 1.0\n")
    assert ledger.start_shard(sm, job, "ingest", 0, "w:1", 3).action == "run"
    ledger.finish_shard(sm, job, "ingest", 0, "k", 0.1)
    assert shard_body(job, "ingest", 0, retries=0, retry=no_retry) == "skipped:done"
