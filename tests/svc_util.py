"""Shared helpers of the service tests: fresh databases, USD snippets, zip builders."""

from __future__ import annotations

import io
import os
import stat
import uuid
import zipfile
from contextlib import contextmanager

import pytest

PG_ADMIN = "postgresql+psycopg2://postgres@127.0.0.1:5432/test"


@contextmanager
def fresh_postgres():
    """Yield the URL of a new, empty PostgreSQL database; drop it afterwards. Skips the test
    when the server is not reachable."""
    sqlalchemy = pytest.importorskip("sqlalchemy")
    admin = sqlalchemy.create_engine(PG_ADMIN, isolation_level="AUTOCOMMIT")
    try:
        with admin.connect() as c:
            c.exec_driver_sql("SELECT 1")
    except Exception as exc:  # noqa: BLE001
        admin.dispose()
        pytest.skip(f"PostgreSQL not reachable at {PG_ADMIN}: {exc}")
    name = f"texelbake_test_{uuid.uuid4().hex[:12]}"
    with admin.connect() as c:
        c.exec_driver_sql(f'CREATE DATABASE "{name}"')
    try:
        yield PG_ADMIN.rsplit("/", 1)[0] + "/" + name
    finally:
        from services.db import _engines

        for key in [k for k in _engines if name in k[0]]:
            _engines.pop(key).dispose()
        with admin.connect() as c:
            c.exec_driver_sql(
                "SELECT pg_terminate_backend(pid) FROM pg_stat_activity "
                f"WHERE datname = '{name}' AND pid <> pg_backend_pid()"
            )
            c.exec_driver_sql(f'DROP DATABASE IF EXISTS "{name}"')
        admin.dispose()


def usda(body: str = "", header: str = "") -> bytes:
    """A small valid layer with one cube; `header` goes into the layer metadata, `body` into
    the prim."""
    return (
        f'#usda 1.0\n(\n    defaultPrim = "World"\n{header}\n)\n'
        f'def Xform "World"\n{{\n    def Cube "Box"\n    {{\n{body}\n    }}\n}}\n'
    ).encode()


def make_zip(
    members: dict[str, bytes],
    *,
    symlinks: dict[str, str] | None = None,
    compression: int = zipfile.ZIP_DEFLATED,
) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=compression) as zf:
        for name, data in members.items():
            info = zipfile.ZipInfo(name)
            info.compress_type = compression
            zf.writestr(info, data)
        for name, target in (symlinks or {}).items():
            info = zipfile.ZipInfo(name)
            info.external_attr = (stat.S_IFLNK | 0o777) << 16
            zf.writestr(info, target)
    return buf.getvalue()


def dir_listing(root) -> list[str]:  # noqa: ANN001
    return sorted(
        os.path.relpath(os.path.join(d, f), root) for d, _, fs in os.walk(root) for f in fs
    )
