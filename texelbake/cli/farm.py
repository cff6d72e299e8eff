"""The farm from the command line: `submit` (one asset or a manifest), `stack` (local processes)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from texelbake.cli.args import add_settings_args, settings_from_args
from texelbake.errors import TexelbakeError

#: `texelbake submit --manifest`: the batch finished, and some item failed or was cancelled
EXIT_ITEMS_FAILED = 4


def cmd_submit_manifest(args: argparse.Namespace) -> int:
    from texelbake_client.batch import failed_items, load_manifest, submit_batch

    if args.file or args.settings or args.set:
        raise TexelbakeError("--manifest takes its files and settings from the manifest: "
                             "give no FILE, --settings or --set with it")
    paths = load_manifest(args.manifest).paths
    batch = submit_batch(Path(args.manifest), server=args.server, token=args.token,
                         out_dir=Path(args.output))
    out = Path(args.output)
    print(f"batch {batch['id']}: {batch['state']}; {batch['counts']['succeeded']} of "
          f"{batch['counts']['total']} items succeeded; results in {out}")
    bad = failed_items(batch, paths)
    for line in bad:
        print(f"texelbake: {line}", file=sys.stderr)
    return EXIT_ITEMS_FAILED if bad else 0


def cmd_submit(args: argparse.Namespace) -> int:
    from texelbake_client.submit import submit

    if args.manifest:
        return cmd_submit_manifest(args)
    if not args.file:
        raise TexelbakeError("submit needs a FILE or --manifest FILE")
    settings = settings_from_args(args)
    result = submit(Path(args.file), server=args.server, token=args.token,
                    out_dir=Path(args.output), settings=settings.model_dump())
    print(result)
    return 0


def cmd_stack(args: argparse.Namespace) -> int:
    # the launcher lives next to the service it launches (stdlib only: importing it pulls in
    # neither FastAPI, Celery nor Redis); the CLI is the one place the core reaches for it
    from farm import stack

    if args.action == "up":
        # tokens, Redis, database, artifact root and secret from TEXELBAKE_* as the server
        # reads them (farm.stack.stack_up); it says which Redis it uses and whether it started it
        for line in stack.stack_up(Path(args.dir)).describe():
            print(line)
    else:
        stack.stack_down(Path(args.dir))
    return 0


def add_parsers(sub: argparse._SubParsersAction) -> None:
    """The subcommands of this group."""
    p = sub.add_parser("submit", help="upload an asset (or a manifest's assets, as one batch) "
                       "to a texelbake server and fetch the result")
    p.add_argument("file", nargs="?")
    p.add_argument("--manifest", help="JSON manifest of many assets (texelbake_client.batch); "
                   f"exit status {EXIT_ITEMS_FAILED} when an item failed")
    p.add_argument("--server", required=True)
    p.add_argument("--token", required=True)
    p.add_argument("-o", "--output", default="result")
    add_settings_args(p)
    p.set_defaults(func=cmd_submit)

    p = sub.add_parser("stack", help="start/stop redis, the API and workers as local processes "
                       "(TEXELBAKE_TOKENS, TEXELBAKE_REDIS_URL and the other TEXELBAKE_* settings "
                       "from the environment, as the server reads them)")
    p.add_argument("action", choices=["up", "down"])
    p.add_argument("--dir", default="var/stack", help="state folder (pids, logs, database)")
    p.set_defaults(func=cmd_stack)
