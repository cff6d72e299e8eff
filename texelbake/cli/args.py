"""Bake settings from the command line: `--settings FILE` and `--set KEY=VALUE`."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from texelbake.errors import TexelbakeError


def settings_from_args(args: argparse.Namespace, base: dict | None = None):
    from pydantic import ValidationError

    from schemas.settings import BakeSettings

    data = dict(base or {})
    if getattr(args, "settings", None):
        data.update(json.loads(Path(args.settings).read_text()))
    for item in getattr(args, "set", None) or []:
        if "=" not in item:
            raise TexelbakeError(f"--set expects KEY=VALUE, got {item!r}")
        key, value = item.split("=", 1)
        try:
            data[key] = json.loads(value)
        except json.JSONDecodeError:
            data[key] = value
    try:
        return BakeSettings(**data)
    except ValidationError as exc:
        raise TexelbakeError(f"invalid bake settings: {exc}") from exc


def add_settings_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--settings", help="JSON file of bake settings (schemas.settings.BakeSettings)")
    p.add_argument("--set", action="append", metavar="KEY=VALUE",
                   help="override one bake setting, e.g. --set atlas_resolution=64")
