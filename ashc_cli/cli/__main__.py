"""``python -m ashc_cli.cli``: the same as ``ashc``."""

from ashc_cli.cli import main

main()
