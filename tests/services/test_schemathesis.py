"""The OpenAPI spec of a real uvicorn passes schemathesis with no 5xx (check ST101
`not_a_server_error`), with a valid token, an uploaded asset and a job present."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import httpx
import pytest

from farm.stack import OWN_REDIS, stack_down, stack_up
from tests.helpers.service import backend_missing, usda

pytestmark = [pytest.mark.service, pytest.mark.timeout(300)]
TOKEN = "schemathesis-token-0123456789"


def test_openapi_no_server_errors(tmp_path):
    exe = shutil.which("schemathesis", path=str(Path(sys.executable).parent))
    if exe is None:
        backend_missing("schemathesis is not installed in this environment")
    stack = stack_up(
        tmp_path / "stack",
        redis_url=OWN_REDIS,
        workers={},
        tokens={TOKEN: "fuzz"},
        environment="test",
        extra_env={"TEXELBAKE_MAX_UPLOAD_BYTES": "100000", "TEXELBAKE_SSE_MAX_SECONDS": "1"},
    )
    try:
        auth = {"Authorization": f"Bearer {TOKEN}"}
        with httpx.Client(base_url=stack.api_url + "/api/v1", headers=auth, timeout=60) as c:
            aid = c.post("/assets", files={"file": ("c.usda", usda())}).json()["id"]
            assert c.post("/jobs", json={"asset_id": aid}).status_code == 201
        r = subprocess.run(
            [
                exe, "run", stack.api_url + "/api/v1/openapi.json",
                "-H", f"Authorization: Bearer {TOKEN}",
                "-c", "not_a_server_error",
                "-n", "15",
                "--generation-deterministic",
                "--request-timeout", "30",
                "--no-color",
            ],
            capture_output=True, text=True, timeout=280, cwd=tmp_path,
        )  # fmt: skip
        report = r.stdout[-6000:] + r.stderr[-2000:]
        assert r.returncode == 0, report
        assert "Server error" not in r.stdout, report
        log = (stack.workdir / "logs" / "api.log").read_text()
        assert "Traceback" not in log, log[-4000:]
    finally:
        stack_down(tmp_path / "stack")
