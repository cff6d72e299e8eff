"""The chaos suite's machinery against real processes (`benchmarks/chaos.py`), two trials on
SQLite: artifact writes failing with ENOSPC for a while (survived by the retries), and a disk
that stays full past the retry budget (the job fails naming ENOSPC and the path; after the
fault clears, `POST /jobs/{id}/resume` completes it with the uninterrupted bake's bytes)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

pytestmark = [pytest.mark.service, pytest.mark.timeout(600)]
_SPEC = importlib.util.spec_from_file_location(
    "chaos", Path(__file__).resolve().parents[2] / "benchmarks" / "chaos.py"
)
chaos = importlib.util.module_from_spec(_SPEC)
_SPEC.loader.exec_module(chaos)


def test_chaos_trials_enospc_and_disk_full_then_resume(cylinder, reference, tmp_path):
    # cylinder, reference: tests/services/conftest.py, the same as chaos.make_scene's
    with chaos.open_farm("sqlite", tmp_path / "sqlite", cylinder, reference) as f:
        rec = chaos.run_trial(f, "sqlite", "enospc", 0, 1, tmp_path / "out")
        assert rec["passed"], repr(rec)
        assert "ENOSPC on artifact writes" in rec["fault"]
        # resume is for failed jobs only: a clear 409 for a finished one (the trial's job
        # succeeded), 404 for none
        r = f.http.post(f"/jobs/{rec['job_id']}/resume")
        assert r.status_code == 409 and r.json()["code"] == "job_not_failed", r.text
        r = f.http.post("/jobs/nosuchjob/resume")
        assert r.status_code == 404 and r.json()["code"] == "job_not_found", r.text

        rec = chaos.run_trial(f, "sqlite", "disk_full", 0, 1, tmp_path / "out")
        assert rec["passed"], repr(rec)
        # the fault struck while writes remained: the job failed, then resumed to success
        assert "No space left on device" in rec["fault"] and "resumed" in rec["fault"], rec
        assert rec["reruns"] > 0
        # and a trial does fail when the result is not the uninterrupted bake's
        f.baseline_hashes = {**f.baseline_hashes, "not/an/artifact.npz": "0" * 64}
        rec = chaos.run_trial(f, "sqlite", "worker_child", 0, 1, tmp_path / "out")
        assert not rec["passed"] and "artifacts differ" in rec["reason"], rec
