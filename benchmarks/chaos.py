"""The chaos suite: bake jobs through the real farm while one fault strikes at a seeded moment.

    .venv/bin/python benchmarks/chaos.py --trials 2 --json bench_out/chaos.json
    .venv/bin/python benchmarks/chaos.py --seed 7 --only-trial sqlite:redis:3   # replay one

Per database (SQLite, and PostgreSQL in its own cluster on a free port under /tmp), one stack
of real processes stays up across trials (`tests/helpers/farm.farm`: redis-server on a
free port, uvicorn, `--workers` (2) prep and numeric Celery prefork workers each). An
uninterrupted job of the small cylinder (`tests/helpers/service.CHEAP_SETTINGS`) first gives the
job's duration, the bytes of every artifact it wrote and the sha256 of its result archive; a
second uninterrupted job and an in-process bake of the same file (`source="copy"`, zipped
without its `run.json`) must give the same archive. Each trial then deletes the content-keyed work folder (so the job
really runs), submits the job, and at a seeded moment in [5 %, 85 %] of that duration injects
one fault of its kind:

- `worker_child`: kill -9 of a pool child holding a shard (of a random worker when none holds
  one; the prefork parent replaces it);
- `worker_whole`: kill -9 of the whole process group of a worker holding a shard (else of a
  random one), restarted after a seeded pause;
- `api`: kill -9 of uvicorn, restarted; `redis`: kill -9 of redis-server (no persistence: the
  queued messages are gone), restarted; `postgres`: an immediate stop of the cluster (its
  crash-restart path), restarted;
- `enospc`, `eacces`: the artifact store's writes fail with that errno for a seeded while
  (`texelbake.io.atomic.failpoint`; shorter than the retry budget);
- `disk_full`: ENOSPC that outlives the retry budget: the job must fail with an error naming
  ENOSPC and the path; then the fault clears and `POST /jobs/{id}/resume` must complete it;
- `hang`: the next shard to start hangs (`workers.tasks` hang failpoint) while its heartbeats
  go on; the shard time limit (`SHARD_TIME_LIMIT` here) must end it and the redelivery complete
  the job.

Recovery is the stack's own (Celery redelivery, the API's sweeper, retries); the suite only
restarts what it killed, as an operator would. A trial passes when the job succeeds; its
result archive has the uninterrupted run's sha256, and equals the in-process bake of the same
file and settings, every file (`tests/helpers/service.assert_same_bake`); every shard row is `done` with completions == 1; every
artifact has the bytes of the uninterrupted run and none was ever rewritten with other bytes
(a watcher hashes each file whenever it changes); and nothing is left behind: no temporary
files under the artifact root, no shard rows without a job, no shard or stage row still
queued or running.

Recovery: for a worker kill that hit a shard, the seconds from the kill -9 to the ledger's next
start of every shard the killed processes held (its `running` events), per kind with the median
in the table.

Trial seeds are derived from `--seed`, the database, the kind and the trial index; the JSON
names the failing ones (`--only-trial db:kind:i` replays one). Loopback only.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import random
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
import traceback
import zlib
from contextlib import ExitStack, contextmanager
from pathlib import Path

import httpx

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from farm import storage  # noqa: E402
from farm.stack import free_port  # noqa: E402
from tests.helpers.farm import (  # noqa: E402
    AUTH,
    child_pids,
    db_url,
    download,
    farm,
    ledger_rows,
)
from tests.helpers.service import CHEAP_SETTINGS, assert_same_bake  # noqa: E402
from texelbake.io.atomic import FAILPOINT_ENV  # noqa: E402

KINDS = ("worker_child", "worker_whole", "api", "redis", "postgres", "enospc", "eacces",
         "disk_full", "hang")
#: worker processes per queue family (prep: ingest, geometry, export; numeric: cpm, avis). Two
#: per family: a worker killed whole takes tens of seconds to come back (its imports, on a
#: loaded machine), and a shard it held is then run again by its family's other worker, as
#: in a farm of more than one worker per family
WORKERS_PER_FAMILY = 2
#: retries of a transient fault: 4, backoff capped at 2 s (0.5..2 s each, jittered, plus the
#: shard's own run each time): a write fault of up to 3 s is survived, a permanent one fails
#: the job within ~15 s
#: the small cylinder's longest shard, the export, takes 3.5-5 s on a quiet machine and 18-21 s
#: on one at load average 35 (two cores): a 30 s limit ends a hang, and spares a healthy shard
SHARD_TIME_LIMIT = 30
FARM_ENV = {"TEXELBAKE_MAX_RETRIES": "4", "TEXELBAKE_RETRY_BACKOFF_MAX": "2",
            "TEXELBAKE_SHARD_TIME_LIMIT": str(SHARD_TIME_LIMIT),
            "TEXELBAKE_SHARD_KILL_GRACE": "2"}  # below the 3 s lease
PG_BIN = sorted(Path("/usr/lib/postgresql").glob("*/bin"))


def trial_seed(seed: int, db: str, kind: str, i: int) -> int:
    return zlib.crc32(f"{seed}/{db}/{kind}/{i}".encode())


# ---------------------------------------------------------------- our own PostgreSQL


class OwnPostgres:
    """A PostgreSQL cluster of our own on a free port under /tmp (never the shared server),
    so a trial may stop it hard and start it again."""

    def __init__(self, base: Path):
        self.dir = base / "pgdata"
        self.sock = base / "pgsock"
        self.port = free_port()
        self.bin = PG_BIN[-1]
        self.log = base / "postgres.log"

    def _run(self, *args: str) -> None:
        cmd = [str(self.bin / args[0]), *args[1:]]
        if os.geteuid() == 0:  # initdb and postgres refuse root
            cmd = ["runuser", "-u", "postgres", "--", *cmd]
        subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)

    def init(self) -> str:
        self.dir.parent.mkdir(parents=True, exist_ok=True)
        self.sock.mkdir(parents=True, exist_ok=True)
        if os.geteuid() == 0:
            shutil.chown(self.dir.parent, "postgres")
            shutil.chown(self.sock, "postgres")
        self._run("initdb", "-D", str(self.dir), "-U", "postgres", "-A", "trust")
        self.start()
        import sqlalchemy

        eng = sqlalchemy.create_engine(f"{self.url('postgres')}", isolation_level="AUTOCOMMIT")
        with eng.connect() as c:
            c.exec_driver_sql("CREATE DATABASE chaos")
        eng.dispose()
        return self.url("chaos")

    def url(self, name: str) -> str:
        return f"postgresql+psycopg2://postgres@127.0.0.1:{self.port}/{name}"

    def start(self) -> None:
        opts = f"-p {self.port} -k {self.sock} -c listen_addresses=127.0.0.1 -c fsync=off"
        self._run("pg_ctl", "-D", str(self.dir), "-l", str(self.log), "-o", opts, "-w", "start")

    def stop(self, mode: str = "fast") -> None:
        self._run("pg_ctl", "-D", str(self.dir), "-m", mode, "-w", "stop")


# ---------------------------------------------------------------- the artifact watcher


def _sha(path: Path) -> str | None:
    try:
        return hashlib.sha256(path.read_bytes()).hexdigest()
    except OSError:
        return None


def tree_hashes(root: Path) -> dict[str, str]:
    out = {}
    for d, _, files in os.walk(root):
        for f in files:
            p = Path(d) / f
            h = _sha(p)
            if h is not None:
                out[str(p.relative_to(root))] = h
    return out


class Watcher(threading.Thread):
    """Hashes every file under `root` whenever its (inode, mtime, size) changes; a file seen
    with two different contents was rewritten with different bytes."""

    def __init__(self, root: Path, every: float = 0.1):
        super().__init__(daemon=True)
        self.root, self.every = root, every
        self.seen: dict[str, tuple] = {}
        self.hashes: dict[str, str] = {}
        self.rewrites: list[str] = []
        self.halt = threading.Event()

    def scan(self) -> None:
        for d, _, files in os.walk(self.root):
            for f in files:
                if f.startswith("."):
                    continue  # a temporary file being written
                p = Path(d) / f
                try:
                    st = p.stat()
                except OSError:
                    continue
                key = (st.st_ino, st.st_mtime_ns, st.st_size)
                rel = str(p.relative_to(self.root))
                if self.seen.get(rel) == key:
                    continue
                self.seen[rel] = key
                h = _sha(p)
                if h is None:
                    continue
                if rel in self.hashes and self.hashes[rel] != h:
                    self.rewrites.append(rel)
                self.hashes[rel] = h

    def run(self) -> None:
        while not self.halt.wait(self.every):
            self.scan()

    def stop(self) -> None:
        self.halt.set()
        self.join(10)
        self.scan()


# ---------------------------------------------------------------- one database's farm


class Farm:
    def __init__(self, stack, base: Path, control: Path, pg: OwnPostgres | None,
                 cylinder: Path, reference: Path):
        self.stack, self.base, self.control, self.pg = stack, base, control, pg
        self.cylinder, self.reference = cylinder, reference
        self.hang_control = control.with_name("hang")
        self.root = Path(stack.env["TEXELBAKE_ARTIFACT_ROOT"])
        self.workers = sorted(n for n in stack.commands if n.startswith("worker-"))
        self.http = httpx.Client(base_url=stack.api_url + "/api/v1", headers=AUTH, timeout=30)
        self.asset_id = self._call("post", "/assets", files={"file": _package(cylinder)})["id"]
        self.baseline_seconds = 0.0
        self.baseline_hashes: dict[str, str] = {}
        self.baseline_archive = ""  # sha256 of the uninterrupted job's result zip

    def _call(self, method: str, url: str, ok=(200, 201, 202), tries: int = 300, **kw) -> dict:
        last = None
        for _ in range(tries):  # the API may be restarting
            try:
                r = getattr(self.http, method)(url, **kw)
                if r.status_code in ok:
                    return r.json()
                last = f"{r.status_code} {r.text[:300]}"
                if r.status_code < 500:
                    break
            except httpx.TransportError as exc:
                last = repr(exc)
            time.sleep(0.2)
        raise RuntimeError(f"{method.upper()} {url}: {last}")

    def workdir(self, job_id: str | None = None) -> Path:
        from schemas.settings import BakeSettings

        with _sm(self.stack)() as s:
            from farm.db import Asset

            sha = s.get(Asset, self.asset_id).sha256
        return storage.work_dir(self.root, sha, BakeSettings(**CHEAP_SETTINGS).digest())

    def submit(self) -> str:
        body = {"asset_id": self.asset_id, "settings": CHEAP_SETTINGS}
        return self._call("post", "/jobs", json=body)["id"]

    def job(self, job_id: str) -> dict:
        return self._call("get", f"/jobs/{job_id}")

    def wait(self, job_id: str, states: tuple[str, ...], timeout: float = 300.0) -> dict:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            j = self.job(job_id)
            if j["state"] in states:
                return j
            if j["state"] in ("failed", "cancelled") and j["state"] not in states:
                raise TrialFailure(f"job ended {j['state']}: {j['error']}")
            time.sleep(0.1)
        raise TrialFailure(f"job {job_id} not {states} within {timeout} s: {j['state']}")

    def revive(self) -> None:
        """Restart whatever is down (after a trial that failed mid-fault)."""
        self.control.unlink(missing_ok=True)
        self.hang_control.unlink(missing_ok=True)
        if "redis" in self.stack.commands:
            self.stack.start("redis")
            self.stack.wait_redis()
        if self.pg is not None:
            try:
                self.pg.start()
            except subprocess.CalledProcessError:
                pass  # already running
        for name in ("api", *self.workers):
            self.stack.start(name)
        self.stack.wait_healthy()


class TrialFailure(AssertionError):
    pass


def _package(path: Path):  # noqa: ANN202
    from texelbake_client.submit import package

    return package(path)


def _sm(stack):  # noqa: ANN001, ANN202
    from farm.db import session_factory

    return session_factory(db_url(stack))


# ---------------------------------------------------------------- faults


def held_shards(f: Farm, job_id: str) -> dict[int, list[tuple[str, int]]]:
    """Pool child pid -> the (stage, shard)s of the job it holds (running in the ledger)."""
    out: dict[int, list[tuple[str, int]]] = {}
    for r in ledger_rows(f.stack, job_id):
        if r.state == "running" and r.worker:
            out.setdefault(int(r.worker.rsplit(":", 1)[1]), []).append((r.stage, r.shard))
    return out


def _victim(f: Farm, rng: random.Random, job_id: str) -> tuple[str, list[int], list]:
    """The worker to kill: one whose pool child holds a shard of the job (a worker lost
    mid-shard), else a random one. Returns its name, its pool children, the shards they hold."""
    held = held_shards(f, job_id)
    kids = {name: sorted(child_pids(f.stack.pids[name])) for name in f.workers
            if name in f.stack.pids}
    busy = [name for name in sorted(kids) if any(k in held for k in kids[name])]
    name = rng.choice(busy or sorted(kids))
    return name, kids[name], [sh for k in kids[name] for sh in held.get(k, [])]


def inject(f: Farm, kind: str, rng: random.Random, job_id: str, lost: dict | None = None) -> str:
    """Inject one fault of `kind` now; returns what was done. A worker kill records in `lost`
    the shards the killed processes held and the wall time of the kill (`recovery_seconds`)."""
    st = f.stack
    pause = rng.uniform(0.2, 1.5)
    lost = {} if lost is None else lost
    if kind == "worker_child":
        name, kids, held = _victim(f, rng, job_id)
        if not kids:
            return f"{name}: no pool child to kill"
        held_pids = held_shards(f, job_id)
        pid = next((k for k in kids if k in held_pids), rng.choice(kids))
        lost.update(shards=held_pids.get(pid, []), at=_utcnow())
        os.kill(pid, signal.SIGKILL)
        return f"kill -9 pool child {pid} of {name} holding {lost['shards'] or 'no shard'}"
    if kind == "worker_whole":
        name, _kids, held = _victim(f, rng, job_id)
        lost.update(shards=held, at=_utcnow())
        st.kill(name)
        time.sleep(pause)
        st.start(name)
        return (f"kill -9 {name} (group) holding {held or 'no shard'}, restarted after "
                f"{pause:.2f} s")
    if kind == "api":
        st.kill("api")
        time.sleep(pause)
        st.start("api")
        st.wait_healthy()
        return f"kill -9 api, restarted after {pause:.2f} s"
    if kind == "redis":
        st.kill("redis")
        time.sleep(pause)
        st.start("redis")
        st.wait_redis()
        return f"kill -9 redis, restarted after {pause:.2f} s"
    if kind == "postgres":
        assert f.pg is not None
        f.pg.stop("immediate")
        time.sleep(pause)
        f.pg.start()
        return f"postgres stopped (immediate), restarted after {pause:.2f} s"
    if kind in ("enospc", "eacces"):
        hold = rng.uniform(1.0, 3.0)
        f.control.write_text(f"{kind.upper()} {f.root}\n")
        time.sleep(hold)
        f.control.unlink()
        return f"{kind.upper()} on artifact writes for {hold:.2f} s"
    if kind == "disk_full":
        f.control.write_text(f"ENOSPC {f.root}\n")
        try:
            j = f.wait(job_id, ("failed", "succeeded"), timeout=120)
        finally:
            f.control.unlink(missing_ok=True)
        if j["state"] != "failed":
            return "disk full too late: the job had finished its writes"
        err = j["error"] or ""
        # the error names ENOSPC and the artifact's path within the farm's storage, never the
        # server's absolute path (job errors are public text)
        if "No space left on device" not in err or "artifacts/" not in err \
                or str(f.root) in err:
            raise TrialFailure(f"failed job's error does not name ENOSPC and the path: {err!r}")
        time.sleep(rng.uniform(0.0, 1.0))
        f._call("post", f"/jobs/{job_id}/resume")
        return f"disk full until the job failed ({err[:120]}), cleared, resumed"
    if kind == "hang":
        f.hang_control.write_text("* once\n")
        deadline = time.monotonic() + 120
        while f.hang_control.exists() and time.monotonic() < deadline:
            if f.job(job_id)["state"] in ("succeeded", "failed"):
                break
            time.sleep(0.1)
        if f.hang_control.exists():
            f.hang_control.unlink(missing_ok=True)
            return "hang armed too late: no shard started after it"
        return f"the next shard to start hung (time limit {SHARD_TIME_LIMIT} s)"
    raise ValueError(kind)


# ---------------------------------------------------------------- checks


def _utcnow():  # noqa: ANN202 - the ledger's clock (naive UTC, `farm.db.utcnow`)
    from farm.db import utcnow

    return utcnow()


def recovery_seconds(f: Farm, job_id: str, lost: dict) -> float | None:
    """Seconds from the kill to the first start of a shard the killed worker held (the
    ledger's `running` events after the kill: the worst of the lost shards, or None when the
    kill hit no shard)."""
    if not lost.get("shards"):
        return None
    from sqlalchemy import select

    from farm.db import Event

    first: dict[tuple[str, int], float] = {}
    with _sm(f.stack)() as s:
        for data, at in s.execute(select(Event.data_json, Event.at).where(
                Event.job_id == job_id, Event.kind == "shard", Event.at >= lost["at"])):
            d = json.loads(data)
            key = (d.get("stage"), d.get("shard"))
            if d.get("state") == "running" and key in set(map(tuple, lost["shards"])):
                first[key] = min(first.get(key, 1e9), (at - lost["at"]).total_seconds())
    if len(first) < len(lost["shards"]):
        return None
    return round(max(first.values()), 3)


def archive_sha256(f: Farm, job_id: str) -> str:
    """sha256 of the job's whole result archive (`GET /jobs/{id}/result`)."""
    r = f.http.get(f"/jobs/{job_id}/result")
    if r.status_code != 200:
        raise TrialFailure(f"GET /jobs/{job_id}/result: {r.status_code} {r.text[:200]}")
    return hashlib.sha256(r.content).hexdigest()


def local_archive_sha256(cylinder: Path, out: Path) -> str:
    """sha256 of the archive the farm would serve for an in-process bake of the same file and
    settings (`source="copy"`, as the farm's result): every file of the output folder but the
    run's facts (`run.json`), zipped as `services.routers.job_files.build_result_zip` does."""
    from schemas.settings import BakeSettings
    from texelbake.io.archive import folder_members, zip_bytes
    from texelbake.pipeline.run import RUN_JSON, bake

    shutil.rmtree(out, ignore_errors=True)
    bake(cylinder, out, BakeSettings(**CHEAP_SETTINGS), progress=False, source="copy",
         workdir=out.with_name(out.name + "_work"))
    members = [(n, p.read_bytes()) for n, p in folder_members(out) if n != RUN_JSON]
    return hashlib.sha256(zip_bytes(members)).hexdigest()


def leftovers(f: Farm) -> list[str]:
    found = []
    for d, _, files in os.walk(f.root):
        for name in files:
            p = Path(d) / name
            rel = p.relative_to(f.root)
            if name.startswith(".") or rel.parts[0] == "tmp":
                found.append(f"temp file {rel}")
    from sqlalchemy import select

    from farm.db import Job, Shard, Stage

    with _sm(f.stack)() as s:
        jobs = set(s.scalars(select(Job.id)))
        live = set(s.scalars(select(Job.id).where(Job.state.in_(["queued", "running"]))))
        for model in (Shard, Stage):
            for jid, stt in s.execute(select(model.job_id, model.state)):
                if jid not in jobs:
                    found.append(f"{model.__tablename__} row of no job ({jid})")
                elif stt in ("queued", "running") and jid not in live:
                    found.append(f"{model.__tablename__} row {stt} of finished job {jid}")
    return found


def run_trial(f: Farm, db: str, kind: str, i: int, seed: int, out: Path) -> dict:
    ts = trial_seed(seed, db, kind, i)
    rng = random.Random(ts)
    wd = f.workdir()
    shutil.rmtree(wd, ignore_errors=True)
    watcher = Watcher(wd)
    watcher.start()
    t0 = time.monotonic()
    rec = {"trial": i, "seed": ts, "kind": kind, "db": db}
    try:
        job_id = f.submit()
        rec["job_id"] = job_id
        # a full disk or a hang must strike while shards remain (the export is the last 10 %;
        # a hang armed after the last shard started never strikes: jobs often run faster than
        # the warm baseline, so a hang is armed in its first 35 %)
        last = {"disk_full": 0.6, "hang": 0.35}.get(kind, 0.85)
        at = rng.uniform(0.05, last) * f.baseline_seconds
        time.sleep(max(0.0, at - (time.monotonic() - t0)))
        rec["fault_at_s"] = round(time.monotonic() - t0, 3)
        lost: dict = {}
        rec["fault"] = inject(f, kind, rng, job_id, lost)
        f.wait(job_id, ("succeeded",))
        rec["seconds"] = round(time.monotonic() - t0, 3)
        rec["recovery_s"] = recovery_seconds(f, job_id, lost)
        watcher.stop()
        problems = []
        rec["archive_sha256"] = archive_sha256(f, job_id)
        if rec["archive_sha256"] != f.baseline_archive:
            problems.append(f"result archive {rec['archive_sha256'][:12]} is not the "
                            f"uninterrupted run's {f.baseline_archive[:12]}")
        res = out / f"{db}-{kind}-{i}"
        shutil.rmtree(res, ignore_errors=True)
        try:
            assert_same_bake(download(f.stack, job_id, res), f.reference)
        except AssertionError as exc:
            problems.append(f"result differs from the uninterrupted bake: {exc}")
        rows = ledger_rows(f.stack, job_id)
        bad = [(r.stage, r.shard, r.state, r.completions) for r in rows
               if r.state != "done" or r.completions != 1]
        if not rows or bad:
            problems.append(f"shard rows not done exactly once: {bad or 'no rows'}")
        rec["reruns"] = sum(r.attempts - 1 for r in rows)
        hashes = tree_hashes(wd)
        if hashes != f.baseline_hashes:
            diff = sorted(k for k in set(hashes) | set(f.baseline_hashes)
                          if hashes.get(k) != f.baseline_hashes.get(k))
            problems.append(f"artifacts differ from the uninterrupted run: {diff[:5]}")
        if watcher.rewrites:
            problems.append(f"artifacts rewritten with other bytes: {watcher.rewrites[:5]}")
        problems += leftovers(f)
        rec["passed"] = not problems
        if problems:
            rec["reason"] = "; ".join(problems)[:2000]
    except Exception as exc:  # noqa: BLE001 - a trial's failure is data
        watcher.halt.set()
        rec["passed"] = False
        rec["reason"] = f"{type(exc).__name__}: {exc}"[:2000]
        rec["traceback"] = traceback.format_exc(limit=4)[-1500:]
        f.revive()
    return rec


# ---------------------------------------------------------------- setup


@contextmanager
def open_farm(db: str, base: Path, cylinder: Path, reference: Path,
              workers_per_family: int = 1):
    with ExitStack() as es:
        pg = None
        url = None
        if db == "postgresql":
            pg = OwnPostgres(base)
            url = pg.init()
            es.callback(pg.stop, "fast")
        control = base / "failpoint"
        n = workers_per_family
        stack = es.enter_context(farm(base / "stack", database_url=url,
                                      workers={"prep": n, "numeric": n}, **FARM_ENV,
                                      **{FAILPOINT_ENV: str(control),
                                         "TEXELBAKE_FAILPOINT_HANG": str(base / "hang")}))
        f = Farm(stack, base, control, pg, cylinder, reference)
        es.callback(f.http.close)
        # the uninterrupted run: the job's duration and the bytes of every artifact
        archives = []
        for _ in range(2):  # the first one warms the workers' imports and caches
            shutil.rmtree(f.workdir(), ignore_errors=True)
            t0 = time.monotonic()
            job_id = f.submit()
            f.wait(job_id, ("succeeded",))
            f.baseline_seconds = time.monotonic() - t0
            archives.append(archive_sha256(f, job_id))
        f.baseline_hashes = tree_hashes(f.workdir())
        # a clean run and its rerun serve one archive, and so does the in-process bake
        f.baseline_archive = archives[-1]
        local = local_archive_sha256(cylinder, base / "local")
        if len({*archives, local}) != 1:
            raise TrialFailure(f"result archives differ without a fault: farm {archives}, "
                               f"in-process {local}")
        assert_same_bake(download(stack, job_id, base / "baseline"), reference)
        yield f


def make_scene(base: Path) -> tuple[Path, Path]:
    from schemas.settings import BakeSettings
    from texelbake.pipeline.run import bake
    from texelbake.testscenes import write_scene

    cylinder = write_scene("cylinder", base / "scene" / "cylinder.usda", "small")
    reference = bake(cylinder, base / "reference", BakeSettings(**CHEAP_SETTINGS), progress=False)
    return cylinder, reference


def _median(xs: list[float]) -> float | None:
    import statistics

    return round(statistics.median(xs), 3) if xs else None


def summary(recs: list[dict]) -> dict:
    return {
        "trials": len(recs),
        "passed": sum(r["passed"] for r in recs),
        "failed_seeds": [r["seed"] for r in recs if not r["passed"]],
        "failures": [{k: r.get(k) for k in ("trial", "seed", "fault", "reason")}
                     for r in recs if not r["passed"]],
        "seconds_mean": round(sum(r.get("seconds", 0) for r in recs) / max(1, len(recs)), 3),
        "reruns": sum(r.get("reruns", 0) for r in recs),
        # seconds from a worker's kill -9 to the shards it held running again (trials whose
        # kill hit a shard)
        "recovery_s": sorted(r["recovery_s"] for r in recs if r.get("recovery_s") is not None),
        "recovery_median_s": _median([r["recovery_s"] for r in recs
                                      if r.get("recovery_s") is not None]),
        "archives": sorted({r["archive_sha256"] for r in recs if r.get("archive_sha256")}),
        # trials whose fault cost at least one shard a re-run (it hit work)
        "hit": sum(1 for r in recs if r.get("reruns", 0) > 0),
        "records": recs,
    }


def run(dbs: list[str], kinds: list[str], trials: int, seed: int, base: Path,
        only: tuple[str, str, int] | None = None, log=print,  # noqa: ANN001
        on_trial=None, workers_per_family: int = WORKERS_PER_FAMILY) -> dict:  # noqa: ANN001
    cylinder, reference = make_scene(base)
    results: dict = {"seed": seed, "trials_per_kind": trials, "settings": CHEAP_SETTINGS,
                     "workers_per_family": workers_per_family, "dbs": {}}
    for db in dbs:
        if only and only[0] != db:
            continue
        with open_farm(db, base / db, cylinder, reference, workers_per_family) as f:
            per: dict = {"baseline_seconds": round(f.baseline_seconds, 3),
                         "baseline_archive": f.baseline_archive, "kinds": {}}
            results["dbs"][db] = per
            log(f"{db}: uninterrupted job {f.baseline_seconds:.1f} s")
            recs: dict[str, list[dict]] = {}
            # round-robin over the kinds: a run stopped early has as many trials of each
            for i in range(trials):
                for kind in kinds:
                    if kind == "postgres" and db != "postgresql":
                        continue
                    if only and (only[1] != kind or only[2] != i):
                        continue
                    rec = run_trial(f, db, kind, i, seed, base / "results")
                    recs.setdefault(kind, []).append(rec)
                    log(f"  {db:10s} {kind:12s} #{i:<3d} seed {rec['seed']:>10d} "
                        f"{'pass' if rec['passed'] else 'FAIL'} {rec.get('seconds', '-')} s "
                        f"recovery {rec.get('recovery_s', '-')} s "
                        f"{rec.get('fault', '')} {rec.get('reason', '')[:300]}", flush=True)
                    per["kinds"][kind] = summary(recs[kind])
                    if on_trial:
                        on_trial(results)
    return results


def table(results: dict) -> str:
    lines = [f"{'db':11s} {'fault':13s} {'trials':>6s} {'passed':>6s} {'mean s':>7s} "
             f"{'reruns':>6s} {'hit':>4s} {'recovery s (median; each)':>26s} {'archive':>8s}"
             "  failed seeds"]
    for db, per in results["dbs"].items():
        for kind, k in per["kinds"].items():
            rec = ("-" if k["recovery_median_s"] is None else
                   f"{k['recovery_median_s']:.2f}; " + ",".join(f"{x:.1f}" for x in k["recovery_s"]))
            same = ("same" if k["archives"] == [per["baseline_archive"]] else
                    "DIFFERS" if k["archives"] else "-")
            lines.append(f"{db:11s} {kind:13s} {k['trials']:6d} {k['passed']:6d} "
                         f"{k['seconds_mean']:7.1f} {k['reruns']:6d} {k['hit']:4d} {rec:>26s} "
                         f"{same:>8s}  {','.join(map(str, k['failed_seeds'])) or '-'}")
        lines.append(f"{db:11s} archive sha256 of the clean run, its rerun and the in-process "
                     f"bake: {per['baseline_archive']}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--trials", type=int, default=2)
    ap.add_argument("--json", type=Path)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--db", default="sqlite,postgresql")
    ap.add_argument("--kinds", default=",".join(KINDS))
    ap.add_argument("--only-trial", help="db:kind:index — replay one trial of --seed")
    ap.add_argument("--keep", action="store_true", help="keep the work folder under /tmp")
    ap.add_argument("--workers", type=int, default=WORKERS_PER_FAMILY,
                    help="worker processes per queue family (prep, numeric)")
    a = ap.parse_args(argv)
    dbs = [d for d in a.db.split(",") if d]
    kinds = [k for k in a.kinds.split(",") if k]
    for k in kinds:
        if k not in KINDS:
            ap.error(f"--kinds: unknown fault kind {k!r}; expected some of {', '.join(KINDS)}")
    for d in dbs:
        if d not in ("sqlite", "postgresql"):
            ap.error(f"--db: unknown database {d!r}; expected sqlite or postgresql")
    only = None
    if a.only_trial:
        db, kind, i = a.only_trial.split(":")
        only = (db, kind, int(i))
        trials = int(i) + 1
    else:
        trials = a.trials
    if not 1 <= trials <= 200:
        ap.error("--trials must be in 1..200")
    base = Path(tempfile.mkdtemp(prefix="texelbake-chaos-"))
    os.chmod(base, 0o755)
    def dump(results: dict) -> None:  # after every trial: a stopped run keeps what it did
        if a.json:
            a.json.parent.mkdir(parents=True, exist_ok=True)
            a.json.write_text(json.dumps(results, indent=1, sort_keys=True) + "\n")

    try:
        results = run(dbs, kinds, trials, a.seed, base, only, on_trial=dump,
                      workers_per_family=a.workers)
    finally:
        if not a.keep:
            shutil.rmtree(base, ignore_errors=True)
    print(table(results))
    dump(results)
    bad = sum(k["trials"] - k["passed"] for p in results["dbs"].values()
              for k in p["kinds"].values())
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
