"""Uploads are hostile until proven otherwise: size caps, safe unpacking, the pxr check.

Flow: stream to a staging file under `<root>/tmp` (size cap, SHA-256 while reading) -> a
checker forked from the warm check server (`services.checkserver`, under CPU and address-space
rlimits) unpacks a `.zip`/`.usdz` into the staging bundle (`services.archive`: every member
checked, inflated bytes counted) and runs `services.validate` -> one atomic rename into
`<root>/assets/<sha256>/`. This process never inflates or parses an upload's bytes. Any
rejection deletes the staging folder: nothing is stored for a rejected upload.
"""
from __future__ import annotations

import contextlib
import hashlib
import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path

from farm import storage
from schemas.common import ErrorCode
from services import archive
from texelbake.io.atomic import replace

KINDS = {".usda": "usda", ".usdc": "usdc", ".usd": "usdc", ".usdz": "usdz", ".zip": "zip"}
LAYER_SUFFIXES = archive.LAYER_SUFFIXES
_SAFE = re.compile(r"[^A-Za-z0-9._-]+")

# stable `detail` prefixes (asserted by the tests); the archive's own come from the checker
UNSUPPORTED = "unsupported file type"
TOO_LARGE = "upload exceeds"
VALIDATE_FAILED = "asset could not be checked"
BOMB_SIZE, BOMB_RATIO, LYING = archive.BOMB_SIZE, archive.BOMB_RATIO, archive.LYING
TOO_MANY, BAD_ZIP, BAD_MEMBER = archive.TOO_MANY, archive.BAD_ZIP, archive.BAD_MEMBER
LINK_MEMBER, NO_ROOT = archive.LINK_MEMBER, archive.NO_ROOT


#: `detail` prefix -> the stable `code` of the error body
CODES: dict[str, ErrorCode] = {
    UNSUPPORTED: ErrorCode.UNSUPPORTED_FILE_TYPE,
    TOO_LARGE: ErrorCode.UPLOAD_TOO_LARGE,
    BOMB_SIZE: ErrorCode.BUNDLE_TOO_LARGE,
    BOMB_RATIO: ErrorCode.COMPRESSION_RATIO,
    LYING: ErrorCode.MEMBER_SIZE_MISMATCH,
    TOO_MANY: ErrorCode.TOO_MANY_MEMBERS,
    BAD_ZIP: ErrorCode.BAD_ZIP,
    BAD_MEMBER: ErrorCode.BAD_MEMBER_PATH,
    LINK_MEMBER: ErrorCode.LINK_MEMBER,
    NO_ROOT: ErrorCode.NO_ROOT_LAYER,
    archive.NAME_TOO_LONG: ErrorCode.BAD_MEMBER_PATH,
    archive.FILE_AND_FOLDER: ErrorCode.BAD_MEMBER_PATH,
    archive.ENCRYPTED: ErrorCode.BAD_ZIP,
    archive.UNSUPPORTED_ENTRY: ErrorCode.BAD_ZIP,
    VALIDATE_FAILED: ErrorCode.ASSET_CHECK_FAILED,
}


class UploadRejected(Exception):
    """A 4xx for the client; `detail` names the offending path. `code` follows from the
    detail's prefix; the pxr checker's own findings are `invalid_asset`."""

    def __init__(self, status: int, detail: str):
        super().__init__(detail)
        self.status = status
        self.detail = detail
        self.code = next(
            (c for prefix, c in CODES.items() if detail.startswith(prefix)),
            ErrorCode.INVALID_ASSET,
        )


@dataclass(frozen=True)
class Staged:
    """An upload that passed every check, staged under `<root>/tmp/<name>/`."""

    sha256: str
    kind: str
    filename: str
    root_layer: str
    size_bytes: int
    n_files: int
    staging: Path  # holds bundle/ and meta.json


def kind_of(filename: str) -> str:
    suffix = Path(filename or "").suffix.lower()
    if suffix not in KINDS:
        raise UploadRejected(
            415,
            f"{UNSUPPORTED}: {filename!r}; expected one of .usda, .usdc, .usd, .usdz, .zip",
        )
    return KINDS[suffix]


def safe_name(filename: str, kind: str) -> str:
    stem = _SAFE.sub("_", Path(filename).stem).strip("._") or "asset"
    return f"{stem[:100]}{Path(filename).suffix.lower()}"


def stream_to_file(chunks, dest: Path, max_bytes: int, filename: str) -> tuple[str, int]:  # noqa: ANN001
    """Write an iterable of byte chunks to `dest`, hashing; 413 past `max_bytes`."""
    h = hashlib.sha256()
    n = 0
    with open(dest, "wb") as f:
        for block in chunks:
            n += len(block)
            if n > max_bytes:
                raise UploadRejected(413, f"{TOO_LARGE} {max_bytes} bytes: {filename}")
            h.update(block)
            f.write(block)
    return h.hexdigest(), n


#: checks running at once per API process (`Settings.validate_concurrency`): 20 concurrent
#: uploads used to start 20 pxr children on a 2-core machine, starving the event loop
_checks: dict[int, threading.BoundedSemaphore] = {}
_checks_lock = threading.Lock()
#: the checker's niceness: status reads and the ledger come before an upload's pxr check
VALIDATE_NICE = 10


def _check_slots(n: int) -> threading.BoundedSemaphore:
    with _checks_lock:
        return _checks.setdefault(n, threading.BoundedSemaphore(n))


#: address space one check may map above the warm checker's own (`Settings.check_memory_bytes`
#: overrides it): a corrupted crate layer or a bomb fails the check, not the machine
CHECK_MEMORY = 2 << 30


def run_validator(
    bundle: Path, root_rel: str, timeout: float, concurrency: int | None = None
) -> list[tuple[str, str]]:
    """The pxr check of an unpacked bundle by a forked checker: its problems, [] if none."""
    req = {"staging": str(bundle.parent), "bundle": str(bundle), "kind": "layer",
           "root": root_rel, "filename": root_rel}  # fmt: skip
    return run_check(req, timeout, concurrency)["problems"]


def run_check(req: dict, timeout: float, concurrency: int | None = None,
              memory: int = CHECK_MEMORY) -> dict:  # fmt: skip
    """One check (`services.checkserver.check_upload`) by a checker forked from the warm
    server (pxr stays out of the API), at most `concurrency` (default: the CPU count) at once,
    at a lower CPU priority, under a CPU rlimit of `timeout` and `memory` bytes of address
    space. Returns `{"files", "root", "problems"}`; raises UploadRejected."""
    req = {**req, "cpu": int(timeout), "memory": int(memory)}
    with _check_slots(concurrency or os.cpu_count() or 1):
        out = _run_checker(req, timeout)
    if "rejected" in out:
        status, detail = out["rejected"]
        raise UploadRejected(int(status), str(detail))
    out["problems"] = [(str(a), str(b)) for a, b in out["problems"]]
    return out


class _CheckServer:
    """The API process's `services.checkserver` (pxr imported once, nice 10): started on the
    first check, restarted when it has died."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.proc: subprocess.Popen | None = None
        self.path = ""

    def socket_path(self) -> str:
        with self.lock:
            if self.proc is None or self.proc.poll() is not None:
                self.path = os.path.join(tempfile.mkdtemp(prefix="texelbake-check-"), "sock")
                env = dict(os.environ)
                env["PYTHONPATH"] = os.pathsep.join(
                    [str(Path(__file__).resolve().parents[1]), env.get("PYTHONPATH", "")]
                )
                env.update(OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")  # fork-safe
                self.proc = subprocess.Popen(
                    [sys.executable, "-m", "services.checkserver", self.path],
                    stdin=subprocess.PIPE, stdout=subprocess.PIPE, env=env,
                )  # fmt: skip
                assert self.proc.stdout is not None
                if self.proc.stdout.readline().strip() != b"ready":
                    self.proc.kill()
                    self.proc.wait()
                    raise UploadRejected(422, f"{VALIDATE_FAILED}: the checker did not start")
            return self.path


_server = _CheckServer()


def _run_checker(req: dict, timeout: float) -> dict:
    """Send `req` to a checker forked from the warm server; killed past `timeout` + 5 s."""
    shown = req.get("filename", "")
    for attempt in range(2):
        path = _server.socket_path()
        conn = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            conn.connect(path)
            break
        except OSError:  # the server died since: start a new one, once
            conn.close()
            if attempt:
                raise UploadRejected(422, f"{VALIDATE_FAILED}: {shown} (no checker)") from None
    deadline = time.monotonic() + timeout + 5
    pid = None
    with conn, conn.makefile("rwb") as f:
        f.write(json.dumps(req).encode() + b"\n")
        f.flush()
        try:
            conn.settimeout(max(0.1, deadline - time.monotonic()))
            pid = int(f.readline() or 0) or None
            conn.settimeout(max(0.1, deadline - time.monotonic()))
            raw = f.readline()
        except (TimeoutError, OSError, ValueError):
            if pid:
                with contextlib.suppress(OSError):
                    os.kill(pid, signal.SIGKILL)
            raise UploadRejected(422, f"{VALIDATE_FAILED}: {shown} (timed out)") from None
    out = None
    try:
        out = json.loads(raw.decode())
        if "rejected" in out or isinstance(out["problems"], list):
            return out
    except (ValueError, KeyError, TypeError):
        pass
    why = out.get("error", "") if isinstance(out, dict) else ""
    why = why or "the checker ended: out of memory or CPU time, or a crash"
    raise UploadRejected(422, f"{VALIDATE_FAILED}: {shown} ({why})")


def stage_upload(chunks, filename: str, root: Path, settings) -> Staged:  # noqa: ANN001
    """Receive an upload and have a checker unpack and check it; on any rejection nothing is
    left on disk. This process only streams the bytes to a file: inflating and parsing them
    happen in the checker, under its memory and CPU limits."""
    kind = kind_of(filename)
    staging = storage.tmp_dir(root) / f"up-{os.urandom(8).hex()}"
    staging.mkdir()
    try:
        raw = staging / "upload.bin"
        sha, size = stream_to_file(chunks, raw, settings.max_upload_bytes, filename)
        bundle = staging / "bundle"
        bundle.mkdir()
        req = {"staging": str(staging), "bundle": str(bundle), "kind": kind,
               "filename": filename, "max_unpacked": settings.max_unpacked_bytes,
               "max_ratio": settings.max_zip_ratio, "max_members": settings.max_zip_members}
        if kind not in ("zip", "usdz"):
            req["root"] = safe_name(filename, kind)
            replace(raw, bundle / req["root"], mode=None)
        out = run_check(req, settings.validate_timeout,
                        getattr(settings, "validate_concurrency", None),
                        getattr(settings, "check_memory_bytes", CHECK_MEMORY))  # fmt: skip
        root_rel, files = str(out["root"]), list(out["files"])
        problems = out["problems"]
        if problems:
            shown = "; ".join(f"{reason}: {path}" for path, reason in problems[:5])
            more = f" (+{len(problems) - 5} more)" if len(problems) > 5 else ""
            raise UploadRejected(422, shown + more)
        meta = {"root_layer": root_rel, "kind": kind, "n_files": len(files)}
        (staging / "meta.json").write_text(json.dumps(meta, sort_keys=True))
        return Staged(sha, kind, filename, root_rel, size, len(files), staging)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise


def commit_staged(staged: Staged, root: Path) -> Path:
    """Atomically move the staged bundle to `<root>/assets/<sha>/`; if another upload of the
    same bytes won the race, keep theirs. Returns the asset folder."""
    final = storage.assets_dir(root) / staged.sha256
    final.parent.mkdir(parents=True, exist_ok=True)
    try:
        os.rename(staged.staging, final)
    except OSError:
        shutil.rmtree(staged.staging, ignore_errors=True)
        if not (final / "meta.json").is_file():
            raise
    return final


def read_meta(asset_folder: Path) -> dict:
    return json.loads((asset_folder / "meta.json").read_text())
