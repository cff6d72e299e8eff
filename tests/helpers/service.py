"""Shared helpers of the service tests: fresh databases, USD snippets, zip builders."""

from __future__ import annotations

import io
import os
import stat
import uuid
import zipfile
from contextlib import contextmanager
from pathlib import Path

import pytest

PG_ADMIN = "postgresql+psycopg2://postgres@127.0.0.1:5432/test"


def backend_missing(reason: str) -> None:
    """A backend or tool a test needs is not here: skip on a developer's machine, but fail
    under CI (`CI=true`, set by `.ci/run`), where a skipped backend would land untested with
    a green run."""
    if os.environ.get("CI", "").lower() in ("1", "true", "yes"):
        pytest.fail(f"CI=true and {reason}", pytrace=False)
    pytest.skip(reason)


@contextmanager
def fresh_postgres():
    """Yield the URL of a new, empty PostgreSQL database; drop it afterwards. Skips the test
    when the server is not reachable (fails under CI: `backend_missing`)."""
    sqlalchemy = pytest.importorskip("sqlalchemy")
    admin = sqlalchemy.create_engine(PG_ADMIN, isolation_level="AUTOCOMMIT")
    try:
        with admin.connect() as c:
            c.exec_driver_sql("SELECT 1")
    except Exception as exc:  # noqa: BLE001
        admin.dispose()
        backend_missing(f"PostgreSQL not reachable at {PG_ADMIN}: {exc}")
    name = f"texelbake_test_{uuid.uuid4().hex[:12]}"
    with admin.connect() as c:
        c.exec_driver_sql(f'CREATE DATABASE "{name}"')
    try:
        yield PG_ADMIN.rsplit("/", 1)[0] + "/" + name
    finally:
        from farm.db import _engines

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


#: the cheapest bake settings that still shard the cpm and avis stages (4 tiles + a top level)
CHEAP_SETTINGS = {
    "atlas_resolution": 32,
    "shard_texels": 16,
    "n_light_dirs": 8,
    "n_view_dirs": 8,
    "samples_per_texel": 8,
    "n_heldout": 8,
    "c_max": 8,
    "n_trials": 1,
    "avis_resolution": 4,
}


def usd_values(root_layer) -> dict:  # noqa: ANN001
    """Every attribute value of the composed stage (payloads loaded), keyed by
    (prim path, attribute name); arrays as numpy, asset paths by their authored path."""
    import numpy as np
    from pxr import Sdf, Usd

    stage = Usd.Stage.Open(str(root_layer), Usd.Stage.LoadAll)
    out = {}
    for prim in stage.TraverseAll():
        for attr in prim.GetAttributes():
            v = attr.Get()
            if isinstance(v, Sdf.AssetPath):
                v = v.path
            elif v is not None and hasattr(v, "__len__") and not isinstance(v, str):
                try:
                    v = np.asarray(v)
                except (TypeError, ValueError):
                    v = str(v)
            out[(str(prim.GetPath()), attr.GetName())] = v
    return out


def assert_same_bake(root_a, root_b) -> int:  # noqa: ANN001
    """Assert two baked results are identical: every composed attribute value and the bytes
    of every map; returns the number of attributes compared."""
    import numpy as np

    va, vb = usd_values(root_a), usd_values(root_b)
    assert sorted(va) == sorted(vb)
    for key in va:
        a, b = va[key], vb[key]
        if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
            a, b = np.asarray(a), np.asarray(b)
            # NaN marks "no value" (e.g. held-out SNR of an empty texel): equal where both NaN
            assert np.array_equal(a, b, equal_nan=a.dtype.kind in "fc"), key
        else:
            assert a == b, (key, a, b)
    da, db = root_a.parent, root_b.parent
    maps = sorted(p.name for p in da.iterdir() if p.suffix in (".exr", ".png", ".usdc"))
    assert maps == sorted(p.name for p in db.iterdir() if p.suffix in (".exr", ".png", ".usdc"))
    for name in maps:
        assert (da / name).read_bytes() == (db / name).read_bytes(), name
    return len(va)


def proc_cpu() -> dict[int, tuple[int, float, float]]:
    """Every live process from /proc: pid -> (parent pid, its own CPU seconds, the CPU seconds
    of the children it reaped). Processes that end while being read are skipped."""
    tick = os.sysconf("SC_CLK_TCK")
    stats: dict[int, tuple[int, float, float]] = {}
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                f = (d / "stat").read_text().rsplit(")", 1)[1].split()
            except OSError:
                continue
            stats[int(d.name)] = (int(f[1]), (int(f[11]) + int(f[12])) / tick,
                                  (int(f[13]) + int(f[14])) / tick)
    return stats
