"""Wire models of uploaded assets (`/api/v1/assets`)."""

from __future__ import annotations

from datetime import datetime

from pydantic import BaseModel, ConfigDict, Field


class AssetPublic(BaseModel):
    """An uploaded, validated asset. The same bytes uploaded twice by one tenant are one asset."""

    model_config = ConfigDict(from_attributes=True)

    id: str = Field(description="Asset id (derived from the tenant and the content hash).")
    sha256: str = Field(description="SHA-256 of the uploaded bytes.")
    filename: str = Field(description="The uploaded file name.")
    kind: str = Field(description="usda | usdc | usdz | zip")
    root_layer: str = Field(description="Root layer, relative to the stored bundle.")
    size_bytes: int
    n_files: int = Field(description="Files in the stored bundle.")
    created_at: datetime


class AssetsPublic(BaseModel):
    data: list[AssetPublic]
    count: int
