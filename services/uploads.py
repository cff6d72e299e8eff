"""Uploads are hostile until proven otherwise: size caps, safe unpacking, the pxr check.

Flow: stream to a staging file under `<root>/tmp` (size cap, SHA-256 while reading) -> unpack
into a staging bundle (`.zip`/`.usdz`: member names, links, member count, unpacked size and
compression ratio checked before and while extracting) -> `services.validate` in a subprocess
-> one atomic rename into `<root>/assets/<sha256>/`. Any rejection deletes the staging folder:
nothing is stored for a rejected upload.
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
import stat
import subprocess
import sys
import tempfile
import threading
import time
import zipfile
from dataclasses import dataclass
from pathlib import Path, PurePosixPath

from farm import storage
from schemas.common import ErrorCode
from texelbake.io.atomic import replace

KINDS = {".usda": "usda", ".usdc": "usdc", ".usd": "usdc", ".usdz": "usdz", ".zip": "zip"}
LAYER_SUFFIXES = (".usd", ".usda", ".usdc")
_SAFE = re.compile(r"[^A-Za-z0-9._-]+")

# stable `detail` prefixes (asserted by the tests)
UNSUPPORTED = "unsupported file type"
TOO_LARGE = "upload exceeds"
BOMB_SIZE = "bundle unpacks to more than"
BOMB_RATIO = "compression ratio above"
LYING = "bundle member inflates beyond its declared size"
TOO_MANY = "bundle has more than"
BAD_ZIP = "not a valid zip archive"
BAD_MEMBER = "bundle member path is not allowed"
LINK_MEMBER = "bundle member is a link"
NO_ROOT = "bundle has no root layer"
VALIDATE_FAILED = "asset could not be checked"


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


def _check_member(info: zipfile.ZipInfo) -> PurePosixPath:
    name = info.filename
    mode = info.external_attr >> 16
    if stat.S_ISLNK(mode):
        raise UploadRejected(422, f"{LINK_MEMBER}: {name}")
    norm = name.replace("\\", "/")
    p = PurePosixPath(norm)
    if (
        not norm
        or norm.startswith("/")
        or re.match(r"^[A-Za-z]:", norm)
        or any(part in ("..",) for part in p.parts)
        or "\x00" in norm
    ):
        raise UploadRejected(422, f"{BAD_MEMBER}: {name}")
    return p


def unpack_zip(
    src: Path,
    dest: Path,
    *,
    max_unpacked: int,
    max_ratio: float,
    max_members: int,
    display: str | None = None,
) -> list[str]:
    """Extract a zip/usdz into `dest` with every hostile case refused; returns member names in
    archive order (files only)."""
    packed = max(os.path.getsize(src), 1)
    shown = display or src.name
    try:
        zf = zipfile.ZipFile(src)
    except (zipfile.BadZipFile, OSError) as exc:
        raise UploadRejected(422, f"{BAD_ZIP}: {shown} ({exc})") from exc
    with zf:
        infos = zf.infolist()
        if len(infos) > max_members:
            raise UploadRejected(413, f"{TOO_MANY} {max_members} members: {shown}")
        declared = sum(i.file_size for i in infos)
        if declared > max_unpacked:
            raise UploadRejected(413, f"{BOMB_SIZE} {max_unpacked} bytes: {shown}")
        if declared / packed > max_ratio:
            raise UploadRejected(413, f"{BOMB_RATIO} {max_ratio:g}: {shown}")
        seen: set[str] = set()
        files: list[str] = []
        total = 0
        for info in infos:
            p = _check_member(info)
            key = str(p).lower()
            if key in seen:
                raise UploadRejected(422, f"{BAD_MEMBER}: {info.filename} (duplicate)")
            seen.add(key)
            if info.file_size / max(info.compress_size, 1) > max_ratio and info.file_size > 4096:
                raise UploadRejected(413, f"{BOMB_RATIO} {max_ratio:g}: {info.filename}")
            target = dest.joinpath(*p.parts)
            if info.is_dir():
                target.mkdir(parents=True, exist_ok=True)
                continue
            target.parent.mkdir(parents=True, exist_ok=True)
            written = 0
            try:
                with zf.open(info) as fin, open(target, "wb") as fout:
                    while block := fin.read(1 << 20):
                        written += len(block)
                        total += len(block)
                        # the header can lie: count what actually comes out
                        if written > info.file_size:
                            raise UploadRejected(413, f"{LYING}: {info.filename}")
                        if total > max_unpacked:
                            raise UploadRejected(
                                413, f"{BOMB_SIZE} {max_unpacked} bytes: {info.filename}"
                            )
                        fout.write(block)
            except (zipfile.BadZipFile, zlib_error(), NotImplementedError, EOFError) as exc:
                raise UploadRejected(422, f"{BAD_ZIP}: {info.filename} ({exc})") from exc
            files.append(str(p))
    return files


def zlib_error() -> type[Exception]:
    import zlib

    return zlib.error


def _root_of_zip(files: list[str], upload_name: str) -> str:
    top = sorted(f for f in files if "/" not in f and f.lower().endswith(LAYER_SUFFIXES))
    if len(top) == 1:
        return top[0]
    stem = Path(upload_name).stem.lower()
    named = [f for f in top if Path(f).stem.lower() == stem]
    if len(named) == 1:
        return named[0]
    if not top:
        raise UploadRejected(422, f"{NO_ROOT}: no top-level .usd/.usda/.usdc in {upload_name}")
    raise UploadRejected(
        422,
        f"{NO_ROOT}: several top-level layers in {upload_name} ({', '.join(top)}); name the "
        f"root like the zip file",
    )


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


def run_validator(
    bundle: Path, root_rel: str, timeout: float, concurrency: int | None = None
) -> list[tuple[str, str]]:
    """`services.validate` in a child process (pxr stays out of the API), at most
    `concurrency` (default: the CPU count) at once, at a lower CPU priority."""
    with _check_slots(concurrency or os.cpu_count() or 1):
        return _run_validator(bundle, root_rel, timeout)


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


def _run_validator(bundle: Path, root_rel: str, timeout: float) -> list[tuple[str, str]]:
    """One check by a checker forked from the warm server; killed past `timeout` + 5 s."""
    for attempt in range(2):
        path = _server.socket_path()
        conn = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            conn.connect(path)
            break
        except OSError:  # the server died since: start a new one, once
            conn.close()
            if attempt:
                raise UploadRejected(422, f"{VALIDATE_FAILED}: {root_rel} (no checker)") from None
    deadline = time.monotonic() + timeout + 5
    pid = None
    with conn, conn.makefile("rwb") as f:
        req = {"bundle": str(bundle), "root": root_rel, "cpu": int(timeout)}
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
            raise UploadRejected(422, f"{VALIDATE_FAILED}: {root_rel} (timed out)") from None
    out = None
    try:
        out = json.loads(raw.decode())
        return [(str(a), str(b)) for a, b in out["problems"]]
    except (ValueError, KeyError, TypeError) as exc:
        why = out.get("error", "") if isinstance(out, dict) else "the checker died"
        raise UploadRejected(422, f"{VALIDATE_FAILED}: {root_rel} ({why})") from exc


def stage_upload(chunks, filename: str, root: Path, settings) -> Staged:  # noqa: ANN001
    """Receive, unpack and check an upload; on any rejection nothing is left on disk."""
    kind = kind_of(filename)
    staging = storage.tmp_dir(root) / f"up-{os.urandom(8).hex()}"
    staging.mkdir()
    try:
        raw = staging / "upload.bin"
        sha, size = stream_to_file(chunks, raw, settings.max_upload_bytes, filename)
        bundle = staging / "bundle"
        bundle.mkdir()
        if kind in ("zip", "usdz"):
            files = unpack_zip(
                raw,
                bundle,
                max_unpacked=settings.max_unpacked_bytes,
                max_ratio=settings.max_zip_ratio,
                max_members=settings.max_zip_members,
                display=filename,
            )
            if kind == "usdz":  # the first member is the default layer (usdz spec)
                if not files or not files[0].lower().endswith(LAYER_SUFFIXES):
                    raise UploadRejected(
                        422, f"{NO_ROOT}: the first member of {filename} is not a USD layer"
                    )
                root_rel = files[0]
            else:
                root_rel = _root_of_zip(files, filename)
            raw.unlink()
        else:
            root_rel = safe_name(filename, kind)
            replace(raw, bundle / root_rel, mode=None)
            files = [root_rel]
        problems = run_validator(bundle, root_rel, settings.validate_timeout,
                                 getattr(settings, "validate_concurrency", None))
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
