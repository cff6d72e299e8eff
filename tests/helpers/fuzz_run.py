"""Run fuzz cases (`tests.helpers.fuzz_cases`) against a real local stack and check what
must hold whatever the input: no 5xx; nothing stored for a rejection (asset and job rows in
the database, bundles and staging files on disk, compared with what was answered 2xx);
every job created reads back (`GET /jobs/{id}` 200); the API process's resident memory and a
parallel health check's latency sampled throughout."""

from __future__ import annotations

import concurrent.futures as cf
import json
import socket
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import httpx

from farm.stack import Stack
from tests.helpers.fuzz_cases import Case, generate
from tests.helpers.service import usda

STALL_S = 2.0
API = "/api/v1"


def rss_mib(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


@dataclass
class Probe:
    """A health check every 50 ms and the API's RSS every 0.5 s, in a thread."""

    stack: Stack
    latencies: list[float] = field(default_factory=list)
    rss: list[float] = field(default_factory=list)
    stop: threading.Event = field(default_factory=threading.Event)

    def run(self) -> None:
        pid, last = self.stack.pids["api"], 0.0
        with httpx.Client(base_url=self.stack.api_url, timeout=60) as c:
            while not self.stop.is_set():
                t0 = time.perf_counter()
                try:
                    c.get(f"{API}/utils/health-check/")
                except httpx.HTTPError:
                    pass
                self.latencies.append(time.perf_counter() - t0)
                if time.perf_counter() - last > 0.5:
                    self.rss.append(rss_mib(pid))
                    last = time.perf_counter()
                self.stop.wait(0.05)


def _send(client: httpx.Client, case: Case, port: int) -> tuple[int, str]:
    """(status or 0 when the server hung up without one, the body's first bytes)."""
    if case.raw is not None:
        with socket.create_connection(("127.0.0.1", port), timeout=5) as s:
            try:
                s.sendall(case.raw)
                s.shutdown(socket.SHUT_WR)
                head = s.recv(4096)
            except OSError:
                return 0, ""
        if not head.startswith(b"HTTP/1.1 "):
            return 0, ""
        return int(head[9:12]), head.decode("latin-1").split("\r\n\r\n", 1)[-1]
    url = API + case.path
    try:
        if case.stream:
            try:
                with client.stream(case.method, url, headers=case.headers, timeout=10) as r:
                    return r.status_code, ""
            except httpx.ReadTimeout:
                return 0, ""
        files = {"file": case.files} if case.files else None
        r = client.request(case.method, url, headers=case.headers, content=case.body,
                           files=files)  # fmt: skip
    except (httpx.LocalProtocolError, UnicodeEncodeError):
        return -1, "the client refused to send it"
    except httpx.TransportError as exc:  # reset, closed or timed out: no answer
        return 0, repr(exc)
    return r.status_code, r.text if r.status_code < 300 else r.text[:300]


def run(stack: Stack, token: str, n: int, seed: int, *, threads: int = 3,
        canary: Path | None = None) -> dict:  # fmt: skip
    """Send `n` cases (seed `seed`) with `threads` clients at once; returns the counts and
    the checks (see the module docstring). `canary`: a file outside the artifact root whose
    text must appear in no answer and no log of the stack."""
    port = int(stack.api_url.rsplit(":", 1)[1])
    auth = {"Authorization": f"Bearer {token}"}
    client = httpx.Client(base_url=stack.api_url, headers=auth, timeout=120)
    first = client.post(f"{API}/assets", files={"file": ("seed.usda", usda())})
    asset_id = first.json()["id"]
    job = client.post(f"{API}/jobs", json={"asset_id": asset_id, "settings": {}})
    job_id = job.json()["id"]
    secret = canary.read_text() if canary else None
    cases = generate(n, seed, token=token, asset_id=asset_id, job_id=job_id, port=port,
                     **({"canary": str(canary)} if canary else {}))  # fmt: skip
    probe = Probe(stack)
    thread = threading.Thread(target=probe.run, daemon=True)
    thread.start()
    time.sleep(0.3)
    by_family: dict[str, Counter] = {}
    failures: list[dict] = []
    accepted_assets, created_jobs = {asset_id}, {job_id}
    lock = threading.Lock()
    answers: list[list] = [[] for _ in cases]  # per case: family, status, the 4xx's start
    t0 = time.perf_counter()

    def one(i_case: tuple[int, Case]) -> None:
        i, case = i_case
        status, text = _send(client, case, port)
        with lock:
            answers[i] = [case.family, status, text[:120] if status >= 300 else ""]
            if secret and secret in text:
                failures.append({"case": i, "family": case.family, "status": status,
                                 "canary": True})  # fmt: skip
            by_family.setdefault(case.family, Counter())[status] += 1
            if status >= 500 or (status == 0 and case.raw is None and not case.stream):
                failures.append({"case": i, "family": case.family, "status": status,
                                 "path": case.path, "answer": text})  # fmt: skip
            if status in (200, 201) and case.path == "/assets":
                accepted_assets.add(json.loads(text)["id"])
            if status == 201 and case.path == "/jobs":
                created_jobs.add(json.loads(text)["id"])
            if status == 201 and case.path == "/batches":
                created_jobs.update(i["job_id"] for i in json.loads(text)["items"])

    try:
        with cf.ThreadPoolExecutor(threads) as ex:
            list(ex.map(one, enumerate(cases)))
        seconds = time.perf_counter() - t0
    finally:
        probe.stop.set()
        thread.join()
    out = {"cases": n, "seed": seed, "seconds": round(seconds, 1),
           "by_family": {k: dict(sorted(v.items())) for k, v in sorted(by_family.items())}}
    out.update(_stored_checks(stack, client, accepted_assets, created_jobs))
    client.close()
    lat = sorted(probe.latencies)
    out.update({
        "responses_5xx": sum(f["status"] >= 500 for f in failures),
        "canary_leaks": sum("canary" in f for f in failures) + bool(secret and any(
            secret in p.read_text(errors="replace") for p in stack.workdir.rglob("*.log"))),
        "no_answer": sum(f["status"] == 0 for f in failures),
        "health_checks": len(lat),
        "health_p50_ms": round(lat[len(lat) // 2] * 1e3, 1) if lat else None,
        "health_max_ms": round(lat[-1] * 1e3, 1) if lat else None,
        "health_stalls_over_2s": sum(v > STALL_S for v in lat),
        "api_rss_start_mib": round(probe.rss[0], 1) if probe.rss else None,
        "api_rss_max_mib": round(max(probe.rss), 1) if probe.rss else None,
        "api_rss_growth_mib": round(max(probe.rss) - probe.rss[0], 1) if probe.rss else None,
        "failures": failures[:50],
        "answers": answers,
    })  # fmt: skip
    out["passed"] = (out["responses_5xx"] == 0 and out["no_answer"] == 0
                     and out["canary_leaks"] == 0
                     and out["health_stalls_over_2s"] == 0
                     and (out["api_rss_growth_mib"] or 0) < 100
                     and out["stored_rejections"] == 0 and out["jobs_unreadable"] == 0)
    return out


def _stored_checks(stack: Stack, client: httpx.Client, assets: set[str],
                   jobs: set[str]) -> dict:  # fmt: skip
    """Rows and files beyond what was answered 2xx, and jobs that do not read back."""
    from sqlalchemy import select

    from farm.db import Asset, Job, session_factory

    sm = session_factory(stack.env["TEXELBAKE_DATABASE_URL"], readonly=True)
    with sm() as s:
        asset_rows = {r.id: r.sha256 for r in s.scalars(select(Asset))}
        job_rows = set(s.scalars(select(Job.id)))
    root = Path(stack.env["TEXELBAKE_ARTIFACT_ROOT"])
    bundles = {p.name for p in (root / "assets").iterdir()} if (root / "assets").exists() else set()
    staging = [p for p in (root / "tmp").rglob("*") if p.is_file()] if (root / "tmp").exists() else []
    accepted_sha = {asset_rows[a] for a in assets if a in asset_rows}
    unreadable = [j for j in sorted(job_rows) if client.get(f"{API}/jobs/{j}").status_code != 200]
    return {
        "assets_accepted": len(assets), "jobs_created": len(jobs),
        "stored_rejections": len(set(asset_rows) - assets) + len(bundles - accepted_sha)
        + len(staging) + len(job_rows - jobs),
        "jobs_read_back": len(job_rows), "jobs_unreadable": len(unreadable),
    }  # fmt: skip
