"""`texelbake stack up` / `down`: the compose stack as local processes, for development and tests.

Starts redis-server (its own on a free port, unless a Redis URL is given: the `redis_url`
argument or `TEXELBAKE_REDIS_URL`, as the server reads it; a local one that does not answer there
is started), one uvicorn API and one
Celery worker per queue family (`prep`: ingest, geometry, export; `numeric`: cpm, avis, btf;
`render`: render), each in its own process group with its log under `<workdir>/logs/`. The pids,
URLs and environment go to `<workdir>/stack.json`; `stack_down(workdir)` stops exactly those
processes. Stdlib only: the core package does not import Celery, FastAPI or Redis.
"""

from __future__ import annotations

import json
import os
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from urllib.parse import urlparse

from schemas.queues import QUEUE_FAMILIES
from texelbake.errors import SettingsError, StageError
from texelbake.io.atomic import atomic_write_bytes

_REPO = Path(__file__).resolve().parents[1]
HEALTH_PATH = "/api/v1/utils/health-check/"


#: tries of the API or Redis on a new free port when the one chosen was taken before the
#: server bound it
BIND_ATTEMPTS = 4

#: `stack_up(redis_url=OWN_REDIS)`: a redis-server of the stack's own on a free port, whatever
#: TEXELBAKE_REDIS_URL says
OWN_REDIS = "own"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def redis_ping(url: str, timeout: float = 0.5) -> bool:
    """True when a Redis server answers PING at `url` (raw RESP over a socket)."""
    u = urlparse(url)
    try:
        with socket.create_connection((u.hostname or "127.0.0.1", u.port or 6379), timeout) as s:
            s.sendall(b"*1\r\n$4\r\nPING\r\n")
            return s.recv(64).startswith((b"+PONG", b"-NOAUTH"))
    except OSError:
        return False


def redis_pid(url: str, timeout: float = 0.5) -> int | None:
    """The process id of the Redis server at `url` (`INFO server`), None where none answers."""
    u = urlparse(url)
    try:
        with socket.create_connection((u.hostname or "127.0.0.1", u.port or 6379), timeout) as s:
            s.sendall(b"*2\r\n$4\r\nINFO\r\n$6\r\nserver\r\n")
            data = b""
            while b"process_id:" not in data or not data.split(b"process_id:", 1)[1].count(b"\r\n"):
                chunk = s.recv(4096)
                if not chunk:
                    return None
                data += chunk
    except OSError:
        return None
    return int(data.split(b"process_id:", 1)[1].split(b"\r\n", 1)[0])


@dataclass
class Stack:
    """Processes of a local stack. `procs` holds only processes this object started."""

    workdir: Path
    api_url: str
    redis_url: str
    env: dict[str, str]
    commands: dict[str, list[str]]
    procs: dict[str, subprocess.Popen] = field(default_factory=dict)
    pids: dict[str, int] = field(default_factory=dict)
    #: where the tokens came from: "argument", "TEXELBAKE_TOKENS" or "new"
    tokens_from: str = "argument"

    def describe(self) -> list[str]:
        """What `texelbake stack up` prints: the API, which Redis (started or not), the tokens."""
        started = "started by this stack" if "redis" in self.commands else (
            "already running: not started, and not stopped, by this stack")
        tokens = json.loads(self.env.get("TEXELBAKE_TOKENS", "{}"))
        tenants = ", ".join(sorted(set(tokens.values())))
        src = {"new": f"a new token for tenant {tenants} (in {self.workdir / 'stack.json'})",
               "TEXELBAKE_TOKENS": f"from TEXELBAKE_TOKENS: tenants {tenants}",
               "argument": f"given: tenants {tenants}"}[self.tokens_from]
        return [f"api: {self.api_url}", f"redis: {self.redis_url} ({started})",
                f"tokens: {src}", f"logs: {self.workdir / 'logs'}"]

    # ---------------------------------------------------------------- processes
    def start(self, name: str) -> int:
        """(Re)start the process `name` (`redis`, `api`, `worker-<family>[-i]`); returns its pid."""
        if name in self.procs and self.procs[name].poll() is None:
            return self.procs[name].pid
        logs = self.workdir / "logs"
        logs.mkdir(parents=True, exist_ok=True)
        log = open(logs / f"{name}.log", "ab")  # noqa: SIM115 - owned by the child
        proc = subprocess.Popen(
            self.commands[name],
            cwd=str(_REPO),
            env=self.env,
            stdout=log,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
        log.close()
        self.procs[name] = proc
        self.pids[name] = proc.pid
        self._save()
        return proc.pid

    def signal(self, name: str, sig: int = signal.SIGTERM) -> None:
        """Send `sig` to the process group of `name` (the worker and its pool children)."""
        pid = self.pids.get(name)
        if pid is None:
            return
        try:
            os.killpg(pid, sig)
        except ProcessLookupError:
            pass

    def stop(self, name: str, timeout: float = 20.0) -> None:
        self.signal(name, signal.SIGTERM)
        proc = self.procs.get(name)
        if proc is not None:
            try:
                proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.signal(name, signal.SIGKILL)
                proc.wait(10)
        else:
            _wait_gone(self.pids.get(name), timeout)
        self.pids.pop(name, None)
        self.procs.pop(name, None)
        self._save()

    def kill(self, name: str) -> None:
        """kill -9 the whole process group of `name`."""
        self.signal(name, signal.SIGKILL)
        proc = self.procs.get(name)
        if proc is not None:
            proc.wait(10)
        self.pids.pop(name, None)
        self.procs.pop(name, None)
        self._save()

    def wait_healthy(self, timeout: float = 60.0) -> None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            try:
                with urllib.request.urlopen(self.api_url + HEALTH_PATH, timeout=2) as r:
                    if r.status == 200:
                        return
            except (urllib.error.URLError, OSError):
                pass
            proc = self.procs.get("api")
            if proc is not None and proc.poll() is not None:
                raise StageError(
                    f"the API exited with {proc.returncode}; see {self.workdir}/logs/api.log; "
                    f"it ends: {self._log_tail('api')!r}"
                )
            time.sleep(0.2)
        raise StageError(f"the API at {self.api_url} was not healthy within {timeout} s")

    def start_bound(self, name: str, wait: Callable[[], None], *,
                    new_port_if_taken: bool) -> None:
        """Start `name` (`api` or `redis`) and `wait()` until it answers. A port chosen by
        `free_port` is free only when it is chosen: another process (any client's outgoing
        connection takes an ephemeral port from the same range) can hold it by the time the
        server binds. With `new_port_if_taken`, a bind refused as "address already in use" is
        retried on another free port, a few times; any other failure is raised."""
        log = self.workdir / "logs" / f"{name}.log"
        for attempt in range(BIND_ATTEMPTS):
            start = log.stat().st_size if log.is_file() else 0
            self.start(name)
            try:
                wait()
                return
            except StageError:
                proc = self.procs.get(name)
                said = log.read_bytes()[start:].decode(errors="replace").lower()
                taken = (proc is not None and proc.poll() is not None
                         and "address already in use" in said)
                if not (new_port_if_taken and taken) or attempt + 1 == BIND_ATTEMPTS:
                    raise
            port = free_port()
            cmd = self.commands[name]
            cmd[cmd.index("--port") + 1] = str(port)
            if name == "api":
                self.api_url = f"http://127.0.0.1:{port}"
            else:  # every process started after Redis reads its URL from the environment
                self.redis_url = f"redis://127.0.0.1:{port}/0"
                self.env["TEXELBAKE_REDIS_URL"] = self.redis_url

    def _log_tail(self, name: str, nbytes: int = 600) -> str:
        path = self.workdir / "logs" / f"{name}.log"
        try:
            with open(path, "rb") as f:
                f.seek(max(0, path.stat().st_size - nbytes))
                return f.read().decode(errors="replace").strip()
        except OSError:
            return ""

    def wait_redis(self, timeout: float = 20.0) -> None:
        """Until Redis answers at redis_url: the stack's own redis-server where it started one
        (its process id, so another Redis that took the port first is not mistaken for it)."""
        deadline = time.monotonic() + timeout
        proc = self.procs.get("redis")
        while not (redis_ping(self.redis_url)
                   and (proc is None or redis_pid(self.redis_url) == proc.pid)):
            if proc is not None and proc.poll() is not None:
                raise StageError(
                    f"redis-server exited with {proc.returncode}; see "
                    f"{self.workdir}/logs/redis.log; it ends: {self._log_tail('redis')!r}"
                )
            if time.monotonic() > deadline:
                raise StageError(f"redis at {self.redis_url} did not answer within {timeout} s")
            time.sleep(0.1)

    def _save(self) -> None:
        state = {
            "api_url": self.api_url,
            "redis_url": self.redis_url,
            "pids": self.pids,
            "commands": self.commands,
            "env": {k: v for k, v in self.env.items() if k.startswith("TEXELBAKE_")},
        }
        atomic_write_bytes(self.workdir / "stack.json",
                           json.dumps(state, indent=2, sort_keys=True).encode())


def _wait_gone(pid: int | None, timeout: float) -> None:
    if pid is None:
        return
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:  # reap it if it is our own child (a zombie still answers kill 0)
            if os.waitpid(pid, os.WNOHANG)[0] == pid:
                return
        except ChildProcessError:
            pass
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return
        time.sleep(0.1)
    try:
        os.killpg(pid, signal.SIGKILL)
    except ProcessLookupError:
        pass


#: uvicorn's C HTTP parser and event loop, asked for by name so a missing one fails the start
#: instead of falling back: with h11 and asyncio a status read cost the API ~2x the CPU, and its
#: p99 under 50 pollers and a burst of uploads was 119 ms, with them 16 ms (benchmarks/load.py)
API_SERVER_ARGS = ("--http", "httptools", "--loop", "uvloop")


def worker_command(name: str, queues: tuple[str, ...], concurrency: int = 1) -> list[str]:
    return [
        sys.executable, "-m", "celery", "-A", "workers.celery_app", "worker",
        "-P", "prefork", "-c", str(concurrency), "--prefetch-multiplier", "1",
        "-Q", ",".join(queues), "-n", f"{name}@%h", "-l", "INFO",
        "--without-gossip", "--without-mingle", "--without-heartbeat",
    ]  # fmt: skip


def stack_up(
    workdir: str | Path,
    *,
    port: int | None = None,
    redis_url: str | None = None,
    database_url: str | None = None,
    artifact_root: str | Path | None = None,
    secret_key: str | None = None,
    tokens: dict[str, str] | None = None,
    workers: dict[str, int] | None = None,
    environment: str = "development",
    extra_env: dict[str, str] | None = None,
    api: bool = True,
    queues: dict[str, tuple[str, ...]] | None = None,
    pin_cpus: dict[str, int] | None = None,
    api_workers: int = 1,
    timeout: float = 60.0,
) -> Stack:
    """Start the stack as local processes and wait until the API is healthy.

    workers : worker process count per queue family (default one each of prep, numeric,
        render); `{}` starts none. Names are `worker-<family>-<i>`.
    redis_url : default `TEXELBAKE_REDIS_URL`, else a redis-server of the stack's own on a free
        port (never one it did not start unless named; `OWN_REDIS`: always so). A local URL
        where nothing answers gets a redis-server of the stack's own there. A port the stack
        chose (the API's too) that another process takes before the server binds it is
        replaced by another (`Stack.start_bound`).
    tokens : bearer token -> tenant (default `TEXELBAKE_TOKENS`, JSON as the server reads it,
        else one fresh token for tenant `dev`; written to stack.json under env
        TEXELBAKE_TOKENS). `secret_key`, `database_url` and `artifact_root` default to their
        `TEXELBAKE_*` variables too.
    queues : queue family -> queues, overriding `QUEUE_FAMILIES` (e.g. a family serving only
        `cpm`, for benchmarks).
    pin_cpus : family -> first CPU: worker i of that family runs on CPU (first + i) % ncpu
        (`taskset`), so one process uses one core even where a library starts a thread per
        core (open3d's ray casting).
    api_workers : uvicorn worker processes of the API.
    Returns the Stack; its `env` is the environment every process got.
    """
    families = dict(QUEUE_FAMILIES) | dict(queues or {})
    workdir = Path(workdir).resolve()
    workdir.mkdir(parents=True, exist_ok=True)
    workers = {"prep": 1, "numeric": 1, "render": 1} if workers is None else dict(workers)
    for fam in workers:
        if fam not in families:
            raise SettingsError(f"unknown queue family {fam!r}; expected one of {sorted(families)}")
    commands: dict[str, list[str]] = {}
    start_redis = False
    tokens, tokens_from = _tokens(tokens)
    if redis_url == OWN_REDIS:
        redis_url = None
    else:
        redis_url = redis_url or os.environ.get("TEXELBAKE_REDIS_URL") or None
    redis_port_chosen = redis_url is None
    secret_key = secret_key or os.environ.get("TEXELBAKE_SECRET_KEY") or None
    database_url = database_url or os.environ.get("TEXELBAKE_DATABASE_URL") or None
    artifact_root = artifact_root or os.environ.get("TEXELBAKE_ARTIFACT_ROOT") or None
    if redis_url is None:  # a Redis of our own: never one another program relies on
        rport = free_port()
        redis_url = f"redis://127.0.0.1:{rport}/0"
        start_redis = True
    elif not redis_ping(redis_url):
        u = urlparse(redis_url)
        if u.hostname not in ("127.0.0.1", "localhost"):
            raise StageError(f"no Redis answers at {redis_url} and it is not local")
        rport = u.port or 6379
        start_redis = True
    if start_redis:
        exe = shutil.which("redis-server") or "/usr/bin/redis-server"
        commands["redis"] = [
            exe, "--port", str(rport), "--bind", "127.0.0.1", "--save", "", "--appendonly", "no",
            "--daemonize", "no", "--dir", str(workdir),
        ]  # fmt: skip
    port_given = port is not None
    port = port or free_port()
    env = dict(os.environ)
    env.update(
        {
            "PYTHONPATH": os.pathsep.join(p for p in (str(_REPO), env.get("PYTHONPATH", "")) if p),
            "TEXELBAKE_ENVIRONMENT": environment,
            "TEXELBAKE_SECRET_KEY": secret_key or secrets.token_hex(16),
            "TEXELBAKE_REDIS_URL": redis_url,
            "TEXELBAKE_ARTIFACT_ROOT": str(Path(artifact_root or workdir / "artifacts").resolve()),
            "TEXELBAKE_TOKENS": json.dumps(tokens),
            "OMP_NUM_THREADS": env.get("OMP_NUM_THREADS", "1"),
        }
    )
    if database_url:
        env["TEXELBAKE_DATABASE_URL"] = database_url
    env.update(extra_env or {})
    commands["api"] = [
        sys.executable, "-m", "uvicorn", "services.main:app", "--host", "127.0.0.1",
        "--port", str(port), "--log-level", "warning", "--workers", str(int(api_workers)),
        *API_SERVER_ARGS,
    ]  # fmt: skip
    ncpu = os.cpu_count() or 1
    for fam, n in sorted(workers.items()):
        for i in range(n):
            name = f"worker-{fam}-{i}"
            commands[name] = worker_command(name, families[fam])
            if pin_cpus and fam in pin_cpus:
                cpu = (pin_cpus[fam] + i) % ncpu
                commands[name] = [shutil.which("taskset") or "taskset", "-c", str(cpu)] + commands[
                    name
                ]
    stack = Stack(workdir, f"http://127.0.0.1:{port}", redis_url, env, commands,
                  tokens_from=tokens_from)
    try:
        if start_redis:
            stack.start_bound("redis", stack.wait_redis, new_port_if_taken=redis_port_chosen)
        if api:
            stack.start_bound("api", lambda: stack.wait_healthy(timeout),
                              new_port_if_taken=not port_given)
        for name in commands:
            if name.startswith("worker-"):
                stack.start(name)
    except BaseException:
        stack_down(workdir)
        raise
    return stack


def _tokens(tokens: dict[str, str] | None) -> tuple[dict[str, str], str]:
    """The stack's bearer tokens and where they came from: the argument, `TEXELBAKE_TOKENS`
    (a JSON object token -> tenant, as `farm.config.Settings` reads it) or a new one."""
    if tokens is not None:
        return dict(tokens), "argument"
    raw = os.environ.get("TEXELBAKE_TOKENS", "").strip()
    if not raw:
        return {secrets.token_urlsafe(16): "dev"}, "new"
    try:
        parsed = json.loads(raw)
    except ValueError as exc:
        raise SettingsError(f"TEXELBAKE_TOKENS: expected a JSON object token -> tenant, got "
                            f"invalid JSON ({exc})") from exc
    if not isinstance(parsed, dict) or not parsed or not all(
            isinstance(k, str) and k and isinstance(v, str) and v for k, v in parsed.items()):
        raise SettingsError("TEXELBAKE_TOKENS: expected a non-empty JSON object of token -> "
                            "tenant strings")
    return parsed, "TEXELBAKE_TOKENS"


def stack_down(workdir: str | Path, timeout: float = 20.0) -> list[str]:
    """Stop the processes recorded in `<workdir>/stack.json` (workers, API, then Redis).
    Returns the names stopped."""
    path = Path(workdir) / "stack.json"
    if not path.is_file():
        return []
    state = json.loads(path.read_text())
    pids: dict[str, int] = state.get("pids", {})
    order = sorted(pids, key=lambda n: (n == "redis", n == "api", n))
    for name in order:
        try:
            os.killpg(pids[name], signal.SIGTERM)
        except ProcessLookupError:
            pass
    for name in order:
        _wait_gone(pids[name], timeout)
    state["pids"] = {}
    path.write_text(json.dumps(state, indent=2, sort_keys=True))
    return order
