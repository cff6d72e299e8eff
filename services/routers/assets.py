"""`/assets`: upload (checked, hashed, deduplicated per tenant) and read."""

from __future__ import annotations

import hashlib

from fastapi import APIRouter, HTTPException, Request, Response, UploadFile, status
from fastapi.concurrency import run_in_threadpool
from sqlalchemy import func, select
from sqlalchemy.exc import IntegrityError

from schemas.asset import AssetPublic, AssetsPublic
from services import uploads
from services.db import Asset
from services.deps import CurrentTenant, LimitQ, SessionDep, SettingsDep, SkipQ, WriterDep

router = APIRouter(prefix="/assets", tags=["assets"])

ASSET_NOT_FOUND = "asset not found"
NO_FILE = "no file in the upload"


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
    responses={
        200: {"model": AssetPublic, "description": "The same bytes were uploaded before."},
        413: {"description": "Too large, or a zip bomb (size or ratio cap)."},
        415: {"description": "Not .usda/.usdc/.usd/.usdz/.zip."},
        422: {"description": "Hostile or broken content; `detail` names the path."},
    },
)
async def create_asset(
    file: UploadFile,
    request: Request,
    response: Response,
    tenant: CurrentTenant,
    settings: SettingsDep,
    writer: WriterDep,
) -> AssetPublic:
    """Upload a USD file, a .usdz, or a .zip bundle with its textures."""
    if not file.filename:
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, NO_FILE)
    root = settings.artifact_root
    try:
        staged = await run_in_threadpool(
            uploads.stage_upload, _chunks(file), file.filename, root, settings
        )
        folder = await run_in_threadpool(uploads.commit_staged, staged, root)
    except uploads.UploadRejected as exc:
        raise HTTPException(exc.status, exc.detail) from exc
    meta = uploads.read_meta(folder)
    aid = asset_id_for(tenant, staged.sha256)
    with writer.begin() as s:
        existing = s.get(Asset, aid)
        if existing is None:
            asset = Asset(
                id=aid,
                tenant=tenant,
                sha256=staged.sha256,
                filename=file.filename[:255],
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
            response.status_code = status.HTTP_200_OK
            return AssetPublic.model_validate(existing)
    return AssetPublic.model_validate(asset)


@router.get("", response_model=AssetsPublic)
def read_assets(
    session: SessionDep, tenant: CurrentTenant, skip: SkipQ = 0, limit: LimitQ = 100
) -> AssetsPublic:
    """This tenant's assets, newest first."""
    q = select(Asset).where(Asset.tenant == tenant)
    count = session.scalar(select(func.count()).select_from(q.subquery())) or 0
    rows = session.scalars(q.order_by(Asset.created_at.desc(), Asset.id).offset(skip).limit(limit))
    return AssetsPublic(data=[AssetPublic.model_validate(a) for a in rows], count=count)


@router.get("/{asset_id}", response_model=AssetPublic)
def read_asset(asset_id: str, session: SessionDep, tenant: CurrentTenant) -> AssetPublic:
    """One asset of this tenant."""
    asset = session.get(Asset, asset_id)
    if asset is None or asset.tenant != tenant:
        raise HTTPException(status.HTTP_404_NOT_FOUND, ASSET_NOT_FOUND)
    return AssetPublic.model_validate(asset)
