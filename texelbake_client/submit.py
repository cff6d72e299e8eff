"""`texelbake submit FILE --server URL`: upload, follow progress, download the baked bundle
(`texelbake submit --manifest FILE`, many assets as one batch: `texelbake_client.batch`).

Uses only httpx and the standard library (no server imports). A layer file that uses other
files (textures, sublayers) is sent as a `.zip` bundle of exactly the files it uses (found with
`texelbake.asset.check_asset_paths`); a folder is zipped whole; `.usdz` and `.zip` go as they are.
"""

from __future__ import annotations

import io
import json
import os
import sys
import time
import zipfile
from collections.abc import Callable, Iterator
from pathlib import Path, PurePosixPath
from typing import Any

import httpx

from texelbake.errors import AssetError, StageError
from texelbake.io.archive import zip_bytes
from texelbake.io.atomic import atomic_write_bytes

API = "/api/v1"
TERMINAL = ("succeeded", "failed", "cancelled")


def _zip_files(files: list[tuple[str, Path]]) -> bytes:
    return zip_bytes((arc, path.read_bytes()) for arc, path in files)


def package(path: str | Path) -> tuple[str, bytes]:
    """(upload name, bytes) for a layer file, a folder, a `.usdz` or a `.zip`."""
    path = Path(path)
    if path.is_dir():
        files = [(p.relative_to(path).as_posix(), p) for p in path.rglob("*") if p.is_file()]
        return f"{path.name}.zip", _zip_files(files)
    if not path.is_file():
        raise AssetError("file to submit does not exist", path=str(path))
    if path.suffix.lower() in (".usdz", ".zip"):
        return path.name, path.read_bytes()
    try:
        from texelbake.asset import check_asset_paths
    except ImportError:  # pxr missing on this machine: send the layer alone
        return path.name, path.read_bytes()
    used = [Path(p) for p in check_asset_paths(path)]
    base = path.resolve().parent
    if len(used) <= 1:
        return path.name, path.read_bytes()
    files = []
    for p in used:
        rel = Path(os.path.relpath(p, base))
        if rel.parts and rel.parts[0] == "..":
            raise AssetError("asset uses a file outside its folder", path=str(p))
        files.append((PurePosixPath(*rel.parts).as_posix(), p))
    return f"{path.stem}.zip", _zip_files(files)


class ProgressBar:
    """A one-line text progress bar on stderr (stdlib only)."""

    def __init__(self, enabled: bool, width: int = 30):
        self.enabled, self.width, self.last = enabled, width, ""

    def show(self, fraction: float, label: str) -> None:
        if not self.enabled:
            return
        n = int(round(max(0.0, min(1.0, fraction)) * self.width))
        line = f"\r[{'#' * n}{'.' * (self.width - n)}] {fraction * 100:5.1f}% {label:<40}"
        if line != self.last:
            sys.stderr.write(line)
            sys.stderr.flush()
            self.last = line

    def close(self) -> None:
        if self.enabled and self.last:
            sys.stderr.write("\n")


def iter_events(
    client: httpx.Client, job_id: str, *, retry: float = 1.0, deadline: float | None = None
) -> Iterator[dict[str, Any]]:
    """Server-sent events of a job, reconnecting (with Last-Event-ID) until the stream ends
    after the job's terminal event."""
    last = None
    final = False
    ev_kind = ev_state = None
    while True:
        headers: dict[str, str] = {"Last-Event-ID": str(last)} if last is not None else {}
        try:
            with client.stream(
                "GET",
                f"{API}/jobs/{job_id}/events",
                headers=headers,
                timeout=httpx.Timeout(10.0, read=60.0),
            ) as r:
                if r.status_code != 200:
                    raise StageError(f"events of job {job_id}: HTTP {r.status_code} {r.read()!r}")
                data: list[str] = []
                for line in r.iter_lines():
                    if line.startswith("data: "):
                        data.append(line[6:])
                    elif line == "" and data:
                        ev = json.loads("\n".join(data))
                        data = []
                        last = ev["seq"]
                        ev_kind, ev_state = ev["kind"], ev["data"].get("state")
                        yield ev
            if final or (ev_kind == "job" and ev_state in TERMINAL):
                return  # drained, or the stream ended on the job's terminal event
            r = client.get(f"{API}/jobs/{job_id}")
            if r.status_code != 200:
                return  # the job is gone: no more events
            # the server closed a long stream: reconnect. A job that finished since is read
            # once more, for the events its last transaction wrote after this stream's read.
            final = r.json()["state"] in TERMINAL
        except (httpx.TransportError, httpx.RemoteProtocolError):
            if deadline is not None and time.monotonic() > deadline:
                raise
            time.sleep(retry)


def settled_status(client: httpx.Client, job_id: str, deadline: float, *,
                   lag: float = 10.0, interval: float = 0.05) -> dict[str, Any]:
    """The job's status once it is terminal, read after its event stream ended. A status
    read may lag the stream: an API process answers it from a version cached for
    `status_cache_seconds` (farm.config), so right after the terminal event it can still say
    "running". A non-terminal read is repeated every `interval` seconds for up to `lag`
    seconds (and not past `deadline`); the last read is returned whatever it says."""
    end = min(deadline, time.monotonic() + lag)
    while True:  # a loop over status reads, a few at most
        job = check_response(client.get(f"{API}/jobs/{job_id}"), "job status").json()
        if job["state"] in TERMINAL or time.monotonic() >= end:
            return job
        time.sleep(interval)


def check_response(r: httpx.Response, what: str) -> httpx.Response:
    if r.status_code >= 400:
        try:
            detail = r.json().get("detail")
        except ValueError:
            detail = r.text[:500]
        raise StageError(f"{what}: HTTP {r.status_code}: {detail}")
    return r


def safe_extract(data: bytes, out_dir: Path) -> list[Path]:
    """Unpack the result zip into `out_dir`, refusing members that would land outside it."""
    out_dir = Path(out_dir).resolve()
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    with zipfile.ZipFile(io.BytesIO(data)) as zf:
        for info in zf.infolist():
            target = (out_dir / info.filename).resolve()
            if out_dir not in target.parents or info.is_dir():
                if info.is_dir():
                    continue
                raise StageError(f"result member escapes the output folder: {info.filename}")
            atomic_write_bytes(target, zf.read(info))
            written.append(target)
    return written


def upload(client: httpx.Client, path: str | Path, what: str = "") -> dict[str, Any]:
    """`package` the file and `POST /assets` it; returns the asset (the server keeps one
    copy per content hash: the same bytes give the same asset)."""
    name, data = package(path)
    label = f"{what}: upload {name}" if what else f"upload {name}"
    return check_response(client.post(f"{API}/assets", files={"file": (name, data)}), label).json()


def submit(
    file: str | Path,
    server: str,
    token: str,
    out_dir: str | Path,
    settings: dict[str, Any] | None = None,
    *,
    progress: bool = True,
    timeout: float = 24 * 3600.0,
    on_event: Callable[[dict[str, Any]], None] | None = None,
    transport: httpx.BaseTransport | None = None,
) -> Path:
    """Upload `file`, create a job with `settings`, follow its events with a progress bar,
    download and unpack the result into `out_dir`. Returns the baked root layer path.

    Raises StageError when the server refuses the upload or the job fails or is cancelled
    (the message carries the server's `detail` / the job's error).
    """
    headers = {"Authorization": f"Bearer {token}"}
    deadline = time.monotonic() + timeout
    bar = ProgressBar(progress)
    with httpx.Client(
        base_url=server.rstrip("/"), headers=headers, timeout=120.0, transport=transport
    ) as c:
        asset = upload(c, file)
        job = check_response(
            c.post(f"{API}/jobs", json={"asset_id": asset["id"], "settings": settings or {}}),
            "create job",
        ).json()
        job_id = job["id"]
        try:
            for ev in iter_events(c, job_id, deadline=deadline):
                if on_event is not None:
                    on_event(ev)
                if ev["kind"] in ("stage", "job") or ev["data"].get("state") == "done":
                    job = check_response(c.get(f"{API}/jobs/{job_id}"), "job status").json()
                    running = [
                        s["name"] for s in job["stages"] if s["state"] in ("queued", "running")
                    ]
                    bar.show(job["progress"], f"{job['state']} {' '.join(running)}")
                if time.monotonic() > deadline:
                    raise StageError(f"job {job_id} did not finish within {timeout} s")
        finally:
            bar.close()
        job = settled_status(c, job_id, deadline)
        if job["state"] != "succeeded":
            raise StageError(f"job {job_id} ended {job['state']}: {job.get('error')}")
        r = check_response(c.get(f"{API}/jobs/{job_id}/result"), "download result")
    files = safe_extract(r.content, Path(out_dir))
    roots = sorted(
        p for p in files if p.name.endswith("_baked.usda") and p.parent == Path(out_dir).resolve()
    )
    if not roots:
        roots = sorted(p for p in files if p.suffix == ".usda")
    if not roots:
        raise StageError(f"the result of job {job_id} holds no .usda root layer")
    return roots[0]
