"""Generated test scenes and what texelbake reads from an asset: `scenes`, `inspect`."""

from __future__ import annotations

import argparse
from pathlib import Path


def cmd_scenes(args: argparse.Namespace) -> int:
    from texelbake.testscenes import SCENE_NAMES, write_scene

    names = SCENE_NAMES if args.name == "all" else (args.name,)
    out = Path(args.output)
    if args.name == "arm":  # the skinned cylinder of seed 002 (texelbake.testscenes.arm)
        from texelbake.testscenes.arm import write_arm

        print(write_arm(out, args.size))
        return 0
    for name in names:
        path = out / f"{name}_{args.size}.usda" if args.name == "all" else out
        print(write_scene(name, path, args.size))
    return 0


def cmd_inspect(args: argparse.Namespace) -> int:
    from texelbake.asset import describe, load_asset

    print(describe(load_asset(args.file)))
    return 0


def add_parsers(sub: argparse._SubParsersAction) -> None:
    """The subcommands of this group."""
    p = sub.add_parser("scenes", help="write a generated test scene as USD")
    p.add_argument("name", choices=["cylinder", "wall", "bolt", "cloisonne", "all", "arm"])
    p.add_argument("-o", "--output", required=True, help="FILE.usda (or a folder with 'all')")
    p.add_argument("--size", choices=["small", "full"], default="small")
    p.set_defaults(func=cmd_scenes)

    p = sub.add_parser("inspect", help="print what texelbake reads from a USD asset")
    p.add_argument("file")
    p.set_defaults(func=cmd_inspect)
