#!/usr/bin/env bash
# The real DCC for the `dcc` tests (issues 22, 23): Blender 5.0.1 as the `bpy` module from PyPI,
# in its own virtualenv (bpy pins its own numpy and is ~1 GB installed, so it stays out of .venv).
# Cached outside the clone; a second run does nothing. Prints the venv's python.
set -euo pipefail
BPY_VERSION=5.0.1
VENV="${TEXELBAKE_DCC_VENV:-$HOME/.cache/texelbake/dcc-venv-bpy$BPY_VERSION}"
if [ ! -f "$VENV/.installed" ]; then
  rm -rf "$VENV"
  mkdir -p "$(dirname "$VENV")"
  python3.11 -m venv "$VENV"
  "$VENV/bin/pip" install -q "bpy==$BPY_VERSION" >&2
  "$VENV/bin/python" -c "import bpy; assert bpy.app.version_string.startswith('$BPY_VERSION'), bpy.app.version_string" >&2
  touch "$VENV/.installed"
fi
echo "$VENV/bin/python"
