"""The real DCC for the `dcc` tests: Blender (the `bpy` module, pinned in scripts/dcc-venv.sh)
runs in its own virtualenv, always in a subprocess, never imported into the test process."""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

import pytest

from tests.svc_util import backend_missing

ROOT = Path(__file__).resolve().parent.parent
VENV_SCRIPT = ROOT / "scripts" / "dcc-venv.sh"


def bpy_python() -> Path:
    """The Python of the bpy virtualenv that `scripts/dcc-venv.sh` made (`make setup` and
    `.ci/run` make it). Skips when it is missing (fails under CI: `backend_missing`)."""
    venv = os.environ.get("TEXELBAKE_DCC_VENV") or str(
        Path.home() / ".cache" / "texelbake" / "dcc-venv-bpy5.0.1")
    exe = Path(venv) / "bin" / "python"
    if not (Path(venv) / ".installed").exists() or not exe.exists():
        backend_missing(f"no bpy virtualenv at {venv}: run scripts/dcc-venv.sh")
    return exe


def run_blender(script: Path | str, *args: str, timeout: float = 600.0) -> dict:
    """Run a Python script inside Blender (headless bpy) with `args` after `--`; the script
    prints one JSON object on its last stdout line, which is returned."""
    exe = bpy_python()
    proc = subprocess.run([str(exe), str(script), "--", *args], capture_output=True,
                          text=True, timeout=timeout, cwd=str(ROOT))
    if proc.returncode != 0:
        pytest.fail(f"Blender script {script} failed ({proc.returncode}):\n"
                    f"{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}", pytrace=False)
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("{")]
    if not lines:
        pytest.fail(f"Blender script {script} printed no JSON:\n{proc.stdout[-3000:]}",
                    pytrace=False)
    return json.loads(lines[-1])


__all__ = ["bpy_python", "run_blender"]
