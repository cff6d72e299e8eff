"""Batches against real processes (redis-server, Celery prefork workers, uvicorn; SQLite and
PostgreSQL): a batch of three items, one of which really fails (a layer without a mesh
uploads fine and fails in the plan stage), its progress, its archive, cancellation,
validation naming the item, another tenant's 404, and `texelbake submit --manifest`."""

from __future__ import annotations

import io
import json
import os
import subprocess
import sys
import time
import zipfile
from pathlib import Path

import httpx
import pytest

from tests.helpers.farm import AUTH, TOKEN, farm, ledger_rows
from tests.helpers.service import CHEAP_SETTINGS, fresh_postgres, usda
from texelbake_client.submit import package

pytestmark = [pytest.mark.service, pytest.mark.timeout(420)]
TOKEN_B = "batch-tenant-b-0123456789"
AUTH_B = {"Authorization": f"Bearer {TOKEN_B}"}
TOKENS = {TOKEN: "farm", TOKEN_B: "other"}
FINISHED = ("succeeded", "failed", "cancelled")
#: a valid layer with no UsdGeom.Mesh: the upload check passes, the plan stage fails it
NO_MESH = usda()
#: the items' bake: the cheap one at a 16² atlas (one cpm shard); what is checked here is the
#: batch (items, states, progress, archive), not the bake's size
BATCH_SETTINGS = {**CHEAP_SETTINGS, "atlas_resolution": 16}


@pytest.fixture(scope="module")
def cylinder(tmp_path_factory) -> Path:
    from texelbake.testscenes import write_scene

    return write_scene("cylinder", tmp_path_factory.mktemp("scene") / "cylinder.usda", "small")


@pytest.fixture(scope="module")
def stack(tmp_path_factory):
    with farm(tmp_path_factory.mktemp("stack"), tokens=TOKENS) as s:
        yield s


def client(stack, auth=AUTH) -> httpx.Client:  # noqa: ANN001
    return httpx.Client(base_url=stack.api_url + "/api/v1", headers=auth, timeout=60)


def wait_batch(c: httpx.Client, batch_id: str, timeout: float = 300.0) -> list[dict]:
    """Poll the batch until it finishes; every status seen, in order."""
    seen = []
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        r = c.get(f"/batches/{batch_id}")
        assert r.status_code == 200, r.text
        seen.append(r.json())
        if seen[-1]["state"] in FINISHED:
            return seen
        time.sleep(0.2)
    raise AssertionError(f"batch did not finish; last status {seen[-1]}")


def members(data: bytes) -> dict[str, bytes]:
    with zipfile.ZipFile(io.BytesIO(data)) as zf:
        return {n: zf.read(n) for n in zf.namelist()}


def run_three_items(stack, c: httpx.Client, cylinder: Path) -> None:  # noqa: ANN001
    """Three items, the middle one fails; the others finish; progress, archive, tenancy."""
    cyl = c.post("/assets", files={"file": package(cylinder)}).json()["id"]
    bad = c.post("/assets", files={"file": ("nomesh.usda", NO_MESH)})
    assert bad.status_code == 201, bad.text
    bad = bad.json()["id"]
    n_jobs = c.get("/jobs").json()["count"]
    r = c.post("/batches", json={
        "name": "three", "settings": BATCH_SETTINGS, "priority": 60,
        "items": [{"asset_id": cyl}, {"asset_id": bad, "priority": 90},
                  {"asset_id": cyl, "settings": {"samples_per_texel": 4}}]})
    assert r.status_code == 201, r.text
    batch = r.json()
    bid = batch["id"]
    assert [i["index"] for i in batch["items"]] == [0, 1, 2]
    assert batch["counts"]["total"] == 3 and c.get("/jobs").json()["count"] == n_jobs + 3
    # items are ordinary jobs: the batch's defaults, overridden per item field by field
    jobs = [c.get(f"/jobs/{i['job_id']}").json() for i in batch["items"]]
    assert [j["priority"] for j in jobs] == [60, 90, 60]
    assert jobs[0]["settings"]["samples_per_texel"] == BATCH_SETTINGS["samples_per_texel"]
    assert jobs[2]["settings"]["samples_per_texel"] == 4
    assert jobs[2]["settings"]["atlas_resolution"] == BATCH_SETTINGS["atlas_resolution"]
    r = c.get(f"/batches/{bid}/result")
    assert r.status_code == 409 and r.json()["code"] == "batch_not_finished", r.text
    # another tenant's batch does not exist for it
    with client(stack, AUTH_B) as b:
        for method, path in (("GET", f"/batches/{bid}"), ("DELETE", f"/batches/{bid}"),
                             ("GET", f"/batches/{bid}/result")):
            r = b.request(method, path)
            assert r.status_code == 404 and r.json()["code"] == "batch_not_found", r.text
        assert b.get("/batches").json()["count"] == 0

    seen = wait_batch(c, bid)
    final = seen[-1]
    assert final["state"] == "failed", final
    assert final["counts"] == {"total": 3, "queued": 0, "running": 0, "succeeded": 2,
                               "failed": 1, "cancelled": 0}
    assert final["progress"] == 1.0 and final["finished_at"] is not None
    states = [i["state"] for i in final["items"]]
    assert states == ["succeeded", "failed", "succeeded"]
    assert "no UsdGeom.Mesh" in final["items"][1]["error"], final["items"][1]
    # the failed item did not stop the others: it failed while they were still unfinished
    assert any(s["items"][1]["state"] == "failed" and s["state"] == "running" for s in seen)
    fractions = [s["progress"] for s in seen]
    assert fractions == sorted(fractions) and any(0 < f < 1 for f in fractions), fractions
    assert c.get(f"/batches/{bid}").json()["counts"]["total"] == 3
    # the listing's summary (from aggregates) says what the batch's own status says
    listing = c.get("/batches").json()
    summary = next(b for b in listing["data"] if b["id"] == bid)
    assert summary == {k: v for k, v in final.items() if k not in ("settings", "items")}

    # the archive: batch.json plus a folder per succeeded item with that job's result
    r = c.get(f"/batches/{bid}/result")
    assert r.status_code == 200 and r.headers["content-type"] == "application/zip", r.text
    zm = members(r.content)
    folders = sorted({n.split("/", 1)[0] for n in zm if "/" in n})
    assert folders == ["000_cylinder", "002_cylinder"], folders
    manifest = json.loads(zm["batch.json"])
    assert [(i["index"], i["state"], i["folder"]) for i in manifest["items"]] == [
        (0, "succeeded", "000_cylinder"), (1, "failed", None), (2, "succeeded", "002_cylinder")]
    assert "no UsdGeom.Mesh" in manifest["items"][1]["error"]
    for it in (final["items"][0], final["items"][2]):
        one = members(c.get(f"/jobs/{it['job_id']}/result").content)
        prefix = f"{it['index']:03d}_cylinder/"
        assert {prefix + n: d for n, d in one.items()} == {
            n: d for n, d in zm.items() if n.startswith(prefix)}
        assert any(n.endswith("_baked.usda") for n in one)
    # deterministic: rebuilt from scratch, the same bytes
    (cached,) = (Path(stack.env["TEXELBAKE_ARTIFACT_ROOT"]) / "batches" / bid).glob("*.zip")
    cached.unlink()
    assert c.get(f"/batches/{bid}/result").content == r.content
    # the two cylinder items are different bakes (samples_per_texel 8 vs 4)
    a0 = next(n for n in zm if n.startswith("000_cylinder/") and n.endswith(".usdc"))
    assert zm[a0] != zm.get(a0.replace("000_", "002_"))


def test_three_items_one_fails_sqlite(stack, cylinder):
    with client(stack) as c:
        run_three_items(stack, c, cylinder)


def test_three_items_one_fails_postgresql(cylinder, tmp_path):
    with fresh_postgres() as url, farm(tmp_path / "stack", database_url=url,
                                       tokens=TOKENS) as pg:
        with client(pg) as c:
            run_three_items(pg, c, cylinder)


def test_bad_item_is_named_and_nothing_is_created(stack):
    with client(stack) as c, client(stack, AUTH_B) as b:
        good = c.post("/assets", files={"file": ("nomesh.usda", NO_MESH)}).json()["id"]
        theirs = b.post("/assets", files={"file": ("theirs.usda", usda(header='doc = "b"'))})
        theirs = theirs.json()["id"]
        before = (c.get("/batches").json()["count"], c.get("/jobs").json()["count"])
        ok = {"asset_id": good}
        cases = [
            ([ok, {"asset_id": good, "settings": {"atlas_resolution": 12}}], 422,
             ["body", "items", 1, "settings"], "atlas_resolution"),
            ([ok, ok, {"asset_id": good, "settings": {"no_such_knob": 1}}], 422,
             ["body", "items", 2, "settings", "no_such_knob"], "no_such_knob"),
            ([{"asset_id": good, "settings": {"shard_texels": 64}}], 422,
             ["body", "items", 0, "settings"], "shard_texels"),  # only wrong merged (atlas 32)
            ([ok, {"asset_id": good, "priority": 101}], 422,
             ["body", "items", 1, "priority"], "100"),
            ([ok, ok, ok, {"asset_id": "nope"}], 404, None, "items[3].asset_id"),
            ([ok, {"asset_id": theirs}], 404, None, "items[1].asset_id"),
        ]
        for items, status, loc, needle in cases:
            r = c.post("/batches", json={"settings": CHEAP_SETTINGS, "items": items})
            assert r.status_code == status, (items, r.text)
            body = r.json()
            if status == 422:
                assert body["code"] == "validation_error"
                issue = next(e for e in body["detail"] if e["loc"][:len(loc)] == loc)
                assert needle in json.dumps(issue), (needle, body)
            else:
                assert body["code"] == "asset_not_found" and needle in body["detail"], body
        for bad_body in ({"items": []}, {"items": [ok], "extra": 1}):
            assert c.post("/batches", json=bad_body).status_code == 422
        after = (c.get("/batches").json()["count"], c.get("/jobs").json()["count"])
        assert after == before
        assert b.get("/batches").json()["count"] == 0


def test_cancel_batch(stack, cylinder):
    slow = {**CHEAP_SETTINGS, "samples_per_texel": 16}  # not a bake another test left cached
    with client(stack) as c:
        cyl = c.post("/assets", files={"file": package(cylinder)}).json()["id"]
        batch = c.post("/batches", json={"settings": slow, "items": [
            {"asset_id": cyl}, {"asset_id": cyl, "settings": {"seed": 1}}]}).json()
        bid = batch["id"]
        deadline = time.monotonic() + 120
        while c.get(f"/batches/{bid}").json()["state"] != "running":
            assert time.monotonic() < deadline
            time.sleep(0.1)
        r = c.delete(f"/batches/{bid}")
        assert r.status_code == 202, r.text
        out = r.json()
        assert out["state"] == "cancelled" and out["counts"]["cancelled"] == 2, out
        time.sleep(3.0)  # nothing runs on after the cancel
        out = c.get(f"/batches/{bid}").json()
        assert [i["state"] for i in out["items"]] == ["cancelled", "cancelled"]
        summary = next(b for b in c.get("/batches").json()["data"] if b["id"] == bid)
        assert summary == {k: v for k, v in out.items() if k not in ("settings", "items")}
        for it in out["items"]:
            assert not any(r.state == "running" for r in ledger_rows(stack, it["job_id"]))
        # a finished batch's archive: the manifest alone (no item succeeded)
        r = c.get(f"/batches/{bid}/result")
        assert r.status_code == 200, r.text
        zm = members(r.content)
        assert list(zm) == ["batch.json"]
        assert [i["state"] for i in json.loads(zm["batch.json"])["items"]] == ["cancelled"] * 2
        assert c.delete(f"/batches/{bid}").json()["state"] == "cancelled"  # idempotent


def test_cli_manifest_end_to_end(stack, cylinder, tmp_path):
    (tmp_path / "in").mkdir()
    (tmp_path / "in" / "nomesh.usda").write_bytes(NO_MESH)
    manifest = tmp_path / "in" / "batch.json"
    manifest.write_text(json.dumps({
        "name": "cli", "settings": BATCH_SETTINGS,
        "items": [{"path": str(cylinder)}, {"path": "nomesh.usda", "priority": 70}]}))
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[2])}
    cmd = [sys.executable, "-m", "texelbake.cli", "submit", "--manifest", str(manifest),
           "--server", stack.api_url, "--token", TOKEN, "-o", str(tmp_path / "out")]
    p = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=360)
    assert p.returncode == 4, (p.stdout, p.stderr)
    assert "1 of 2 items succeeded" in p.stdout, p.stdout
    assert "items[1]" in p.stderr and "nomesh.usda: failed" in p.stderr, p.stderr
    assert "no UsdGeom.Mesh" in p.stderr
    assert "%" in p.stderr  # the one-line progress bar
    out = tmp_path / "out"
    doc = json.loads((out / "batch.json").read_text())
    assert [i["state"] for i in doc["items"]] == ["succeeded", "failed"]
    assert list((out / "000_cylinder").glob("*_baked.usda")), sorted(os.listdir(out))
    assert not (out / "001_nomesh").exists()
    # a manifest the server refuses (an item's settings): exit 2 naming the item; no batch
    with client(stack) as c:
        n = c.get("/batches").json()["count"]
        manifest.write_text(json.dumps({"settings": CHEAP_SETTINGS, "items": [
            {"path": "nomesh.usda"}, {"path": "nomesh.usda", "settings": {"c_max": 0}}]}))
        p = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=120)
        assert p.returncode == 2 and "HTTP 422" in p.stderr and "c_max" in p.stderr, p.stderr
        assert "'items', 1" in p.stderr, p.stderr
        # a missing file: exit 2 naming the item before anything is sent
        manifest.write_text(json.dumps({"items": [{"path": "nomesh.usda"},
                                                  {"path": "gone.usda"}]}))
        p = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=120)
        assert p.returncode == 2 and "gone.usda" in p.stderr, p.stderr
        assert c.get("/batches").json()["count"] == n


@pytest.mark.parametrize("doc,needle", [
    ([], "JSON object"),
    ({"items": []}, "non-empty list"),
    ({"items": [{"path": "a.usda"}], "sttings": {}}, "unknown keys ['sttings']"),
    ({"items": [{"path": "a.usda"}, {"file": "a.usda"}]}, "items[1] needs a string `path`"),
    ({"items": [{"path": "a.usda", "prio": 1}]}, "items[0]: unknown keys ['prio']"),
    ({"items": [{"path": "a.usda"}, {"path": "b.usda"}]}, "items[1]: "),
])
def test_manifest_shape_errors(tmp_path, doc, needle):
    """A manifest's shape is checked before anything is uploaded (no server needed)."""
    from texelbake.errors import SettingsError
    from texelbake_client.batch import load_manifest

    (tmp_path / "a.usda").write_bytes(NO_MESH)
    m = tmp_path / "m.json"
    m.write_text(json.dumps(doc))
    with pytest.raises(SettingsError) as err:
        load_manifest(m)
    assert needle in str(err.value) and str(m) in str(err.value)


def test_manifest_paths_resolve_against_its_folder(tmp_path):
    from texelbake_client.batch import load_manifest

    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "a.usda").write_bytes(NO_MESH)
    m = tmp_path / "sub" / "m.json"
    m.write_text(json.dumps({"settings": {"c_max": 8}, "priority": 7, "items": [
        {"path": "a.usda", "priority": 9}, {"path": str(tmp_path / "sub" / "a.usda")}]}))
    got = load_manifest(m)
    assert got.paths == [tmp_path / "sub" / "a.usda"] * 2
    assert got.body == {"settings": {"c_max": 8}, "priority": 7}
    assert got.items == [{"priority": 9}, {}]
