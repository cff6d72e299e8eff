"""Stock validation of USD files: pxr's validators run in a fresh interpreter that never
imports texelbake (and without the plug-in path), as any other tool would open our output."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

#: run in a fresh interpreter: stock pxr only; fails if texelbake was imported somehow
STOCK_VALIDATE = r"""
import json, sys
from pxr import Usd, UsdValidation
out = {}
for path in sys.argv[1:]:
    stage = Usd.Stage.Open(path)
    ctx = UsdValidation.ValidationContext(
        list(UsdValidation.ValidationRegistry().GetAllValidatorMetadata()), True)
    out[path] = [f"{e.GetName()}: {e.GetMessage()}" for e in ctx.Validate(stage)
                 if e.GetType() == UsdValidation.ValidationErrorType.Error]
assert not [m for m in sys.modules if m.split(".")[0] in ("texelbake", "schemas")]
print(json.dumps(out))
"""


def stock_errors(*paths: Path) -> dict[str, list[str]]:
    """{path: [error, ...]} from pxr's validators in a fresh process (no texelbake, no plug-in
    path)."""
    env = {k: v for k, v in os.environ.items()
           if not k.startswith(("PXR_", "PYTHONPATH"))}
    r = subprocess.run([sys.executable, "-c", STOCK_VALIDATE, *map(str, paths)],
                       capture_output=True, text=True, timeout=300, env=env, cwd="/")
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout.strip().splitlines()[-1])
