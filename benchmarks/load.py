"""The API under load (issue 16, item 5): 50 clients polling job status, 20 concurrent uploads and
20 concurrent job submissions, against SQLite and against PostgreSQL.

    .venv/bin/python benchmarks/load.py --json bench_out/load.json [--seconds 20] [--db sqlite]

Method: a real stack per backend (`farm.stack.stack_up`: uvicorn, its own redis-server, one
prep and one numeric Celery worker on the same cores), two tenants. A bake runs through the
clock (`Baker`: the small cylinder at the chaos suite's cheap settings, a new seed per job so
each really bakes, the next submitted when one ends; the table says what fraction of the clock
a bake was in flight); the 20 submitted jobs queue behind it. `--no-bake`: no workers, so
submitted jobs stay queued and every request is the API's and the database's own work. Before the clock: one asset and one job per tenant, then one client polls
alone for `--baseline` seconds (the floor the machine sets today). Then, at once, on loopback
only and bounded in count and time:
- 50 pollers, each with its own connection, `GET /jobs/{id}` of their tenant's job every
  `--poll` seconds for `--seconds`; they run as asyncio tasks in a process of their own (as 50
  threads beside the uploaders they measured mostly their own GIL convoy);
- 20 uploaders, each `POST /assets` once with a distinct small layer (distinct bytes, so no
  upload is deduplicated; each is checked in a child process with pxr, as every upload is);
- 20 submitters, each `POST /jobs` once for its tenant's asset.
Every response is timed twice: by the client (what the bar is about) and by the API itself
(`Server-Timing: app;dur=`, from the app receiving the request to its response headers); a
client or a machine too loaded to send and read in time shows as the gap between the two. The
table gives per endpoint the count, p50, p99 and max latency (client) and p50/p99 (server), the
status codes, errors by kind (transport errors, 5xx, and any body that says "database is
locked", which must never reach a client), and the machine's load average before and after.
Bar: status reads p99 <= 50 ms (client), no 5xx, no "database is locked", no request lost (a
client timeout hides the server's late answer). Also reported: CPU seconds of the pollers, the
writers, the API and the API's upload-check processes, and the status reads split into those
sent while the writes were in flight and those sent after. Knobs (all reported in the table and
the JSON): `--pollers/--uploads/--submits` (0 for attribution runs), `--api-workers`,
`--client-nice N` (the upload and submission clients at nice N, standing in for clients on
other machines; the pollers always run at the benchmark's own priority), `--stagger` (pollers'
first reads spread over one interval instead of all in step). Times are of a 2-core machine that also runs
the uploads' validation, so the status p99 is measured while the CPU is shared with 20 pxr
checks, and with whatever else the machine runs (the load average says how much).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import multiprocessing as mp
import os
import sys
import tempfile
import threading
import time
import uuid
from collections import Counter
from pathlib import Path
from urllib.parse import urlsplit

import httpx
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # first: before benchmarks/ (whose farm.py is not the package)

from farm.stack import free_port, stack_down, stack_up  # noqa: E402
from tests.helpers.service import proc_cpu  # noqa: E402

TOKENS = {"load-token-a-0123456789abcdef": "team-a", "load-token-b-0123456789abcdef": "team-b"}
PG_ADMIN = "postgresql+psycopg2://postgres@127.0.0.1:5432/test"
SETTINGS = {"atlas_resolution": 8, "samples_per_texel": 4, "c_max": 4}
#: the bake kept running through the clock (`Baker`): the chaos suite's cheap sharded bake
BAKE_SETTINGS = {"atlas_resolution": 32, "shard_texels": 16, "n_light_dirs": 8,
                 "n_view_dirs": 8, "samples_per_texel": 8, "n_heldout": 8, "c_max": 8,
                 "n_trials": 1, "avis_resolution": 4}
STATUS = "GET /jobs/{id}"


def layer(i: int) -> bytes:
    """A small valid layer, distinct per i (a comment), so uploads are not deduplicated."""
    return (f"#usda 1.0\n(\n    defaultPrim = \"Root\"\n    upAxis = \"Y\"\n"
            f"    metersPerUnit = 1\n    doc = \"load {i}\"\n)\n"
            "def Xform \"Root\"\n{\n    def Mesh \"Tri\"\n    {\n"
            "        int[] faceVertexCounts = [3]\n        int[] faceVertexIndices = [0, 1, 2]\n"
            "        point3f[] points = [(0, 0, 0), (1, 0, 0), (0, 1, 0)]\n    }\n}\n").encode()


def server_ms(r: httpx.Response) -> float | None:
    """The API's own time for a response (`Server-Timing: app;dur=MS`)."""
    v = r.headers.get("server-timing", "")
    try:
        return float(v.split("dur=")[1]) if "dur=" in v else None
    except ValueError:
        return None


#: one response: (client seconds, status code, server ms, body says locked, transport error)
Sample = tuple[float | None, int | None, float | None, bool, str | None]


class Recorder:
    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.rows: dict[str, list[float]] = {}
        self.server: dict[str, list[float]] = {}
        self.codes: dict[str, Counter] = {}
        self.errors: Counter = Counter()

    def add(self, endpoint: str, dt: float | None, code: int | None, srv: float | None,
            locked: bool, error: str | None) -> None:
        with self.lock:
            if error is not None or dt is None or code is None:
                self.errors[f"{endpoint}: {error}"] += 1
                return
            self.rows.setdefault(endpoint, []).append(dt)
            if srv is not None:
                self.server.setdefault(endpoint, []).append(srv)
            self.codes.setdefault(endpoint, Counter())[str(code)] += 1
            if code >= 500:
                self.errors[f"{endpoint}: {code}"] += 1
            if locked:
                self.errors[f"{endpoint}: database is locked"] += 1

    def call(self, endpoint: str, fn) -> httpx.Response | None:  # noqa: ANN001
        t0 = time.perf_counter()
        try:
            r = fn()
        except httpx.HTTPError as exc:
            self.add(endpoint, None, None, None, False, type(exc).__name__)
            return None
        self.add(endpoint, time.perf_counter() - t0, r.status_code, server_ms(r),
                 "database is locked" in r.text, None)
        return r

    def table(self) -> dict:
        out = {}
        for ep, lat in sorted(self.rows.items()):
            a = np.asarray(lat) * 1e3
            srv = np.asarray(self.server.get(ep) or [np.nan])
            out[ep] = {"n": int(a.size), "p50_ms": float(np.percentile(a, 50)),
                       "p99_ms": float(np.percentile(a, 99)), "max_ms": float(a.max()),
                       "server_p50_ms": float(np.percentile(srv, 50)),
                       "server_p99_ms": float(np.percentile(srv, 99)),
                       "codes": dict(self.codes[ep])}
        return out


async def _poll(api: str, token: str, job_id: str, stop_at: float, poll: float,
                out: list[Sample], delay: float = 0.0, sent_at: list[float] | None = None,
                ) -> None:
    """One polling client with its own keep-alive connection: GET the job until `stop_at`.
    A minimal HTTP/1.1 client on asyncio streams (status line, headers, Content-Length body):
    httpx spent about a millisecond of the client's CPU per request, which on a loaded 2-core
    machine made the pollers measure themselves."""
    u = urlsplit(api)
    req = (f"GET {u.path}/jobs/{job_id} HTTP/1.1\r\nHost: {u.netloc}\r\n"
           f"Authorization: Bearer {token}\r\n\r\n").encode()
    reader, writer = await asyncio.open_connection(u.hostname, u.port)
    await asyncio.sleep(delay)
    try:
        while time.time() < stop_at:
            t0 = time.perf_counter()
            try:
                writer.write(req)
                head = await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), 30)
                lines = head.decode("latin-1").split("\r\n")
                headers = {k.strip().lower(): v.strip() for k, _, v in
                           (ln.partition(":") for ln in lines[1:] if ln)}
                body = await reader.readexactly(int(headers.get("content-length", "0")))
            except (TimeoutError, OSError, asyncio.IncompleteReadError) as exc:
                out.append((None, None, None, False, type(exc).__name__))
                return
            dt = time.perf_counter() - t0
            v = headers.get("server-timing", "")
            srv = float(v.split("dur=")[1]) if "dur=" in v else None
            out.append((dt, int(lines[0].split()[1]), srv, b"database is locked" in body, None))
            if sent_at is not None:  # aligned with `out`'s answered samples (no await between)
                sent_at.append(time.time() - dt)
            await asyncio.sleep(poll)
    finally:
        writer.close()


def _pollers(api: str, jobs: list[tuple[str, str]], start_at: float, stop_at: float,
             poll: float, q, nice: int, stagger: bool = False) -> None:  # noqa: ANN001
    """The pollers' process: one asyncio client per (token, job); puts the samples on `q`."""
    if nice:
        os.nice(nice)
    out: list[Sample] = []
    sent_at: list[float] = []

    async def main() -> None:
        await asyncio.sleep(max(0.0, start_at - time.time()))
        n = len(jobs)  # staggered: poller i starts i/n of a poll interval late
        await asyncio.gather(*(_poll(api, t, j, stop_at, poll, out, poll * i / n if stagger
                                     else 0.0, sent_at) for i, (t, j) in enumerate(jobs)))

    asyncio.run(main())
    t = os.times()
    q.put(("polls", (out, t.user + t.system, sent_at)))


def _writers(api: str, tokens: list[str], assets: dict[str, str], uploads: int, submits: int,
             start_at: float, seconds: float, q, nice: int, ready) -> None:  # noqa: ANN001
    """The writers' process: `uploads` threads each POST /assets once, `submits` threads each
    POST /jobs once, all started at `start_at`; puts (endpoint, sample) pairs on `q`."""
    if nice:
        os.nice(nice)
    out: list[tuple[str, Sample]] = []
    lock = threading.Lock()

    def call(endpoint: str, fn) -> None:  # noqa: ANN001
        t0 = time.perf_counter()
        try:
            r = fn()
        except httpx.HTTPError as exc:
            sample: Sample = (None, None, None, False, type(exc).__name__)
        else:
            sample = (time.perf_counter() - t0, r.status_code, server_ms(r),
                      "database is locked" in r.text, None)
        with lock:
            out.append((endpoint, sample))

    # the clients are built before the clock, without a TLS context (the API is plain http on
    # loopback): loading the CA bundle cost ~50 ms of CPU per client, 40 of them overran the
    # start and competed with the pollers while the writes were timed
    clients = [httpx.Client(base_url=api, headers={"Authorization": f"Bearer {tokens[i % 2]}"},
                            timeout=180, verify=False) for i in range(uploads + submits)]
    ready.set()

    def uploader(i: int) -> None:
        call("POST /assets", lambda: clients[i].post(
            "/assets", files={"file": (f"load{i}.usda", layer(i))}))

    def submitter(i: int) -> None:
        call("POST /jobs", lambda: clients[uploads + i].post(
            "/jobs", json={"asset_id": assets[tokens[i % 2]], "settings": SETTINGS}))

    threads = ([threading.Thread(target=uploader, args=(i,)) for i in range(uploads)]
               + [threading.Thread(target=submitter, args=(i,)) for i in range(submits)])
    time.sleep(max(0.0, start_at - time.time()))
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=seconds + 240)
    for c in clients:
        c.close()
    t = os.times()
    q.put(("writes", (out, t.user + t.system, [time.time()])))  # when the last write ended


def _tree_cpu(pid: int) -> tuple[float, float]:
    """CPU seconds of a process and its live descendants: (their own, their reaped children's,
    e.g. the API's finished pxr checks)."""
    stats = proc_cpu()
    own = kids = 0.0
    todo = [pid]
    while todo:
        p = todo.pop()
        if p in stats:
            own, kids = own + stats[p][1], kids + stats[p][2]
        todo.extend(c for c, v in stats.items() if v[0] == p)
    return own, kids


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


class Baker(threading.Thread):
    """Keeps one bake running on the stack's workers until `stop_at`: the small cylinder at
    `BAKE_SETTINGS`, a new seed per job (a new content key, so every job really bakes), the
    next submitted when the last ends; its status read every half second (one more light
    client). Records each job's id, state and wall seconds."""

    def __init__(self, api: str, token: str, asset_id: str, stop_at: float):
        super().__init__(daemon=True)
        self.api, self.token, self.asset_id, self.stop_at = api, token, asset_id, stop_at
        self.jobs: list[dict] = []
        self.error: str | None = None

    def run(self) -> None:
        try:
            with httpx.Client(base_url=self.api, timeout=60, headers={
                    "Authorization": f"Bearer {self.token}"}) as c:
                seed = 1
                while time.time() < self.stop_at:
                    t0 = time.time()
                    r = c.post("/jobs", json={"asset_id": self.asset_id, "priority": 10,
                                              "settings": {**BAKE_SETTINGS, "seed": seed}})
                    r.raise_for_status()
                    job = {"id": r.json()["id"], "seed": seed, "submitted": t0}
                    self.jobs.append(job)
                    while True:
                        state = c.get(f"/jobs/{job['id']}").json()["state"]
                        job["state"] = state
                        if state in ("succeeded", "failed", "cancelled"):
                            break
                        time.sleep(0.5)
                    job["seconds"] = time.time() - t0
                    seed += 1
        except Exception as exc:  # noqa: BLE001 - reported with the run
            self.error = f"{type(exc).__name__}: {exc}"


def bake_overlap(jobs: list[dict], start: float, stop: float) -> float:
    """Fraction of [start, stop] during which a bake job was in flight."""
    busy = sum(max(0.0, min(stop, j["submitted"] + j.get("seconds", stop - j["submitted"]))
                   - max(start, j["submitted"])) for j in jobs)
    return busy / max(stop - start, 1e-9)


def run(db: str, seconds: float, poll: float, work: Path, baseline: float = 3.0, *,
        pollers: int = 50, uploads: int = 20, submits: int = 20, client_nice: int = 0,
        api_workers: int = 1, stagger: bool = False, bake: bool = True) -> dict:
    drop = None
    url = None
    if db == "postgresql":
        url, drop = fresh_pg()
    stack_dir = work / f"stack-{db}"
    # with a bake: one prep and one numeric worker (the farm's smallest), on the same 2 cores
    stack = stack_up(stack_dir, redis_url=f"redis://127.0.0.1:{free_port()}/0",
                     database_url=url, workers={"prep": 1, "numeric": 1} if bake else {},
                     tokens=TOKENS, environment="test",
                     artifact_root=work / f"artifacts-{db}", api_workers=api_workers)
    api = stack.api_url + "/api/v1"
    rec, base = Recorder(), Recorder()
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
        baker = None
        if bake:
            from texelbake.testscenes import write_scene
            from texelbake_client.submit import package

            scene = write_scene("cylinder", work / f"scene-{db}" / "cylinder.usda", "small")
            with httpx.Client(base_url=api, timeout=120, headers={
                    "Authorization": f"Bearer {tokens[0]}"}) as c:
                r = c.post("/assets", files={"file": package(scene)})
                r.raise_for_status()
                bake_asset = r.json()["id"]
        # the floor: one client alone polls the same job back to back
        with httpx.Client(base_url=api, headers={"Authorization": f"Bearer {tokens[0]}"},
                          timeout=30) as c:
            t_end = time.perf_counter() + baseline
            while time.perf_counter() < t_end:
                base.call(STATUS, lambda: c.get(f"/jobs/{seed[tokens[0]][1]}"))
        load_before = os.getloadavg()
        ctx = mp.get_context("fork")  # before this process starts any thread
        q = ctx.Queue()
        ready = ctx.Event()
        start_at = time.time() + 4.0  # the client processes import and connect first
        polls = ctx.Process(target=_pollers, args=(
            api, [(tokens[i % 2], seed[tokens[i % 2]][1]) for i in range(pollers)], start_at,
            start_at + seconds, poll, q, 0, stagger))
        writes = ctx.Process(target=_writers, args=(
            api, tokens, {t: seed[t][0] for t in tokens}, uploads, submits, start_at, seconds,
            q, client_nice, ready))
        polls.start()
        writes.start()
        if bake:  # started at once: its first stages run before the clock
            baker = Baker(api, tokens[0], bake_asset, start_at + seconds)
            baker.start()
        if not ready.wait(max(0.0, start_at - time.time())):
            raise RuntimeError("the writers were not ready before the clock; raise the delay")
        t0 = time.perf_counter()
        api_cpu0 = _tree_cpu(stack.pids["api"])
        cpu: dict[str, float] = {}
        marks: dict[str, list[float]] = {}
        for _ in range(2):
            kind, (data, cpu[kind], marks[kind]) = q.get(timeout=seconds + 300)
            if kind == "polls":
                data_polls = data
                for sample in data:
                    rec.add(STATUS, *sample)
            else:
                for ep, sample in data:
                    rec.add(ep, *sample)
        api_cpu1 = _tree_cpu(stack.pids["api"])
        cpu["api"] = api_cpu1[0] - api_cpu0[0]
        cpu["api_children"] = api_cpu1[1] - api_cpu0[1]
        polls.join(timeout=30)
        writes.join(timeout=30)
        wall = time.perf_counter() - t0
        if baker is not None:
            baker.join(timeout=600)
        load_after = os.getloadavg()
    finally:
        stack_down(stack_dir)
        if drop is not None:
            drop()
    endpoints = rec.table()
    # the status reads sent while the writes were in flight, and those sent after the last
    writes_end = marks["writes"][0]
    lat = [x[0] for x in data_polls if x[0] is not None]
    during = [d for a, d in zip(marks["polls"], lat, strict=True) if a < writes_end]
    after = [d for a, d in zip(marks["polls"], lat, strict=True) if a >= writes_end]

    def pct(v: list[float]) -> dict:
        a = np.asarray(v) * 1e3
        return {"n": int(a.size), "p50_ms": float(np.percentile(a, 50)) if a.size else None,
                "p99_ms": float(np.percentile(a, 99)) if a.size else None}

    status_split = {"writes_seconds": writes_end - start_at, "during_writes": pct(during),
                    "after_writes": pct(after)}
    status = endpoints.get(STATUS, {})
    locked = sum(v for k, v in rec.errors.items() if "database is locked" in k)
    five = sum(v for k, v in rec.errors.items() if k.split(": ")[1].startswith("5"))
    lost = sum(v for k, v in rec.errors.items() if k.split(": ")[1][0].isalpha()
               and "database is locked" not in k)  # transport errors (timeouts, resets)
    return {"db": db, "wall_seconds": wall, "endpoints": endpoints,
            "clients": {"pollers": pollers, "poll_seconds": poll, "uploads": uploads,
                        "submits": submits, "nice": client_nice,
                        "staggered": stagger}, "api_workers": api_workers,
            "baseline_1_client": base.table().get(STATUS, {}), "status_split": status_split,
            "bake": None if baker is None else {
                "settings": BAKE_SETTINGS, "jobs": baker.jobs, "error": baker.error,
                "in_flight_fraction": bake_overlap(baker.jobs, start_at, start_at + seconds)},
            "cpu_seconds": {"pollers": cpu["polls"], "writers": cpu["writes"],
                            "api": cpu["api"], "api_children (upload checks)": cpu["api_children"]},
            "loadavg_before": list(load_before), "loadavg_after": list(load_after),
            "cpus": os.cpu_count(), "errors": dict(rec.errors), "bar": {
                "status_p99_ms": status.get("p99_ms"),
                "status_server_p99_ms": status.get("server_p99_ms"),
                "status_p99_le_50ms": bool(status) and status["p99_ms"] <= 50.0,
                "no_5xx": five == 0, "no_database_locked": locked == 0,
                "no_transport_errors": lost == 0}}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", type=Path)
    ap.add_argument("--seconds", type=float, default=20.0, help="how long the pollers poll")
    ap.add_argument("--poll", type=float, default=0.1, help="seconds between a poller's reads")
    ap.add_argument("--baseline", type=float, default=3.0,
                    help="seconds one client polls alone before the clock (the machine's floor)")
    ap.add_argument("--db", choices=("sqlite", "postgresql", "both"), default="both")
    ap.add_argument("--keep", type=Path, default=None,
                    help="run in this folder and keep it (stack logs) instead of a temporary one")
    ap.add_argument("--pollers", type=int, default=50)
    ap.add_argument("--uploads", type=int, default=20)
    ap.add_argument("--submits", type=int, default=20)
    ap.add_argument("--client-nice", type=int, default=0,
                    help="run the upload and submission clients (not the pollers, who measure) "
                    "at this niceness, standing in for clients on other machines (reported)")
    ap.add_argument("--stagger", action="store_true",
                    help="spread the pollers' first reads over one poll interval (default: all "
                    "50 start at once and stay roughly in step, the harder case)")
    ap.add_argument("--api-workers", type=int, default=1, help="uvicorn worker processes")
    ap.add_argument("--no-bake", action="store_true",
                    help="no workers and no bake (by default one prep and one numeric worker "
                    "keep a bake running through the clock)")
    args = ap.parse_args(argv)
    kw = {"stagger": args.stagger, "pollers": args.pollers, "uploads": args.uploads, "submits": args.submits,
              "client_nice": args.client_nice, "api_workers": args.api_workers,
              "bake": not args.no_bake}
    dbs = ("sqlite", "postgresql") if args.db == "both" else (args.db,)
    if args.keep is not None:
        args.keep.mkdir(parents=True, exist_ok=True)
        results = [run(db, args.seconds, args.poll, args.keep, args.baseline, **kw) for db in dbs]
    else:
        with tempfile.TemporaryDirectory(prefix="texelbake-load-") as tmp:
            results = [run(db, args.seconds, args.poll, Path(tmp), args.baseline, **kw) for db in dbs]
    print(f"{'db':>10} {'endpoint':>22} {'n':>6} {'p50 ms':>8} {'p99 ms':>8} {'max ms':>8} "
          f"{'srv p50':>8} {'srv p99':>8}  codes")
    for r in results:
        c = r["clients"]
        print(f"{r['db']:>10} clients: {c['pollers']} pollers every {c['poll_seconds']} s, "
              f"{c['uploads']} uploads, {c['submits']} submissions, their clients' niceness "
              f"{c['nice']}{' (stand-in for clients on other machines)' if c['nice'] else ''}"
              f"{', pollers staggered' if c['staggered'] else ', pollers in step'}"
              f"; API workers {r['api_workers']}")
        print(f"{r['db']:>10} CPU seconds: " + ", ".join(
            f"{k} {v:.1f}" for k, v in r["cpu_seconds"].items()) + f" over {r['wall_seconds']:.1f} s")
        sp = r["status_split"]
        print(f"{r['db']:>10} status reads sent while the writes were in flight (first "
              f"{sp['writes_seconds']:.1f} s): n {sp['during_writes']['n']} p50 "
              f"{sp['during_writes']['p50_ms'] or 0:.1f} p99 {sp['during_writes']['p99_ms'] or 0:.1f}"
              f" ms; after: n {sp['after_writes']['n']} p50 {sp['after_writes']['p50_ms'] or 0:.1f}"
              f" p99 {sp['after_writes']['p99_ms'] or 0:.1f} ms")
        if r["bake"]:
            bk = r["bake"]
            done = ", ".join(f"{j.get('state', '?')} {j.get('seconds', 0):.0f} s"
                             for j in bk["jobs"])
            print(f"{r['db']:>10} bake: {len(bk['jobs'])} job(s) ({done}), in flight "
                  f"{bk['in_flight_fraction']:.0%} of the clock"
                  f"{'; error ' + bk['error'] if bk['error'] else ''}")
        rows = [("GET /jobs/{id} alone", r["baseline_1_client"]), *r["endpoints"].items()]
        for ep, e in rows:
            if not e:
                continue
            print(f"{r['db']:>10} {ep:>22} {e['n']:>6} {e['p50_ms']:>8.1f} {e['p99_ms']:>8.1f} "
                  f"{e['max_ms']:>8.1f} {e['server_p50_ms']:>8.1f} {e['server_p99_ms']:>8.1f}  "
                  f"{e['codes']}")
        b = r["bar"]
        verdict = "holds" if all((b["status_p99_le_50ms"], b["no_5xx"], b["no_database_locked"],
                                  b["no_transport_errors"])) else "does NOT hold"
        print(f"{r['db']:>10} bar (status p99 <= 50 ms, no 5xx, no 'database is locked', "
              f"no request lost): {verdict}; errors {r['errors'] or 'none'}; load average "
              f"{r['loadavg_before'][0]:.1f} -> {r['loadavg_after'][0]:.1f} on {r['cpus']} CPUs")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        command = "benchmarks/load.py " + " ".join(sys.argv[1:] if argv is None else argv)
        args.json.write_text(json.dumps({"command": command, "runs": results}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
