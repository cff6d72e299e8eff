"""docker-compose.yml: `docker compose config` accepts it, required variables fail fast, and
every Celery queue has a worker service."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
from pathlib import Path

import pytest

from schemas.queues import QUEUE_FAMILIES, QUEUES
from tests.helpers.service import backend_missing

pytestmark = pytest.mark.service
COMPOSE = Path(__file__).resolve().parents[2] / "docker-compose.yml"
REQUIRED = ("TEXELBAKE_SECRET_KEY", "TEXELBAKE_TOKENS", "POSTGRES_PASSWORD")


def compose_cmd() -> list[str]:
    docker = shutil.which("docker")
    if (
        docker
        and subprocess.run([docker, "compose", "version"], capture_output=True).returncode == 0
    ):
        return [docker, "compose"]
    if shutil.which("docker-compose"):
        return [shutil.which("docker-compose")]  # type: ignore[list-item]
    # Debian's docker-compose package checks the file without an engine; `make setup` and
    # .ci/run install it, so under CI=true its absence fails
    backend_missing("neither `docker compose` nor `docker-compose` is installed")


def run_config(env_extra: dict[str, str], *args: str) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k not in REQUIRED}
    env.update(env_extra)
    return subprocess.run(
        [*compose_cmd(), "-f", str(COMPOSE), "config", *args],
        capture_output=True,
        text=True,
        env=env,
        timeout=60,
        cwd=COMPOSE.parent,
    )


GOOD = {
    "TEXELBAKE_SECRET_KEY": "k" * 32,
    "TEXELBAKE_TOKENS": '{"t": "a"}',
    "POSTGRES_PASSWORD": "p",
}


def test_compose_config_accepts_and_lists_services():
    r = run_config(GOOD, "--services")
    assert r.returncode == 0, r.stderr
    services = set(r.stdout.split())
    assert {"redis", "postgres", "api", "dashboard", "worker-render"} <= services
    assert {f"worker-{fam}" for fam in QUEUE_FAMILIES} <= services


@pytest.mark.parametrize("missing", REQUIRED)
def test_required_variables_fail_fast(missing):
    env = {k: v for k, v in GOOD.items() if k != missing}
    r = run_config(env, "-q")
    assert r.returncode != 0
    assert missing in r.stderr


def test_every_queue_has_a_worker_and_healthchecks():
    text = COMPOSE.read_text()
    served: set[str] = set()
    for m in re.finditer(r"-Q[\", ]+([a-z,]+)", text):
        served |= set(m.group(1).split(","))
    assert served == set(QUEUES)
    r = run_config(GOOD)
    assert r.returncode == 0, r.stderr
    assert r.stdout.count("healthcheck:") >= 7  # redis, postgres, api, 3 workers, dashboard
    for flag in ("--prefetch-multiplier", "-P prefork"):
        assert flag.split()[0] in text
