"""`/jobs/{id}/result`, `/jobs/{id}/previews/{name}`, `/jobs/{id}/report`: the files of a
finished job, read from its output folder (split from `services.routers.jobs`, which holds the
jobs' lifecycle). A tenant sees only its own jobs: anyone else's is a 404."""

from __future__ import annotations

import json
import re
from pathlib import Path

from fastapi import APIRouter, Request, status
from fastapi.responses import FileResponse, JSONResponse

from farm import storage
from schemas.common import ErrorCode
from services.deps import CurrentTenant, SessionDep, SettingsDep
from services.errors import ApiError, errors
from services.routers.jobs import (
    BINARY,
    JOB_404,
    JOB_409,
    OCTET,
    _media_type,
    _own_job,
    _require_done,
)
from texelbake.io.archive import zip_folder
from texelbake.io.atomic import atomic_write_bytes

router = APIRouter(prefix="/jobs", tags=["jobs"])

PREVIEW_NOT_FOUND = "preview not found"
REPORT_NOT_FOUND = "report not found"
#: a preview's file name: no separators, no leading dot
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,200}$")
#: media types of preview files by suffix (not guessed: `mimetypes` differs between machines)
PREVIEW_TYPES = {".png": "image/png", ".exr": "image/x-exr", ".json": "application/json",
                 ".gif": "image/gif"}


def build_result_zip(out_dir: Path, dest: Path) -> Path:
    """Zip the baked bundle deterministically (sorted names, fixed times), atomically."""
    if dest.is_file():
        return dest
    return atomic_write_bytes(dest, zip_folder(out_dir))


@router.get(
    "/{job_id}/result",
    response_class=FileResponse,
    operation_id="read_job_result",
    responses={
        200: {
            "content": {"application/zip": {"schema": BINARY}, OCTET: {"schema": BINARY}},
            "description": "The baked USD bundle (a zip).",
        },
        **errors(401, JOB_404, JOB_409, 422),
    },
)
def read_job_result(
    job_id: str,
    request: Request,
    session: SessionDep,
    tenant: CurrentTenant,
    settings: SettingsDep,
) -> FileResponse:
    """The baked USD bundle (root layer, payload, maps, report) as a zip."""
    job = _own_job(session, job_id, tenant)
    _require_done(job)
    root = settings.artifact_root
    dest = build_result_zip(
        storage.job_out(root, job.id), storage.job_dir(root, job.id) / "result.zip"
    )
    return FileResponse(
        dest, media_type=_media_type(request, "application/zip"), filename=f"{job.id}.zip"
    )


@router.get(
    "/{job_id}/previews/{name}",
    response_class=FileResponse,
    operation_id="read_job_preview",
    responses={
        200: {
            "content": {
                "image/png": {"schema": BINARY},
                "image/x-exr": {"schema": BINARY},
                "image/gif": {"schema": BINARY},
                OCTET: {"schema": BINARY},
                "application/json": {"schema": {"type": "object"}},
            },
            "description": "A preview: an sRGB `.png`, a linear `.exr`, the render "
            "report `.json`, or the deformed frames' `animation.gif`; the media type follows "
            "the name.",
        },
        **errors(
            401, (404, "`job_not_found`, or `preview_not_found`: no such preview."), 422
        ),
    },
)
def read_job_preview(
    job_id: str,
    name: str,
    request: Request,
    session: SessionDep,
    tenant: CurrentTenant,
    settings: SettingsDep,
) -> FileResponse:
    """One preview file of a finished job (names are listed in the job's `previews`)."""
    job = _own_job(session, job_id, tenant)
    folder = storage.job_out(settings.artifact_root, job.id) / "previews"
    path = folder / name
    if not _NAME.match(name) or not path.is_file() or path.is_symlink():
        raise ApiError(status.HTTP_404_NOT_FOUND, PREVIEW_NOT_FOUND, ErrorCode.PREVIEW_NOT_FOUND)
    native = PREVIEW_TYPES.get(path.suffix.lower(), OCTET)
    return FileResponse(path, media_type=_media_type(request, native))


@router.get(
    "/{job_id}/report",
    operation_id="read_job_report",
    responses={
        200: {
            "content": {"application/json": {"schema": {"type": "object"}}},
            "description": "The bake report (`report.json` of the result bundle).",
        },
        **errors(
            401,
            (404, "`job_not_found`, or `report_not_found`: the bundle has no report."),
            JOB_409,
            422,
        ),
    },
)
def read_job_report(
    job_id: str, session: SessionDep, tenant: CurrentTenant, settings: SettingsDep
) -> JSONResponse:
    """The bake report (measurements, quality, warnings, skipped stages) of a finished job."""
    job = _own_job(session, job_id, tenant)
    _require_done(job)
    path = storage.job_out(settings.artifact_root, job.id) / "report.json"
    if not path.is_file():
        raise ApiError(status.HTTP_404_NOT_FOUND, REPORT_NOT_FOUND, ErrorCode.REPORT_NOT_FOUND)
    return JSONResponse(json.loads(path.read_text()))
