"""The ``ashc`` console script: imports the command line and runs it, so that Ctrl-C while the numerical libraries
load (the first second or two) ends like any later interrupt, in one line and exit code 130, not a traceback."""

from __future__ import annotations

import sys

from ashc_cli.errors import INTERRUPTED


def main() -> None:
    """Run ``ashc`` with ``sys.argv``; exit 130 on Ctrl-C at any point, the import of the libraries included."""
    try:
        from ashc_cli.cli import main as cli_main

        cli_main()
    except KeyboardInterrupt:
        sys.stderr.write(INTERRUPTED + "\n")
        sys.exit(130)
