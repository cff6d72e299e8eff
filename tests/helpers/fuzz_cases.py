"""Structure-aware fuzz cases for the API (`benchmarks/fuzz_uploads.py`, and a seeded sample
in `tests/services/test_fuzz_sample.py`). `generate(n, seed)` draws `n` requests from the
families below with `random.Random(seed)`, so a seed replays a run exactly:

- zip / usdz bytes: a valid bundle with bytes flipped, inserted, cut;
- zip / usdz structure: member names (escaping, long, Unicode, duplicated, file-and-folder),
  header fields (flags, version, method, sizes, offsets), lying sizes, many members, nesting;
- USD text: token-level mutations of a valid layer (values, asset paths, nesting, Unicode);
- USD crate: bytes of a valid `.usdc` flipped, cut, or an array's count made to lie;
- settings drawn from `BakeSettings`'s JSON Schema at and past every bound, non-finite
  numbers (lists too), wrong types, lone surrogates, for `POST /jobs` and `POST /batches`;
- headers: `Authorization` variants, `Last-Event-ID`, and a `Content-Length` that lies.
"""

from __future__ import annotations

import io
import json
import random
import warnings
import zipfile
from dataclasses import dataclass, field
from functools import cache

from tests.helpers.hostile_zips import cases as hostile_zips
from tests.helpers.hostile_zips import patch, set_cd_offset, understated
from tests.helpers.service import usda

SUFFIXES = (".usda", ".usdc", ".usd", ".usdz", ".zip")
TEX = '        asset inputs:file = @{}@'
ESCAPES = ("../outside.usda", "../../etc/passwd", "/etc/hostname", "file:///etc/passwd",
           "http://example.com/a.usda", "sub/../../x.usda", "C:/x.usda", "./missing.png",
           "%2e%2e/x.usda", "/proc/self/environ", "tex/<UDIM>.png", "a\\..\\..\\b.png")  # fmt: skip
ODD = ("\ud800", "\udfff", "\x00", "\u202e", "\ufeff", "é" * 300, "𝔘" * 100, "a" * 5000,
       "CON", "..", " ", "\n", "x" * 255, "\u0301", "\uffff")  # fmt: skip
NON_FINITE = ("NaN", "Infinity", "-Infinity", "1e999", "-1e999")


@dataclass
class Case:
    """One request. `body` is raw bytes (JSON written with non-finite numbers and escapes
    as the family needs); `files` a multipart upload; `raw` a whole HTTP/1.1 request sent on
    a socket (for headers a client library would refuse or fix)."""

    family: str
    method: str
    path: str
    headers: dict[str, str] = field(default_factory=dict)
    body: bytes | None = None
    files: tuple[str, bytes] | None = None
    raw: bytes | None = None
    stream: bool = False  # an events stream: read the status line and hang up


def _zip(members: list[tuple[str, bytes]], stored: bool = False) -> bytes:
    buf = io.BytesIO()
    method = zipfile.ZIP_STORED if stored else zipfile.ZIP_DEFLATED
    with warnings.catch_warnings(), zipfile.ZipFile(buf, "w", method) as zf:
        warnings.simplefilter("ignore")  # duplicate names are one of the cases
        for name, data in members:
            info = zipfile.ZipInfo(name)
            info.compress_type = method
            zf.writestr(info, data)
    return buf.getvalue()


@cache
def crate() -> bytes:
    """A valid `.usdc` with an array large enough to be read zero-copy (pxr in this process
    only; the API never imports it)."""
    import tempfile
    from pathlib import Path

    import numpy as np
    from pxr import Usd, UsdGeom, Vt

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "c.usdc"
        stage = Usd.Stage.CreateNew(str(path))
        mesh = UsdGeom.Mesh.Define(stage, "/Root/M")
        stage.SetDefaultPrim(stage.GetPrimAtPath("/Root"))
        mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(
            np.arange(3000 * 3, dtype=np.float32).reshape(3000, 3)))  # fmt: skip
        mesh.CreateFaceVertexCountsAttr([3] * 1000)
        mesh.CreateFaceVertexIndicesAttr(list(range(3000)))
        stage.Save()
        return path.read_bytes()


def _flip(rng: random.Random, data: bytes, k: int) -> bytes:
    b = bytearray(data)
    for _ in range(k):
        op = rng.random()
        i = rng.randrange(max(len(b), 1))
        if op < 0.6 and b:
            b[i] = rng.randrange(256)
        elif op < 0.8:
            b[i:i] = bytes(rng.randrange(256) for _ in range(rng.randint(1, 8)))
        else:
            del b[i : i + rng.randint(1, 16)]
    return bytes(b)


def _usda_text(rng: random.Random, canary: str) -> bytes:
    base = usda(rng.choice(["", TEX.format("tex/a.png")]))
    lines = base.split(b"\n")
    op = rng.randrange(9)
    if op == 0:
        return base[: rng.randrange(len(base))]
    if op == 1:
        return base.replace(b"tex/a.png", rng.choice(ESCAPES + (canary,)).encode())
    if op == 2:
        i = rng.randrange(len(lines))
        return b"\n".join(lines[:i] + lines[i:][1:])
    if op == 3:
        depth = rng.choice([50, 500, 5000])
        return b"#usda 1.0\n" + b'def "a" {\n' * depth + b"}\n" * depth
    if op == 4:
        vals = rng.choice(["nan", "inf", "-inf", "1e309", "-0", "9" * 400])
        return base.replace(b"def Cube", f"double big = {vals}\n    def Cube".encode())
    if op == 5:
        name = rng.choice(ODD).encode("utf-8", "surrogatepass")
        return base.replace(b'"Box"', b'"' + name + b'"')
    if op == 6:
        return base.replace(b"#usda 1.0", rng.choice([b"#usda 9.9", b"#usdc 1.0", b"", b"PXR-USDC"]))
    if op == 7:
        n = rng.choice([10, 1000, 200_000])
        return base.replace(b"def Cube", b"int[] a = [" + b"1," * n + b"1]\n    def Cube")
    return _flip(rng, base, rng.randint(1, 6))


def _usdc(rng: random.Random) -> bytes:
    data = crate()
    op = rng.randrange(4)
    if op == 0:
        return data[: rng.randrange(len(data))]
    if op == 1:
        return _flip(rng, data, rng.randint(1, 8))
    if op == 2:  # an array's element count that lies (a zero-copy range past the file)
        import numpy as np

        pts = np.arange(3000 * 3, dtype=np.float32).tobytes()[:64]
        at, b = data.find(pts), bytearray(data)
        b[at - 8 : at] = rng.choice([3001, 3000 * 1000, 2**40, 2**64 - 1]).to_bytes(8, "little")
        return bytes(b)
    b = bytearray(data)  # the table of contents' offsets at the end
    i = len(b) - rng.randint(1, 200)
    b[i : i + 8] = rng.randrange(2**64).to_bytes(8, "little")
    return bytes(b)


@cache
def _many(n: int) -> bytes:
    """A bundle of `n` members besides its root layer (built once per `n`: slow to write)."""
    return _zip([("scene.usda", usda())] + [(f"m{i}.txt", b"x") for i in range(n)])


def _zip_structure(rng: random.Random, stored: bool) -> bytes:
    root = ("scene.usda", usda(TEX.format("tex/a.png")))
    tex = ("tex/a.png", b"\x89PNG fake")
    base = _zip([root, tex], stored)
    op = rng.randrange(12)
    if op == 0:
        name = rng.choice(ESCAPES + ODD + ("tex/", "tex//a.png", "TEX/A.PNG", "./tex/a.png"))
        try:
            return _zip([root, tex, (name, b"x")], stored)
        except (UnicodeEncodeError, ValueError):
            return _zip([root, tex, ("x" * rng.choice([256, 4100]), b"x")], stored)
    if op == 1:
        return _zip([root, tex, tex], stored)
    if op == 2:
        field_ = rng.choice(["flags", "version", "method", "csize", "usize"])
        width = 2 if field_ in ("flags", "version", "method") else 4
        return patch(base, rng.choice(["scene.usda", "tex/a.png"]), field_,
                     rng.randrange(2 ** (8 * width)))  # fmt: skip
    if op == 3:
        return set_cd_offset(base, rng.choice([0, 1, 10**6, 2**32 - 2, len(base)]))
    if op == 4:
        return understated(rng.choice([1, 4, 16]), declared=rng.choice([0, 10, 100]))
    if op == 5:
        return _many(rng.choice([10, 5000]))
    if op == 6:
        inner = _zip([root, tex])
        for i in range(rng.randint(1, 3)):
            inner = _zip([(f"inner{i}.zip", inner)], stored=True)
        return inner
    if op == 7:
        return _zip([("a/b", b"x"), ("a/b/c.usda", usda()), root], stored)
    if op == 8:
        return _zip([tex, root], stored)  # usdz: first member not a layer
    if op == 9:
        return _zip([root, ("pad.bin", b"\0" * rng.choice([1 << 20, 8 << 20]))])
    if op == 10:
        return rng.choice(list(hostile_zips().values()))[0]
    return _zip([], stored)


def upload_case(rng: random.Random, canary: str) -> Case:
    family = rng.choice(["zip bytes", "zip structure", "usdz bytes", "usdz structure",
                         "usda text", "usdc crate", "odd filename", "valid"])  # fmt: skip
    stored = family.startswith("usdz")
    suffix = ".usdz" if stored else ".zip"
    if family.endswith("bytes"):
        base = _zip([("scene.usda", usda(TEX.format("tex/a.png"))), ("tex/a.png", b"png")], stored)
        data, name = _flip(rng, base, rng.randint(1, 12)), "scene" + suffix
    elif family.endswith("structure"):
        data, name = _zip_structure(rng, stored), "scene" + suffix
    elif family == "usda text":
        data, name = _usda_text(rng, canary), "layer.usda"
    elif family == "usdc crate":
        data, name = _usdc(rng), rng.choice(["layer.usdc", "layer.usd"])
    elif family == "odd filename":
        data = usda()
        name = rng.choice(ODD) + rng.choice(SUFFIXES + (".obj", "", ".USDA"))
    else:
        data, name = usda(f"        # {rng.random()}"), "valid.usda"
    return Case(family, "POST", "/assets", files=(name, data))


def _schema_values(rng: random.Random, spec: dict) -> object:
    """A value at, just past, or far past a bound of one JSON Schema property, or of the
    wrong type."""
    kind = spec.get("type")
    lo = spec.get("minimum", spec.get("exclusiveMinimum"))
    hi = spec.get("maximum", spec.get("exclusiveMaximum"))
    pick = rng.random()
    if pick < 0.15:
        return rng.choice([None, True, "x", [], {}, "\ud800", 1.5, -1, 2**64, "1e3"])
    if kind == "integer":
        edges = [v for b in (lo, hi) if b is not None for v in (b - 1, b, b + 1)]
        return rng.choice(edges + [0, -(2**63), 2**63, 2**70])
    if kind == "number":
        edges = [v for b in (lo, hi) if b is not None for v in (b, b - 1e-9, b + 1e-9)]
        return rng.choice(edges + ["NaN", "Infinity", "-Infinity", -0.0, 1e308, 5e-324])
    if kind == "array":
        item = spec.get("items", {})
        return [_schema_values(rng, item) for _ in range(rng.choice([0, 1, 2, 5, 1000]))]
    if "enum" in spec:
        return rng.choice(spec["enum"] + ["", spec["enum"][0].upper(), "\x00"])
    if kind == "string":
        return rng.choice(["", "a" * 201, "\ud800", "\x00", "../../etc/passwd", "é"])
    return rng.choice([True, False, 0, 1, "true"])


def _json(obj: object) -> bytes:
    """JSON with the non-finite numbers written as bare tokens (`NaN`, `Infinity`) and lone
    surrogates as `\\ud800` escapes, as a hostile client would send them."""
    text = json.dumps(obj, ensure_ascii=True, allow_nan=True)
    for token in NON_FINITE:
        text = text.replace(f'"{token}"', token)
    return text.encode()


@cache
def settings_schema() -> dict:
    from schemas.settings import BakeSettings

    return BakeSettings.model_json_schema()["properties"]


def settings_case(rng: random.Random, asset_id: str) -> Case:
    props = settings_schema()
    keys = rng.sample(sorted(props), rng.randint(1, 3))
    cfg: dict[str, object] = {k: _schema_values(rng, props[k]) for k in keys}
    if rng.random() < 0.1:
        cfg[rng.choice(["no_such_field", "\ud800", "", "a" * 300])] = 1
    aid = asset_id if rng.random() < 0.8 else rng.choice(ODD + ("a" * 65, "", "0"))
    if rng.random() < 0.75:
        return Case("settings: job", "POST", "/jobs", {"Content-Type": "application/json"},
                    _json({"asset_id": aid, "settings": cfg}))  # fmt: skip
    item = {"asset_id": aid, "settings": cfg if rng.random() < 0.5 else None}
    body = {"name": rng.choice([None, "b", "\ud800", "n" * 201]), "items": [item],
            "settings": {} if rng.random() < 0.5 else cfg}  # fmt: skip
    return Case("settings: batch", "POST", "/batches", {"Content-Type": "application/json"},
                _json(body))  # fmt: skip


def header_case(rng: random.Random, token: str, job_id: str, port: int) -> Case:
    op = rng.randrange(3)
    if op == 0:
        auth = rng.choice(["", "Bearer", "Bearer ", f"bearer {token}", f"BEARER {token}",
                           f"Bearer  {token}", f"Basic {token}", f"Bearer {token}x",
                           "Bearer " + "a" * 10000, f"Bearer {token}\t", "Token x"])  # fmt: skip
        method, path = rng.choice([("GET", "/jobs"), ("GET", f"/jobs/{job_id}"),
                                   ("DELETE", "/jobs/nope"), ("POST", "/jobs")])  # fmt: skip
        return Case("header: authorization", method, path, {"Authorization": auth},
                    b"{}" if method == "POST" else None)  # fmt: skip
    if op == 1:
        value = rng.choice(["99999999999999999999999", "-1", "0", "9223372036854775807",
                            "9223372036854775808", "abc", "1e3", " 5 ", "\u0661\u0662", "",
                            "0x10"])  # fmt: skip
        path = rng.choice([f"/jobs/{job_id}/events", "/events"])
        return Case("header: last-event-id", "GET", path, {"Last-Event-ID": value}, stream=True)
    declared = rng.choice([0, 1, 10, 10**6, 10**12, -1])
    sent = rng.choice([b"", b"{}", b"x" * 100])
    lie = rng.choice([str(declared), "abc", f"{declared}, {declared}", "1" * 40])
    raw = (f"POST /api/v1/jobs HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n"
           f"Authorization: Bearer {token}\r\nContent-Type: application/json\r\n"
           f"Content-Length: {lie}\r\nConnection: close\r\n\r\n").encode() + sent  # fmt: skip
    return Case("header: content-length", "POST", "/jobs", raw=raw)


def generate(n: int, seed: int, *, token: str, asset_id: str, job_id: str, port: int,
             canary: str = "/etc/shadow") -> list[Case]:  # fmt: skip
    """`n` cases, the same for the same arguments: about 45 % uploads, 40 % settings, 15 %
    headers. `canary`: a server file outside the artifact root that layers point at."""
    rng = random.Random(seed)
    out = []
    for _ in range(n):
        r = rng.random()
        if r < 0.45:
            out.append(upload_case(rng, canary))
        elif r < 0.85:
            out.append(settings_case(rng, asset_id))
        else:
            out.append(header_case(rng, token, job_id, port))
    return out
