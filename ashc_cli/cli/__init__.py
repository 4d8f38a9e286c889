"""The ``ashc`` command line: a thin typer layer over :mod:`ashc_cli.design.pipeline` and :mod:`ashc_cli.outputs.query`.

The shared parts are in :mod:`~ashc_cli.cli.common`; the commands in three rooms: the flow chart's
(:mod:`~ashc_cli.cli.stage_commands`), the products built on a design (:mod:`~ashc_cli.cli.product_commands`) and
those that read a finished one (:mod:`~ashc_cli.cli.output_commands`).

One output channel: stdout carries only a command's result (a summary line or table, JSON, file paths);
progress goes to stderr, for every command: one line per stage (``<stage> <status> <seconds> s
<headline>``) and, when stderr is a terminal, a live display (:class:`Progress`) while a step runs.

Every error the tool means to report is an :class:`~ashc_cli.errors.AshcError`; the CLI prints it as one
line ``error: <where>: <what>; expected <what>`` on stderr and exits with its code (2 spec, 3 design
condition, 4 numerical, 5 artefact; 1 for an internal bug).  ``--debug`` anywhere on the line shows the
traceback instead.
"""

# isort: off
# Importing the command modules registers their commands, in this order (the order of `ashc --help`).
from ashc_cli.cli import stage_commands  # noqa: F401
from ashc_cli.cli import product_commands  # noqa: F401
from ashc_cli.cli import output_commands  # noqa: F401
# isort: on
from ashc_cli.cli.common import Progress, app, main, plain_text

__all__ = ["app", "main", "Progress", "plain_text"]
