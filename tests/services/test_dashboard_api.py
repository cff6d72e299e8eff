"""The API side of the dashboard, in process (no servers): the built bundle served at `/` after
the API routes (which keep answering in the error model), a clear 503 without a build, the job
list's server-side filters and paging, and the farm snapshot (ledger counts, another tenant's
shards without their job id, the broker down)."""

from __future__ import annotations

import json
import uuid

import pytest
from fastapi.testclient import TestClient

from farm import ledger
from farm.config import Settings
from farm.db import Asset
from services.main import DASHBOARD_NOT_BUILT, create_app
from services.routers.farm import farm_snapshot

TOKENS = {"tok-a-0123456789abcdef": "studio-a", "tok-b-0123456789abcdef": "studio-b"}
A = {"Authorization": "Bearer tok-a-0123456789abcdef"}
B = {"Authorization": "Bearer tok-b-0123456789abcdef"}
INDEX = "<!doctype html><title>texelbake</title><div id=app></div>"


def make_app(root, web_dist):  # noqa: ANN001
    settings = Settings(
        artifact_root=root,
        environment="test",
        secret_key="dashboard-secret-key",
        redis_url="redis://127.0.0.1:1/0",  # nothing listens there: the broker is down
        tokens=TOKENS,
        web_dist=web_dist,
    )
    return create_app(settings, sweeper=False)


@pytest.fixture
def dist(tmp_path):
    d = tmp_path / "dist"
    (d / "assets").mkdir(parents=True)
    (d / "index.html").write_text(INDEX)
    (d / "assets" / "app.js").write_text("console.log(1)")
    return d


def add_asset(app, tenant: str) -> str:  # noqa: ANN001
    aid = "a" + uuid.uuid4().hex[:20]
    with app.state.writer.begin() as s:
        s.add(Asset(id=aid, tenant=tenant, sha256=uuid.uuid4().hex * 2, filename="x.usda",
                    kind="usda", root_layer="x.usda", size_bytes=1, n_files=1))  # fmt: skip
    return aid


def add_job(app, tenant: str, asset: str, plan: bool = False) -> str:  # noqa: ANN001
    jid = uuid.uuid4().hex
    ledger.create_job(app.state.writer, jid, tenant, asset, "{}")
    if plan:
        ledger.record_plan(
            app.state.writer, jid, [("ingest", "ingest", 1, ()), ("cpm", "cpm", 3, ("ingest",))], []
        )
    return jid


def test_bundle_served_at_root_after_the_api(tmp_path, dist):
    app = make_app(tmp_path / "art", dist)
    with TestClient(app) as c:
        r = c.get("/")
        assert r.status_code == 200 and r.text == INDEX
        assert r.headers["content-type"].startswith("text/html")
        r = c.get("/assets/app.js")
        assert r.status_code == 200 and r.text == "console.log(1)"
        # the API is matched first and answers as before
        r = c.get("/api/v1/jobs")
        assert r.status_code == 401 and r.json()["code"] == "not_authenticated"
        assert c.get("/api/v1/openapi.json").json()["info"]["title"] == "texelbake"
        r = c.get("/api/v1/no-such-route")
        assert r.status_code == 404 and r.json()["code"] == "not_found"
        r = c.get("/assets/missing.js")
        assert r.status_code == 404 and r.json()["code"] == "not_found"


def test_root_without_a_build_is_a_clear_503(tmp_path):
    app = make_app(tmp_path / "art", tmp_path / "no-dist")
    with TestClient(app) as c:
        r = c.get("/")
        assert r.status_code == 503
        body = r.json()
        assert body["code"] == "service_unavailable"
        assert DASHBOARD_NOT_BUILT in body["detail"] and "no-dist" in body["detail"]
        assert c.get("/api/v1/jobs", headers=A).status_code == 200


def test_job_list_filters_pages_and_tenants(tmp_path, dist):
    app = make_app(tmp_path / "art", dist)
    with TestClient(app) as c:  # the lifespan stores the tokens
        a1, a2, b1 = (
            add_asset(app, "studio-a"),
            add_asset(app, "studio-a"),
            add_asset(app, "studio-b"),
        )
        queued = [add_job(app, "studio-a", a1) for _ in range(3)]
        running = [add_job(app, "studio-a", a2, plan=True) for _ in range(2)]
        other = add_job(app, "studio-b", b1)

        body = c.get("/api/v1/jobs", headers=A).json()
        assert body["count"] == 5 and other not in [j["id"] for j in body["data"]]
        body = c.get("/api/v1/jobs?state=running", headers=A).json()
        assert body["count"] == 2 and sorted(j["id"] for j in body["data"]) == sorted(running)
        assert all(j["state"] == "running" for j in body["data"])
        body = c.get(f"/api/v1/jobs?asset_id={a1}", headers=A).json()
        assert sorted(j["id"] for j in body["data"]) == sorted(queued)
        # paging: count is the filtered total, pages do not overlap
        p1 = c.get("/api/v1/jobs?limit=2&skip=0", headers=A).json()
        p2 = c.get("/api/v1/jobs?limit=2&skip=2", headers=A).json()
        assert p1["count"] == p2["count"] == 5 and len(p1["data"]) == len(p2["data"]) == 2
        assert not {j["id"] for j in p1["data"]} & {j["id"] for j in p2["data"]}
        # another tenant's asset filter finds nothing of ours, and the other tenant sees its own
        assert c.get(f"/api/v1/jobs?asset_id={b1}", headers=A).json()["count"] == 0
        assert [j["id"] for j in c.get("/api/v1/jobs", headers=B).json()["data"]] == [other]
        r = c.get("/api/v1/jobs?state=sleeping", headers=A)
        assert r.status_code == 422 and r.json()["code"] == "validation_error"


def test_farm_snapshot_counts_and_masks_other_tenants(tmp_path, dist):
    app = make_app(tmp_path / "art", dist)
    with TestClient(app) as c:
        mine = add_job(app, "studio-a", add_asset(app, "studio-a"), plan=True)
        theirs = add_job(app, "studio-b", add_asset(app, "studio-b"), plan=True)
        w = app.state.writer
        assert ledger.start_shard(w, mine, "ingest", 0, "host-a:11", 3).action == "run"
        assert ledger.start_shard(w, theirs, "ingest", 0, "host-b:22", 3).action == "run"

        snap = farm_snapshot(
            app.state.reader, app.state.celery, "redis://127.0.0.1:1/0", "studio-a"
        )
        assert snap.broker is False and snap.workers == []
        q = {x.name: x for x in snap.queues}
        assert q["ingest"].running == 2 and q["ingest"].queued == 0 and q["ingest"].length is None
        assert q["cpm"].running == 0 and q["cpm"].queued == 0  # cpm waits on ingest: pending
        cur = {(x.job_id, x.worker) for x in snap.current}
        assert cur == {(mine, "host-a:11"), (None, "host-b:22")}

        body = c.get("/api/v1/farm", headers=B).json()
        assert {(x["job_id"], x["worker"]) for x in body["current"]} == {
            (None, "host-a:11"),
            (theirs, "host-b:22"),
        }
        assert c.get("/api/v1/farm").status_code == 401


def test_farm_events_stream_a_snapshot(tmp_path, dist):
    app = make_app(tmp_path / "art", dist)
    app.state.settings.sse_max_seconds = 0.1
    with TestClient(app) as c:
        with c.stream("GET", "/api/v1/farm/events", headers=A) as r:
            assert r.status_code == 200
            assert r.headers["content-type"].startswith("text/event-stream")
            text = "".join(r.iter_text())
    blocks = [b for b in text.split("\n\n") if b.strip()]
    assert blocks and blocks[0].startswith("id: 1\nevent: farm\ndata: ")
    snap = json.loads(blocks[0].split("data: ", 1)[1])
    assert {q["name"] for q in snap["queues"]} >= {"ingest", "cpm", "render"}


def sse_blocks(text: str) -> list[dict]:
    out = []
    for block in (b for b in text.split("\n\n") if b.strip()):
        fields = dict(line.split(": ", 1) for line in block.splitlines() if ": " in line)
        out.append(
            {"id": fields.get("id"), "event": fields["event"], "data": json.loads(fields["data"])}
        )
    return out


def test_tenant_events_stream_only_this_tenants_jobs(tmp_path, dist):
    app = make_app(tmp_path / "art", dist)
    app.state.settings.sse_max_seconds = 0.3
    with TestClient(app) as c:
        mine = add_job(app, "studio-a", add_asset(app, "studio-a"), plan=True)
        theirs = add_job(app, "studio-b", add_asset(app, "studio-b"), plan=True)
        with c.stream("GET", "/api/v1/events", headers={**A, "Last-Event-ID": "0"}) as r:
            assert r.status_code == 200
            got = sse_blocks("".join(r.iter_text()))
        assert got[0]["event"] == "ready" and got[0]["id"] == "0"
        evs = got[1:]
        assert evs and {e["data"]["job_id"] for e in evs} == {mine}
        assert [e["event"] for e in evs][:2] == ["job", "job"]  # queued, then running
        seqs = [int(e["id"]) for e in evs]
        assert seqs == sorted(seqs)
        # resuming after the last one sent: nothing old again; without Last-Event-ID the
        # stream starts now (the client re-reads its list on `ready`)
        with c.stream("GET", "/api/v1/events", headers={**A, "Last-Event-ID": str(seqs[-1])}) as r:
            assert [b["event"] for b in sse_blocks("".join(r.iter_text()))] == ["ready"]
        with c.stream("GET", "/api/v1/events", headers=B) as r:
            blocks = sse_blocks("".join(r.iter_text()))
        assert [b["event"] for b in blocks] == ["ready"]
        assert int(blocks[0]["id"]) >= max(seqs)
        with c.stream("GET", "/api/v1/events", headers={**B, "Last-Event-ID": "0"}) as r:
            ids = {b["data"]["job_id"] for b in sse_blocks("".join(r.iter_text()))[1:]}
        assert ids == {theirs}
        assert c.get("/api/v1/events").status_code == 401
