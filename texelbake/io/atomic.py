"""Atomic file writes, one way: a temporary file in the target's folder, flushed to disk, then
renamed over the target (POSIX rename is atomic within a file system), and removed if
anything fails — a reader sees the old file or the new one, never half of one, and a crash
leaves no partial target. Every writer of texelbake, the service and the workers goes
through `atomic_path` (or `atomic_write_bytes`, `replace`).

Test hook (the chaos suite, `benchmarks/chaos.py`): when the environment variable
`TEXELBAKE_FAILPOINT_WRITES` names a control file and that file holds an errno name
(`ENOSPC`, `EACCES`, ...) and optionally a path fragment, every atomic write to a path
containing the fragment fails with that errno, as a full or read-only disk would: the
temporary file is removed and the target is untouched. Unset (production), it costs one
environment lookup per write."""

from __future__ import annotations

import errno
import json
import os
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any


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


#: names the fault-injection control file (a test hook; see the module docstring)
FAILPOINT_ENV = "TEXELBAKE_FAILPOINT_WRITES"


def control_words(env: str) -> list[str]:
    """The words of the fault-injection control file the environment variable `env` names;
    [] when it is unset or the file is absent (the test hooks' one reader)."""
    control = os.environ.get(env)
    if not control:
        return []
    try:
        return Path(control).read_text().split()
    except OSError:
        return []


def failpoint(path: str | Path) -> None:
    """Raise the OSError the control file of `FAILPOINT_ENV` asks for on a write to `path`;
    nothing when the variable is unset, the file is absent or empty, or the path does not
    contain the fragment."""
    words = control_words(FAILPOINT_ENV)
    if not words:
        return
    control = os.environ[FAILPOINT_ENV]
    code = getattr(errno, words[0], None)
    if not isinstance(code, int):
        raise ValueError(f"{FAILPOINT_ENV} control file {control}: {words[0]!r} is no errno name")
    if len(words) > 1 and words[1] not in str(path):
        return
    raise OSError(code, os.strerror(code), str(path))


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
        failpoint(path)
        replace(tmp, path, mode=mode)
    finally:
        tmp.unlink(missing_ok=True)


def atomic_write_bytes(path: str | Path, data: bytes) -> Path:
    """Write `data` to `path` atomically (`atomic_path`)."""
    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return path


def atomic_json(path: str | Path, obj: Any) -> None:
    """Write `obj` as indented, key-sorted JSON to `path` atomically (numpy scalars as numbers,
    anything else JSON cannot hold as its string)."""
    atomic_write_bytes(path, json.dumps(obj, indent=2, sort_keys=True,
                                        default=lambda o: o.item() if hasattr(o, "item")
                                        else str(o)).encode())
