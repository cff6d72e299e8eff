"""Unpack a zip/usdz upload with every hostile case refused, naming the member.

Runs in the upload checker (`services.checkserver`), never in the API process: inflation is
bounded there by the checker's memory and CPU rlimits as well as by the counts below. What is
refused, each with a stable `detail` prefix (`services.uploads` maps them to error codes):
the archive cannot be read (no end record, a central directory past the file), too many
members, a declared or an actually inflated size past the cap (bytes are counted as they come
out, the header's claim is not trusted), a member whose data inflates past its declared size,
a compression ratio past the cap, a member name that escapes the bundle or is a link, a name
part longer than the file system's NAME_MAX or a path longer than its PATH_MAX, a member that
is both a file and a folder (in either order), an encrypted member, a zip version or a
compression method this reader does not know. No message holds a server path.
"""

from __future__ import annotations

import os
import re
import stat
import struct
import zipfile
import zlib
from pathlib import Path, PurePosixPath

# stable `detail` prefixes (asserted by the tests)
BOMB_SIZE = "bundle unpacks to more than"
BOMB_RATIO = "compression ratio above"
LYING = "bundle member inflates beyond its declared size"
TOO_MANY = "bundle has more than"
BAD_ZIP = "not a valid zip archive"
BAD_MEMBER = "bundle member path is not allowed"
LINK_MEMBER = "bundle member is a link"
NAME_TOO_LONG = "bundle member name is too long"
FILE_AND_FOLDER = "bundle member is both a file and a folder"
ENCRYPTED = "bundle member is encrypted"
UNSUPPORTED_ENTRY = "bundle member uses an unsupported zip feature"
NO_ROOT = "bundle has no root layer"
LAYER_SUFFIXES = (".usd", ".usda", ".usdc")

#: compression methods `zipfile` inflates as a stream (stored, deflate, bzip2, lzma)
METHODS = {zipfile.ZIP_STORED: "stored", zipfile.ZIP_DEFLATED: "deflate",
           zipfile.ZIP_BZIP2: "bzip2", zipfile.ZIP_LZMA: "lzma"}  # fmt: skip
_DRIVE = re.compile(r"^[A-Za-z]:")
BLOCK = 1 << 16


class ArchiveRejected(Exception):
    """A 4xx for the client: `status` and a `detail` that names the member (or the upload)."""

    def __init__(self, status: int, detail: str):
        super().__init__(detail)
        self.status = status
        self.detail = detail


def _shown(name: str, limit: int = 200) -> str:
    """A member name as it goes into a message: printable, and not longer than `limit`."""
    text = name.encode("utf-8", "backslashreplace").decode("ascii", "backslashreplace")
    text = "".join(ch if ch.isprintable() else repr(ch)[1:-1] for ch in text)
    return text if len(text) <= limit else f"{text[:limit]}… ({len(name)} characters)"


def _member_path(info: zipfile.ZipInfo, name_max: int, path_max: int) -> PurePosixPath:
    name = info.filename
    shown = _shown(name)
    if stat.S_ISLNK(info.external_attr >> 16):
        raise ArchiveRejected(422, f"{LINK_MEMBER}: {shown}")
    norm = name.replace("\\", "/")
    p = PurePosixPath(norm)
    if (not norm.strip("/") or norm.startswith("/") or _DRIVE.match(norm)
            or ".." in p.parts or "\x00" in norm):  # fmt: skip
        raise ArchiveRejected(422, f"{BAD_MEMBER}: {shown}")
    try:
        encoded = [part.encode("utf-8") for part in p.parts]
    except UnicodeEncodeError:
        raise ArchiveRejected(422, f"{BAD_MEMBER}: {shown} (not valid Unicode)") from None
    if any(len(part) > name_max for part in encoded):
        raise ArchiveRejected(422, f"{NAME_TOO_LONG}: {shown} (a part over {name_max} bytes)")
    if sum(len(part) + 1 for part in encoded) > path_max:
        raise ArchiveRejected(422, f"{NAME_TOO_LONG}: {shown} (the path over {path_max} bytes)")
    if info.flag_bits & 0x1:
        raise ArchiveRejected(422, f"{ENCRYPTED}: {shown}")
    if info.extract_version > zipfile.MAX_EXTRACT_VERSION:
        raise ArchiveRejected(422, f"{UNSUPPORTED_ENTRY}: {shown} (zip version "
                                   f"{info.extract_version / 10:.1f})")
    if info.compress_type not in METHODS:
        raise ArchiveRejected(422, f"{UNSUPPORTED_ENTRY}: {shown} (compression method "
                                   f"{info.compress_type})")
    return p


def _check_tree(infos: list[zipfile.ZipInfo], paths: list[PurePosixPath]) -> None:
    """Duplicates (case-insensitively: bundles move between file systems) and a member that
    is a file and, through another member, a folder too."""
    files: dict[str, str] = {}  # lower-cased path -> the member's name
    folders: set[str] = set()  # explicit folder members and every member's parents
    for info, p in zip(infos, paths, strict=True):
        key = str(p).lower()
        shown = _shown(info.filename)
        for parent in list(p.parents)[:-1]:
            if str(parent).lower() in files:
                raise ArchiveRejected(422, f"{FILE_AND_FOLDER}: {_shown(str(parent))}")
            folders.add(str(parent).lower())
        if info.is_dir() and key in files:
            raise ArchiveRejected(422, f"{FILE_AND_FOLDER}: {shown}")
        if key in files:
            raise ArchiveRejected(422, f"{BAD_MEMBER}: {shown} (duplicate)")
        if info.is_dir():
            folders.add(key)
        elif key in folders:
            raise ArchiveRejected(422, f"{FILE_AND_FOLDER}: {shown}")
        else:
            files[key] = info.filename


def unpack_zip(src: Path, dest: Path, *, max_unpacked: int, max_ratio: float,
               max_members: int, display: str) -> list[str]:  # fmt: skip
    """Extract the zip/usdz `src` into the empty folder `dest`; returns the member files'
    paths relative to `dest`, in archive order. Raises ArchiveRejected (`display` names the
    upload in messages about the whole archive)."""
    packed = max(os.path.getsize(src), 1)
    shown = _shown(display)
    _check_end_record(src, packed, shown)
    try:
        zf = zipfile.ZipFile(src)
    except NotImplementedError:  # a central header's zip version: name its member
        raise ArchiveRejected(422, _unknown_version(src)) from None
    except (zipfile.BadZipFile, OSError, ValueError, EOFError) as exc:
        raise ArchiveRejected(422, f"{BAD_ZIP}: {shown} ({_reason(exc)})") from None
    dest_len = len(os.fsencode(os.path.realpath(dest))) + 1
    name_max = os.pathconf(dest, "PC_NAME_MAX")
    path_max = os.pathconf(dest, "PC_PATH_MAX") - dest_len - 1
    with zf:
        infos = zf.infolist()
        if len(infos) > max_members:
            raise ArchiveRejected(413, f"{TOO_MANY} {max_members} members: {shown}")
        declared = sum(i.file_size for i in infos)
        if declared > max_unpacked:
            raise ArchiveRejected(413, f"{BOMB_SIZE} {max_unpacked} bytes: {shown}")
        if declared / packed > max_ratio:
            raise ArchiveRejected(413, f"{BOMB_RATIO} {max_ratio:g}: {shown}")
        for info in infos:
            if info.header_offset + 30 > packed:
                raise ArchiveRejected(422, f"{BAD_ZIP}: {_shown(info.filename)} (its header "
                                           f"is past the end of the file)")
        paths = [_member_path(i, name_max, path_max) for i in infos]
        _check_tree(infos, paths)
        files: list[str] = []
        total = 0
        for info, p in zip(infos, paths, strict=True):
            target = dest.joinpath(*p.parts)
            if info.is_dir():
                target.mkdir(parents=True, exist_ok=True)
                continue
            if info.file_size / max(info.compress_size, 1) > max_ratio and info.file_size > 4096:
                raise ArchiveRejected(413, f"{BOMB_RATIO} {max_ratio:g}: {_shown(info.filename)}")
            target.parent.mkdir(parents=True, exist_ok=True)
            total = _inflate(zf, info, target, total, max_unpacked)
            files.append(str(p))
    return files


def _check_end_record(src: Path, size: int, shown: str) -> None:
    """The end record's central directory must lie inside the file (the reader would
    otherwise take the difference for data prepended to the archive and seek before it)."""
    with open(src, "rb") as f:
        f.seek(max(0, size - (1 << 16) - 22))
        tail = f.read()
    at = tail.rfind(b"PK\x05\x06")
    if at < 0 or at + 22 > len(tail):
        return  # no end record: the reader says so
    cd_size, cd_offset = struct.unpack_from("<II", tail, at + 12)
    if cd_offset != 0xFFFFFFFF and cd_offset + cd_size > size:
        raise ArchiveRejected(422, f"{BAD_ZIP}: {shown} (the central directory offset "
                                   f"{cd_offset} is past the end of the file, {size} bytes)")


def _unknown_version(src: Path) -> str:
    """The detail for a central header whose zip version this reader does not know."""
    data = src.read_bytes()
    start = 0
    while (i := data.find(b"PK\x01\x02", start)) >= 0 and i + 46 <= len(data):
        start = i + 4
        version, nlen = struct.unpack_from("<H", data, i + 6)[0], struct.unpack_from(
            "<H", data, i + 28)[0]
        if version % 256 > zipfile.MAX_EXTRACT_VERSION:
            name = data[i + 46 : i + 46 + nlen].decode("utf-8", "replace")
            return f"{UNSUPPORTED_ENTRY}: {_shown(name)} (zip version {version % 256 / 10:.1f})"
    return f"{UNSUPPORTED_ENTRY}: an unknown zip version"


def _inflate(zf: zipfile.ZipFile, info: zipfile.ZipInfo, target: Path, total: int,
             max_unpacked: int) -> int:  # fmt: skip
    """Stream one member to `target`, counting the bytes that come out; returns the new
    running total."""
    shown = _shown(info.filename)
    written = 0
    try:
        with zf.open(info) as fin, open(target, "xb") as fout:
            while block := fin.read(BLOCK):
                written += len(block)
                total += len(block)
                if written > info.file_size:  # the header can lie: count what comes out
                    raise ArchiveRejected(413, f"{LYING}: {shown}")
                if total > max_unpacked:
                    raise ArchiveRejected(413, f"{BOMB_SIZE} {max_unpacked} bytes: {shown}")
                fout.write(block)
    except ArchiveRejected:
        raise
    except (zipfile.BadZipFile, zlib.error, NotImplementedError, EOFError, RuntimeError,
            ValueError, OSError, LookupError) as exc:  # fmt: skip
        raise ArchiveRejected(422, f"{BAD_ZIP}: {shown} ({_reason(exc)})") from None
    return total


def _reason(exc: BaseException) -> str:
    """The library's reason without any file path it may hold (an OSError's `filename`)."""
    if isinstance(exc, OSError) and exc.strerror:
        return exc.strerror
    return f"{exc}"[:160] or type(exc).__name__


def root_layer(files: list[str], upload_name: str, *, usdz: bool) -> str:
    """The root layer among an archive's member files: a usdz's first member (the usdz spec);
    a zip's only top-level layer, or the one named like the zip."""
    shown = _shown(upload_name)
    if usdz:
        if not files or not files[0].lower().endswith(LAYER_SUFFIXES):
            raise ArchiveRejected(422, f"{NO_ROOT}: the first member of {shown} is not a USD "
                                       f"layer")
        return files[0]
    top = sorted(f for f in files if "/" not in f and f.lower().endswith(LAYER_SUFFIXES))
    if len(top) == 1:
        return top[0]
    stem = PurePosixPath(upload_name).stem.lower()
    named = [f for f in top if PurePosixPath(f).stem.lower() == stem]
    if len(named) == 1:
        return named[0]
    if not top:
        raise ArchiveRejected(422, f"{NO_ROOT}: no top-level .usd/.usda/.usdc in {shown}")
    listed = ", ".join(_shown(f, 80) for f in top[:10])
    raise ArchiveRejected(422, f"{NO_ROOT}: several top-level layers in {shown} ({listed}); "
                               f"name the root like the zip file")
