"""One error body for the whole API: `{"detail": ..., "code": ...}` (`schemas.common.ErrorPublic`).

Routes raise `ApiError(status, detail, code)`; the handlers installed by `install` give every
other error (an unknown route, a request that does not validate, a bare `HTTPException`, an
unhandled exception) the same shape with a code chosen by status. `errors(...)` declares the
statuses a route can return, each with the model and the codes it may carry, for the OpenAPI
`responses` of the route.
"""

from __future__ import annotations

import logging
import math
from typing import Any

from fastapi import FastAPI, HTTPException, Request
from fastapi.encoders import jsonable_encoder
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, Response
from sqlalchemy.exc import OperationalError
from sqlalchemy.exc import TimeoutError as SATimeoutError
from starlette.exceptions import HTTPException as StarletteHTTPException

from schemas.common import ErrorCode, ErrorPublic

log = logging.getLogger("texelbake.api")

#: the code of an error raised without one (FastAPI's, Starlette's), by status
DEFAULT_CODES: dict[int, ErrorCode] = {
    400: ErrorCode.BAD_REQUEST,
    401: ErrorCode.NOT_AUTHENTICATED,
    403: ErrorCode.FORBIDDEN,
    404: ErrorCode.NOT_FOUND,
    405: ErrorCode.METHOD_NOT_ALLOWED,
    409: ErrorCode.CONFLICT,
    413: ErrorCode.PAYLOAD_TOO_LARGE,
    415: ErrorCode.UNSUPPORTED_MEDIA_TYPE,
    422: ErrorCode.VALIDATION_ERROR,
    500: ErrorCode.INTERNAL_ERROR,
    503: ErrorCode.SERVICE_UNAVAILABLE,
}


class ApiError(HTTPException):
    """An `HTTPException` with its stable `code`."""

    def __init__(
        self,
        status_code: int,
        detail: str,
        code: ErrorCode | str,
        headers: dict[str, str] | None = None,
    ):
        super().__init__(status_code, detail, headers=headers)
        self.code = str(code)


def code_for(exc: StarletteHTTPException) -> str:
    code = getattr(exc, "code", None)
    if code:
        return str(code)
    return str(DEFAULT_CODES.get(exc.status_code, ErrorCode.HTTP_ERROR))


def error_body(detail: Any, code: ErrorCode | str) -> dict[str, Any]:
    return {"detail": detail, "code": str(code)}


async def _http_error(request: Request, exc: Exception) -> Response:
    assert isinstance(exc, StarletteHTTPException)
    headers = getattr(exc, "headers", None)
    if exc.status_code < 200 or exc.status_code in (204, 304):
        return Response(status_code=exc.status_code, headers=headers)
    return JSONResponse(
        error_body(_json_safe(exc.detail), code_for(exc)), status_code=exc.status_code,
        headers=headers,
    )


def _json_safe(obj: Any) -> Any:
    """Anything a request sent, made renderable when echoed back (the offending `input` of a
    validation error, a field name): JSON has no NaN or Infinity, so such floats become their
    string names; a string that is not valid Unicode (a lone surrogate such as `"\\ud800"`)
    has such characters spelled as escapes (`\\ud800`)."""
    if isinstance(obj, float) and not math.isfinite(obj):
        return str(obj)
    if isinstance(obj, str):
        return obj.encode("utf-8", "backslashreplace").decode("utf-8")
    if isinstance(obj, dict):
        return {_json_safe(k): _json_safe(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_json_safe(v) for v in obj]
    return obj


async def _validation_error(request: Request, exc: Exception) -> Response:
    """The problems as `detail`, made encodable (`_json_safe`): FastAPI's own handler answered
    500 when a field's bad value was NaN, Infinity or a lone surrogate."""
    assert isinstance(exc, RequestValidationError)
    return JSONResponse(
        error_body(_json_safe(jsonable_encoder(exc.errors())), ErrorCode.VALIDATION_ERROR),
        status_code=422,
    )


#: seconds a client should wait before retrying a request the database could not serve
RETRY_AFTER_S = 1
DB_BUSY = "the job database is busy; retry the request"


async def _database_error(request: Request, exc: Exception) -> Response:
    """The database could not serve the request now: SQLite's write lock was held past the
    busy timeout, a pool had no free connection, or the server is unreachable (restarting).
    A 503 with `Retry-After`; the driver's message ("database is locked") is logged, never
    sent to the client."""
    log.warning("database unavailable on %s %s: %s", request.method, request.url.path,
                str(exc).splitlines()[0][:200])
    return JSONResponse(
        error_body(f"{DB_BUSY} after {RETRY_AFTER_S} s", ErrorCode.SERVICE_UNAVAILABLE),
        status_code=503,
        headers={"Retry-After": str(RETRY_AFTER_S)},
    )


async def _internal_error(request: Request, exc: Exception) -> Response:
    log.error("unhandled %s on %s %s", type(exc).__name__, request.method, request.url.path)
    return JSONResponse(
        error_body("internal server error", ErrorCode.INTERNAL_ERROR), status_code=500
    )


def install(app: FastAPI) -> None:
    app.add_exception_handler(StarletteHTTPException, _http_error)
    app.add_exception_handler(RequestValidationError, _validation_error)
    app.add_exception_handler(OperationalError, _database_error)
    app.add_exception_handler(SATimeoutError, _database_error)
    app.add_exception_handler(Exception, _internal_error)


#: what each status means on any route, and the codes it carries there
STANDARD: dict[int, str] = {
    400: "The request body could not be parsed (`bad_request`).",
    401: "No bearer token (`not_authenticated`) or an unknown one (`invalid_token`).",
    413: "The request body is larger than the upload cap (`upload_too_large`).",
    422: "The request does not validate (`validation_error`; `detail` lists the problems).",
    503: "The job database is busy or restarting (`service_unavailable`); retry after the "
    "`Retry-After` seconds.",
}


def errors(*specs: int | tuple[int, str]) -> dict[int | str, dict[str, Any]]:
    """OpenAPI `responses` for the error statuses of a route: each with `ErrorPublic`.
    A spec is a status (described by `STANDARD`) or `(status, description)`."""
    out: dict[int | str, dict[str, Any]] = {}
    for spec in specs:
        status, text = spec if isinstance(spec, tuple) else (spec, STANDARD[spec])
        out[status] = {"model": ErrorPublic, "description": text}
    return out
