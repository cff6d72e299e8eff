"""File access for ingest (plain files and `.usdz` members): texture images and MERL tables."""

from __future__ import annotations

import os
import tempfile
import zipfile
from pathlib import Path

import numpy as np

from texelbake.errors import AssetError, AssetPathError
from texelbake.io.images import read_pixels


def _read_resolved_bytes(resolved: str, prim: str) -> bytes:
    from pxr import Ar

    try:
        if Ar.IsPackageRelativePath(resolved):
            package, member = Ar.SplitPackageRelativePathOuter(resolved)
            with zipfile.ZipFile(package) as zf:
                return zf.read(member)
        return Path(resolved).read_bytes()
    except (OSError, KeyError, zipfile.BadZipFile) as exc:
        raise AssetPathError(f"cannot read '{resolved}': {exc}", path=resolved, prim=prim) from exc


def load_image(resolved: str, prim: str) -> tuple[np.ndarray, bool, str]:
    """Pixels of an image through OpenImageIO.

    returns : pixels (h, w, c) float32 (row 0 = top), whether the file stores 8-bit channels,
        the file's "wrapmodes" metadata ("" when absent)
    """
    from pxr import Ar

    def read(filename: str) -> tuple[np.ndarray, bool, str]:
        pixels, info = read_pixels(filename, prim=prim)
        return pixels, info.is_8bit, str(info.attributes.get("wrapmodes", "") or "")

    if Ar.IsPackageRelativePath(resolved):
        data = _read_resolved_bytes(resolved, prim)
        suffix = Path(Ar.SplitPackageRelativePathInner(resolved)[1]).suffix
        with tempfile.TemporaryDirectory() as tmp:
            local = os.path.join(tmp, "texture" + suffix)
            Path(local).write_bytes(data)
            return read(local)
    if not os.path.isfile(resolved):
        raise AssetPathError(f"texture '{resolved}' does not exist", path=resolved, prim=prim)
    return read(resolved)


def load_merl(resolved: str, prim: str) -> np.ndarray:
    """A MERL .binary BRDF -> (3, n_th, n_td, n_pd) float64 via `texelbake.brdf.read_merl`
    (channel scales (1, 1.15, 1.66) / 1500 applied; standard files are (3, 90, 90, 180)).

    A file inside a `.usdz` is copied to a temporary file first (the reader takes a path).
    """
    from pxr import Ar

    from texelbake.brdf import read_merl

    def read(filename: str) -> np.ndarray:
        try:
            return np.asarray(read_merl(filename), dtype=np.float64)
        except AssetError as exc:  # re-raised naming the shader prim as well
            raise AssetError(f"{exc} (measured BRDF '{resolved}')", path=resolved,
                             prim=prim) from exc

    if Ar.IsPackageRelativePath(resolved):
        data = _read_resolved_bytes(resolved, prim)
        with tempfile.TemporaryDirectory() as tmp:
            local = os.path.join(tmp, "brdf.binary")
            Path(local).write_bytes(data)
            return read(local)
    if not os.path.isfile(resolved):
        raise AssetPathError(f"measured BRDF '{resolved}' does not exist", path=resolved,
                             prim=prim)
    return read(resolved)
