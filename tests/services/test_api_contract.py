"""The OpenAPI contract of the API, in process (no servers): the upload is binary, binary
responses have media types and a binary schema, every error status of every route is the one
error model, operation ids are explicit, and the handlers answer in that model."""

from __future__ import annotations

import pytest

from farm.config import Settings
from schemas.common import ErrorCode
from services.main import create_app
from services.uploads import CODES, UploadRejected

REF = "#/components/schemas/ErrorPublic"
BINARY = {"type": "string", "format": "binary"}
OPERATION_IDS = {
    ("get", "/api/v1/utils/health-check/"): "health_check",
    ("post", "/api/v1/assets"): "create_asset",
    ("get", "/api/v1/assets"): "list_assets",
    ("get", "/api/v1/assets/{asset_id}"): "read_asset",
    ("post", "/api/v1/jobs"): "create_job",
    ("get", "/api/v1/jobs"): "list_jobs",
    ("get", "/api/v1/jobs/{job_id}"): "read_job",
    ("delete", "/api/v1/jobs/{job_id}"): "cancel_job",
    ("post", "/api/v1/jobs/{job_id}/resume"): "resume_job",
    ("get", "/api/v1/jobs/{job_id}/events"): "read_job_events",
    ("get", "/api/v1/jobs/{job_id}/result"): "read_job_result",
    ("get", "/api/v1/jobs/{job_id}/previews/{name}"): "read_job_preview",
    ("get", "/api/v1/jobs/{job_id}/report"): "read_job_report",
    ("get", "/api/v1/jobs/{job_id}/viewer"): "read_job_viewer",
    ("get", "/api/v1/jobs/{job_id}/viewer/{name}"): "read_job_viewer_file",
    ("post", "/api/v1/batches"): "create_batch",
    ("get", "/api/v1/batches"): "list_batches",
    ("get", "/api/v1/batches/{batch_id}"): "read_batch",
    ("delete", "/api/v1/batches/{batch_id}"): "cancel_batch",
    ("get", "/api/v1/batches/{batch_id}/result"): "read_batch_result",
    ("get", "/api/v1/events"): "read_events",
    ("get", "/api/v1/farm"): "read_farm",
    ("get", "/api/v1/farm/events"): "read_farm_events",
}


@pytest.fixture(scope="module")
def app(tmp_path_factory):
    settings = Settings(
        artifact_root=tmp_path_factory.mktemp("art"),
        environment="test",
        secret_key="contract-secret-key",
        redis_url="redis://127.0.0.1:1/0",
        tokens={"contract-token-0123456789": "t"},
    )
    return create_app(settings, sweeper=False)


@pytest.fixture(scope="module")
def spec(app) -> dict:
    return app.openapi()


def ops(spec: dict):
    for path, item in spec["paths"].items():
        for method, op in item.items():
            yield method, path, op


def test_operation_ids_are_explicit_and_stable(app, spec):
    assert {(m, p): op["operationId"] for m, p, op in ops(spec)} == OPERATION_IDS
    for route in app.routes:
        if getattr(route, "include_in_schema", False) and hasattr(route, "operation_id"):
            assert route.operation_id, route.path


def test_upload_file_is_binary(spec):
    body = spec["paths"]["/api/v1/assets"]["post"]["requestBody"]["content"]
    ref = body["multipart/form-data"]["schema"]["$ref"].rsplit("/", 1)[1]
    file = spec["components"]["schemas"][ref]["properties"]["file"]
    assert file["type"] == "string" and file["format"] == "binary"


@pytest.mark.parametrize(
    "path,media",
    [("/api/v1/jobs/{job_id}/result", "application/zip"),
     ("/api/v1/jobs/{job_id}/previews/{name}", "image/png")],
)  # fmt: skip
def test_binary_responses_declared(spec, path, media):
    content = spec["paths"][path]["get"]["responses"]["200"]["content"]
    assert list(content)[0] == media
    assert content[media]["schema"] == BINARY
    assert content["application/octet-stream"]["schema"] == BINARY


def test_every_error_status_is_the_error_model(spec):
    assert "HTTPValidationError" not in spec["components"]["schemas"]
    err = spec["components"]["schemas"]["ErrorPublic"]
    assert set(err["required"]) == {"detail", "code"}
    for method, path, op in ops(spec):
        statuses = {s for s in op["responses"] if s[0] in "45"}
        if path.endswith("health-check/"):
            continue  # 503 there is the health body itself
        assert {"401", "422"} <= statuses, (method, path)
        if "{" in path:
            assert "404" in statuses, (method, path)
        for s in statuses:
            schema = op["responses"][s]["content"]["application/json"]["schema"]
            assert schema == {"$ref": REF}, (method, path, s)
    upload = spec["paths"]["/api/v1/assets"]["post"]["responses"]
    assert {"400", "401", "413", "415", "422"} <= set(upload)
    for path in ("/api/v1/jobs/{job_id}/result", "/api/v1/jobs/{job_id}/report"):
        assert "409" in spec["paths"][path]["get"]["responses"]


def test_upload_rejections_have_codes():
    for prefix, code in CODES.items():
        assert UploadRejected(413, f"{prefix}: x").code == code
    assert UploadRejected(422, "/World/Box: points: NaN").code == ErrorCode.INVALID_ASSET
    # several refusals share a code (a name too long is a bad member path); no prefix may
    # shadow another, or the code would depend on the table's order
    assert not [(a, b) for a in CODES for b in CODES if a != b and b.startswith(a)]


def test_handlers_answer_in_the_error_model(app):
    from fastapi.testclient import TestClient

    with TestClient(app) as c:
        r = c.get("/api/v1/jobs")
        assert r.status_code == 401 and r.headers["www-authenticate"] == "Bearer"
        assert r.json() == {"detail": "not authenticated", "code": "not_authenticated"}
        auth = {"Authorization": "Bearer contract-token-0123456789"}
        r = c.get("/api/v1/jobs/nope", headers=auth)
        assert r.json() == {"detail": "job not found", "code": "job_not_found"}
        r = c.get("/api/v1/jobs?limit=0", headers=auth)
        assert r.status_code == 422 and r.json()["code"] == "validation_error"
        assert r.json()["detail"][0]["loc"] == ["query", "limit"]
        r = c.get("/api/v1/no-such-route")
        assert r.status_code == 404 and r.json()["code"] == "not_found"
        r = c.post("/api/v1/assets", headers=auth, files={"file": ("x.txt", b"hello")})
        assert r.status_code == 415 and r.json()["code"] == "unsupported_file_type"


def test_octet_stream_alias_is_honoured_on_accept():
    from starlette.requests import Request

    from services.routers.jobs import _media_type

    def req(accept: str | None) -> Request:
        headers = [] if accept is None else [(b"accept", accept.encode())]
        return Request({"type": "http", "method": "GET", "headers": headers})

    assert _media_type(req(None), "application/zip") == "application/zip"
    assert _media_type(req("*/*"), "image/png") == "image/png"
    assert _media_type(req("application/octet-stream"), "image/png") == "application/octet-stream"
    assert _media_type(req("application/zip, application/octet-stream"), "application/zip") == (
        "application/zip"
    )
