"""Build the Blender add-on `blender/texelbake_submit` as an installable extension zip
(`<id>-<version>.zip`, Blender 4.2+ extension format): `make addon`, or
`python scripts/build_addon.py [-o DIR]`. Standard library only; the zip is deterministic
(sorted members, fixed timestamps), so a rebuild of the same sources is byte-identical.
Blender's own checker: `<bpy python> .../bl_pkg/cli/blender_ext.py validate ZIP`
(tests/dcc/test_addon.py runs it)."""

from __future__ import annotations

import argparse
import sys
import tomllib
import zipfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
SOURCE = ROOT / "blender" / "texelbake_submit"
ZIP_DATE = (1980, 1, 1, 0, 0, 0)


def build(out_dir: Path, source: Path = SOURCE) -> Path:
    """Write `<id>-<version>.zip` of `source` into `out_dir`; returns its path."""
    manifest = tomllib.loads((source / "blender_manifest.toml").read_text())
    files = sorted(p for p in source.rglob("*") if p.is_file()
                   and "__pycache__" not in p.parts and p.suffix != ".pyc")
    out_dir.mkdir(parents=True, exist_ok=True)
    dest = out_dir / f"{manifest['id']}-{manifest['version']}.zip"
    tmp = dest.with_name(dest.name + ".part")
    with zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED) as zf:
        for p in files:
            info = zipfile.ZipInfo(p.relative_to(source).as_posix(), ZIP_DATE)
            info.compress_type = zipfile.ZIP_DEFLATED
            info.external_attr = 0o644 << 16
            zf.writestr(info, p.read_bytes())
    tmp.replace(dest)
    return dest


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("-o", "--out-dir", type=Path, default=ROOT / "build")
    args = ap.parse_args(argv)
    print(build(args.out_dir))
    return 0


if __name__ == "__main__":
    sys.exit(main())
