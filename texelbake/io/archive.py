"""Deterministic zip archives, one way: members sorted by name, a fixed timestamp, fixed
permissions — the same files give the same bytes (uploads, results, `.npz` artifacts)."""

from __future__ import annotations

import io
import zipfile
from collections.abc import Iterable
from pathlib import Path

#: the timestamp of every member (zip's epoch: 1980-01-01)
EPOCH = (1980, 1, 1, 0, 0, 0)


def zip_bytes(members: Iterable[tuple[str, bytes]], *, deflate: bool = True,
              mode: int | None = 0o644, sort: bool = True) -> bytes:
    """The zip of (name, data) members, sorted by name unless `sort` is False (the caller's
    order, itself deterministic). deflate : ZIP_DEFLATED, else STORED (`.npz` files are
    stored); mode : Unix permissions recorded per member (None: none)."""
    compression = zipfile.ZIP_DEFLATED if deflate else zipfile.ZIP_STORED
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=compression) as zf:
        for name, data in sorted(members, key=lambda m: m[0]) if sort else members:
            info = zipfile.ZipInfo(name, date_time=EPOCH)
            info.compress_type = compression
            if mode is not None:
                info.external_attr = mode << 16
            zf.writestr(info, data)
    return buf.getvalue()


def write_zip(dest: Path, members: Iterable[tuple[str, Path | bytes]], *,
              deflate: bool = True, mode: int | None = 0o644) -> Path:
    """The bytes of `zip_bytes(members)` written to `dest` atomically, a member's data read
    from its file (a `Path`) only while it is written: an archive of many bundles never
    sits in memory whole."""
    from texelbake.io.atomic import atomic_path

    compression = zipfile.ZIP_DEFLATED if deflate else zipfile.ZIP_STORED
    with atomic_path(dest) as tmp, zipfile.ZipFile(tmp, "w", compression=compression) as zf:
        for name, data in sorted(members, key=lambda m: m[0]):
            info = zipfile.ZipInfo(name, date_time=EPOCH)
            info.compress_type = compression
            if mode is not None:
                info.external_attr = mode << 16
            zf.writestr(info, data.read_bytes() if isinstance(data, Path) else data)
    return Path(dest)


def folder_members(folder: Path, prefix: str = "", *,
                   skip_hidden: bool = True) -> list[tuple[str, Path]]:
    """(prefix + name relative to `folder`, path) of every file under `folder`, as
    `zip_folder` takes them."""
    folder = Path(folder)
    out = []
    for p in folder.rglob("*"):
        rel = p.relative_to(folder)
        if p.is_file() and not (skip_hidden and any(s.startswith(".") for s in rel.parts)):
            out.append((prefix + rel.as_posix(), p))
    return out


def zip_folder(folder: Path, *, skip_hidden: bool = True) -> bytes:
    """`zip_bytes` of every file under `folder` (names relative to it, POSIX separators);
    files or folders whose name starts with "." are left out when `skip_hidden`."""
    members = folder_members(folder, skip_hidden=skip_hidden)
    return zip_bytes((name, p.read_bytes()) for name, p in members)
