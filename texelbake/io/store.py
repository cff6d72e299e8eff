"""The artifact store: a directory shared by every worker; arrays written atomically.

Names are content-derived (the caller puts a digest of inputs and settings in the key), files are
written to a temporary name in the same directory and renamed, so a crashed writer leaves nothing
half-written and a retried task is harmless. `.npz` files are written with fixed zip timestamps so
the same arrays give the same bytes.
"""

from __future__ import annotations

import hashlib
import json
import shutil
import struct
import zipfile
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

from texelbake.errors import StageError
from texelbake.io.archive import EPOCH
from texelbake.io.atomic import atomic_path, atomic_write_bytes
from texelbake.io.spool import spooled_file


def file_sha256(path: str | Path, chunk: int = 1 << 20) -> str:
    """Hex SHA-256 of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()


#: a member's size is not known before numpy writes its header: this bound on the header
#: (numpy pads it to a multiple of 64 bytes; a few hundred for any shape we store) lets
#: `write_npz` decide zip64 as `ZipFile.writestr` does from the real size
_NPY_HEADER_BOUND = 4096
#: bytes per read when a spooled member is copied into an `.npz`
_COPY_BLOCK = 16 << 20
#: members smaller than this are read into memory by `read_npz(mmap=True)`, not mapped
MMAP_MIN_BYTES = 1 << 20


def _npz_members(arrays: Mapping[str, Any]) -> Iterator[tuple[str, np.ndarray]]:
    for name in sorted(arrays):  # by array name, as `.npz` artifacts always were
        arr = np.asanyarray(arrays[name])
        if arr.dtype == object:
            raise StageError(f"artifact array {name!r} has dtype object; store plain arrays")
        yield f"{name}.npy", arr


def write_npz(f: BinaryIO, arrays: Mapping[str, Any]) -> None:
    """Deterministic `.npz` (sorted keys, fixed timestamps, no compression) written to the
    seekable binary file `f`, each array streamed by numpy's own writer in 16 MiB pieces: a
    stage's arrays are never held twice (a 512^2 geometry artifact is 2.5 GB); a member that
    is a `texelbake.io.spool.FileSpool` array is copied from its file. The bytes are those
    `zip_bytes` gives for the same members (a test holds it)."""
    with zipfile.ZipFile(f, "w", compression=zipfile.ZIP_STORED) as zf:
        for name, arr in _npz_members(arrays):
            info = zipfile.ZipInfo(name, date_time=EPOCH)
            info.compress_type = zipfile.ZIP_STORED
            info.file_size = arr.nbytes + _NPY_HEADER_BOUND  # rewritten with the real size
            spooled = spooled_file(arr)
            with zf.open(info, "w") as dest:
                if spooled is None:
                    np.lib.format.write_array(dest, arr, allow_pickle=False)
                else:
                    # a `.npy` file of texelbake.io.spool: its bytes are what write_array would
                    # write (same header); copied by reads, its pages never enter this process
                    with open(spooled[0], "rb") as src:
                        shutil.copyfileobj(src, dest, _COPY_BLOCK)


def read_npz(path: Path, names: Callable[[str], bool] | None = None, *, mmap: bool = False
             ) -> dict[str, np.ndarray]:
    """The arrays of an `.npz` file; with `names`, only those it accepts. mmap : map every
    stored member of at least MMAP_MIN_BYTES read-only from the file instead of reading it,
    so a process pays in memory only for the pages it touches (a shard of a 512^2 bake reads
    its tile's samples of a 2.5 GB geometry artifact). numpy maps `.npy` files but not the
    members of an `.npz` (np.load ignores mmap_mode there), hence the zip local header read
    here: a stored member's bytes are a plain `.npy` file at a known offset."""
    out: dict[str, np.ndarray] = {}
    with zipfile.ZipFile(path) as zf, open(path, "rb") as f:
        for info in zf.infolist():
            name = info.filename.removesuffix(".npy")
            if names is not None and not names(name):
                continue
            if not mmap or info.compress_type != zipfile.ZIP_STORED \
                    or info.file_size < MMAP_MIN_BYTES:
                with zf.open(info) as member:
                    out[name] = np.lib.format.read_array(member, allow_pickle=False)
                continue
            f.seek(info.header_offset)
            head = f.read(30)  # the local file header's fixed part (APPNOTE 4.3.7)
            if head[:4] != b"PK\x03\x04":
                raise StageError(f"{path}: member {info.filename} has no local header")
            n_name, n_extra = struct.unpack("<HH", head[26:30])
            f.seek(info.header_offset + 30 + n_name + n_extra)
            version = np.lib.format.read_magic(f)
            read_header = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                           else np.lib.format.read_array_header_2_0)
            shape, fortran, dtype = read_header(f)
            out[name] = np.asarray(np.memmap(path, dtype=dtype, mode="r", offset=f.tell(),
                                             shape=shape, order="F" if fortran else "C"))
    return out


class ArtifactStore:
    """Arrays and JSON under one root directory, addressed by relative keys like
    `cpm/3f2a.../shard-00004.npz`."""

    def __init__(self, root: str | Path):
        self.root = Path(root)
        self.root.mkdir(parents=True, exist_ok=True)

    def path(self, key: str) -> Path:
        p = (self.root / key).resolve()
        if self.root.resolve() not in p.parents:
            raise StageError(f"artifact key {key!r} escapes the store root {self.root}")
        return p

    def exists(self, key: str) -> bool:
        return self.path(key).is_file()

    def write_arrays(self, key: str, arrays: Mapping[str, Any]) -> str:
        with atomic_path(self.path(key)) as tmp, open(tmp, "wb") as f:
            write_npz(f, arrays)
        return key

    def read_arrays(self, key: str, names: Callable[[str], bool] | None = None, *,
                    mmap: bool = False) -> dict[str, np.ndarray]:
        """The arrays of an npz artifact; with `names`, only those it accepts (the others
        are not read from the file); mmap : large arrays mapped read-only (`read_npz`)."""
        p = self.path(key)
        if not p.is_file():
            raise StageError(f"artifact {key} is missing from {self.root}")
        return read_npz(p, names, mmap=mmap)

    def write_json(self, key: str, obj: Any) -> str:
        data = json.dumps(obj, indent=2, sort_keys=True, default=_json_default).encode()
        atomic_write_bytes(self.path(key), data)
        return key

    def read_json(self, key: str) -> Any:
        p = self.path(key)
        if not p.is_file():
            raise StageError(f"artifact {key} is missing from {self.root}")
        return json.loads(p.read_text())


def _json_default(o: Any) -> Any:
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")
