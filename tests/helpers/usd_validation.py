"""Stock validation of USD files: pxr's validators run in a fresh interpreter that never
imports texelbake (and without the plug-in path), as any other tool would open our output.

What the fresh process does with each file is what a viewer does on open: open the stage
(payloads loaded), traverse every prim, resolve each mesh's bound material and each shader's
Sdr node for every source type it names, then run every registered validator (each time range)
over the stage. Anything pxr prints on the way (its warnings go to stderr) is returned too:
opening our output must print nothing."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

#: run in a fresh interpreter: stock pxr only; fails if texelbake was imported somehow
STOCK_VALIDATE = r"""
import json, sys
from pxr import Usd, UsdGeom, UsdShade, UsdValidation
out = {}
for path in sys.argv[1:]:
    stage = Usd.Stage.Open(path)
    for prim in stage.Traverse():
        if prim.IsA(UsdGeom.Mesh):
            UsdShade.MaterialBindingAPI(prim).ComputeBoundMaterial()
        shader = UsdShade.Shader(prim)
        if shader:
            for source_type in shader.GetSourceTypes():
                shader.GetShaderNodeForSourceType(source_type)
    ctx = UsdValidation.ValidationContext(
        list(UsdValidation.ValidationRegistry().GetAllValidatorMetadata()), True)
    out[path] = [f"{e.GetName()}: {e.GetMessage()}" for e in ctx.Validate(stage)
                 if e.GetType() == UsdValidation.ValidationErrorType.Error]
assert not [m for m in sys.modules if m.split(".")[0] in ("texelbake", "schemas")]
print(json.dumps(out))
"""


def stock_check(*paths: Path) -> tuple[dict[str, list[str]], str]:
    """({path: [error, ...]}, what pxr printed to stderr) from a fresh process (no texelbake,
    no plug-in path) that opens each file as a viewer would and validates it."""
    env = {k: v for k, v in os.environ.items()
           if not k.startswith(("PXR_", "PYTHONPATH", "TF_"))}
    r = subprocess.run([sys.executable, "-c", STOCK_VALIDATE, *map(str, paths)],
                       capture_output=True, text=True, timeout=300, env=env, cwd="/")
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout.strip().splitlines()[-1]), r.stderr


def stock_errors(*paths: Path) -> dict[str, list[str]]:
    """{path: [error, ...]} from pxr's validators in a fresh process (`stock_check`); also
    asserts that opening and validating the files printed nothing."""
    errors, printed = stock_check(*paths)
    assert printed == "", f"a stock pxr printed on opening {[str(p) for p in paths]}:\n{printed}"
    return errors
