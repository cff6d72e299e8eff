"""`python -m texelbake.cli`: the `texelbake` command."""

import sys

from texelbake.cli import main

if __name__ == "__main__":
    sys.exit(main())
