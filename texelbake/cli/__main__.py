"""`python -m texelbake.cli`: the `texelbake` command."""

import sys

from texelbake.cli import main

sys.exit(main())
