"""The upload checker's warm fork server: `python -m services.checkserver SOCKET`, started by
the API process on its first upload (`services.uploads`), never imported by it.

It lowers its own CPU priority (`VALIDATE_NICE`, inherited by every checker), imports pxr and
the core's asset check once (~0.6 s of CPU that every upload used to pay in a fresh
interpreter), then serves a Unix socket: per connection it forks one checker, which answers
its pid, runs `services.validate.check_bundle` under its own CPU rlimit and answers
`{"problems": [...]}` (or `{"error": ...}`). A crash, a hang or the rlimit ends only that
checker (the API kills it by pid past the timeout); the server reaps them. It exits when the
API closes its stdin (the API died or stopped).
"""

from __future__ import annotations

import contextlib
import json
import os
import resource
import select
import signal
import socket
import sys
from pathlib import Path

VALIDATE_NICE = 10  # the same as services.uploads.VALIDATE_NICE (asserted by the tests)


def _serve_one(conn: socket.socket) -> None:
    """In the forked checker: read the request, answer pid, check, answer the result."""
    from services.validate import check_bundle

    f = conn.makefile("rwb")
    req = json.loads(f.readline())
    f.write(f"{os.getpid()}\n".encode())
    f.flush()
    cpu = int(req["cpu"])
    resource.setrlimit(resource.RLIMIT_CPU, (cpu, cpu))
    try:
        out = {"problems": [list(p) for p in check_bundle(Path(req["bundle"]), req["root"])]}
    except Exception as exc:  # noqa: BLE001 - reported as a failed check
        out = {"error": f"{type(exc).__name__}: {exc}"[:200]}
    f.write(json.dumps(out).encode() + b"\n")
    f.flush()


def main(argv: list[str]) -> int:
    os.nice(VALIDATE_NICE)
    from pxr import Sdf, Tf, Usd, UsdUtils  # noqa: F401

    import services.validate  # noqa: F401

    try:
        import texelbake.asset  # noqa: F401 - the core's check (services.validate._core_check)
    except ImportError:  # pragma: no cover
        pass
    path = argv[0]
    # a stop of the API's process group (SIGTERM) still removes the socket below
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(0))
    try:
        return _serve(path)
    finally:  # the socket and its private folder (services.uploads made it) go with the server
        with contextlib.suppress(OSError):
            os.unlink(path)
            os.rmdir(os.path.dirname(path))


def _serve(path: str) -> int:
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as srv:
        srv.bind(path)
        srv.listen(64)
        sys.stdout.write("ready\n")
        sys.stdout.flush()
        while True:
            ready, _, _ = select.select([srv, sys.stdin], [], [], 1.0)
            while True:  # reap finished checkers
                try:
                    pid, _ = os.waitpid(-1, os.WNOHANG)
                except ChildProcessError:
                    break
                if pid == 0:
                    break
            if sys.stdin in ready and not sys.stdin.buffer.read1(1 << 10):
                return 0  # the API is gone
            if srv in ready:
                conn, _ = srv.accept()
                if os.fork() == 0:
                    code = 1
                    try:
                        srv.close()
                        _serve_one(conn)
                        code = 0
                    finally:
                        os._exit(code)
                conn.close()


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
