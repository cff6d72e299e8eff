"""The upload checker's warm fork server: `python -m services.checkserver SOCKET`, started by
the API process on its first upload (`services.uploads`), never imported by it.

It lowers its own CPU priority (`VALIDATE_NICE`, inherited by every checker), imports pxr and
the core's asset check once (~0.6 s of CPU that every upload used to pay in a fresh
interpreter), then serves a Unix socket: per connection it forks one checker, which answers
its pid, sets its hard limits (CPU seconds, address space above the server's), unpacks a
zip/usdz (`services.archive`), runs `services.validate.check_bundle` and answers
`{"files", "root", "problems"}`, `{"rejected": [status, detail]}` or `{"error": ...}`. An
upload's bytes are inflated and parsed only here, never in the API process. A crash, a hang
or a limit ends only that checker (the API kills it by pid past the timeout); the server reaps them. It exits when the
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


def _vm_bytes() -> int:
    """This process's virtual memory size (the baseline RLIMIT_AS is counted from)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmSize:"):
            return int(line.split()[1]) * 1024
    return 0


def limit_self(cpu_seconds: int, memory_bytes: int) -> None:
    """The checker's hard limits: CPU seconds, and `memory_bytes` of address space above what
    the warm server already mapped (pxr and the core are imported before the fork)."""
    resource.setrlimit(resource.RLIMIT_CPU, (cpu_seconds, cpu_seconds))
    if memory_bytes > 0:
        cap = _vm_bytes() + memory_bytes
        resource.setrlimit(resource.RLIMIT_AS, (cap, cap))


def check_upload(req: dict) -> dict:
    """Unpack (a zip or usdz) and check one staged upload: `req` names the staging folder
    (holding `upload.bin` for an archive), the bundle folder (holding the root layer, or the
    archive's members once unpacked), the kind, the upload's name and the archive limits. Returns `{"files", "root", "problems"}` or `{"rejected": [status,
    detail]}`; no message holds a server path."""
    from services import archive
    from services.validate import check_bundle

    staging, bundle = Path(req["staging"]), Path(req["bundle"])
    try:
        if req["kind"] in ("zip", "usdz"):
            raw = staging / "upload.bin"
            files = archive.unpack_zip(
                raw, bundle, max_unpacked=int(req["max_unpacked"]),
                max_ratio=float(req["max_ratio"]), max_members=int(req["max_members"]),
                display=req["filename"])  # fmt: skip
            root = archive.root_layer(files, req["filename"], usdz=req["kind"] == "usdz")
            raw.unlink()
        else:
            root = req["root"]
            files = [root]
    except archive.ArchiveRejected as exc:
        return {"rejected": [exc.status, exc.detail]}
    problems = check_bundle(bundle, root)
    return {"files": files, "root": root,
            "problems": [[scrub(a, staging), scrub(b, staging)] for a, b in problems]}


def scrub(text: str, staging: Path) -> str:
    """`text` without the staging folder's absolute path (bundle paths become relative)."""
    for base in {str(staging), os.path.realpath(staging)}:
        text = text.replace(f"{base}/bundle/", "").replace(f"{base}/", "").replace(base, "")
    return text


def _serve_one(conn: socket.socket) -> None:
    """In the forked checker: read the request, answer pid, check, answer the result."""
    f = conn.makefile("rwb")
    req = json.loads(f.readline())
    f.write(f"{os.getpid()}\n".encode())
    f.flush()
    limit_self(int(req["cpu"]), int(req.get("memory", 0)))
    try:
        out = check_upload(req)
    except MemoryError:
        out = {"error": "the check ran out of memory"}
    except Exception as exc:  # noqa: BLE001 - reported as a failed check
        out = {"error": scrub(f"{type(exc).__name__}: {exc}", Path(req["staging"]))[:200]}
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
