"""`/assets`: upload (checked, hashed, deduplicated per tenant) and read."""

from __future__ import annotations

import hashlib
from typing import Annotated

from fastapi import APIRouter, File, Request, Response, UploadFile, status
from fastapi.concurrency import run_in_threadpool
from sqlalchemy import func, select
from sqlalchemy.exc import IntegrityError

from farm import storage
from farm.db import Asset
from schemas.asset import AssetPublic, AssetsPublic
from schemas.common import ErrorCode
from services import uploads
from services.deps import CurrentTenant, LimitQ, SessionDep, SettingsDep, SkipQ, WriterDep
from services.errors import ApiError, errors

router = APIRouter(prefix="/assets", tags=["assets"])

ASSET_NOT_FOUND = "asset not found"
NO_FILE = "no file in the upload"

ASSET_404 = (404, "`asset_not_found`: no such asset for this tenant.")

#: the multipart file part, declared as binary (`type: string, format: binary`): OpenAPI 3.1's
#: `contentMediaType` alone makes generated clients send a string instead of the file
UploadPart = Annotated[
    UploadFile,
    File(
        description="The USD file (.usda/.usdc/.usd), a .usdz, or a .zip bundle.",
        json_schema_extra={"format": "binary"},
    ),
]


def asset_id_for(tenant: str, sha256: str) -> str:
    return "a" + hashlib.sha256(f"{tenant}\0{sha256}".encode()).hexdigest()[:31]


def _chunks(upload: UploadFile):
    upload.file.seek(0)
    while block := upload.file.read(1 << 20):
        yield block


@router.post(
    "",
    response_model=AssetPublic,
    status_code=status.HTTP_201_CREATED,
    operation_id="create_asset",
    responses={
        200: {"model": AssetPublic, "description": "The same bytes were uploaded before."},
        **errors(
            400,
            401,
            (
                413,
                "Too large (`upload_too_large`), or a zip bomb: `bundle_too_large`, "
                "`compression_ratio_too_high`, `too_many_members`, "
                "`bundle_member_size_mismatch`.",
            ),
            (415, "Not .usda/.usdc/.usd/.usdz/.zip (`unsupported_file_type`)."),
            (
                422,
                "Hostile or broken content, `detail` names the path: `invalid_asset`, "
                "`asset_check_failed`, `bad_zip`, `bad_member_path`, `link_member`, "
                "`no_root_layer`, `no_file`; or a request that does not validate "
                "(`validation_error`).",
            ),
        ),
    },
)
async def create_asset(
    file: UploadPart,
    request: Request,
    response: Response,
    tenant: CurrentTenant,
    settings: SettingsDep,
    writer: WriterDep,
) -> AssetPublic:
    """Upload a USD file, a .usdz, or a .zip bundle with its textures."""
    if not file.filename:
        raise ApiError(status.HTTP_422_UNPROCESSABLE_CONTENT, NO_FILE, ErrorCode.NO_FILE)
    root = settings.artifact_root
    try:
        staged = await run_in_threadpool(
            uploads.stage_upload, _chunks(file), file.filename, root, settings
        )
        folder = await run_in_threadpool(uploads.commit_staged, staged, root)
    except uploads.UploadRejected as exc:
        raise ApiError(exc.status, storage.public_text(exc.detail, root), exc.code) from exc
    meta = uploads.read_meta(folder)
    asset, created = await run_in_threadpool(
        _record_asset, writer, tenant, staged, file.filename or "", meta
    )
    if not created:
        response.status_code = status.HTTP_200_OK
    return asset


def _record_asset(
    writer, tenant: str, staged: uploads.Staged, filename: str, meta: dict  # noqa: ANN001
) -> tuple[AssetPublic, bool]:
    """Insert the asset row (or find the same bytes' row); in a worker thread, so a wait for
    the database's write lock never blocks the event loop. Returns (asset, created)."""
    aid = asset_id_for(tenant, staged.sha256)
    with writer.begin() as s:
        existing = s.get(Asset, aid)
        if existing is None:
            asset = Asset(
                id=aid,
                tenant=tenant,
                sha256=staged.sha256,
                filename=filename[:255],
                kind=meta["kind"],
                root_layer=meta["root_layer"],
                size_bytes=staged.size_bytes,
                n_files=int(meta["n_files"]),
            )
            s.add(asset)
            try:
                s.flush()
            except IntegrityError:
                s.rollback()
                existing = s.get(Asset, aid)
        if existing is not None:
            return AssetPublic.model_validate(existing), False
    return AssetPublic.model_validate(asset), True


@router.get(
    "", response_model=AssetsPublic, operation_id="list_assets", responses=errors(401, 422)
)
def read_assets(
    session: SessionDep, tenant: CurrentTenant, skip: SkipQ = 0, limit: LimitQ = 100
) -> AssetsPublic:
    """This tenant's assets, newest first."""
    q = select(Asset).where(Asset.tenant == tenant)
    count = session.scalar(select(func.count()).select_from(q.subquery())) or 0
    rows = session.scalars(q.order_by(Asset.created_at.desc(), Asset.id).offset(skip).limit(limit))
    return AssetsPublic(data=[AssetPublic.model_validate(a) for a in rows], count=count)


@router.get(
    "/{asset_id}",
    response_model=AssetPublic,
    operation_id="read_asset",
    responses=errors(401, ASSET_404, 422),
)
def read_asset(asset_id: str, session: SessionDep, tenant: CurrentTenant) -> AssetPublic:
    """One asset of this tenant."""
    asset = session.get(Asset, asset_id)
    if asset is None or asset.tenant != tenant:
        raise ApiError(status.HTTP_404_NOT_FOUND, ASSET_NOT_FOUND, ErrorCode.ASSET_NOT_FOUND)
    return AssetPublic.model_validate(asset)
