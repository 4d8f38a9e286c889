"""What every ``ashc`` command shares: the typer app, the option types, the error guard (one line on stderr, the
documented exit code), the live progress display on stderr and the step that brings a design up to date."""

from __future__ import annotations

import functools
import os
import json
import re
import sys
import traceback
import warnings
from pathlib import Path
from typing import Annotated

import numpy as np
import typer

from ashc_cli.errors import INTERRUPTED, AshcError, SpecError
from ashc_cli.outputs.numbers import no_negative_zero, number_text

# The design machinery (sympy, scipy, cvxpy, numba: about a second to import) is imported inside the commands
# that use it, never here: `ashc --help`, `--version` and an error in the arguments return at once.

#: The falsify product's name (``ashc_cli.products.falsify.NAME``; a test keeps the two equal).
FALSIFY = "falsify"

#: What `ashc eval` evaluates (the keys of ``ashc_cli.outputs.query.EVALUABLE``; a test keeps the two equal).
EVALUABLE_NAMES = ("p", "kappa", "m", "delta", "b", "c", "theta")


def engine():
    """The design pipeline, imported on first use with the products registered on it (falsify, tradeoff).

    Returns
    -------
    module
        :mod:`ashc_cli.design.pipeline`.
    """
    import ashc_cli.products  # noqa: F401  (registers falsify and tradeoff with the pipeline)
    from ashc_cli.design import pipeline

    return pipeline

app = typer.Typer(
    name="ashc",
    help=(
        "Approximate simulation-based hierarchical control (ASHC) design for nonlinear input-affine systems.\n\n"
        "Write a YAML spec of your plant and abstraction, run `ashc design SPEC` to get a certified "
        "abstraction, interface and error bound (one HDF5 artefact per stage under outputs/<name>/), then "
        "`ashc simulate SPEC` to see it work and `ashc summary DIR --json` for the numbers.\n\n"
        "Results go to stdout; progress (one line per stage, and a live display when stderr is a terminal) "
        "and errors go to stderr.\n\n"
        "Exit codes: 0 done; 2 bad spec or argument; 3 a design condition fails; 4 numerical failure; "
        "5 artefact problem; 1 internal error. Add --debug anywhere for a traceback."
    ),
    add_completion=True,
    pretty_exceptions_enable=False,
    rich_markup_mode=None,
)

_DEBUG = False


def _print_version(value: bool) -> None:
    if value:
        from ashc_cli import __version__

        typer.echo(f"ashc {__version__}")
        raise typer.Exit(0)


@app.callback(invoke_without_command=True)
def _root(ctx: typer.Context,
          version: Annotated[bool, typer.Option("--version", "-V", help="Print the ashc version and exit.", callback=_print_version, is_eager=True)] = False) -> None:
    """Bare ``ashc`` prints the help and exits 0."""
    if ctx.invoked_subcommand is None:
        typer.echo(ctx.get_help())
        raise typer.Exit(0)

SpecArg = Annotated[Path, typer.Argument(metavar="SPEC", help="The YAML spec (see docs/spec-format.md).", show_default=False)]
OutOpt = Annotated[Path | None, typer.Option("--out", help="Artefact folder [default: outputs/<spec name>].", show_default=False)]
ForceOpt = Annotated[bool, typer.Option("--force", help="Recompute every needed stage even if up to date.")]
JsonOpt = Annotated[bool, typer.Option("--json", help="Print the result as JSON on stdout.")]
NumericOpt = Annotated[bool | None, typer.Option("--numeric/--symbolic", help=(
    "Force the numeric fast paths (grids and interpolants) or the symbolic ones (sympy) [default: numeric above 12 states]. "
    "Stages already up to date are kept (a note on stderr names them): add --force when switching on an existing folder."), show_default=False)]


def frozen_opt(text: str):
    """A ``--frozen`` option with the help ``text`` (what it freezes differs between commands).

    Parameters
    ----------
    text : str
        The option's help.

    Returns
    -------
    typing.Annotated
        ``bool`` annotated with the typer option.
    """
    return Annotated[bool, typer.Option("--frozen", help=text)]


#: --frozen of the stage commands: the stage itself may run, its upstream may not.
StageFrozenOpt = frozen_opt("Never rerun an upstream stage: fail (exit 5, naming the stage) if one is stale. This stage itself "
                             "runs if stale; with --force it always runs, and only it.")


def guard(fn):
    """Run a command body, turning ashc's errors into one line on stderr and the documented exit code.

    Parameters
    ----------
    fn : callable
        The command's body.

    Returns
    -------
    callable
        ``fn`` wrapped: an :class:`~ashc_cli.errors.AshcError` exits with its code, Ctrl-C with 130, any other
        exception with 1 (a traceback only with ``--debug``).
    """

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except AshcError as exc:
            if _DEBUG:
                traceback.print_exc()
            typer.echo(f"error: {exc.line()}", err=True)
            raise typer.Exit(exc.exit_code) from None
        except KeyboardInterrupt:
            typer.echo(INTERRUPTED, err=True)
            raise typer.Exit(130) from None
        except BrokenPipeError:
            # The reader went away (`ashc summary out | head`): nothing more to say to it, and no error of ashc's.
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
            raise typer.Exit(0) from None
        except (typer.Exit, typer.Abort):
            raise
        except Exception as exc:  # a bug: say so in one line unless debugging
            if _DEBUG:
                raise
            typer.echo(f"error: internal: {type(exc).__name__}: {' '.join(str(exc).split())[:300]}; rerun with --debug and report it", err=True)
            raise typer.Exit(1) from None

    return wrapper


#: "-0", "-0.0", "-0e+00" standing alone in a text (not "-0.5", not "x-0").
_NEGATIVE_ZERO = re.compile(r"(?<![\w.])-(0(?:\.0*)?(?:[eE][+-]?0+)?)(?![\w.])")


def plain_text(text: str) -> str:
    """``text`` with every standalone negative zero ("-0", "-0.0") written without its sign.

    For lines whose numbers were formatted elsewhere (stage headlines); numbers the CLI formats itself go
    through :func:`ashc_cli.outputs.query.number_text`.

    Parameters
    ----------
    text : str
        A line to print.

    Returns
    -------
    str
    """
    return _NEGATIVE_ZERO.sub(r"\1", text)


class Progress:
    """What a command shows on stderr while it works (stdout carries only its result).

    Every stage prints one line, ``<stage> <status> <seconds> s  <headline>``, whatever stderr is.  When
    stderr is a terminal, a step that takes time (a stage being computed, the falsification, a sweep, a
    regression run, drawing figures) also shows a live display while it runs (rich): a spinner with the time
    so far, or a bar, with the runs per second for falsify and the combinations done for sweep.  The display
    is erased when the step ends, so what stays on the screen is what a pipe receives.

    Parameters
    ----------
    live : bool, optional
        Show the live display [default: whether stderr is a terminal].

    Notes
    -----
    Use it as a context manager, so that an error stops the display before its message is printed.
    """

    def __init__(self, live: bool | None = None):
        self.live = sys.stderr.isatty() if live is None else live
        self._display = None
        self._task = None
        self._shown_up_to_date: set[str] = set()

    def __enter__(self) -> Progress:
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

    def line(self, text: str) -> None:
        """Print one line on stderr (above the live display, if one is shown)."""
        text = plain_text(text)
        if self._display is not None:
            self._display.console.print(text, markup=False, highlight=False, emoji=False, soft_wrap=True)
        else:
            typer.echo(text, err=True)

    def result(self, text: str) -> None:
        """Print one line of the result on stdout while a step is shown (the display is erased and drawn again)."""
        if self._display is None:
            typer.echo(text)
            return
        self._display.stop()
        typer.echo(text)
        self._display.start()

    def start(self, what: str, total: int | None = None, count: bool = False) -> None:
        """Show the live display of one step (only when stderr is a terminal).

        Parameters
        ----------
        what : str
            The step, e.g. ``"simulate: no artefact yet"``.
        total : int, optional
            The number of steps, for a bar; None shows a spinner and the time so far.
        count : bool
            Show "done/total" rather than a percentage.
        """
        if not self.live:
            return
        self.stop()
        from rich.console import Console
        from rich.progress import (BarColumn, MofNCompleteColumn, Progress as RichProgress, SpinnerColumn, TaskProgressColumn,
                                   TextColumn, TimeElapsedColumn)

        columns = [SpinnerColumn(), TextColumn("{task.description}", markup=False), BarColumn(bar_width=24)]
        if total is not None:
            columns.append(MofNCompleteColumn() if count else TaskProgressColumn())
        columns += [TimeElapsedColumn(), TextColumn("{task.fields[note]}", markup=False)]
        # stdout is not redirected: it carries the result, never the display.
        self._display = RichProgress(*columns, console=Console(stderr=True), transient=True, redirect_stdout=False)
        self._task = self._display.add_task(what, total=total, note="")
        self._display.start()

    def update(self, completed: int | None = None, note: str | None = None) -> None:
        """Move the bar to ``completed`` steps and/or set the note after it (e.g. the runs per second)."""
        if self._display is None:
            return
        fields = {} if note is None else {"note": note}
        self._display.update(self._task, completed=completed, **fields)

    def stop(self) -> None:
        """Erase the live display, if one is shown."""
        if self._display is not None:
            self._display.stop()
            self._display = self._task = None

    def on_start(self, stage: str, reason: str) -> None:
        """Called by :func:`ashc_cli.design.pipeline.run` before a stage is computed: show it while it runs."""
        from ashc_cli.products.falsify import SEGMENTS

        self.start(f"{stage}: {reason}", total=SEGMENTS if stage == FALSIFY else None)

    def on_stage(self, report) -> None:
        """Called after each stage: erase the display and print the stage line (an "up to date" line once per
        command: ``report`` brings the design up to date for simulate, falsify and itself)."""
        self.stop()
        if report.status == "up to date":
            if report.stage in self._shown_up_to_date:
                return
            self._shown_up_to_date.add(report.stage)
        self.line(f"{report.stage:<10} {report.status:<10} {report.seconds:7.2f} s  {report.headline}")


def load(spec_path: Path, out: Path | None):
    """The spec and its artefact folder (``--out``, or outputs/<spec name>).

    Parameters
    ----------
    spec_path : Path
        The YAML spec.
    out : Path or None
        ``--out``.

    Returns
    -------
    spec : Spec
    folder : Path
    """
    from ashc_cli.problem.spec import load_spec

    spec = load_spec(spec_path)
    folder = Path(out if out is not None else engine().default_out(spec))
    usable_folder(folder, "--out" if out is not None else "name")
    return spec, folder


def usable_folder(folder: Path, field: str) -> None:
    """Refuse, before anything is computed, an artefact folder that cannot exist: a file on the way, a path under
    /proc or /dev/null, a folder that cannot be created.  A missing folder is created and removed again (the probe
    leaves nothing behind; the stage that writes creates it for good).

    Parameters
    ----------
    folder : Path
        The artefact folder.
    field : str
        What the error names (``--out``, or ``name`` for the default ``outputs/<name>``).

    Raises
    ------
    SpecError
        Exit 2, one line naming the field, the path and why.
    """
    from ashc_cli.errors import SpecError

    expected = "a folder that exists or can be created (--out PATH)"
    if folder.exists():
        if not folder.is_dir():
            raise SpecError(field, f"'{folder}' is a file, not a folder", expected)
        return
    missing = []
    p = folder
    while not p.exists() and p.parent != p:
        missing.append(p)
        p = p.parent
    if not p.is_dir():
        raise SpecError(field, f"'{folder}' lies under '{p}', which is a file, not a folder", expected)
    created = []
    try:
        for q in reversed(missing):
            q.mkdir()
            created.append(q)
    except OSError as exc:
        raise SpecError(field, f"'{folder}' cannot be created ({exc.strerror or type(exc).__name__})", expected) from None
    finally:
        for q in reversed(created):
            try:
                q.rmdir()
            except OSError:
                pass


def run_targets(spec_path: Path, out: Path | None, targets, force: bool, progress: Progress, frozen=False, numeric: bool | None = None):
    """Load the spec and bring ``targets`` up to date (:func:`ashc_cli.design.pipeline.run`), with progress on stderr.

    Parameters
    ----------
    spec_path, out : Path, Path or None
        The spec and ``--out``.
    targets : sequence of str
        The stages (or products) wanted; their stale upstream stages run first.
    force : bool
        ``--force``: recompute every needed stage that is not frozen.
    frozen : bool or iterable of str
        As :func:`ashc_cli.design.pipeline.frozen_stages`: True freezes every stage upstream of the targets, an
        iterable exactly the stages it names.
    progress : Progress
        Where each stage's line goes.
    numeric : bool or None
        ``--numeric/--symbolic`` (None: by the plant's size).

    Returns
    -------
    spec : Spec
    folder : Folder
        The folder as this command has seen it (pass it on, so that each artefact is read once).
    arts : dict of str to Artefact
    """
    spec, path = load(spec_path, out)
    pipeline = engine()
    folder = pipeline.Folder(path)
    kept = []

    def on_stage(report) -> None:
        if report.status != "ran":
            kept.append(report.stage)
        progress.on_stage(report)

    arts = pipeline.run(spec, folder, targets, force=force, frozen=frozen, on_stage=on_stage, on_start=progress.on_start, numeric=numeric)
    if numeric is not None and kept:
        progress.line(f"note: {'--numeric' if numeric else '--symbolic'} did not apply to the stage(s) kept as they were "
                      f"({', '.join(kept)}); add --force to recompute them")
    return spec, folder, arts


def exclusive(force: bool, frozen: bool, command: str) -> None:
    """Refuse --force with --frozen on a command for which they contradict (every stage against none).

    Parameters
    ----------
    force, frozen : bool
        The two options.
    command : str
        The command's name, for the message.

    Raises
    ------
    SpecError
        When both are given (exit 2).
    """
    if force and frozen:
        raise SpecError("--force", f"cannot be combined with --frozen on `ashc {command}` (--force recomputes every stage it needs, "
                        "--frozen none)", "one of --force and --frozen")


def emit_json(obj) -> None:
    """Print ``obj`` as one JSON document on stdout (-0.0 as 0.0).

    Parameters
    ----------
    obj : object
        Anything ``json.dumps`` takes.
    """
    typer.echo(json.dumps(no_negative_zero(obj), indent=2, sort_keys=False))


STAGE_HELP = {
    "stabilise": "Certify stabilisability: solve (or verify) the LMI A(u)^T M + M A(u) <= -lambda M at the vertices of U (eq. (28)); store M, lambda and the margins.",
    "manifold": "Solve the invariance PDE dp/dxi phi_bar = f_bar(p) + g(p) l(xi) for p (eq. (14a)); store p and its residual on V.",
    "kappa": "Compose the abstract output map kappa = h o p (eq. (14b)).",
    "inverse": "Find the left inverse m of p and check injectivity, V covering Y (eq. (10)), conditions (i)-(ii) of Theorem 6 and where m is real.",
    "delta": "Check delta's rank on V and build the m-relation link v = b(x) + c(x) u (Theorem 5).",
    "bound": "Compute alpha_h, epsilon, dbar (q = 0 and least squares, eq. (37)) and the gain G of the error bound (eq. (38)).",
    "simulate": "Run the tracking and m-relation scenarios of the spec (Figs. 7, 8, 9, 10), designing first if needed. A scenario check "
                "that fails (psi not settled, u outside U, an m-relation run that leaves where m is certified while the tracking run "
                "completes, ...) is printed as 'FAILED (simulated)' and listed by `ashc check`; the exit status stays 0, since it "
                "observes one run and is not a design condition of Problem 1. A scenario that stops with nothing else completed exits 3.",
}

#: The one-line summary of every command in `ashc --help` (click would cut the help at its first ". ",
#: which in "(eq. (28))" is mid-sentence).
SHORT_HELP = {
    "stabilise": "Certify stabilisability: the LMI for M and lambda on U.",
    "manifold": "Solve the invariance PDE for the manifold map p.",
    "kappa": "Compose the abstract output map kappa = h o p.",
    "inverse": "Find the left inverse m of p and where it is certified.",
    "delta": "Check delta's rank on V and build the m-relation link.",
    "bound": "Compute the error bound: alpha_h, epsilon, dbar and gain G.",
    "simulate": "Run the spec's tracking and m-relation scenarios.",
    "design": "Run the design stages stabilise..bound (the stale ones).",
    "check": "Give the verdict on Problem 1, one row per condition.",
    "plot": "Draw the paper's figures for this design (PNG, PDF or SVG).",
    "falsify": "Search for a run that breaks the certified error bound.",
    "report": "Write a self-contained HTML page for a design review.",
    "synthesize": "Solve the output task on the abstraction, for the plant.",
    "sweep": "Design the spec over a grid of parameter values (Dask).",
    "example": "Write an example spec: one shipped, or a scalable plant.",
    "regress": "Rerun a folder of specs and compare with golden values.",
    "summary": "Print each stage's headline numbers, formulas and checks.",
    "eval": "Evaluate a stored function (p, kappa, m, ...) or u_w at a point.",
    "tradeoff": "Time to reach the levels against the guaranteed tolerance.",
    "export": "Write the design as C99 code and header, or a numpy module.",
    "version": "Print the ashc version.",
}



RunsOpt = Annotated[int, typer.Option("--runs", min=1, max=100000, help="Number of closed-loop runs, shared among the search strategies (compiled, over every core).")]
SeedOpt = Annotated[int, typer.Option("--seed", help="Random seed: the same seed gives the same batch.")]
TFinalOpt = Annotated[float | None, typer.Option("--t-final", help="Length of each run in seconds, > 0 [default: the spec's tracking t_final].", show_default=False)]
#: report's falsify settings: given, they must match a stored falsify.h5 (else it reruns); omitted, any stored one is used.
ReportRunsOpt = Annotated[int | None, typer.Option("--runs", min=1, max=100000, show_default=False, help=(
    "Runs of the falsification [default: those of a falsify.h5 already made for this design, else 32]. Given, a falsify.h5 made "
    "with another number is run again."))]
ReportSeedOpt = Annotated[int | None, typer.Option("--seed", show_default=False, help=(
    "Random seed of the falsification [default: that of a stored falsify.h5, else 0]. Given, a falsify.h5 made with another "
    "seed is run again."))]
ReportTFinalOpt = Annotated[float | None, typer.Option("--t-final", show_default=False, help=(
    "Length of each falsification run in seconds, > 0 [default: that of a stored falsify.h5, else the spec's tracking t_final]. "
    "Given, a falsify.h5 made with another length is run again."))]
#: The falsification settings report uses when there is no falsify.h5 to reuse.
REPORT_RUNS, REPORT_SEED = 32, 0


def positive_t_final(t_final: float | None) -> None:
    """Refuse a --t-final that is not a positive, finite number of seconds (exit 2, before any work).

    Parameters
    ----------
    t_final : float or None
        ``--t-final`` (None: not given).
    """
    if t_final is not None and not (np.isfinite(t_final) and t_final > 0):
        raise SpecError("--t-final", f"{number_text(t_final, 'g')} s", "a positive, finite length of run in seconds")


def current_artefact(spec, folder, stage: str):
    """The folder's artefact of ``stage`` if it was made from this spec and from the design stages now in the
    folder, else None (see :func:`product_staleness`).

    Parameters
    ----------
    spec : Spec
    folder : Folder
    stage : str
        A stage or product name (``simulate``, ``falsify``).

    Returns
    -------
    Artefact or None
    """
    return None if product_staleness(spec, folder, stage) else folder.read(stage)


def product_staleness(spec, folder, stage: str) -> str | None:
    """Why the folder's artefact of ``stage`` does not belong to the design now in the folder, None if it does.

    Parameters
    ----------
    spec : Spec
    folder : Folder
    stage : str
        A stage or product name (``simulate``, ``falsify``).

    Returns
    -------
    str or None
        "no artefact yet", "made from another spec", "made for an earlier design (<stage>.h5 changed since)" (an upstream artefact it
        recorded has been recomputed since), or None.
    """
    artefact_path = engine().artefact_path
    if not artefact_path(folder.path, stage).exists():
        return "no artefact yet"
    art = folder.read(stage)
    if not engine().made_from(spec, stage, art.provenance):
        return "made from another spec"
    for up, sha in (art.provenance.get("upstream") or {}).items():
        if artefact_path(folder.path, up).exists() and folder.read(up).provenance.get("sha256") != sha:
            return f"made for an earlier design ({up}.h5 changed since)"
    return None


def main(argv: list[str] | None = None) -> None:
    """Console entry point (``ashc``).

    ``--debug`` (anywhere on the line, any number of times) is taken out before typer parses the rest, so it
    is no option of any command and appears in no option list: it shows tracebacks and library warnings.

    Parameters
    ----------
    argv : list of str, optional
        The arguments after ``ashc`` (default: ``sys.argv[1:]``).
    """
    global _DEBUG
    args = list(sys.argv[1:] if argv is None else argv)
    if "--debug" in args:
        _DEBUG = True
        args = [a for a in args if a != "--debug"]
    else:
        warnings.simplefilter("ignore")  # the one-line error contract: library warnings only with --debug
    # typer's usage errors (a bad option value, a missing argument, an unknown option) in ashc's one-line form
    # rather than click's four lines (typer vendors click as typer._click).
    from typer import _click

    _click.exceptions.UsageError.show = lambda self, file=None: typer.echo(usage_line(self, args), err=True)
    app(args=args, prog_name="ashc")


#: click's and typer's wording of a bad option value, and what ashc says instead.
_VALUE_WORDING = (
    (re.compile(r"Input should be a valid integer.*"), "a whole number"),
    (re.compile(r"Input should be a valid number.*"), "a number"),
    (re.compile(r"Input should be greater than or equal to (\S+)"), r"a number >= \1"),
    (re.compile(r"Input should be less than or equal to (\S+)"), r"a number <= \1"),
    (re.compile(r"Input should be greater than (\S+)"), r"a number > \1"),
    (re.compile(r"(?:Value error, )?'[^']*' is not one of (.*?)\.?$"), r"one of \1"),
)


def usage_line(exc, args: list[str]) -> str:
    """A usage error (bad option value, missing argument, unknown option or command) as ashc's one line:
    ``error: --runs: 0; expected a number >= 1 (ashc falsify --help)``.

    Parameters
    ----------
    exc : click.UsageError
        What click raised.
    args : list of str
        The command line (to echo the value given).

    Returns
    -------
    str
    """
    from typer._click.exceptions import BadParameter, MissingParameter

    where = f" (see `{exc.ctx.command_path} --help`)" if getattr(exc, "ctx", None) is not None else ""
    if isinstance(exc, BadParameter) and not isinstance(exc, MissingParameter) and exc.param is not None:
        names = list(getattr(exc.param, "opts", [])) or [exc.param.human_readable_name]
        value = next((args[i + 1] for i, a in enumerate(args[:-1]) if a in names), None)
        value = value if value is not None else next((a.split("=", 1)[1] for a in args if a.split("=", 1)[0] in names and "=" in a), None)
        expected = exc.message
        for pattern, text in _VALUE_WORDING:
            if pattern.fullmatch(expected.strip()):
                expected = pattern.sub(text, expected.strip())
                break
        shown = "" if value is None else f"{value!r}; "
        return f"error: {names[0]}: {shown}expected {expected}{where}"
    return f"error: {exc.format_message().rstrip('.')}{where}"
