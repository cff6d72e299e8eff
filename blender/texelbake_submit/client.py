"""The texelbake API as the Blender add-on speaks it: standard library only, no `bpy`.

Blender guarantees neither `requests` nor `httpx`, so HTTP is `urllib.request` (multipart
upload encoded here). Everything the add-on does off Blender's main thread lives here:
`Submission` runs upload -> job -> polling -> download -> unpack in one background thread and
publishes a snapshot the add-on's timer copies into the panel. The baked result is a zip of a
`<stem>_baked.usda` root with a `LOD` variant set; Blender's USD importer has no variant picker
and Blender's Python has no `pxr`, so `write_lod_layer` writes a small text layer that sublayers
the root and selects one LOD, which the importer then reads (invisible prims skipped).

Errors from the server are `ApiError(status, code, detail)`: `str(err)` starts with the
server's own `detail` words.
"""

from __future__ import annotations

import io
import json
import os
import re
import threading
import time
import urllib.error
import urllib.request
import uuid
import zipfile
from pathlib import Path
from typing import Any

API = "/api/v1"
TERMINAL = ("succeeded", "failed", "cancelled")
#: a fixed timestamp for every zip member: the same export uploads the same bytes (same asset)
ZIP_DATE = (1980, 1, 1, 0, 0, 0)


class ApiError(Exception):
    """An error answer of the server (`ErrorPublic`: `detail` + `code`), or a transport
    failure (`status` 0, `code` "unreachable")."""

    def __init__(self, status: int, code: str, detail: Any, what: str = ""):
        self.status, self.code, self.detail, self.what = status, code, detail, what
        super().__init__(str(self))

    def __str__(self) -> str:
        where = f" ({self.what}: HTTP {self.status}, {self.code})" if self.status else (
            f" ({self.what})" if self.what else "")
        return f"{detail_text(self.detail)}{where}"


def detail_text(detail: Any) -> str:
    """The server's `detail` as one line: a string as is; a validation error list as
    `field: message; ...` (FastAPI's `loc` without the leading `body`)."""
    if isinstance(detail, str):
        return detail
    if isinstance(detail, list):
        parts = []
        for item in detail:
            if isinstance(item, dict):
                loc = [str(p) for p in item.get("loc", []) if p != "body"]
                parts.append(f"{'.'.join(loc)}: {item.get('msg', '')}" if loc
                             else str(item.get("msg", "")))
            else:
                parts.append(str(item))
        return "; ".join(parts)
    return json.dumps(detail)


def multipart(field: str, filename: str, data: bytes) -> tuple[bytes, str]:
    """(body, content type) of a multipart/form-data request with one file field."""
    boundary = f"texelbake-{uuid.uuid4().hex}"
    safe_name = filename.replace('"', "_").replace("\r", "_").replace("\n", "_")
    head = (
        f"--{boundary}\r\n"
        f'Content-Disposition: form-data; name="{field}"; filename="{safe_name}"\r\n'
        "Content-Type: application/octet-stream\r\n\r\n"
    ).encode()
    return head + data + f"\r\n--{boundary}--\r\n".encode(), f"multipart/form-data; boundary={boundary}"


class Client:
    """Bearer-token calls to one texelbake server (`server` is its base URL, e.g.
    `http://127.0.0.1:8000`)."""

    def __init__(self, server: str, token: str, timeout: float = 120.0):
        if not server.startswith(("http://", "https://")):
            raise ApiError(0, "bad_server_url",
                           f"server URL {server!r} must start with http:// or https://",
                           "preferences")
        self.server, self.token, self.timeout = server.rstrip("/"), token, timeout

    def request(self, method: str, path: str, *, body: bytes | None = None,
                content_type: str | None = None, what: str = "") -> bytes:
        headers = {"Authorization": f"Bearer {self.token}", "Accept": "application/json"}
        if content_type:
            headers["Content-Type"] = content_type
        req = urllib.request.Request(self.server + API + path, data=body, headers=headers,
                                     method=method)
        try:
            with urllib.request.urlopen(req, timeout=self.timeout) as r:  # noqa: S310 - http(s) only
                return r.read()
        except urllib.error.HTTPError as e:
            raw = e.read()
            try:
                err = json.loads(raw)
                detail, code = err.get("detail", raw.decode(errors="replace")), err.get(
                    "code", "http_error")
            except (ValueError, AttributeError):
                detail, code = raw.decode(errors="replace")[:500] or e.reason, "http_error"
            raise ApiError(e.code, str(code), detail, what or f"{method} {path}") from None
        except (urllib.error.URLError, OSError) as e:
            reason = getattr(e, "reason", e)
            raise ApiError(0, "unreachable", f"cannot reach {self.server}: {reason}",
                           what or f"{method} {path}") from None

    def json(self, method: str, path: str, payload: Any = None, what: str = "") -> Any:
        body = None if payload is None else json.dumps(payload).encode()
        raw = self.request(method, path, body=body,
                           content_type="application/json" if body is not None else None,
                           what=what)
        return json.loads(raw)

    def upload(self, filename: str, data: bytes) -> dict[str, Any]:
        """POST /assets: the asset record (`id`, `root_layer`, ...)."""
        body, ctype = multipart("file", filename, data)
        return json.loads(self.request("POST", "/assets", body=body, content_type=ctype,
                                       what=f"upload {filename}"))

    def create_job(self, asset_id: str, settings: dict[str, Any]) -> dict[str, Any]:
        return self.json("POST", "/jobs", {"asset_id": asset_id, "settings": settings},
                         what="create job")

    def job(self, job_id: str) -> dict[str, Any]:
        return self.json("GET", f"/jobs/{job_id}", what="job status")

    def cancel(self, job_id: str) -> dict[str, Any]:
        return self.json("DELETE", f"/jobs/{job_id}", what="cancel job")

    def result(self, job_id: str) -> bytes:
        return self.request("GET", f"/jobs/{job_id}/result", what="download result")


def zip_folder(folder: str | Path) -> bytes:
    """Every file under `folder` (sorted, fixed timestamps) as zip bytes."""
    folder = Path(folder)
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf:
        for p in sorted(q for q in folder.rglob("*") if q.is_file()):
            info = zipfile.ZipInfo(p.relative_to(folder).as_posix(), ZIP_DATE)
            info.compress_type = zipfile.ZIP_DEFLATED
            info.external_attr = 0o644 << 16
            zf.writestr(info, p.read_bytes())
    return buf.getvalue()


def safe_extract(data: bytes, out_dir: str | Path) -> list[Path]:
    """Unpack a result zip into `out_dir`, refusing members that would land outside it."""
    out = Path(out_dir).resolve()
    out.mkdir(parents=True, exist_ok=True)
    written = []
    with zipfile.ZipFile(io.BytesIO(data)) as zf:
        for info in zf.infolist():
            if info.is_dir():
                continue
            target = (out / info.filename).resolve()
            if out not in target.parents:
                raise ApiError(0, "bad_result", f"result member escapes the folder: "
                               f"{info.filename}", "unpack result")
            target.parent.mkdir(parents=True, exist_ok=True)
            tmp = target.with_name(target.name + ".part")
            tmp.write_bytes(zf.read(info))
            os.replace(tmp, target)
            written.append(target)
    return written


def baked_root(out_dir: str | Path) -> Path:
    """The `<stem>_baked.usda` root layer at the top of an unpacked result."""
    roots = sorted(Path(out_dir).glob("*_baked.usda"))
    if len(roots) != 1:
        raise ApiError(0, "bad_result", f"expected one *_baked.usda in {out_dir}, found "
                       f"{[p.name for p in roots]}", "unpack result")
    return roots[0]


_HEADER_FIELDS = {
    "defaultPrim": re.compile(r'^\s*defaultPrim\s*=\s*"([^"]+)"', re.M),
    "upAxis": re.compile(r'^\s*upAxis\s*=\s*"([^"]+)"', re.M),
    "metersPerUnit": re.compile(r"^\s*metersPerUnit\s*=\s*([0-9.eE+-]+)", re.M),
}
_LOD_VARIANT = re.compile(r'^\s*"(LOD\d+)"\s*\{', re.M)


def read_root(root: str | Path) -> dict[str, Any]:
    """What the importer needs from a baked root (a `.usda` texelbake wrote): `defaultPrim`,
    `upAxis`, `metersPerUnit` and the LOD variant names, sorted by index."""
    text = Path(root).read_text(encoding="utf-8")
    if not text.startswith("#usda"):
        raise ApiError(0, "bad_result", f"{root} is not a .usda text layer", "read result")
    head_end = text.find("\n)\n")
    head = text[: head_end if head_end > 0 else len(text)]
    info: dict[str, Any] = {}
    for key, pat in _HEADER_FIELDS.items():
        m = pat.search(head)
        info[key] = m.group(1) if m else None
    if info["defaultPrim"] is None:
        raise ApiError(0, "bad_result", f"{root} has no defaultPrim", "read result")
    info["metersPerUnit"] = float(info["metersPerUnit"] or 0.01)
    info["upAxis"] = info["upAxis"] or "Y"
    set_at = text.find('variantSet "LOD"')
    lods = sorted(set(_LOD_VARIANT.findall(text[set_at:]))) if set_at >= 0 else []
    info["lods"] = sorted(lods, key=lambda n: int(n[3:]))
    if not info["lods"]:
        raise ApiError(0, "bad_result", f"{root} has no LOD variant set", "read result")
    return info


def write_lod_layer(root: str | Path, lod: int, dest: str | Path | None = None) -> Path:
    """A layer beside `root` that sublayers it and selects variant `LOD<lod>` on its default
    prim, with the root's stage metadata (a sublayer's is not used). Returns its path."""
    root = Path(root)
    info = read_root(root)
    name = f"LOD{int(lod)}"
    if name not in info["lods"]:
        raise ApiError(0, "bad_lod", f"LOD {lod} is not one of the result's LODs "
                       f"({', '.join(info['lods'])})", "import")
    dest = Path(dest) if dest else root.with_name(f"{root.stem}_{name}.usda")
    rel = os.path.relpath(root, dest.parent).replace(os.sep, "/")
    text = (
        "#usda 1.0\n(\n"
        f'    defaultPrim = "{info["defaultPrim"]}"\n'
        f"    metersPerUnit = {info['metersPerUnit']!r}\n"
        f'    subLayers = [\n        @./{rel}@\n    ]\n'
        f'    upAxis = "{info["upAxis"]}"\n)\n\n'
        f'over "{info["defaultPrim"]}" (\n    variants = {{\n'
        f'        string LOD = "{name}"\n    }}\n)\n{{\n}}\n'
    )
    dest.write_text(text, encoding="utf-8")
    return dest


class Submission:
    """One submit, run in a background thread: upload `data` as `filename`, create a job with
    `settings`, poll it every `poll_seconds`, and when it succeeds download and unpack the
    result into `out_dir`. `snapshot()` is safe to call from any thread."""

    def __init__(self, client: Client, filename: str, data: bytes, settings: dict[str, Any],
                 out_dir: str | Path, poll_seconds: float = 1.0):
        self.client, self.filename, self.data = client, filename, data
        self.settings, self.out_dir, self.poll_seconds = settings, Path(out_dir), poll_seconds
        self._lock = threading.Lock()
        self._cancel = threading.Event()
        self._detached = threading.Event()
        self._state: dict[str, Any] = {
            "phase": "uploading", "progress": 0.0, "message": f"uploading {filename}",
            "job_id": "", "asset_id": "", "root": "", "lods": [], "error": "",
            "error_code": "", "started": time.time(),
        }
        self._thread = threading.Thread(target=self._run, name="texelbake-submit", daemon=True)

    def start(self) -> Submission:
        self._thread.start()
        return self

    def snapshot(self) -> dict[str, Any]:
        with self._lock:
            return dict(self._state)

    @property
    def finished(self) -> bool:
        return self.snapshot()["phase"] in ("done", "failed", "cancelled", "error")

    def cancel(self) -> None:
        """Ask the thread to cancel the job on the server (at its next poll)."""
        self._cancel.set()

    def detach(self) -> None:
        """Stop following the job (it keeps running on the farm): the thread ends at its next
        poll without cancelling or downloading."""
        self._detached.set()

    def join(self, timeout: float | None = None) -> None:
        self._thread.join(timeout)

    def _set(self, **kw: Any) -> None:
        with self._lock:
            self._state.update(kw)

    def _run(self) -> None:
        try:
            self._steps()
        except ApiError as e:
            self._set(phase="error", error=str(e), error_code=e.code, message=str(e))
        except Exception as e:  # noqa: BLE001 - shown in the panel, not lost in a thread
            self._set(phase="error", error=f"{type(e).__name__}: {e}", error_code="client",
                      message=f"{type(e).__name__}: {e}")

    def _steps(self) -> None:
        asset = self.client.upload(self.filename, self.data)
        self._set(asset_id=asset["id"], message=f"uploaded {asset.get('root_layer', '')}")
        job = self.client.create_job(asset["id"], self.settings)
        job_id = job["id"]
        self._set(job_id=job_id, phase=job["state"], message=f"job {job_id[:8]} {job['state']}")
        while job["state"] not in TERMINAL:
            if self._cancel.wait(self.poll_seconds):
                job = self.client.cancel(job_id)
                break
            if self._detached.is_set():
                self._set(phase="cancelled", error=f"job {job_id[:8]} no longer followed",
                          error_code="detached", message=f"job {job_id[:8]} no longer followed")
                return
            job = self.client.job(job_id)
            running = [s["name"] for s in job.get("stages", [])
                       if s.get("state") in ("queued", "running")]
            self._set(phase=job["state"], progress=float(job.get("progress", 0.0)),
                      message=f"job {job_id[:8]} {job['state']}"
                              + (f": {', '.join(running)}" if running else ""))
        if job["state"] != "succeeded":
            why = job.get("error") or job["state"]
            self._set(phase="failed" if job["state"] == "failed" else "cancelled",
                      error=f"job {job_id[:8]} {job['state']}: {why}", error_code=job["state"],
                      message=f"job {job_id[:8]} {job['state']}: {why}")
            return
        self._set(phase="downloading", progress=1.0, message=f"downloading job {job_id[:8]}")
        dest = self.out_dir / job_id
        safe_extract(self.client.result(job_id), dest)
        root = baked_root(dest)
        lods = read_root(root)["lods"]
        quality = job.get("outcome") or "completed"
        self._set(phase="done", root=str(root), lods=lods,
                  message=f"job {job_id[:8]} {quality}: {len(lods)} LODs ({', '.join(lods)})")
