"""The artifact store: a directory shared by every worker; arrays written atomically.

Names are content-derived (the caller puts a digest of inputs and settings in the key), files are
written to a temporary name in the same directory and renamed, so a crashed writer leaves nothing
half-written and a retried task is harmless. `.npz` files are written with fixed zip timestamps so
the same arrays give the same bytes.
"""

from __future__ import annotations

import hashlib
import io
import json
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from texelbake.archive import zip_bytes
from texelbake.atomic import atomic_write_bytes
from texelbake.errors import StageError


def file_sha256(path: str | Path, chunk: int = 1 << 20) -> str:
    """Hex SHA-256 of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()


def npz_bytes(arrays: Mapping[str, Any]) -> bytes:
    """Deterministic `.npz` bytes (sorted keys, fixed timestamps, no compression)."""
    members = []
    for name in sorted(arrays):  # by array name, as `.npz` artifacts always were
        arr = np.asanyarray(arrays[name])
        if arr.dtype == object:
            raise StageError(f"artifact array {name!r} has dtype object; store plain arrays")
        member = io.BytesIO()
        np.lib.format.write_array(member, arr, allow_pickle=False)
        members.append((f"{name}.npy", member.getvalue()))
    return zip_bytes(members, deflate=False, mode=None, sort=False)


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
        atomic_write_bytes(self.path(key), npz_bytes(arrays))
        return key

    def read_arrays(self, key: str, names: Callable[[str], bool] | None = None
                    ) -> dict[str, np.ndarray]:
        """The arrays of an npz artifact; with `names`, only those it accepts (the others
        are not read from the file)."""
        p = self.path(key)
        if not p.is_file():
            raise StageError(f"artifact {key} is missing from {self.root}")
        with np.load(p, allow_pickle=False) as z:
            return {k: z[k] for k in z.files if names is None or names(k)}

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
