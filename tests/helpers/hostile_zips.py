"""Hostile zip archives built at the byte level, shared by the upload tests and the fuzzer
(`tests/helpers/fuzz.py`): each is a small valid bundle with one header field or member
changed, and the member (or upload) name the 4xx must carry."""

from __future__ import annotations

import struct
import zipfile
import zlib
from functools import cache

from tests.helpers.service import make_zip, usda

LOCAL, CENTRAL, END = b"PK\x03\x04", b"PK\x01\x02", b"PK\x05\x06"
#: byte offsets of header fields (APPNOTE 4.3.7 local, 4.3.12 central, 4.3.16 end record)
LOCAL_FIELDS = {"version": 4, "flags": 6, "method": 8, "csize": 18, "usize": 22}
CENTRAL_FIELDS = {"version": 6, "flags": 8, "method": 10, "csize": 20, "usize": 24}


def headers(z: bytes | bytearray, name: str) -> list[tuple[int, dict[str, int]]]:
    """(offset, field offsets) of the local and central headers of member `name`."""
    found = []
    for sig, fields, name_at in ((LOCAL, LOCAL_FIELDS, 30), (CENTRAL, CENTRAL_FIELDS, 46)):
        start = 0
        while (i := z.find(sig, start)) >= 0:
            start = i + 4
            nlen = struct.unpack_from("<H", z, i + name_at - (4 if sig == LOCAL else 18))[0]
            if bytes(z[i + name_at : i + name_at + nlen]) == name.encode():
                found.append((i, fields))
    return found


def patch(z: bytes, name: str, field: str, value: int) -> bytes:
    """`z` with `field` of member `name` set to `value` in both of its headers."""
    out = bytearray(z)
    for at, fields in headers(out, name):
        width = 4 if field in ("csize", "usize") else 2
        out[at + fields[field] : at + fields[field] + width] = value.to_bytes(width, "little")
    return bytes(out)


def set_cd_offset(z: bytes, offset: int) -> bytes:
    """`z` with the end record's central-directory offset set to `offset`."""
    out = bytearray(z)
    i = out.rfind(END)
    out[i + 16 : i + 20] = offset.to_bytes(4, "little")
    return bytes(out)


@cache
def understated(n_mib: int, declared: int = 100) -> bytes:
    """A bundle whose `pad.bin` inflates to `n_mib` MiB of zeros while its headers say
    `declared` bytes (deflate packs 1 MiB of zeros into ~1 kB: a tiny upload that would
    inflate to gigabytes if the header were trusted)."""
    comp = zlib.compressobj(9, zlib.DEFLATED, -15)
    block = bytes(1 << 20)
    stream = b"".join(comp.compress(block) for _ in range(n_mib)) + comp.flush()
    # the raw deflate stream written as a stored member, then re-labelled deflate and lying
    z = make_zip({"scene.usda": usda(), "pad.bin": stream}, compression=zipfile.ZIP_STORED)
    z = patch(z, "pad.bin", "method", zipfile.ZIP_DEFLATED)
    return patch(z, "pad.bin", "usize", declared)


def cases() -> dict[str, tuple[bytes, str]]:
    """name -> (zip bytes, text the 4xx detail must contain). Each answered 500 before the
    archive was unpacked in the checker with the member checks of `services.archive`."""
    root = {"scene.usda": usda()}
    long_part = "n" * 300 + ".png"
    long_path = "/".join(["d" * 200] * 25) + "/a.png"
    base = make_zip({**root, "tex/a.png": b"png"})
    return {
        "name over NAME_MAX": (make_zip({**root, long_part: b"x"}), "nnnnnnnn"),
        "path over PATH_MAX": (make_zip({**root, long_path: b"x"}), "dddddddd"),
        "file then folder": (make_zip({**root, "tex": b"x", "tex/a.png": b"y"}), "tex"),
        "folder then file": (make_zip({**root, "tex/a.png": b"y", "tex": b"x"}), "tex"),
        "encrypted flag": (patch(base, "tex/a.png", "flags", 0x1), "tex/a.png"),
        "unknown zip version": (patch(base, "tex/a.png", "version", 99), "tex/a.png"),
        "unknown compression method": (patch(base, "tex/a.png", "method", 99), "tex/a.png"),
        "central directory past the file": (set_cd_offset(base, 10**9), "scene.zip"),
    }
