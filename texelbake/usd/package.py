"""The baked result as files that travel: the source copied beside it, or one `.usdz`."""

from __future__ import annotations

import shutil
from pathlib import Path

from pxr import Sdf

from texelbake.errors import AssetError
from texelbake.io.atomic import replace


def copy_source(source_layer: Path, dependencies: list[str], dest: Path) -> Path:
    """Copy the source layer and the files it references (paths relative to its folder) into
    `dest`; returns the copied root layer."""
    src_root = Path(source_layer).resolve().parent
    for dep in sorted({str(Path(d).resolve()) for d in dependencies} | {str(source_layer)}):
        rel = Path(dep).resolve().relative_to(src_root)
        target = dest / rel
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(dep, target)
    return dest / Path(source_layer).resolve().relative_to(src_root)


def pack_usdz(root_layer: Path) -> Path:
    """The baked result with everything it references (the source where it lies, payload,
    maps, shader definitions) in one `<root stem>.usdz` beside it (UsdUtils' packager,
    which rewrites the asset paths into the package). Returns the package path."""
    from pxr import UsdUtils

    root_layer = Path(root_layer)
    out = root_layer.with_suffix(".usdz")
    tmp = out.with_name(f".{out.stem}.tmp.usdz")
    if not UsdUtils.CreateNewUsdzPackage(Sdf.AssetPath(str(root_layer)), str(tmp)):
        raise AssetError("could not pack the baked result into a .usdz", path=str(out))
    replace(tmp, out)
    return out

