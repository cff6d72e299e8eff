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


class Parser(argparse.ArgumentParser):
    """An argument parser whose epilog may be a function, called only when help is printed
    (the settings' table imports pydantic; `texelbake --help` stays instant)."""

    def format_help(self) -> str:
        if callable(self.epilog):
            self.epilog = self.epilog()
        return super().format_help()


def settings_help() -> str:
    """Every bake setting with its default, by group (`schemas.settings`): the epilog of each
    command that takes settings."""
    import textwrap

    from schemas.settings import BakeSettings

    groups: dict[str, list[str]] = {}
    for name, f in BakeSettings.model_fields.items():
        extra = f.json_schema_extra if isinstance(f.json_schema_extra, dict) else {}
        default = f.default if not isinstance(f.default, tuple) else list(f.default)
        groups.setdefault(str(extra.get("group", "settings")), []).append(
            f"{name}={json.dumps(default)}")
    lines = ["bake settings (--set KEY=VALUE; descriptions in the API schema), by group, with "
             "their defaults:"]
    for group, items in groups.items():
        lines += textwrap.wrap(", ".join(items), 96, initial_indent=f"  {group}: ",
                               subsequent_indent="    ")
    return "\n".join(lines)


def add_settings_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--settings", help="JSON file of bake settings (schemas.settings.BakeSettings)")
    p.add_argument("--set", action="append", metavar="KEY=VALUE",
                   help="override one bake setting, e.g. --set atlas_resolution=64")
    p.epilog = settings_help  # type: ignore[assignment]  # Parser calls it
    p.formatter_class = argparse.RawDescriptionHelpFormatter
