"""Small wire models shared by every resource."""

from __future__ import annotations

from enum import StrEnum

from pydantic import BaseModel, ConfigDict, Field


class Message(BaseModel):
    message: str


class HealthCheck(BaseModel):
    status: str
    database: bool
    broker: bool
    version: str


class ErrorCode(StrEnum):
    """The stable machine-readable `code` of every error body. A client branches on `code`;
    `detail` is for people (its wording may change). New codes may be added; a code's
    meaning never changes."""

    # request shape
    BAD_REQUEST = "bad_request"
    VALIDATION_ERROR = "validation_error"
    NOT_FOUND = "not_found"
    METHOD_NOT_ALLOWED = "method_not_allowed"
    # authentication
    NOT_AUTHENTICATED = "not_authenticated"
    INVALID_TOKEN = "invalid_token"
    FORBIDDEN = "forbidden"
    # resources
    ASSET_NOT_FOUND = "asset_not_found"
    JOB_NOT_FOUND = "job_not_found"
    PREVIEW_NOT_FOUND = "preview_not_found"
    REPORT_NOT_FOUND = "report_not_found"
    JOB_NOT_FINISHED = "job_not_finished"
    BATCH_NOT_FOUND = "batch_not_found"
    BATCH_NOT_FINISHED = "batch_not_finished"
    JOB_NOT_FAILED = "job_not_failed"
    # uploads
    NO_FILE = "no_file"
    UNSUPPORTED_FILE_TYPE = "unsupported_file_type"
    UPLOAD_TOO_LARGE = "upload_too_large"
    BUNDLE_TOO_LARGE = "bundle_too_large"
    COMPRESSION_RATIO = "compression_ratio_too_high"
    MEMBER_SIZE_MISMATCH = "bundle_member_size_mismatch"
    TOO_MANY_MEMBERS = "too_many_members"
    BAD_ZIP = "bad_zip"
    BAD_MEMBER_PATH = "bad_member_path"
    LINK_MEMBER = "link_member"
    NO_ROOT_LAYER = "no_root_layer"
    ASSET_CHECK_FAILED = "asset_check_failed"
    INVALID_ASSET = "invalid_asset"
    # anything else
    CONFLICT = "conflict"
    PAYLOAD_TOO_LARGE = "payload_too_large"
    UNSUPPORTED_MEDIA_TYPE = "unsupported_media_type"
    SERVICE_UNAVAILABLE = "service_unavailable"
    INTERNAL_ERROR = "internal_error"
    HTTP_ERROR = "http_error"


class ValidationIssue(BaseModel):
    """One problem of a request that did not validate (FastAPI's own shape)."""

    model_config = ConfigDict(extra="allow")

    loc: list[str | int]
    msg: str
    type: str


class ErrorPublic(BaseModel):
    """Every 4xx/5xx body of the API. `detail` is what the server always said (a sentence,
    or for `validation_error` the list of problems); `code` is stable and machine-readable."""

    detail: str | list[ValidationIssue] = Field(
        description="For people: a sentence naming the problem (and the offending path of an "
        "upload), or, with code `validation_error`, the list of request problems."
    )
    code: str = Field(
        description="Stable and machine-readable; one of: "
        + ", ".join(f"`{c.value}`" for c in ErrorCode)
        + ". Clients should treat an unknown code by its HTTP status.",
        examples=["job_not_found"],
    )
