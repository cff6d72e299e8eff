"""Hostile input at volume (issue 16, item 4): a property-based fuzzer (hypothesis) sends
malformed uploads and job settings to a real API process and counts the answers.

    .venv/bin/python benchmarks/fuzz_uploads.py --examples 1000 --json PATH [--seed N]

Starts the API (no workers: only the request path is under test) on its own Redis and a
fresh SQLite database, with a canary file beside the artifact root, then draws uploads from
these families: garbage bytes under every accepted suffix; valid USD truncated or with
flipped bytes; layers whose asset paths escape the bundle (`..`, absolute paths, URLs, the
canary); zips with escaping member names, too many members, a high compression ratio, a
nested zip; a layer declaring a huge array; odd filenames; and job settings with NaN, Inf,
wrong types and unknown fields. Duplicate uploads of the same bytes are sent concurrently.

Checks after the run, printed beside the counts by status code: 0 responses 5xx, 0 requests
over 10 s, 0 files stored for a rejected upload (every stored bundle belongs to an accepted
upload; the staging folder is empty), and the canary's contents in no response and no log.
Failing examples are printed with the seed that replays them.
"""

from __future__ import annotations

import argparse
import concurrent.futures as cf
import io
import json
import math
import shutil
import sys
import tempfile
import time
import zipfile
from collections import Counter
from pathlib import Path

import httpx
from hypothesis import HealthCheck, given, seed, settings
from hypothesis import strategies as st

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from farm.stack import free_port, stack_down, stack_up  # noqa: E402

TOKEN = "fuzz-token-0123456789abcdef"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
CANARY = "CANARY-8f2e61c0-texelbake-must-never-read-this"
SUFFIXES = (".usda", ".usdc", ".usd", ".usdz", ".zip")
VALID = b"""#usda 1.0
(
    defaultPrim = "Root"
    upAxis = "Y"
    metersPerUnit = 1
)
def Xform "Root"
{
    def Mesh "Tri"
    {
        int[] faceVertexCounts = [3]
        int[] faceVertexIndices = [0, 1, 2]
        point3f[] points = [(0, 0, 0), (1, 0, 0), (0, 1, 0)]
    }
}
"""


def _layer_with_asset(path: str) -> bytes:
    return VALID.replace(b'def Mesh "Tri"', (
        f'def Mesh "Tri" (\n        references = @{path}@\n    )').encode())


def _zip(members: list[tuple[str, bytes]], *, compress: bool = True) -> bytes:
    buf = io.BytesIO()
    mode = zipfile.ZIP_DEFLATED if compress else zipfile.ZIP_STORED
    with zipfile.ZipFile(buf, "w", compression=mode) as zf:
        for name, data in members:
            zf.writestr(name, data)
    return buf.getvalue()


def uploads(canary: Path):
    """The families of hostile uploads, as a hypothesis strategy of (family, name, bytes)."""
    name = st.sampled_from(SUFFIXES).map(lambda s: "asset" + s)
    garbage = st.tuples(st.just("garbage"), name, st.binary(max_size=4096))
    truncated = st.tuples(st.just("truncated"), st.just("asset.usda"),
                          st.integers(0, len(VALID) - 1).map(lambda n: VALID[:n]))
    flipped = st.tuples(
        st.just("flipped"), st.just("asset.usda"),
        st.lists(st.tuples(st.integers(0, len(VALID) - 1), st.integers(0, 255)), min_size=1,
                 max_size=8).map(lambda fl: bytes(
                     b if i not in dict(fl) else dict(fl)[i] for i, b in enumerate(VALID))))
    escape_paths = st.sampled_from([
        "../outside.usda", "../../etc/passwd", str(canary), f"file://{canary}",
        "http://example.com/a.usda", "/etc/hostname", "sub/../../x.usda", "C:/x.usda",
        "./missing.usda", "%2e%2e/x.usda"])
    escape = st.tuples(st.just("asset-path escape"), st.just("asset.usda"),
                       escape_paths.map(_layer_with_asset))
    zip_escape = st.tuples(st.just("zip member escape"), st.just("bundle.zip"),
                           st.sampled_from(["../evil.usda", "/abs.usda", "a/../../b.usda",
                                            "ok/../../../c.usda"]).map(
                               lambda m: _zip([("root.usda", VALID), (m, VALID)])))
    bomb_ratio = st.tuples(st.just("zip bomb: ratio"), st.just("bomb.zip"),
                           st.integers(8, 40).map(lambda mb: _zip(
                               [("root.usda", VALID), ("pad.bin", b"\0" * (mb << 20))])))
    bomb_members = st.tuples(st.just("zip bomb: members"), st.just("many.zip"),
                             st.integers(4100, 6000).map(lambda n: _zip(
                                 [("root.usda", VALID)] + [(f"m{i}.txt", b"x")
                                                          for i in range(n)])))
    nested = st.tuples(st.just("zip bomb: nested"), st.just("nested.zip"),
                       st.integers(1, 4).map(lambda d: _nest(d)))
    huge = st.tuples(st.just("huge declared array"), st.just("asset.usda"),
                     st.integers(10**6, 3 * 10**6).map(lambda n: VALID.replace(
                         b"int[] faceVertexCounts = [3]",
                         b"int[] faceVertexCounts = [" + b"3," * n + b"3]")))
    odd = st.tuples(st.just("odd filename"),
                    st.text(min_size=1, max_size=300).map(lambda t: t + ".usda"),
                    st.just(VALID))
    return st.one_of(garbage, truncated, flipped, escape, zip_escape, bomb_ratio,
                     bomb_members, nested, huge, odd)


def _nest(depth: int) -> bytes:
    data = _zip([("root.usda", VALID)])
    for i in range(depth):
        data = _zip([(f"inner{i}.zip", data)], compress=False)
    return data


SETTINGS = st.dictionaries(
    st.sampled_from(["atlas_resolution", "eps_db", "c_max", "psi", "samples_per_texel",
                     "n_trials", "no_such_field", "weights", "seed"]),
    st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.integers(-2**40, 2**40),
              st.text(max_size=20), st.none(), st.booleans(), st.lists(st.integers(),
                                                                        max_size=3)),
    max_size=4)


def run(examples: int, seed_value: int, work: Path) -> dict:
    canary = work / "canary.usda"
    canary.write_text(f'#usda 1.0\n# {CANARY}\ndef "X" {{}}\n')
    stack = stack_up(work / "stack", redis_url=f"redis://127.0.0.1:{free_port()}/0",
                     workers={}, tokens={TOKEN: "fuzz"}, environment="test",
                     artifact_root=work / "artifacts")
    api = stack.api_url
    codes: Counter = Counter()
    by_family: dict[str, Counter] = {}
    failures: list[dict] = []
    accepted: set[str] = set()
    slow = 0
    bodies: list[str] = []
    client = httpx.Client(base_url=api, headers=AUTH, timeout=30.0)

    def send(family: str, filename: str, data: bytes) -> httpx.Response | None:
        nonlocal slow
        t0 = time.perf_counter()
        try:
            r = client.post("/api/v1/assets", files={"file": (filename, data)})
        except httpx.HTTPError as exc:
            failures.append({"family": family, "error": repr(exc), "filename": filename[:80]})
            return None
        if time.perf_counter() - t0 > 10.0:
            slow += 1
        codes[r.status_code] += 1
        by_family.setdefault(family, Counter())[r.status_code] += 1
        bodies.append(r.text)
        if r.status_code >= 500:
            failures.append({"family": family, "status": r.status_code,
                             "filename": filename[:80], "bytes": len(data)})
        elif r.status_code in (200, 201):
            accepted.add(r.json()["sha256"])
        return r

    @seed(seed_value)
    @settings(max_examples=examples, deadline=None, database=None,
              suppress_health_check=list(HealthCheck))
    @given(up=uploads(canary), cfg=SETTINGS)
    def one(up, cfg):
        family, filename, data = up
        send(family, filename, data)
        # settings against a real asset id: malformed values must come back 4xx
        r = client.post("/api/v1/jobs", content=json.dumps(
            {"asset_id": asset_id, "settings": cfg}, allow_nan=True),
            headers={"Content-Type": "application/json"})
        codes[r.status_code] += 1
        by_family.setdefault("job settings", Counter())[r.status_code] += 1
        bodies.append(r.text)
        nonfinite = any(isinstance(v, float) and not math.isfinite(v) for v in cfg.values())
        if r.status_code >= 500 or (r.status_code < 300 and nonfinite):
            failures.append({"family": "job settings", "status": r.status_code,
                             "settings": repr(cfg)[:200]})

    try:
        first = send("valid", "valid.usda", VALID)
        assert first is not None and first.status_code in (200, 201), first
        asset_id = first.json()["id"]
        t0 = time.perf_counter()
        one()
        # duplicate, concurrent uploads of the same bytes: one bundle, no error
        with cf.ThreadPoolExecutor(8) as ex:
            dup = list(ex.map(lambda i: send("duplicate", f"dup{i}.usda", VALID + b"#d\n"),
                              range(16)))
        seconds = time.perf_counter() - t0
        log_text = "".join(p.read_text(errors="replace")
                           for p in (work / "stack").rglob("*.log"))
    finally:
        client.close()
        stack_down(stack.workdir)
    stored = {p.parent.name for p in (work / "artifacts" / "assets").glob("*/bundle")}
    staging = [p for p in (work / "artifacts" / "tmp").rglob("*") if p.is_file()]
    leaked = sum(CANARY in b for b in bodies) + (CANARY in log_text)
    out = {
        "examples": examples, "seed": seed_value, "requests": sum(codes.values()),
        "seconds": round(seconds, 1),
        "status_codes": dict(sorted(codes.items())),
        "by_family": {k: dict(sorted(v.items())) for k, v in sorted(by_family.items())},
        "responses_5xx": sum(n for c, n in codes.items() if c >= 500),
        "requests_over_10s": slow, "transport_errors": sum("error" in f for f in failures),
        "bundles_stored_not_accepted": len(stored - accepted),
        "staging_files_left": len(staging),
        "canary_leaks": int(leaked),
        "duplicates_ok": all(r is not None and r.status_code in (200, 201) for r in dup),
        "failures": failures[:50],
    }
    out["nonfinite_settings_accepted"] = sum(
        f.get("family") == "job settings" and f.get("status", 500) < 300 for f in failures)
    out["passed"] = (out["responses_5xx"] == 0 and slow == 0 and out["transport_errors"] == 0
                     and out["nonfinite_settings_accepted"] == 0
                     and out["bundles_stored_not_accepted"] == 0
                     and out["staging_files_left"] == 0 and leaked == 0
                     and out["duplicates_ok"])
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--examples", type=int, default=1000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", type=Path, required=True)
    args = ap.parse_args(argv)
    tmp = Path(tempfile.mkdtemp(prefix="texelbake-fuzz-"))
    out = run(args.examples, args.seed, tmp)
    if out["passed"]:
        shutil.rmtree(tmp, ignore_errors=True)
    else:  # the stack's logs and the stored files, for the failures below
        print(f"kept {tmp}")
    print(f"{out['requests']} requests in {out['seconds']} s "
          f"({out['examples']} examples, seed {out['seed']})")
    print(f"{'family':<22} status codes")
    for fam, c in out["by_family"].items():
        print(f"{fam:<22} {c}")
    for key in ("responses_5xx", "requests_over_10s", "transport_errors",
                "bundles_stored_not_accepted", "staging_files_left", "canary_leaks",
                "nonfinite_settings_accepted", "duplicates_ok"):
        print(f"{key:<28} {out[key]}")
    for f in out["failures"][:10]:
        print("FAILURE", f)
    print("passed" if out["passed"] else "NOT PASSED (see failures; replay with --seed)")
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(out, indent=2, default=lambda o: None if (
        isinstance(o, float) and not math.isfinite(o)) else str(o)))
    return 0 if out["passed"] else 1


if __name__ == "__main__":
    sys.exit(main())
