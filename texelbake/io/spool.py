"""Arrays of known shape filled a block of rows at a time, in memory or in `.npy` files.

The geometry stage makes its per-sample arrays (16.8 M samples, 2.5 GB at a 512² atlas, ten
times that at 1k²) in chunks. `MemorySpool` keeps them as numpy arrays (tests, small bakes);
`FileSpool` writes each chunk straight into a `.npy` file with plain file writes and reads
rows back the same way, so a process holds one chunk, never the whole array, and the page
cache, not the process, holds the rest. Its `arrays()` are read-only `np.memmap`s of those
files; `texelbake.io.store.write_npz` copies such a member from its file in blocks instead of
touching its pages (memory bounded per worker whatever the atlas size).

numpy's `open_memmap` writes the header (the same bytes `np.save` writes for that dtype and
shape) and sizes the file; the rows are then written with `os.pwrite`-style file writes, not
through the map: a mapped page that has been written stays in the process' resident set.
"""

from __future__ import annotations

import os
import shutil
import socket
import tempfile
from pathlib import Path
from typing import BinaryIO

import numpy as np

from texelbake.errors import ShapeError


class MemorySpool:
    """Arrays in memory."""

    def __init__(self) -> None:
        self._arrays: dict[str, np.ndarray] = {}

    def allocate(self, name: str, dtype: np.dtype | type, shape: tuple[int, ...]) -> None:
        self._arrays[name] = np.zeros(shape, dtype)

    def write(self, name: str, start: int, rows: np.ndarray) -> None:
        self._arrays[name][start:start + len(rows)] = rows

    def read(self, name: str, start: int, stop: int) -> np.ndarray:
        return self._arrays[name][start:stop]

    def drop(self, name: str) -> None:
        del self._arrays[name]

    def arrays(self) -> dict[str, np.ndarray]:
        return dict(self._arrays)

    def close(self) -> None:
        self._arrays.clear()


class FileSpool:
    """Arrays in `.npy` files under a fresh directory inside `parent` (the artifact store,
    so a 10 GB spool lands on the store's disk, not in /tmp). `close` removes the files;
    the arrays from `arrays()` must not be used after it."""

    def __init__(self, parent: str | Path) -> None:
        Path(parent).mkdir(parents=True, exist_ok=True)
        self.dir = Path(tempfile.mkdtemp(prefix=f"{_prefix()}{os.getpid()}-", dir=parent))
        self._meta: dict[str, tuple[np.dtype, tuple[int, ...], int]] = {}
        self._files: dict[str, BinaryIO] = {}  # open while the array is filled and read

    @staticmethod
    def sweep(parent: str | Path) -> list[Path]:
        """Remove the spools under `parent` left by processes of this host that no longer
        run (a worker killed mid-stage cannot close its spool); returns what it removed.
        Spools of other hosts on a shared store are left to their own hosts."""
        removed = []
        for d in Path(parent).glob(f"{_prefix()}*"):
            pid = d.name[len(_prefix()):].split("-", 1)[0]
            if pid.isdigit() and not pid_alive(int(pid)):
                shutil.rmtree(d, ignore_errors=True)
                removed.append(d)
        return removed

    def _path(self, name: str) -> Path:
        # a leading dot, as every file still being written in the store has (atomic_path):
        # tools that watch the store skip it (benchmarks/chaos.py)
        return self.dir / f".{name}.npy"

    def allocate(self, name: str, dtype: np.dtype | type, shape: tuple[int, ...]) -> None:
        dt = np.dtype(dtype)
        mm = np.lib.format.open_memmap(self._path(name), mode="w+", dtype=dt, shape=shape)
        offset = int(mm.offset)
        del mm  # header written, file sized; nothing was touched
        self._meta[name] = (dt, tuple(shape), offset)
        self._files[name] = open(self._path(name), "r+b")  # noqa: SIM115 (closed by drop/close)

    def _row_bytes(self, name: str) -> int:
        dt, shape, _ = self._meta[name]
        return dt.itemsize * int(np.prod(shape[1:], dtype=np.int64))

    def write(self, name: str, start: int, rows: np.ndarray) -> None:
        dt, shape, offset = self._meta[name]
        rows = np.ascontiguousarray(rows, dtype=dt)
        if rows.shape[1:] != shape[1:] or start < 0 or start + len(rows) > shape[0]:
            raise ShapeError(f"spool {name}: rows {rows.shape} at {start} do not fit {shape}")
        f = self._files[name]
        f.seek(offset + start * self._row_bytes(name))
        f.write(rows.data)

    def read(self, name: str, start: int, stop: int) -> np.ndarray:
        dt, shape, offset = self._meta[name]
        stop = min(stop, shape[0])
        f = self._files[name]
        f.flush()
        f.seek(offset + start * self._row_bytes(name))
        out = np.empty((max(stop - start, 0), *shape[1:]), dt)
        if f.readinto(out.data) != out.nbytes:  # type: ignore[attr-defined]
            raise ShapeError(f"spool {name}: rows {start}:{stop} are past the end of its file")
        return out

    def drop(self, name: str) -> None:
        """Forget a scratch array and remove its file."""
        self._files.pop(name).close()
        del self._meta[name]
        self._path(name).unlink()

    def arrays(self) -> dict[str, np.ndarray]:
        for f in self._files.values():
            f.flush()
        return {name: np.load(self._path(name), mmap_mode="r") for name in self._meta}

    def close(self) -> None:
        for f in self._files.values():
            f.close()
        self._files.clear()
        shutil.rmtree(self.dir, ignore_errors=True)
        self._meta.clear()


def _prefix() -> str:
    return f".spool-{socket.gethostname()}-"


def pid_alive(pid: int) -> bool:
    """Whether process `pid` of this host runs: a zombie (killed, not yet reaped by its
    parent) is dead, so what a killed worker left is taken over at once."""
    try:
        with open(f"/proc/{int(pid)}/stat", "rb") as f:
            return f.read().rsplit(b")", 1)[1].split()[0] != b"Z"
    except FileNotFoundError:
        return False
    except (OSError, IndexError):  # no /proc: ask the kernel (a zombie then counts as alive)
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return False
        except PermissionError:  # another user's process
            return True
        return True


def spooled_file(arr: np.ndarray) -> tuple[str, int] | None:
    """(path, data offset) when `arr` is a whole `.npy` file mapped read-only by
    `np.load(mmap_mode="r")` (a `FileSpool` array): its bytes from 0 are the `.npy` file."""
    if not isinstance(arr, np.memmap) or arr.filename is None:
        return None
    path = str(arr.filename)
    if not path.endswith(".npy") or not arr.flags.c_contiguous:
        return None
    if os.path.getsize(path) != int(arr.offset) + arr.nbytes:
        return None
    with open(path, "rb") as f:  # a view of the same bytes under another shape or dtype
        version = np.lib.format.read_magic(f)
        shape, fortran, dtype = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                                 else np.lib.format.read_array_header_2_0)(f)
    if tuple(shape) != arr.shape or fortran or dtype != arr.dtype:
        return None
    return path, int(arr.offset)
