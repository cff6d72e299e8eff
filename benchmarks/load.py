"""The API under load (issue 16, item 5): 50 clients polling job status, 20 concurrent uploads and
20 concurrent job submissions, against SQLite and against PostgreSQL.

    .venv/bin/python benchmarks/load.py --json bench_out/load.json [--seconds 20] [--db sqlite]

Method: a real stack per backend (`services.stack.stack_up`: uvicorn, its own redis-server, no
workers, so submitted jobs stay queued and every request is the API's and the database's own
work), two tenants. Before the clock: one asset and one job per tenant. Then, at once, on
loopback only and bounded in count and time:
- 50 pollers, each with its own connection, `GET /jobs/{id}` of their tenant's job every
  `--poll` seconds for `--seconds`;
- 20 uploaders, each `POST /assets` once with a distinct small layer (distinct bytes, so no
  upload is deduplicated; each is checked in a child process with pxr, as every upload is);
- 20 submitters, each `POST /jobs` once for its tenant's asset.
Every response is timed; the table gives per endpoint the count, p50, p99 and max latency, the
status codes, and errors by kind (transport errors, 5xx, and any body that says "database is
locked", which must never reach a client). Bar: status reads p99 <= 50 ms, no 5xx, no
"database is locked", no request lost (a client timeout hides the server's late answer). Times are of a 2-core machine that also runs the uploads' validation, so
the status p99 is measured while the CPU is shared with 20 pxr checks.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import threading
import time
import uuid
from collections import Counter
from pathlib import Path

import httpx
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from services.stack import free_port, stack_down, stack_up  # noqa: E402

TOKENS = {"load-token-a-0123456789abcdef": "team-a", "load-token-b-0123456789abcdef": "team-b"}
PG_ADMIN = "postgresql+psycopg2://postgres@127.0.0.1:5432/test"
SETTINGS = {"atlas_resolution": 8, "samples_per_texel": 4, "c_max": 4}


def layer(i: int) -> bytes:
    """A small valid layer, distinct per i (a comment), so uploads are not deduplicated."""
    return (f"#usda 1.0\n(\n    defaultPrim = \"Root\"\n    upAxis = \"Y\"\n"
            f"    metersPerUnit = 1\n    doc = \"load {i}\"\n)\n"
            "def Xform \"Root\"\n{\n    def Mesh \"Tri\"\n    {\n"
            "        int[] faceVertexCounts = [3]\n        int[] faceVertexIndices = [0, 1, 2]\n"
            "        point3f[] points = [(0, 0, 0), (1, 0, 0), (0, 1, 0)]\n    }\n}\n").encode()


class Recorder:
    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.rows: dict[str, list[float]] = {}
        self.codes: dict[str, Counter] = {}
        self.errors: Counter = Counter()

    def call(self, endpoint: str, fn) -> httpx.Response | None:  # noqa: ANN001
        t0 = time.perf_counter()
        try:
            r = fn()
        except httpx.HTTPError as exc:
            with self.lock:
                self.errors[f"{endpoint}: {type(exc).__name__}"] += 1
            return None
        dt = time.perf_counter() - t0
        with self.lock:
            self.rows.setdefault(endpoint, []).append(dt)
            self.codes.setdefault(endpoint, Counter())[str(r.status_code)] += 1
            if r.status_code >= 500:
                self.errors[f"{endpoint}: {r.status_code}"] += 1
            if "database is locked" in r.text:
                self.errors[f"{endpoint}: database is locked"] += 1
        return r


def fresh_pg() -> tuple[str, object]:
    import sqlalchemy

    admin = sqlalchemy.create_engine(PG_ADMIN, isolation_level="AUTOCOMMIT")
    name = f"texelbake_load_{uuid.uuid4().hex[:10]}"
    with admin.connect() as c:
        c.exec_driver_sql(f'CREATE DATABASE "{name}"')

    def drop() -> None:
        with admin.connect() as c:
            c.exec_driver_sql("SELECT pg_terminate_backend(pid) FROM pg_stat_activity "
                              f"WHERE datname = '{name}' AND pid <> pg_backend_pid()")
            c.exec_driver_sql(f'DROP DATABASE IF EXISTS "{name}"')
        admin.dispose()

    return PG_ADMIN.rsplit("/", 1)[0] + "/" + name, drop


def run(db: str, seconds: float, poll: float, work: Path) -> dict:
    drop = None
    url = None
    if db == "postgresql":
        url, drop = fresh_pg()
    stack_dir = work / f"stack-{db}"
    stack = stack_up(stack_dir, redis_url=f"redis://127.0.0.1:{free_port()}/0",
                     database_url=url, workers={}, tokens=TOKENS, environment="test",
                     artifact_root=work / f"artifacts-{db}")
    api = stack.api_url + "/api/v1"
    rec = Recorder()
    try:
        seed = {}
        for k, (token, _) in enumerate(TOKENS.items()):
            with httpx.Client(base_url=api, headers={"Authorization": f"Bearer {token}"},
                              timeout=60) as c:
                aid = c.post("/assets", files={"file": (f"seed{k}.usda", layer(-1 - k))})
                aid.raise_for_status()
                job = c.post("/jobs", json={"asset_id": aid.json()["id"], "settings": SETTINGS})
                job.raise_for_status()
                seed[token] = (aid.json()["id"], job.json()["id"])
        tokens = list(TOKENS)
        stop = time.perf_counter() + seconds

        def poller(i: int) -> None:
            token = tokens[i % 2]
            with httpx.Client(base_url=api, headers={"Authorization": f"Bearer {token}"},
                              timeout=30) as c:
                while time.perf_counter() < stop:
                    rec.call("GET /jobs/{id}", lambda: c.get(f"/jobs/{seed[token][1]}"))
                    time.sleep(poll)

        def uploader(i: int) -> None:
            token = tokens[i % 2]
            with httpx.Client(base_url=api, headers={"Authorization": f"Bearer {token}"},
                              timeout=120) as c:
                rec.call("POST /assets", lambda: c.post(
                    "/assets", files={"file": (f"load{i}.usda", layer(i))}))

        def submitter(i: int) -> None:
            token = tokens[i % 2]
            with httpx.Client(base_url=api, headers={"Authorization": f"Bearer {token}"},
                              timeout=60) as c:
                rec.call("POST /jobs", lambda: c.post(
                    "/jobs", json={"asset_id": seed[token][0], "settings": SETTINGS}))

        threads = ([threading.Thread(target=poller, args=(i,)) for i in range(50)]
                   + [threading.Thread(target=uploader, args=(i,)) for i in range(20)]
                   + [threading.Thread(target=submitter, args=(i,)) for i in range(20)])
        t0 = time.perf_counter()
        for t in threads:
            t.start()
        for t in threads:
            t.join(timeout=seconds + 180)
        wall = time.perf_counter() - t0
    finally:
        stack_down(stack_dir)
        if drop is not None:
            drop()
    endpoints = {}
    for ep, lat in sorted(rec.rows.items()):
        a = np.asarray(lat) * 1e3
        endpoints[ep] = {"n": int(a.size), "p50_ms": float(np.percentile(a, 50)),
                         "p99_ms": float(np.percentile(a, 99)), "max_ms": float(a.max()),
                         "codes": dict(rec.codes[ep])}
    status = endpoints.get("GET /jobs/{id}", {})
    locked = sum(v for k, v in rec.errors.items() if "database is locked" in k)
    five = sum(v for k, v in rec.errors.items() if k.split(": ")[1].startswith("5"))
    lost = sum(v for k, v in rec.errors.items() if k.split(": ")[1][0].isalpha()
               and "database is locked" not in k)  # transport errors (timeouts, resets)
    return {"db": db, "wall_seconds": wall, "endpoints": endpoints,
            "errors": dict(rec.errors), "bar": {
                "status_p99_ms": status.get("p99_ms"),
                "status_p99_le_50ms": bool(status) and status["p99_ms"] <= 50.0,
                "no_5xx": five == 0, "no_database_locked": locked == 0,
                "no_transport_errors": lost == 0}}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", type=Path)
    ap.add_argument("--seconds", type=float, default=20.0, help="how long the pollers poll")
    ap.add_argument("--poll", type=float, default=0.1, help="seconds between a poller's reads")
    ap.add_argument("--db", choices=("sqlite", "postgresql", "both"), default="both")
    ap.add_argument("--keep", type=Path, default=None,
                    help="run in this folder and keep it (stack logs) instead of a temporary one")
    args = ap.parse_args(argv)
    dbs = ("sqlite", "postgresql") if args.db == "both" else (args.db,)
    if args.keep is not None:
        args.keep.mkdir(parents=True, exist_ok=True)
        results = [run(db, args.seconds, args.poll, args.keep) for db in dbs]
    else:
        with tempfile.TemporaryDirectory(prefix="texelbake-load-") as tmp:
            results = [run(db, args.seconds, args.poll, Path(tmp)) for db in dbs]
    print(f"{'db':>10} {'endpoint':>16} {'n':>6} {'p50 ms':>8} {'p99 ms':>8} {'max ms':>8}  codes")
    for r in results:
        for ep, e in r["endpoints"].items():
            print(f"{r['db']:>10} {ep:>16} {e['n']:>6} {e['p50_ms']:>8.1f} {e['p99_ms']:>8.1f} "
                  f"{e['max_ms']:>8.1f}  {e['codes']}")
        b = r["bar"]
        verdict = "holds" if all((b["status_p99_le_50ms"], b["no_5xx"], b["no_database_locked"],
                                  b["no_transport_errors"])) else "does NOT hold"
        print(f"{r['db']:>10} bar (status p99 <= 50 ms, no 5xx, no 'database is locked', "
              f"no request lost): "
              f"{verdict}; errors {r['errors'] or 'none'}")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"runs": results}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
