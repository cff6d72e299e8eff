"""Typed dependencies shared by the routers: settings, sessions, the current tenant."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Annotated

from fastapi import Depends, HTTPException, Query, Request, status
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from sqlalchemy.orm import Session, sessionmaker

from services.auth import tenant_of
from services.config import Settings

NOT_AUTHENTICATED = "not authenticated"
INVALID_TOKEN = "invalid token"

_bearer = HTTPBearer(auto_error=False, description="A tenant's API token.")


def get_settings_dep(request: Request) -> Settings:
    return request.app.state.settings


def get_writer(request: Request) -> sessionmaker:
    """The session factory for ledger transitions (write transactions)."""
    return request.app.state.writer


def get_session(request: Request) -> Iterator[Session]:
    """A read session (SQLite: deferred transactions, never waits on writers)."""
    with request.app.state.reader() as s:
        yield s


SettingsDep = Annotated[Settings, Depends(get_settings_dep)]
WriterDep = Annotated[sessionmaker, Depends(get_writer)]
SessionDep = Annotated[Session, Depends(get_session)]


def get_current_tenant(
    request: Request,
    creds: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)],
) -> str:
    if creds is None or not creds.credentials:
        raise HTTPException(
            status.HTTP_401_UNAUTHORIZED, NOT_AUTHENTICATED, headers={"WWW-Authenticate": "Bearer"}
        )
    st: Settings = request.app.state.settings
    tenant = tenant_of(request.app.state.reader, st.secret_key, creds.credentials)
    if tenant is None:
        raise HTTPException(
            status.HTTP_401_UNAUTHORIZED, INVALID_TOKEN, headers={"WWW-Authenticate": "Bearer"}
        )
    return tenant


CurrentTenant = Annotated[str, Depends(get_current_tenant)]


#: paging of listings; out-of-range values are a 422, never a database overflow
SkipQ = Annotated[int, Query(ge=0, le=1_000_000_000)]
LimitQ = Annotated[int, Query(ge=1, le=1000)]
