"""Typed dependencies shared by the routers: settings, sessions, the current tenant, the
bounded query parameters and headers."""

from __future__ import annotations

import time
from collections.abc import AsyncIterator
from functools import partial
from typing import Annotated

from fastapi import Depends, Header, Query, Request, status
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from sqlalchemy.orm import Session, sessionmaker

from farm.config import Settings
from schemas.common import ErrorCode
from services.auth import tenant_by_digest, token_digest
from services.errors import ApiError

NOT_AUTHENTICATED = "not authenticated"
INVALID_TOKEN = "invalid token"

_bearer = HTTPBearer(auto_error=False, description="A tenant's API token.")


# The dependencies are `async def` on purpose: a sync dependency costs a thread-pool hop per
# request, which dominated the latency of `GET /jobs/{id}` under 50 concurrent clients.


async def get_settings_dep(request: Request) -> Settings:
    return request.app.state.settings


async def get_writer(request: Request) -> sessionmaker:
    """The session factory for ledger transitions (write transactions)."""
    return request.app.state.writer


async def get_session(request: Request) -> AsyncIterator[Session]:
    """A read session (SQLite: deferred transactions, never waits on writers). Queries on it
    are short indexed reads."""
    with request.app.state.reader() as s:
        yield s


SettingsDep = Annotated[Settings, Depends(get_settings_dep)]
WriterDep = Annotated[sessionmaker, Depends(get_writer)]
SessionDep = Annotated[Session, Depends(get_session)]


class TokenCache:
    """digest -> (tenant, expiry): a token lookup costs one dict access for `ttl` seconds."""

    def __init__(self, ttl: float = 30.0, size: int = 4096):
        self.ttl, self.size = ttl, size
        self._d: dict[str, tuple[str, float]] = {}

    def get(self, digest: str) -> str | None:
        hit = self._d.get(digest)
        if hit is None or hit[1] < time.monotonic():
            return None
        return hit[0]

    def put(self, digest: str, tenant: str) -> None:
        if len(self._d) >= self.size:
            self._d.clear()
        self._d[digest] = (tenant, time.monotonic() + self.ttl)


async def tenant_of_token(state, token: str) -> str | None:  # noqa: ANN001 - the app's state
    """The tenant of a bearer token, or None: from the process's token cache, else one
    indexed database read on the loop's read threads (`services.status_cache.LoopReads`)."""
    digest = token_digest(state.settings.secret_key, token)
    cache: TokenCache = state.token_cache
    tenant = cache.get(digest)
    if tenant is None:
        tenant = await state.loop_reads.run(partial(tenant_by_digest, digest=digest))
        if tenant is not None:
            cache.put(digest, tenant)
    return tenant


def unauthenticated(detail: str = NOT_AUTHENTICATED) -> ApiError:
    """The 401 of a request without a valid token (`detail`: NOT_AUTHENTICATED or
    INVALID_TOKEN)."""
    code = ErrorCode.NOT_AUTHENTICATED if detail == NOT_AUTHENTICATED else ErrorCode.INVALID_TOKEN
    return ApiError(status.HTTP_401_UNAUTHORIZED, detail, code,
                    headers={"WWW-Authenticate": "Bearer"})  # fmt: skip


async def get_current_tenant(
    request: Request,
    creds: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)],
) -> str:
    """The tenant of the request's bearer token. The scheme is matched case-insensitively
    (`bearer` is `Bearer`, RFC 7235 section 2.1), for every method alike."""
    if creds is None or not creds.credentials:
        raise unauthenticated(NOT_AUTHENTICATED)
    tenant = await tenant_of_token(request.app.state, creds.credentials)
    if tenant is None:
        raise unauthenticated(INVALID_TOKEN)
    return tenant


CurrentTenant = Annotated[str, Depends(get_current_tenant)]


#: paging of listings; out-of-range values are a 422, never a database overflow
SkipQ = Annotated[int, Query(ge=0, le=1_000_000_000)]
LimitQ = Annotated[int, Query(ge=1, le=1000)]

#: the largest event sequence number the database holds (a signed 64-bit integer)
MAX_EVENT_SEQ = 2**63 - 1


async def get_last_event_id(last_event_id: Annotated[str | None, Header()] = None) -> int | None:
    """`Last-Event-ID` as an event sequence number: a decimal integer in 0..MAX_EVENT_SEQ.
    Anything else (not a number, negative, too large for the database) is ignored as if not
    sent: a browser's EventSource resends whatever id it was given, so a 422 would make it
    reconnect in a loop."""
    if last_event_id is None:
        return None
    text = last_event_id.strip()
    if not (text.isascii() and text.isdigit() and len(text) <= len(str(MAX_EVENT_SEQ))):
        return None
    seq = int(text)
    return seq if seq <= MAX_EVENT_SEQ else None


LastEventId = Annotated[int | None, Depends(get_last_event_id)]
