"""Where things live under the artifact root (shared by the API and every worker).

<root>/assets/<sha256>/bundle/...      an accepted upload (read-only after the rename)
<root>/work/<key>/artifacts/...        stage artifacts; key = hash(asset sha, settings)
<root>/jobs/<job id>/out/...           the baked USD bundle, report.json, previews/
<root>/jobs/<job id>/result.zip        the bundle as one download (built on first request)
<root>/jobs/<job id>/run.json          the run's facts (stage seconds, worker, date): they differ
                                       between runs, so they stay out of out/ and result.zip
<root>/batches/<id>/result-<digest>.zip a finished batch as one download (per batch.json)
<root>/tmp/                            staging of uploads (same filesystem: atomic renames)
"""

from __future__ import annotations

import hashlib
from pathlib import Path


def assets_dir(root: Path) -> Path:
    return Path(root) / "assets"


def asset_bundle(root: Path, sha256: str) -> Path:
    return assets_dir(root) / sha256 / "bundle"


def tmp_dir(root: Path) -> Path:
    d = Path(root) / "tmp"
    d.mkdir(parents=True, exist_ok=True)
    return d


def work_dir(root: Path, asset_sha256: str, settings_digest: str) -> Path:
    key = hashlib.sha256(f"{asset_sha256}:{settings_digest}".encode()).hexdigest()[:24]
    return Path(root) / "work" / key


def job_dir(root: Path, job_id: str) -> Path:
    return Path(root) / "jobs" / job_id


def job_run(root: Path, job_id: str) -> Path:
    """The job's run facts (`texelbake.stages.write_run`), beside its result zip."""
    return job_dir(root, job_id) / "run.json"


def job_out(root: Path, job_id: str) -> Path:
    return job_dir(root, job_id) / "out"


def batch_dir(root: Path, batch_id: str) -> Path:
    return Path(root) / "batches" / batch_id
