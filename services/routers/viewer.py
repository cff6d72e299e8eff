"""`/jobs/{id}/viewer`: what the dashboard's WebGL viewer and texel inspector read of a
finished bake (LOD meshes, texel arrays, a_vis polar grids, BTF maps and direction tables),
extracted once from the baked USD by `services.viewer_data` in a child process (pxr stays out
of the API) into `<job dir>/viewer/`."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

from fastapi import APIRouter, status
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import FileResponse, JSONResponse

from farm import storage
from schemas.common import ErrorCode
from services.deps import CurrentTenant, SessionDep, SettingsDep
from services.errors import ApiError, errors
from services.routers.jobs import BINARY, JOB_404, JOB_409, OCTET, _own_job, _require_done

router = APIRouter(prefix="/jobs", tags=["viewer"])

VIEWER_FILE_NOT_FOUND = "viewer file not found"
VIEWER_FAILED = "the viewer data could not be extracted from the baked USD"
#: seconds the extraction child may take
EXTRACT_TIMEOUT = 300.0
_NAME = re.compile(r"^[a-z0-9_]{1,40}\.(bin|json|png)$")
_TYPES = {".bin": OCTET, ".json": "application/json", ".png": "image/png"}


def viewer_dir(root: Path, job_id: str) -> Path:
    return storage.job_dir(root, job_id) / "viewer"


def ensure_viewer(root: Path, job_id: str) -> Path:
    """The job's viewer folder, extracted by the child on first use."""
    out = viewer_dir(root, job_id)
    if (out / "manifest.json").is_file():
        return out
    roots = sorted(storage.job_out(root, job_id).glob("*_baked.usda"))
    if not roots:
        raise ApiError(
            status.HTTP_404_NOT_FOUND,
            f"{VIEWER_FAILED}: the job's bundle has no *_baked.usda",
            ErrorCode.NOT_FOUND,
        )
    cmd = [sys.executable, "-m", "services.viewer_data", str(roots[0]), str(out)]
    try:
        r = subprocess.run(
            cmd,
            capture_output=True,
            text=True,
            timeout=EXTRACT_TIMEOUT,
            cwd=Path(__file__).parents[2],
        )
        lines = [ln for ln in r.stdout.splitlines() if ln.startswith("{")]
        reply = json.loads(lines[-1]) if lines else {"error": r.stderr[-500:]}
    except (subprocess.TimeoutExpired, ValueError) as exc:
        reply = {"error": repr(exc)}
    if "error" in reply or not (out / "manifest.json").is_file():
        raise ApiError(
            status.HTTP_500_INTERNAL_SERVER_ERROR,
            f"{VIEWER_FAILED} ({roots[0].name}): {reply.get('error')}",
            ErrorCode.INTERNAL_ERROR,
        )
    return out


@router.get(
    "/{job_id}/viewer",
    operation_id="read_job_viewer",
    responses={
        200: {
            "content": {"application/json": {"schema": {"type": "object"}}},
            "description": "The viewer manifest (`services/viewer_data.py`): atlas size, LOD "
            "meshes, texel arrays, a_vis grid, BTF layout (null without BTF maps).",
        },
        **errors(401, JOB_404, JOB_409, 422, (500, "`internal_error`: extraction failed.")),
    },
)
async def read_job_viewer(
    job_id: str, session: SessionDep, tenant: CurrentTenant, settings: SettingsDep
) -> JSONResponse:
    """What the 3-D viewer and the texel inspector need of a finished job (extracted once)."""
    job = _own_job(session, job_id, tenant)
    _require_done(job)
    out = await run_in_threadpool(ensure_viewer, settings.artifact_root, job.id)
    return JSONResponse(json.loads((out / "manifest.json").read_text()))


@router.get(
    "/{job_id}/viewer/{name}",
    response_class=FileResponse,
    operation_id="read_job_viewer_file",
    responses={
        200: {
            "content": {
                OCTET: {"schema": BINARY},
                "application/json": {"schema": {"type": "object"}},
                "image/png": {"schema": BINARY},
            },
            "description": "One file named in the manifest: little-endian float32 `.bin` "
            "arrays (shapes in the manifest), `texels.json`, the fallback `.png` maps.",
        },
        **errors(
            401,
            (404, "`job_not_found`, or `not_found`: no such viewer file."),
            JOB_409,
            422,
            (500, "`internal_error`: extraction failed."),
        ),
    },
)
async def read_job_viewer_file(
    job_id: str, name: str, session: SessionDep, tenant: CurrentTenant, settings: SettingsDep
) -> FileResponse:
    """One viewer file of a finished job."""
    job = _own_job(session, job_id, tenant)
    _require_done(job)
    if not _NAME.match(name):
        raise ApiError(status.HTTP_404_NOT_FOUND, VIEWER_FILE_NOT_FOUND, ErrorCode.NOT_FOUND)
    out = await run_in_threadpool(ensure_viewer, settings.artifact_root, job.id)
    path = out / name
    if not path.is_file() or path.is_symlink():
        raise ApiError(status.HTTP_404_NOT_FOUND, VIEWER_FILE_NOT_FOUND, ErrorCode.NOT_FOUND)
    return FileResponse(path, media_type=_TYPES[path.suffix])
