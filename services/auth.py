"""Bearer tokens. The database stores HMAC-SHA256(secret_key, token), never the token."""

from __future__ import annotations

import hashlib
import hmac
import secrets

from sqlalchemy import select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import sessionmaker

from farm.db import ApiToken


def token_digest(secret_key: str, token: str) -> str:
    return hmac.new(secret_key.encode(), token.encode(), hashlib.sha256).hexdigest()


def issue_token(sm: sessionmaker, secret_key: str, tenant: str) -> str:
    """Create a new bearer token for `tenant`; the token itself is returned once, never stored."""
    token = secrets.token_urlsafe(32)
    with sm.begin() as s:
        s.add(ApiToken(digest=token_digest(secret_key, token), tenant=tenant))
    return token


def ensure_tokens(sm: sessionmaker, secret_key: str, tokens: dict[str, str]) -> None:
    """Register the bootstrap tokens of the settings (token -> tenant), idempotently."""
    for token, tenant in sorted(tokens.items()):
        d = token_digest(secret_key, token)
        try:
            with sm.begin() as s:
                if s.get(ApiToken, d) is None:
                    s.add(ApiToken(digest=d, tenant=tenant))
        except IntegrityError:  # another API process registered it first
            pass


def tenant_by_digest(sm: sessionmaker, digest: str) -> str | None:
    with sm() as s:
        return s.scalar(select(ApiToken.tenant).where(ApiToken.digest == digest))


def tenant_of(sm: sessionmaker, secret_key: str, token: str) -> str | None:
    return tenant_by_digest(sm, token_digest(secret_key, token))
