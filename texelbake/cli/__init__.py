"""`texelbake` command line: scenes, inspect, bake, demo, render, srf-capture, export, report,
submit, stack.

Heavy modules are imported inside each command so `texelbake --help` is instant.
Exit status: 0 done, 2 error (texelbake.errors), 3 `bake` finished below a quality target
(texelbake.stages.quality; `--accept-below-target` makes it 0), 4 `submit --manifest`: the batch
finished but some item failed or was cancelled (each is printed).
"""

from __future__ import annotations

import argparse
import sys

from texelbake.cli import bake, farm, render, scenes
from texelbake.cli.args import Parser
from texelbake.errors import TexelbakeError


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(prog="texelbake", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    for group in (scenes, bake, render, farm):
        group.add_parsers(sub)
    return parser


def _show_asset_warnings_plainly() -> None:
    """An asset's warnings on the terminal as "warning: <message>" lines (Python's default
    format adds the file and source line of texelbake's reader, which names nothing in the
    asset); other warnings keep the default format."""
    import warnings

    from texelbake.asset.values import AssetWarning

    default = warnings.formatwarning

    def fmt(message, category, filename, lineno, line=None):
        if issubclass(category, AssetWarning):
            return f"warning: {message}\n"
        return default(message, category, filename, lineno, line)

    warnings.formatwarning = fmt  # type: ignore[assignment]


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    _show_asset_warnings_plainly()
    try:
        return int(args.func(args) or 0)
    except TexelbakeError as exc:
        print(f"texelbake: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
