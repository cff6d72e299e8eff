"""Interactive reads while uploads are processed (issue 16, item 5; benchmarks/load.py): the
upload checks run in checkers forked from a warm, niced check server (real processes, real
pxr), and a cached status read is answered before the framework (real uvicorn)."""

from __future__ import annotations

import os
import time
from pathlib import Path

import httpx
import pytest

from farm.db import session_factory
from farm.ledger import cancel_job
from farm.stack import OWN_REDIS, free_port, stack_down, stack_up
from services import checkserver, uploads
from tests.helpers.service import proc_cpu, usda

pytestmark = [pytest.mark.service, pytest.mark.timeout(180)]

TOK_A, TOK_B = "token-status-a-0123456789", "token-status-b-0123456789"


def _checks_cpu() -> float:
    """CPU seconds of this process's descendants: live ones, what they reaped, and what this
    process reaped (a checker run with `subprocess.run`)."""
    stats = {pid: (ppid, own + reaped) for pid, (ppid, own, reaped) in proc_cpu().items()}
    t = os.times()
    total, todo = t.children_user + t.children_system, [os.getpid()]
    while todo:
        p = todo.pop()
        kids = [c for c, v in stats.items() if v[0] == p]
        total += sum(stats[c][1] for c in kids)
        todo.extend(kids)
    return total


def test_upload_checks_are_forked_warm_and_niced(tmp_path):
    """After the first check, a check costs its own work, not a fresh interpreter importing pxr
    (~0.65 s of CPU each, 20 uploads = 13 s of a 2-core machine's CPU under the load test);
    the checkers run at `VALIDATE_NICE`; a checker that dies (CPU rlimit) ends only itself."""
    assert checkserver.VALIDATE_NICE == uploads.VALIDATE_NICE
    (tmp_path / "ok.usda").write_bytes(usda())
    (tmp_path / "bad.usda").write_text("#usda 1.0\n(\n    subLayers = [@../../etc/x.usda@]\n)\n")
    assert uploads.run_validator(tmp_path, "ok.usda", 60) == []  # starts the server
    n = 6
    cpu0 = _checks_cpu()
    for _ in range(n):
        assert uploads.run_validator(tmp_path, "ok.usda", 60) == []
    problems = uploads.run_validator(tmp_path, "bad.usda", 60)
    assert problems and problems[0][1] == "asset path escapes the bundle"
    spent = _checks_cpu() - cpu0
    assert spent < 0.25 * (n + 1), f"{n + 1} checks took {spent:.2f} s of CPU"

    server = uploads._server.proc
    assert server is not None and server.poll() is None
    stat = Path(f"/proc/{server.pid}/stat").read_text().rsplit(")", 1)[1].split()
    # the fork server's niceness: VALIDATE_NICE above the process that started it (os.nice
    # adds; a suite run under `nice` starts it higher), inherited by every checker
    assert int(stat[16]) == min(19, os.nice(0) + uploads.VALIDATE_NICE)

    with pytest.raises(uploads.UploadRejected) as exc:  # RLIMIT_CPU of 0 s kills the checker
        uploads.run_validator(tmp_path, "ok.usda", 0.5)
    assert exc.value.detail.startswith(uploads.VALIDATE_FAILED)
    assert server.poll() is None and uploads._server.proc is server  # the server lives on
    assert uploads.run_validator(tmp_path, "ok.usda", 60) == []


@pytest.fixture(scope="module")
def api(tmp_path_factory):
    work = tmp_path_factory.mktemp("stack")
    db = f"sqlite:///{work / 'ledger.sqlite'}"
    stack = stack_up(
        work, redis_url=OWN_REDIS, workers={},
        tokens={TOK_A: "tenant-a", TOK_B: "tenant-b"}, environment="test", database_url=db,
        extra_env={"TEXELBAKE_STATUS_CACHE_SECONDS": "3"},
    )  # fmt: skip
    try:
        yield stack, db
    finally:
        stack_down(work)


def _client(stack, token: str) -> httpx.Client:
    return httpx.Client(base_url=stack.api_url + "/api/v1",
                        headers={"Authorization": f"Bearer {token}"}, timeout=60)


def test_cached_status_read_skips_the_framework_and_never_crosses_tenants(api):
    stack, db = api
    with _client(stack, TOK_A) as a, _client(stack, TOK_B) as b:
        aid = a.post("/assets", files={"file": ("cube.usda", usda())}).json()["id"]
        jid = a.post("/jobs", json={"asset_id": aid}).json()["id"]
        first = a.get(f"/jobs/{jid}")
        second = a.get(f"/jobs/{jid}")
        assert first.status_code == second.status_code == 200
        assert "status;desc=hit" in second.headers["server-timing"]
        assert "app;dur=" in second.headers["server-timing"]
        assert second.content == first.content and second.json()["id"] == jid
        assert second.headers["content-type"] == first.headers["content-type"]
        # the same job with another tenant's token, no token, a wrong token: the route's answers
        assert b.get(f"/jobs/{jid}").status_code == 404
        assert httpx.get(f"{stack.api_url}/api/v1/jobs/{jid}").status_code == 401
        bad = httpx.get(f"{stack.api_url}/api/v1/jobs/{jid}",
                        headers={"Authorization": "Bearer not-a-token-0123456789"})
        assert bad.status_code == 401 and "server-timing" in bad.headers
        assert "status;desc=hit" not in bad.headers["server-timing"]
        # this process's own cancel drops the cached version: the next read is fresh
        assert a.delete(f"/jobs/{jid}").status_code == 202
        assert a.get(f"/jobs/{jid}").json()["state"] == "cancelled"

        # a change by another process (a worker's ledger transition) shows within the version
        # cache's lifetime (3 s here), never later
        jid2 = a.post("/jobs", json={"asset_id": aid}).json()["id"]
        assert a.get(f"/jobs/{jid2}").json()["state"] == "queued"
        cancel_job(session_factory(db), jid2)
        t0 = time.monotonic()
        while a.get(f"/jobs/{jid2}").json()["state"] != "cancelled":
            assert time.monotonic() - t0 < 3 + 3, "a stale status outlived the version cache"
            time.sleep(0.1)


def _redis(port: int, workdir: Path):
    import shutil
    import subprocess

    from farm.stack import redis_ping

    proc = subprocess.Popen([shutil.which("redis-server") or "/usr/bin/redis-server", "--port",
                             str(port), "--bind", "127.0.0.1", "--save", "", "--appendonly", "no",
                             "--dir", str(workdir)], stdout=subprocess.DEVNULL)
    t0 = time.monotonic()
    while not redis_ping(f"redis://127.0.0.1:{port}/0"):
        assert time.monotonic() - t0 < 20, "redis-server did not start"
        time.sleep(0.05)
    return proc


def test_broker_run_id_is_cheap_and_follows_a_restart(tmp_path):
    """POST /jobs reads Redis' run id on every call: one pooled connection and no parse of the
    whole INFO section (it was a new connection and 40 % of a submission's CPU), and still a
    new id after a restart and None while Redis is down."""
    from farm.broker import broker_run_id

    port = free_port()
    url = f"redis://127.0.0.1:{port}/0"
    proc = _redis(port, tmp_path)
    try:
        first = broker_run_id(url)
        assert first and len(first) == 40
        t0 = time.process_time()
        assert all(broker_run_id(url) == first for _ in range(200))
        cpu = time.process_time() - t0
        assert cpu < 0.3, f"200 run-id reads took {cpu:.2f} s of CPU"
        proc.kill()
        proc.wait()
        assert broker_run_id(url, timeout=0.5) is None
        proc = _redis(port, tmp_path)
        second = broker_run_id(url)
        assert second and second != first
    finally:
        proc.kill()
        proc.wait()


def _alive(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def test_check_server_leaves_nothing_behind_when_the_api_stops(tmp_path):
    """The check server lives with its API process: a stack stop ends it and removes its
    socket folder."""
    stack = stack_up(tmp_path / "stack", redis_url=OWN_REDIS,
                     workers={}, tokens={TOK_A: "tenant-a"}, environment="test")
    try:
        with _client(stack, TOK_A) as a:
            assert a.post("/assets", files={"file": ("cube.usda", usda())}).status_code == 201
        servers = []
        for d in Path("/proc").iterdir():
            try:
                cmd = (d / "cmdline").read_bytes().split(b"\0")
                ppid = int((d / "stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, ValueError, IndexError):
                continue
            if b"services.checkserver" in cmd and ppid == stack.pids["api"]:
                servers.append((int(d.name), Path(cmd[cmd.index(b"services.checkserver") + 1]
                                                  .decode())))
        assert len(servers) == 1, servers
        pid, sock = servers[0]
        assert sock.exists()
    finally:
        stack_down(tmp_path / "stack")
    t0 = time.monotonic()
    while _alive(pid):
        assert time.monotonic() - t0 < 10, "the check server outlived its API"
        time.sleep(0.1)
    assert not sock.parent.exists()
