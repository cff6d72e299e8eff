"""One root error and typed subclasses. Messages name the file, prim path or field,
and the expected vs actual value. The API maps them to 4xx."""

from __future__ import annotations


class TexelbakeError(Exception):
    """Root of every error texelbake raises on purpose."""


class AssetError(TexelbakeError):
    """The input asset is unusable (no mesh, bad indices, NaN points, missing file, ...)."""

    def __init__(self, message: str, *, path: str | None = None, prim: str | None = None):
        self.path = path
        self.prim = prim
        where = ", ".join(x for x in (f"file {path}" if path else "", f"prim {prim}" if prim else "") if x)
        super().__init__(f"{message} ({where})" if where else message)


class AssetPathError(AssetError):
    """An asset path inside the asset is absolute, escapes its folder, is a URL or does not exist."""


class ShapeError(TexelbakeError, ValueError):
    """An array argument has the wrong shape or dtype."""


class SettingsError(TexelbakeError, ValueError):
    """A bake setting is out of range or inconsistent."""


class NumericalError(TexelbakeError):
    """A computation could not produce a finite result where one was required."""


class StageError(TexelbakeError):
    """A pipeline stage is missing its inputs or cannot run for this asset."""


class AssetWarning(UserWarning):
    """A recoverable problem in an asset (dropped faces, unsupported shader network, ...).

    Defined here, in a module that imports nothing, because a warning's class is imported
    wherever it is reported: pytest-xdist's controller re-imports it to show a worker's
    warning, and importing `texelbake.asset` there loaded pxr and the ray caster into a process
    that then aborted at exit."""

