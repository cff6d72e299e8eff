"""A seeded sample of the fuzz suite (`benchmarks/fuzz_uploads.py` runs 2,000+ cases) against
a real uvicorn, Redis and SQLite: every case answered below 500, nothing stored for a
rejection, every job created reads back, the API's memory flat and its health check fast."""

from __future__ import annotations

import pytest

from farm.stack import OWN_REDIS, stack_down, stack_up
from tests.helpers.fuzz_cases import generate
from tests.helpers.fuzz_run import run

pytestmark = [pytest.mark.service, pytest.mark.timeout(180)]

TOK = "token-fuzz-sample-0123456789"
N_CASES = 50


def test_generator_is_seeded_and_covers_every_family():
    a = generate(400, 7, token=TOK, asset_id="a", job_id="j", port=1)
    b = generate(400, 7, token=TOK, asset_id="a", job_id="j", port=1)
    assert [(c.family, c.body, c.files, c.raw) for c in a] == [
        (c.family, c.body, c.files, c.raw) for c in b]
    assert {c.family for c in a} >= {
        "zip bytes", "zip structure", "usdz bytes", "usdz structure", "usda text",
        "usdc crate", "odd filename", "settings: job", "settings: batch",
        "header: authorization", "header: last-event-id", "header: content-length"}


def test_seeded_fuzz_sample(tmp_path):
    canary = tmp_path / "canary.usda"
    canary.write_text('#usda 1.0\n# CANARY-fuzz-sample-never-read\ndef "X" {}\n')
    work = tmp_path / "stack"
    stack = stack_up(work, redis_url=OWN_REDIS, workers={},
                     tokens={TOK: "fuzz"}, environment="test",
                     database_url=f"sqlite:///{tmp_path / 'ledger.sqlite'}")  # fmt: skip
    try:
        out = run(stack, TOK, N_CASES, seed=20261205, canary=canary)
    finally:
        stack_down(work)
    assert out["responses_5xx"] == 0 and out["no_answer"] == 0, out["failures"]
    assert out["stored_rejections"] == 0
    assert out["jobs_unreadable"] == 0 and out["jobs_read_back"] == out["jobs_created"]
    assert out["health_stalls_over_2s"] == 0, out["health_max_ms"]
    assert out["api_rss_growth_mib"] < 100
    assert out["canary_leaks"] == 0
    assert sum(sum(v.values()) for v in out["by_family"].values()) == N_CASES
