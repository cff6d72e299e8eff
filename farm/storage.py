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
import os
import re
import sys
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


#: pxr's error preamble: the C++ function, line and build path before the commentary
_PXR_PREAMBLE = re.compile(r"Error in '[^']*' at line \d+ in file [^ ]+ : ")


def public_text(text: str, root: Path) -> str:
    """`text` (an error a client will read) without server paths: a file of an asset's bundle
    is named relative to the bundle, other paths under `root` relative to it, paths of the
    code and the interpreter by their tail; pxr's preamble goes."""
    text = _PXR_PREAMBLE.sub("", text)
    roots = {str(root), os.path.realpath(root)}
    for base in sorted(roots, key=len, reverse=True):
        text = re.sub(re.escape(f"{base}/assets/") + r"[0-9a-f]{64}/bundle/", "", text)
        text = text.replace(f"{base}/", "").replace(base, "<storage>")
    code = str(Path(__file__).resolve().parents[1])
    for base in sorted({code, sys.prefix, sys.base_prefix}, key=len, reverse=True):
        text = text.replace(f"{base}/", "…/")
    return text
