"""The cost of batches to the API (issue 16, item 1): `POST /batches` of N items, reading the
batch, listing, cancelling, against SQLite and PostgreSQL.

    .venv/bin/python benchmarks/batches.py --json bench_out/batches.json [--sizes 10,100,1000]

Method: a real stack per backend (`farm.stack.stack_up`: uvicorn and its own redis-server,
no workers, so every item's job stays queued and each request is the API's and the
database's own work), one tenant, one uploaded asset. Per size N, on loopback only: one
`POST /batches` of N items (every item validated, then the batch and N jobs in one
transaction, N plan messages sent), `--reads` times `GET /batches/{id}` (p50, max), one
`GET /batches`, one `DELETE /batches/{id}` (N jobs cancelled), then `GET /batches/{id}/result`
(the archive of a batch with no succeeded item: `batch.json` alone). Bounded: sizes ≤ 5,000,
reads ≤ 100.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import httpx
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from farm.stack import free_port, stack_down, stack_up  # noqa: E402

TOKEN = "bench-batches-0123456789abcdef"
SETTINGS = {"atlas_resolution": 8, "samples_per_texel": 4, "c_max": 4}
LAYER = b'#usda 1.0\n(\n    defaultPrim = "World"\n)\ndef Xform "World"\n{\n    def Cube "Box"\n    {\n    }\n}\n'


def _timed(fn):  # noqa: ANN001, ANN202
    t = time.perf_counter()
    r = fn()
    return r, (time.perf_counter() - t) * 1000.0


def run_backend(db: str, sizes: list[int], reads: int, work: Path) -> list[dict]:
    database_url = None
    admin = name = None
    if db == "postgresql":
        import sqlalchemy

        admin = sqlalchemy.create_engine("postgresql+psycopg2://postgres@127.0.0.1:5432/test",
                                         isolation_level="AUTOCOMMIT")
        name = f"texelbake_bench_batches_{os.getpid()}"
        with admin.connect() as c:
            c.exec_driver_sql(f'CREATE DATABASE "{name}"')
        database_url = f"postgresql+psycopg2://postgres@127.0.0.1:5432/{name}"
    stack = stack_up(work, redis_url=f"redis://127.0.0.1:{free_port()}/0", database_url=database_url,
                     tokens={TOKEN: "bench"}, workers={}, environment="test")
    rows = []
    try:
        with httpx.Client(base_url=stack.api_url + "/api/v1", timeout=600,
                          headers={"Authorization": f"Bearer {TOKEN}"}) as c:
            aid = c.post("/assets", files={"file": ("world.usda", LAYER)}).json()["id"]
            for n in sizes:
                body = {"settings": SETTINGS,
                        "items": [{"asset_id": aid, "priority": i % 101} for i in range(n)]}
                r, create_ms = _timed(lambda body=body: c.post("/batches", json=body))
                assert r.status_code == 201, r.text
                bid = r.json()["id"]
                times = []
                for _ in range(reads):
                    rr, ms = _timed(lambda bid=bid: c.get(f"/batches/{bid}"))
                    assert rr.status_code == 200 and rr.json()["counts"]["total"] == n
                    times.append(ms)
                rl, list_ms = _timed(lambda: c.get("/batches"))
                assert rl.status_code == 200
                rd, cancel_ms = _timed(lambda bid=bid: c.delete(f"/batches/{bid}"))
                assert rd.status_code == 202 and rd.json()["counts"]["cancelled"] == n, rd.text
                ra, result_ms = _timed(lambda bid=bid: c.get(f"/batches/{bid}/result"))
                assert ra.status_code == 200
                rows.append({"db": db, "items": n, "create_ms": create_ms,
                             "read_p50_ms": float(np.percentile(times, 50)),
                             "read_max_ms": max(times), "list_ms": list_ms,
                             "cancel_ms": cancel_ms, "result_ms": result_ms})
    finally:
        stack_down(work)
        if admin is not None:
            from farm.db import _engines

            for key in [k for k in _engines if name and name in k[0]]:
                _engines.pop(key).dispose()
            with admin.connect() as c:
                c.exec_driver_sql(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)')
            admin.dispose()
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", type=Path)
    ap.add_argument("--sizes", default="10,100,1000")
    ap.add_argument("--reads", type=int, default=20)
    ap.add_argument("--db", choices=("sqlite", "postgresql", "both"), default="both")
    args = ap.parse_args(argv)
    sizes = [int(x) for x in args.sizes.split(",")]
    if any(not 1 <= n <= 5000 for n in sizes) or not 1 <= args.reads <= 100:
        ap.error("sizes must be 1..5000 and --reads 1..100")
    rows: list[dict] = []
    for db in (("sqlite", "postgresql") if args.db == "both" else (args.db,)):
        with tempfile.TemporaryDirectory(prefix=f"bench-batches-{db}-") as tmp:
            rows += run_backend(db, sizes, args.reads, Path(tmp))
    head = ("db", "items", "create_ms", "read_p50_ms", "read_max_ms", "list_ms", "cancel_ms",
            "result_ms")
    print(" ".join(f"{h:>11}" for h in head))
    for r in rows:
        print(" ".join(f"{r[h]:>11}" if isinstance(r[h], str | int) else f"{r[h]:>11.1f}"
                       for h in head))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"rows": rows, "load": os.getloadavg()}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
