"""The API as an integrator meets it: a Python client generated from the served
`/api/v1/openapi.json` with the pinned `openapi-python-client` (no generator warning allowed)
drives a bake on a real stack (redis-server, uvicorn, Celery workers) through generated code
only: upload, job, polling, events, report, result, previews, cancel; and a wrong token, an
unknown job and rejected uploads come back parsed as the declared error model."""

from __future__ import annotations

import importlib
import io
import os
import shutil
import subprocess
import sys
import time
import zipfile
from pathlib import Path

import httpx
import pytest

from farm.stack import OWN_REDIS, stack_down, stack_up
from tests.helpers.service import CHEAP_SETTINGS, backend_missing, make_zip, usda

pytestmark = [pytest.mark.service, pytest.mark.timeout(600)]
TOKEN = "client-token-0123456789abcdef"
PACKAGE = "texelbake_generated_client"
#: the version pinned in pyproject.toml's `dev` extras
GENERATOR_VERSION = "0.29.1"


@pytest.fixture(scope="module")
def stack(tmp_path_factory):
    work = tmp_path_factory.mktemp("stack")
    st = stack_up(
        work,
        redis_url=OWN_REDIS,
        tokens={TOKEN: "studio"},
        workers={"prep": 1, "numeric": 1, "render": 1},
        environment="test",
        extra_env={"TEXELBAKE_MAX_UPLOAD_BYTES": "2000000", "TEXELBAKE_SSE_MAX_SECONDS": "30"},
    )
    try:
        yield st
    finally:
        stack_down(work)


@pytest.fixture(scope="module")
def gen(stack, tmp_path_factory):
    """Generate the client from the served schema; import it as `PACKAGE`."""
    bindir = Path(sys.executable).parent
    exe = shutil.which("openapi-python-client", path=str(bindir))
    if exe is None:
        backend_missing("openapi-python-client is not installed in this environment")
    out = tmp_path_factory.mktemp("generated")
    version = subprocess.run([exe, "--version"], capture_output=True, text=True, check=True)
    assert GENERATOR_VERSION in version.stdout, version.stdout
    # the generator's post hooks run ruff: the virtualenv's own, first on PATH
    env = {**os.environ, "PATH": f"{bindir}{os.pathsep}{os.environ.get('PATH', '')}"}
    r = subprocess.run(
        [
            exe, "generate",
            "--url", stack.api_url + "/api/v1/openapi.json",
            "--meta", "none",
            "--output-path", str(out / PACKAGE),
            "--fail-on-warning",
        ],
        capture_output=True, text=True, timeout=300, env=env, cwd=out,
    )  # fmt: skip
    log = r.stdout + r.stderr
    assert r.returncode == 0, log
    assert "warning" not in log.lower(), log
    sys.path.insert(0, str(out))
    try:
        yield importlib.import_module(PACKAGE)
    finally:
        sys.path.remove(str(out))
        for name in [m for m in sys.modules if m == PACKAGE or m.startswith(PACKAGE + ".")]:
            del sys.modules[name]


@pytest.fixture(scope="module")
def client(gen, stack):
    with gen.AuthenticatedClient(
        base_url=stack.api_url, token=TOKEN, timeout=httpx.Timeout(120)
    ) as c:
        yield c


@pytest.fixture(scope="module")
def cylinder(tmp_path_factory) -> Path:
    from texelbake.testscenes import write_scene

    return write_scene("cylinder", tmp_path_factory.mktemp("scene") / "cylinder.usda", "small")


def m(name: str):
    return importlib.import_module(f"{PACKAGE}.{name}")


def upload(client, name: str, data: bytes):
    models, types = m("models"), m("types")
    body = models.BodyCreateAsset(
        file=types.File(
            payload=io.BytesIO(data), file_name=name, mime_type="application/octet-stream"
        )
    )
    return m("api.assets.create_asset").sync_detailed(client=client, body=body)


def create_job(client, asset_id: str, settings: dict):
    models = m("models")
    body = models.JobCreate(asset_id=asset_id, settings=models.BakeSettings.from_dict(settings))
    return m("api.jobs.create_job").sync_detailed(client=client, body=body)


def assert_error(resp, status: int, code: str):
    ErrorPublic = m("models").ErrorPublic
    assert resp.status_code == status, (resp.status_code, resp.content)
    assert isinstance(resp.parsed, ErrorPublic), resp.parsed
    assert resp.parsed.code == code, resp.parsed
    return resp.parsed


def test_bake_through_the_generated_client(client, cylinder):
    JobPublic, ErrorPublic = m("models").JobPublic, m("models").ErrorPublic

    # the scene's texelbake shaders name texelbake_shaders.usda beside it: a bundle of both
    bundle = make_zip({"cylinder.usda": cylinder.read_bytes(),
                       "texelbake_shaders.usda":
                           (cylinder.parent / "texelbake_shaders.usda").read_bytes()})
    r = upload(client, "cylinder.zip", bundle)
    assert r.status_code == 201, r.content
    asset = r.parsed
    assert asset.root_layer == "cylinder.usda" and len(asset.sha256) == 64
    again = upload(client, "cylinder.zip", bundle)
    assert again.status_code == 200 and again.parsed.id == asset.id

    # a 16² atlas: this checks the generated client's calls, not the bake's size
    r = create_job(client, asset.id, {**CHEAP_SETTINGS, "atlas_resolution": 16, "previews": True})
    assert r.status_code == 201, r.content
    job = r.parsed
    assert isinstance(job, JobPublic) and str(job.state) == "queued"

    # the result of an unfinished job is the declared 409
    assert_error(
        m("api.jobs.read_job_result").sync_detailed(client=client, job_id=job.id),
        409,
        "job_not_finished",
    )

    deadline = time.monotonic() + 420
    while str(job.state) not in ("succeeded", "failed", "cancelled"):
        assert time.monotonic() < deadline, job.to_dict()
        time.sleep(0.5)
        job = m("api.jobs.read_job").sync(client=client, job_id=job.id)
        assert isinstance(job, JobPublic)
    assert str(job.state) == "succeeded", job.error
    assert job.progress == 1.0 and "render" in [s.name for s in job.stages]

    listed = m("api.jobs.list_jobs").sync(client=client)
    assert job.id in [j.id for j in listed.data]

    events = m("api.jobs.read_job_events").sync(client=client, job_id=job.id)
    assert isinstance(events, str) and "event: job" in events and "succeeded" in events

    report = m("api.jobs.read_job_report").sync(client=client, job_id=job.id)
    assert not isinstance(report, ErrorPublic) and report.to_dict(), report

    result = m("api.jobs.read_job_result").sync(client=client, job_id=job.id)
    with zipfile.ZipFile(result.payload) as zf:
        names = zf.namelist()
    assert "report.json" in names and any(n.endswith((".usda", ".usdc")) for n in names), names

    assert job.previews, job.to_dict()
    magic = {".png": b"\x89PNG\r\n\x1a\n", ".exr": b"v/1\x01", ".json": b"{"}
    assert {Path(n).suffix for n in job.previews} >= {".png", ".exr", ".json"}, job.previews
    for name in job.previews:
        f = m("api.jobs.read_job_preview").sync(client=client, job_id=job.id, name=name)
        head = magic[Path(name).suffix]
        assert f.payload.read(len(head)) == head, name
    assert_error(
        m("api.jobs.read_job_preview").sync_detailed(client=client, job_id=job.id, name="nope.png"),
        404,
        "preview_not_found",
    )

    # cancel: a second job, cancelled before it finishes
    second = create_job(client, asset.id, CHEAP_SETTINGS).parsed
    cancelled = m("api.jobs.cancel_job").sync(client=client, job_id=second.id)
    assert isinstance(cancelled, JobPublic) and str(cancelled.state) == "cancelled"
    again = m("api.jobs.read_job").sync(client=client, job_id=second.id)
    assert str(again.state) == "cancelled"


def test_errors_parse_as_the_error_model(gen, stack, client):
    with gen.AuthenticatedClient(base_url=stack.api_url, token="not-a-token") as wrong:
        err = assert_error(
            m("api.jobs.list_jobs").sync_detailed(client=wrong), 401, "invalid_token"
        )
        assert err.detail == "invalid token"
        assert_error(upload(wrong, "cube.usda", usda()), 401, "invalid_token")
    with gen.Client(base_url=stack.api_url) as anonymous:
        assert_error(
            m("api.jobs.read_job").sync_detailed(client=anonymous, job_id="x"),
            401,
            "not_authenticated",
        )

    err = assert_error(
        m("api.jobs.read_job").sync_detailed(client=client, job_id="0" * 32), 404, "job_not_found"
    )
    assert err.detail == "job not found"
    assert_error(
        m("api.jobs.cancel_job").sync_detailed(client=client, job_id="0" * 32), 404, "job_not_found"
    )
    assert_error(
        m("api.assets.read_asset").sync_detailed(client=client, asset_id="a0"),
        404,
        "asset_not_found",
    )

    # rejected uploads: wrong type, broken content, a bundle without a root layer, too large
    err = assert_error(upload(client, "notes.txt", b"hello"), 415, "unsupported_file_type")
    assert "notes.txt" in err.detail
    assert_error(
        upload(client, "broken.usda", b"#usda 1.0\n(\n def def def {{{"), 422, "invalid_asset"
    )
    assert_error(upload(client, "bundle.zip", make_zip({"tex/a.png": b"x"})), 422, "no_root_layer")
    assert_error(upload(client, "big.usda", b"#" * 2_200_000), 413, "upload_too_large")

    # a request that does not validate: `detail` is the list of problems
    aid = upload(client, "cube.usda", usda()).parsed.id
    err = assert_error(create_job(client, aid, {"atlas_resolution": 12}), 422, "validation_error")
    assert isinstance(err.detail, list) and "power of two" in err.detail[0].msg


def test_batch_through_the_generated_client(client):
    """`/batches` through generated code: create (item settings override the batch's), read
    until finished, list, the archive, cancel, and the declared errors."""
    models = m("models")
    aid = upload(client, "nomesh.usda", usda()).parsed.id  # uploads; fails in the plan stage
    body = models.BatchCreate.from_dict({
        "name": "gen", "settings": CHEAP_SETTINGS, "priority": 40,
        "items": [{"asset_id": aid, "settings": {"samples_per_texel": 4}},
                  {"asset_id": aid, "priority": 80}]})
    r = m("api.batches.create_batch").sync_detailed(client=client, body=body)
    assert r.status_code == 201, r.content
    batch = r.parsed
    assert isinstance(batch, models.BatchPublic) and batch.counts.total == 2
    assert [i.priority for i in batch.items] == [40, 80]
    deadline = time.monotonic() + 120
    while str(batch.state) not in ("succeeded", "failed", "cancelled"):
        assert time.monotonic() < deadline, batch.to_dict()
        time.sleep(0.5)
        batch = m("api.batches.read_batch").sync(client=client, batch_id=batch.id)
    assert str(batch.state) == "failed" and batch.counts.failed == 2 and batch.progress == 1.0
    assert all("no UsdGeom.Mesh" in i.error for i in batch.items)
    listed = m("api.batches.list_batches").sync(client=client)
    assert batch.id in [b.id for b in listed.data]
    result = m("api.batches.read_batch_result").sync(client=client, batch_id=batch.id)
    with zipfile.ZipFile(result.payload) as zf:
        assert zf.namelist() == ["batch.json"]
    again = m("api.batches.cancel_batch").sync(client=client, batch_id=batch.id)
    assert isinstance(again, models.BatchPublic) and str(again.state) == "failed"
    for op in ("read_batch", "cancel_batch", "read_batch_result"):
        assert_error(m(f"api.batches.{op}").sync_detailed(client=client, batch_id="0" * 32),
                     404, "batch_not_found")
    bad = models.BatchCreate.from_dict({"items": [{"asset_id": "0" * 32}]})
    err = assert_error(m("api.batches.create_batch").sync_detailed(client=client, body=bad),
                       404, "asset_not_found")
    assert "items[0].asset_id" in err.detail
