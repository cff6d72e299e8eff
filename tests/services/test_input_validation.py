"""Validated on the way in, the same on the way out, against a real uvicorn on PostgreSQL (no
workers): settings with NaN or Infinity inside a list, a lone surrogate in any string, an
out-of-range `Last-Event-ID`. Each is a 422 naming the field (or, for the header, ignored),
nothing is stored, and every job the requests left behind reads back. Also the events client's
last read of a job that ends between two of its streams."""

from __future__ import annotations

import json

import httpx
import pytest
from sqlalchemy import text

from farm.db import session_factory
from tests.helpers.farm import AUTH, TOKEN, db_url, farm
from tests.helpers.service import CHEAP_SETTINGS, fresh_postgres, usda

pytestmark = [pytest.mark.service, pytest.mark.timeout(180)]

JSON = {"Content-Type": "application/json"}
#: settings values JSON cannot carry back (as sent: JSON extensions, a lone surrogate)
NON_FINITE = ("[Infinity]", "[NaN]", "[-Infinity]", "[512.0, Infinity]", "[1e7]")
SURROGATE = '"\\ud800"'


@pytest.fixture(scope="module")
def stack(tmp_path_factory):
    with fresh_postgres() as url, farm(
        tmp_path_factory.mktemp("stack"), database_url=url, workers={}, tokens={TOKEN: "farm"},
        TEXELBAKE_SSE_MAX_SECONDS="1",
    ) as s:
        yield s


@pytest.fixture
def c(stack):
    with httpx.Client(base_url=stack.api_url + "/api/v1", headers=AUTH, timeout=60) as client:
        yield client


@pytest.fixture(scope="module")
def asset(stack) -> str:
    with httpx.Client(base_url=stack.api_url + "/api/v1", headers=AUTH, timeout=60) as client:
        r = client.post("/assets", files={"file": ("cube.usda", usda())})
        assert r.status_code == 201, r.text
        return r.json()["id"]


def counts(c: httpx.Client) -> tuple[int, int]:
    return c.get("/jobs").json()["count"], c.get("/batches").json()["count"]


def post_raw(c: httpx.Client, path: str, body: str) -> httpx.Response:
    """POST a JSON text as written (NaN, Infinity and lone surrogates are not `json=` data)."""
    return c.post(path, content=body.encode("ascii"), headers=JSON)


def assert_422_at(r: httpx.Response, loc: list) -> None:
    """A 422 in the error model whose `detail` names the field at `loc`."""
    assert r.status_code == 422, (loc, r.status_code, r.text)
    body = r.json()  # the body renders: valid UTF-8 JSON
    assert body["code"] == "validation_error", body
    assert any(e["loc"][:len(loc)] == loc for e in body["detail"]), (loc, body)


@pytest.mark.parametrize("bad", NON_FINITE)
def test_non_finite_list_entry_is_422_and_nothing_is_stored(c, asset, bad):
    before = counts(c)
    r = post_raw(c, "/jobs",
                 f'{{"asset_id": "{asset}", "settings": {{"lod_switch_px": {bad}}}}}')
    assert_422_at(r, ["body", "settings", "lod_switch_px"])
    cheap = json.dumps(CHEAP_SETTINGS)[:-1]
    r = post_raw(c, "/batches", f'{{"settings": {cheap}, "lod_switch_px": {bad}}}, '
                                f'"items": [{{"asset_id": "{asset}"}}]}}')
    assert_422_at(r, ["body", "settings", "lod_switch_px"])
    r = post_raw(c, "/batches", f'{{"settings": {cheap}}}, "items": [{{"asset_id": "{asset}"}}, '
                                f'{{"asset_id": "{asset}", "settings": {{"lod_switch_px": {bad}}}}}]}}')
    assert_422_at(r, ["body", "items", 1, "settings", "lod_switch_px"])
    assert counts(c) == before


@pytest.mark.parametrize(("body", "loc"), [
    ('{"asset_id": %s}', ["body", "asset_id"]),
    ('{"asset_id": "@", "settings": {"warp": %s}}', ["body", "settings", "warp"]),
    ('{"asset_id": "@", "settings": {%s: 1}}', ["body", "settings"]),
])
def test_lone_surrogate_in_a_job_is_422_naming_the_field(c, asset, body, loc):
    before = counts(c)
    r = post_raw(c, "/jobs", body.replace("@", asset) % SURROGATE)
    assert_422_at(r, loc)
    assert "\\ud800" in r.text  # echoed back as an escape
    assert counts(c) == before


@pytest.mark.parametrize(("body", "loc"), [
    ('{"name": %s, "items": [{"asset_id": "@"}]}', ["body", "name"]),
    ('{"items": [{"asset_id": %s}]}', ["body", "items", 0, "asset_id"]),
    ('{"settings": {"warp": %s}, "items": [{"asset_id": "@"}]}', ["body", "settings", "warp"]),
    ('{"items": [{"asset_id": "@"}, {"asset_id": "@", "settings": {"warp": %s}}]}',
     ["body", "items", 1, "settings", "warp"]),
    ('{"items": [{"asset_id": "@", "settings": {%s: 1}}]}', ["body", "items", 0, "settings"]),
])
def test_lone_surrogate_in_a_batch_is_422_naming_the_field(c, asset, body, loc):
    before = counts(c)
    r = post_raw(c, "/batches", body.replace("@", asset) % SURROGATE)
    assert_422_at(r, loc)
    assert counts(c) == before


def events(c: httpx.Client, path: str, last_event_id: str | None) -> tuple[int, str]:
    headers = {} if last_event_id is None else {"Last-Event-ID": last_event_id}
    with c.stream("GET", path, headers=headers) as s:
        return s.status_code, "".join(s.iter_text())


@pytest.mark.parametrize("given", ["99999999999999999999999", str(2**63), "-1", "x", "1e3"])
def test_out_of_range_last_event_id_is_ignored(c, asset, given):
    """Not a sequence number (0..2^63-1): the job's stream replays from its first event, the
    tenant's starts from now (as with no header); never a database overflow."""
    jid = c.post("/jobs", json={"asset_id": asset}).json()["id"]
    assert c.delete(f"/jobs/{jid}").status_code == 202  # terminal: its stream ends
    status, body = events(c, f"/jobs/{jid}/events", given)
    assert status == 200 and body == events(c, f"/jobs/{jid}/events", None)[1]
    assert '"state": "cancelled"' in body, body
    status, body = events(c, "/events", given)
    assert status == 200 and "event: ready" in body, body
    newest = json.loads(body.split("event: ready\ndata: ")[1].split("\n")[0])["after"]
    assert newest >= int(body.split("id: ")[1].split("\n")[0]) > 0


def test_largest_last_event_id_is_a_valid_position(c, asset):
    jid = c.post("/jobs", json={"asset_id": asset}).json()["id"]
    assert c.delete(f"/jobs/{jid}").status_code == 202
    assert events(c, f"/jobs/{jid}/events", str(2**63 - 1)) == (200, "")
    status, body = events(c, "/events", str(2**63 - 1))
    assert status == 200 and body.startswith(f"id: {2**63 - 1}\nevent: ready"), body


def test_a_stored_row_that_does_not_read_back_still_reads(stack, c, asset):
    """A job or batch stored before its settings were checked (`[null]` where a number
    belongs) answers 200, its unreadable field shown at its default."""
    jid = c.post("/jobs", json={"asset_id": asset, "settings": {"seed": 7}}).json()["id"]
    r = c.post("/batches", json={"items": [{"asset_id": asset}]})
    bid = r.json()["id"]
    bad = json.dumps({"seed": 7, "lod_switch_px": [None]})
    with session_factory(db_url(stack)).begin() as s:
        s.execute(text("UPDATE jobs SET settings_json = :v WHERE id = :id"), {"v": bad, "id": jid})
        s.execute(text("UPDATE batches SET settings_json = :v WHERE id = :id"),
                  {"v": bad, "id": bid})
    r = c.get(f"/jobs/{jid}")
    assert r.status_code == 200, r.text
    assert r.json()["settings"]["seed"] == 7 and r.json()["settings"]["lod_switch_px"] == [256, 64]
    assert c.delete(f"/jobs/{jid}").status_code == 202
    assert c.get(f"/batches/{bid}").status_code == 200


def test_events_client_drains_a_job_that_ends_between_streams(stack, c, asset):
    """The job's stream closes (`sse_max_seconds`, 1 s here) while the job is queued, and the
    job is cancelled after that stream's last read, before the client asks for its state: the
    client reads the events once more and yields the cancellation, the stream's last event."""
    from texelbake_client.submit import API, iter_events

    jid = c.post("/jobs", json={"asset_id": asset}).json()["id"]
    state_url = f"{API}/jobs/{jid}"
    cancelled: list[int] = []

    def cancel_before_state_check(request: httpx.Request) -> None:
        if request.method == "GET" and request.url.path == state_url and not cancelled:
            cancelled.append(c.delete(f"/jobs/{jid}").status_code)

    with httpx.Client(base_url=stack.api_url, headers=AUTH, timeout=60,
                      event_hooks={"request": [cancel_before_state_check]}) as client:
        events = list(iter_events(client, jid))
    assert cancelled == [202]
    assert events[-1]["kind"] == "job" and events[-1]["data"]["state"] == "cancelled", events
    assert [e["seq"] for e in events] == sorted({e["seq"] for e in events})


def test_every_job_reads_back(c, asset):
    """Last: every job the requests above left behind reads back (200), none answers 500; a
    job and a batch made here are among them, whichever tests ran before on this stack."""
    mine = {c.post("/jobs", json={"asset_id": asset}).json()["id"]}
    r = c.post("/batches", json={"items": [{"asset_id": asset}]})
    assert r.status_code == 201, r.text
    jobs = c.get("/jobs", params={"limit": 1000}).json()["data"]
    assert mine <= {j["id"] for j in jobs}, jobs
    for j in jobs:
        assert c.get(f"/jobs/{j['id']}").status_code == 200, j
        assert c.delete(f"/jobs/{j['id']}").status_code == 202, j
    for b in c.get("/batches").json()["data"]:
        assert c.get(f"/batches/{b['id']}").status_code == 200, b


def test_settings_that_would_not_read_back_are_refused_at_their_loc():
    """The last guard before a job is stored: a spec whose JSON does not read back."""
    from fastapi.exceptions import RequestValidationError

    from services.submission import JobSpec, check_readable

    good = JobSpec("a", "{}", 50)
    check_readable([good])
    bad = JobSpec("a", '{"lod_switch_px": [null]}', 50, ("body", "items", 3, "settings"))
    with pytest.raises(RequestValidationError) as exc:
        check_readable([good, bad])
    assert [e["loc"] for e in exc.value.errors()] == [
        ["body", "items", 3, "settings", "lod_switch_px", 0]]
