"""``python -m ashc_cli``: the same as ``ashc``."""

from ashc_cli.console import main

main()
