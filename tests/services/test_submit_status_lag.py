"""`texelbake submit` when the job's status lags its event stream: an API process answers a
status read from a version cached for `status_cache_seconds`, so the read right after the
stream's terminal event may still say "running" (the farm's end-to-end test met it on
PostgreSQL). The client reads the status again until it is terminal, within a bound. The
server here is an httpx transport in this process that answers the protocol's four calls with
a status that turns terminal only after `stale` more reads: the lag is set exactly, which a
real stack cannot do on demand (the real stack's runs are `test_farm.py`'s)."""

from __future__ import annotations

import io
import json
import zipfile

import httpx
import pytest

from texelbake.errors import StageError
from texelbake_client import submit as submit_mod


def _server(stale: int, final: str = "succeeded") -> tuple[httpx.MockTransport, dict]:
    """A transport answering upload, create, events (one terminal job event), status
    ("running" for the first `stale` reads after the stream ended, then `final`) and
    result (a zip of one baked root layer); `seen` counts the status reads."""
    seen = {"status": 0}
    zbuf = io.BytesIO()
    with zipfile.ZipFile(zbuf, "w") as z:
        z.writestr("asset_baked.usda", "#usda 1.0\n")

    def handle(req: httpx.Request) -> httpx.Response:
        path = req.url.path
        if path.endswith("/assets"):
            return httpx.Response(201, json={"id": "a1"})
        if path.endswith("/jobs") and req.method == "POST":
            return httpx.Response(201, json={"id": "j1", "state": "queued"})
        if path.endswith("/events"):
            ev = {"seq": 1, "kind": "job", "data": {"state": final}}
            return httpx.Response(200, text=f"data: {json.dumps(ev)}\n\n",
                                  headers={"content-type": "text/event-stream"})
        if path.endswith("/result"):
            return httpx.Response(200, content=zbuf.getvalue())
        if path.endswith("/jobs/j1"):
            seen["status"] += 1
            after = seen["status"] - 1  # reads made after the first one (the loop's)
            state = "running" if after <= stale else final
            return httpx.Response(200, json={"id": "j1", "state": state, "progress": 100,
                                             "stages": [], "error": None})
        return httpx.Response(404, json={"detail": path})

    return httpx.MockTransport(handle), seen


@pytest.fixture
def layer(tmp_path):
    p = tmp_path / "asset.usda"
    p.write_text("#usda 1.0\n")
    return p


def test_a_status_behind_the_stream_is_read_again(layer, tmp_path, monkeypatch):
    """The terminal event arrives, the next three status reads still say "running": the
    client reads again and returns the result once the status says "succeeded"."""
    monkeypatch.setattr(submit_mod.time, "sleep", lambda s: None)
    transport, seen = _server(stale=3)
    root = submit_mod.submit(layer, "http://api", "t", tmp_path / "out", progress=False,
                             transport=transport)
    assert root.name == "asset_baked.usda" and root.is_file()
    assert seen["status"] == 1 + 3 + 1  # the loop's read, three stale ones, the settled one


def test_a_status_that_never_settles_is_reported(layer, tmp_path, monkeypatch):
    """A status still "running" after the bound: the job is reported as it reads, not
    waited for without end."""
    clock = iter(range(0, 10_000))
    monkeypatch.setattr(submit_mod.time, "monotonic", lambda: float(next(clock)))
    monkeypatch.setattr(submit_mod.time, "sleep", lambda s: None)
    transport, _ = _server(stale=10_000)
    with pytest.raises(StageError, match="ended running"):
        submit_mod.submit(layer, "http://api", "t", tmp_path / "out", progress=False,
                          transport=transport, timeout=5_000)


def test_a_failed_job_is_reported_with_its_state(layer, tmp_path, monkeypatch):
    monkeypatch.setattr(submit_mod.time, "sleep", lambda s: None)
    transport, _ = _server(stale=1, final="failed")
    with pytest.raises(StageError, match="ended failed"):
        submit_mod.submit(layer, "http://api", "t", tmp_path / "out", progress=False,
                          transport=transport)
