"""Hostile input at volume: a structure-aware fuzz suite against a real local stack.

    .venv/bin/python benchmarks/fuzz_uploads.py --cases 2000 [--seed N] [--json PATH]

Starts the API (no workers: the request path is under test) on its own Redis and a fresh
SQLite database, with a canary file beside the artifact root, and sends `--cases` requests
drawn by `tests.helpers.fuzz_cases` (zip and usdz mutations at the byte and the structure
level, USD text and crate mutations, settings from `BakeSettings`'s JSON Schema at and past
their bounds with non-finite values, Unicode edge cases, `Authorization`, `Last-Event-ID` and
lying `Content-Length` headers) from three clients at once, while a health check runs every
50 ms and the API's resident memory is sampled (`tests.helpers.fuzz_run`).

Passes with: 0 answers 5xx, 0 requests without an answer, 0 health checks over 2 s, API
memory growth under 100 MiB, 0 rows or files stored for a rejection, every job created
reading back (`GET /jobs/{id}` 200), the canary in no answer and no log. Prints a table by
family and status code, and writes the JSON (default `benchmarks/results/fuzz_uploads.json`).
A failing case is replayed with the same `--seed` and `--cases`.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # before benchmarks/ (its farm.py is not the farm package)

from farm.stack import free_port, stack_down, stack_up  # noqa: E402
from tests.helpers.fuzz_run import run  # noqa: E402

TOKEN = "fuzz-token-0123456789abcdef"
CANARY = "CANARY-8f2e61c0-texelbake-must-never-read-this"
CHECKS = ("responses_5xx", "no_answer", "health_stalls_over_2s", "health_p50_ms",
          "health_max_ms", "api_rss_start_mib", "api_rss_max_mib", "api_rss_growth_mib",
          "stored_rejections", "assets_accepted", "jobs_created", "jobs_read_back",
          "jobs_unreadable", "canary_leaks")  # fmt: skip


def fuzz(cases: int, seed: int, work: Path) -> dict:
    canary = work / "canary.usda"
    canary.write_text(f'#usda 1.0\n# {CANARY}\ndef "X" {{}}\n')
    stack = stack_up(work / "stack", redis_url=f"redis://127.0.0.1:{free_port()}/0",
                     workers={}, tokens={TOKEN: "fuzz"}, environment="test",
                     artifact_root=work / "artifacts",
                     database_url=f"sqlite:///{work / 'ledger.sqlite'}")  # fmt: skip
    try:
        return run(stack, TOKEN, cases, seed, canary=canary)
    finally:
        stack_down(stack.workdir)


def table(out: dict) -> str:
    codes = sorted({c for v in out["by_family"].values() for c in v}, key=int)
    lines = [f"{'family':<24}" + "".join(f"{c:>7}" for c in codes)]
    for fam, v in out["by_family"].items():
        lines.append(f"{fam:<24}" + "".join(f"{v.get(c, 0):>7}" for c in codes))
    lines.append("(status 0: the server closed without an answer, accepted only for a lying "
                 "Content-Length or an events stream; -1: the client refused to send it)")
    lines += [f"{k:<28} {out[k]}" for k in CHECKS]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cases", type=int, default=2000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", type=Path, default=ROOT / "benchmarks/results/fuzz_uploads.json")
    args = ap.parse_args(argv)
    tmp = Path(tempfile.mkdtemp(prefix="texelbake-fuzz-"))
    out = fuzz(args.cases, args.seed, tmp)
    if out["passed"]:
        shutil.rmtree(tmp, ignore_errors=True)
    else:  # the stack's logs and the stored files, for the failures below
        print(f"kept {tmp}")
    print(f"{out['cases']} cases in {out['seconds']} s (seed {out['seed']})")
    print(table(out))
    for f in out["failures"][:10]:
        print("FAILURE", f)
    print("passed" if out["passed"] else "NOT PASSED (see failures; replay with --seed)")
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(out, indent=2, sort_keys=True))
    return 0 if out["passed"] else 1


if __name__ == "__main__":
    sys.exit(main())
