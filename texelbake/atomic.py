"""Atomic file writes, one way: a temporary file in the target's folder, flushed to disk, then
renamed over the target (POSIX rename is atomic within a file system), and removed if
anything fails — a reader sees the old file or the new one, never half of one, and a crash
leaves no partial target. Every writer of texelbake, the service and the workers goes
through `atomic_path` (or `atomic_write_bytes`, `replace`)."""

from __future__ import annotations

import os
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path


def replace(src: str | Path, dst: str | Path, *, mode: int | None = 0o644) -> Path:
    """Flush `src` to disk and rename it over `dst` (same file system), then flush the
    folder's entry. mode : permissions to give `src` first (mkstemp makes 0600), or None."""
    src, dst = Path(src), Path(dst)
    if src.is_file():  # fsync through a read-only descriptor (works for 0444 files too)
        fd = os.open(src, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
    if mode is not None:
        os.chmod(src, mode)
    os.replace(src, dst)
    try:
        fd = os.open(dst.parent, os.O_RDONLY)
    except OSError:  # a folder that cannot be opened (some file systems): the rename stands
        return dst
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)
    return dst


@contextmanager
def atomic_path(path: str | Path, *, mode: int = 0o644) -> Iterator[Path]:
    """Yield a temporary path beside `path` (same suffix, so format-by-extension writers such
    as OpenImageIO and USD work); when the block ends without error the file written there
    replaces `path` (`replace`); on error it is removed and `path` is untouched. The folder
    is created if missing."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, name = tempfile.mkstemp(dir=path.parent, prefix=f".{path.stem}.", suffix=path.suffix)
    os.close(fd)
    tmp = Path(name)
    try:
        yield tmp
        replace(tmp, path, mode=mode)
    finally:
        tmp.unlink(missing_ok=True)


def atomic_write_bytes(path: str | Path, data: bytes) -> Path:
    """Write `data` to `path` atomically (`atomic_path`)."""
    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return path
