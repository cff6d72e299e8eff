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


def make_job(st, sm, layer_text: str | bytes, name: str = "a.usda") -> str:
    sha = "f" * 64
    bundle = storage.asset_bundle(st.artifact_root, sha)
    bundle.mkdir(parents=True)
    data = layer_text.encode() if isinstance(layer_text, str) else layer_text
    (bundle / name).write_bytes(data)
    with sm.begin() as s:
        s.add(
            Asset(
                id="a1",
                tenant="t",
                sha256=sha,
                filename=name,
                kind="usda",
                root_layer=name,
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
        assert str(st.artifact_root) not in j.error and "/assets/" not in j.error, j.error
        assert s.scalar(select(Shard.attempts).where(Shard.stage == "ingest")) == 1


def test_corrupt_crate_fails_naming_the_file_without_server_paths(env, tmp_path):
    """A crate layer whose array count points past the file (pxr: "Zero-copy data range
    out-of-bounds" when the value is read) that reached a worker: the job fails with pxr's
    reason naming the layer, as bad input (no retry, no traceback), without pxr's C++
    preamble or any server path."""
    import numpy as np
    from pxr import Usd, UsdGeom, Vt

    from workers.tasks import shard_body

    st, sm = env
    stage = Usd.Stage.CreateNew(str(tmp_path / "m.usdc"))
    pts = np.arange(9000, dtype=np.float32).reshape(3000, 3)
    mesh = UsdGeom.Mesh.Define(stage, "/Root/M")
    mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(pts))
    mesh.CreateFaceVertexCountsAttr([3] * 1000)
    mesh.CreateFaceVertexIndicesAttr(list(range(3000)))
    stage.SetDefaultPrim(stage.GetPrimAtPath("/Root"))
    stage.Save()
    data = bytearray((tmp_path / "m.usdc").read_bytes())
    at = data.find(pts.tobytes()[:64])
    data[at - 8 : at] = (3000 * 100_000).to_bytes(8, "little")
    job = make_job(st, sm, bytes(data), name="broken.usdc")
    assert shard_body(job, "ingest", 0, retries=0, retry=no_retry) == "failed"
    with sm() as s:
        j = s.get(Job, job)
    assert j.state == "failed" and "pxr cannot read broken.usdc" in j.error, j.error
    assert "Zero-copy data range out-of-bounds" in j.error and "Traceback" not in j.error
    for server in (str(tmp_path), "Error in '", "/opt/", ".cpp"):
        assert server not in j.error, j.error


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
