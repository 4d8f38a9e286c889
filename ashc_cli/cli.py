"""The ``ashc`` command line: a thin typer layer over :mod:`ashc_cli.design.pipeline` and :mod:`ashc_cli.outputs.query`.

One output channel: stdout carries only a command's result (a summary line or table, JSON, file paths);
progress goes to stderr, for every command: one line per stage (``<stage> <status> <seconds> s
<headline>``) and, when stderr is a terminal, a live display (:class:`Progress`) while a step runs.

Every error the tool means to report is an :class:`~ashc_cli.errors.AshcError`; the CLI prints it as one
line ``error: <where>: <what>; expected <what>`` on stderr and exits with its code (2 spec, 3 design
condition, 4 numerical, 5 artefact; 1 for an internal bug).  ``--debug`` anywhere on the line shows the
traceback instead.
"""

from __future__ import annotations

import functools
import json
import re
import sys
import traceback
import warnings
from enum import Enum
from pathlib import Path
from typing import Annotated

import numpy as np
import typer

from ashc_cli import __version__
from ashc_cli.errors import ArtefactError, AshcError, SpecError
from ashc_cli.products.falsify import NAME as FALSIFY, SEGMENTS, headline as falsify_headline
from ashc_cli.design.pipeline import DESIGN, STAGES, Folder, StageReport, artefact_path, default_out, load_all, needed, run, run_for_verdict
from ashc_cli.products.campaign import falsify_differs, falsify_t_final, run_falsify
from ashc_cli.paper import cite
from ashc_cli.outputs.query import EVALUABLE, evaluate, no_negative_zero, number_text, parse_point, summary
from ashc_cli.problem.spec import load_spec
from ashc_cli.design.verdict import verdict
from ashc_cli.design.stages.bound import gain_text, region_text

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
    add_completion=False,
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    rich_markup_mode=None,
)

_DEBUG = False

SpecArg = Annotated[Path, typer.Argument(metavar="SPEC", help="The YAML spec (see docs/spec-format.md).", show_default=False)]
OutOpt = Annotated[Path | None, typer.Option("--out", help="Artefact folder [default: outputs/<spec name>].", show_default=False)]
ForceOpt = Annotated[bool, typer.Option("--force", help="Recompute every needed stage even if up to date.")]
JsonOpt = Annotated[bool, typer.Option("--json", help="Print the result as JSON on stdout.")]
NumericOpt = Annotated[bool | None, typer.Option("--numeric/--symbolic", help=(
    "Force the numeric fast paths (grids and interpolants) or the symbolic ones (sympy) [default: numeric above 12 states]. "
    "Stages already up to date are kept (a note on stderr names them): add --force when switching on an existing folder."), show_default=False)]


def _frozen_opt(text: str):
    """A ``--frozen`` option with the help ``text`` (what it freezes differs between commands)."""
    return Annotated[bool, typer.Option("--frozen", help=text)]


#: --frozen of the stage commands: the stage itself may run, its upstream may not.
StageFrozenOpt = _frozen_opt("Never rerun an upstream stage: fail (exit 5, naming the stage) if one is stale. This stage itself "
                             "runs if stale; with --force it always runs, and only it.")


def _guard(fn):
    """Run a command body, turning ashc's errors into one line on stderr and the documented exit code."""

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
            typer.echo("error: interrupted; artefacts written before the interruption are intact", err=True)
            raise typer.Exit(130) from None
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
        self.start(f"{stage}: {reason}", total=SEGMENTS if stage == FALSIFY else None)

    def on_stage(self, report: StageReport) -> None:
        """Called after each stage: erase the display and print the stage line."""
        self.stop()
        self.line(f"{report.stage:<10} {report.status:<10} {report.seconds:7.2f} s  {report.headline}")


def _load(spec_path: Path, out: Path | None):
    """The spec and its artefact folder (``--out``, or outputs/<spec name>)."""
    spec = load_spec(spec_path)
    return spec, Path(out if out is not None else default_out(spec))


def _run(spec_path: Path, out: Path | None, targets, force: bool, progress: Progress, frozen=False, numeric: bool | None = None):
    """Load the spec and bring ``targets`` up to date (:func:`ashc_cli.design.pipeline.run`), with progress on stderr.

    Returns
    -------
    spec : Spec
    folder : Folder
        The folder as this command has seen it (pass it on, so that each artefact is read once).
    arts : dict of str to Artefact
    """
    spec, path = _load(spec_path, out)
    folder = Folder(path)
    kept = []

    def on_stage(report: StageReport) -> None:
        if report.status != "ran":
            kept.append(report.stage)
        progress.on_stage(report)

    arts = run(spec, folder, targets, force=force, frozen=frozen, on_stage=on_stage, on_start=progress.on_start, numeric=numeric)
    if numeric is not None and kept:
        progress.line(f"note: {'--numeric' if numeric else '--symbolic'} did not apply to the stage(s) kept as they were "
                      f"({', '.join(kept)}); add --force to recompute them")
    return spec, folder, arts


def _exclusive(force: bool, frozen: bool, command: str) -> None:
    """Refuse --force with --frozen on a command for which they contradict (every stage against none)."""
    if force and frozen:
        raise SpecError("--force", f"cannot be combined with --frozen on `ashc {command}` (--force recomputes every stage it needs, "
                        "--frozen none)", "one of --force and --frozen")


def _emit_json(obj) -> None:
    """Print ``obj`` as one JSON document on stdout (-0.0 as 0.0)."""
    typer.echo(json.dumps(no_negative_zero(obj), indent=2, sort_keys=False))


_STAGE_HELP = {
    "stabilise": "Certify stabilisability: solve (or verify) the LMI A(u)^T M + M A(u) <= -lambda M at the vertices of U (eq. egLMI); store M, lambda and the margins.",
    "manifold": "Solve the invariance PDE dp/dxi phi_bar = f_bar(p) + g(p) l(xi) for p (eq. SimuDesignCond1); store p and its residual on V.",
    "kappa": "Compose the abstract output map kappa = h o p (eq. SimuDesignCond2).",
    "inverse": "Find the left inverse m of p and check injectivity, V covering Y (eq. SimuLocalRequire), conditions (i)-(ii) of Theorem mCondi and where m is real.",
    "delta": "Check delta's rank on V and build the m-relation link v = b(x) + c(x) u (Theorem mRelateDelta).",
    "bound": "Compute alpha_h, epsilon, dbar (q = 0 and least squares, eq. iota) and the gain G of the error bound (eq. egErrorBound).",
    "simulate": "Run the tracking and m-relation scenarios of the spec (Figs. Example_BoundedIn/Out, Example_mRelationIn/Out), designing first if needed. A scenario check "
                "that fails (psi not settled, u outside U, ...) is printed as 'FAILED (simulated)' and listed by `ashc check`; the exit "
                "status stays 0, since it observes one run and is not a design condition of Problem 1.",
}

#: The one-line summary of every command in `ashc --help` (click would cut the help at its first ". ",
#: which in "(eq. egLMI)" is mid-sentence).
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
    "sweep": "Design the spec over a grid of parameter values (Dask).",
    "example": "Write the spec of a scalable example plant.",
    "regress": "Rerun a folder of specs and compare with golden values.",
    "summary": "Print each stage's headline numbers, formulas and checks.",
    "eval": "Evaluate a stored function (p, kappa, m, ...) or u_w at a point.",
    "tradeoff": "Time to reach the levels against the guaranteed tolerance.",
    "export": "Write the design as C99 code (file and header) or a numpy module.",
    "version": "Print the ashc version.",
}


def _make_stage_command(stage: str):
    def command(spec: SpecArg, out: OutOpt = None, force: ForceOpt = False, as_json: JsonOpt = False, frozen: StageFrozenOpt = False,
                numeric: NumericOpt = None) -> None:
        with Progress() as progress:
            _, folder, arts = _run(spec, out, [stage], force, progress, frozen=frozen, numeric=numeric)
        if as_json:
            _emit_json(summary({stage: arts[stage]})[stage])
        else:
            typer.echo(str(artefact_path(folder.path, stage)))

    command.__name__ = f"{stage}_command"
    command.__doc__ = (cite(_STAGE_HELP[stage]) + " Runs any stale upstream stage first (unless --frozen).\n\n"
                       f"Prints the artefact's path ({stage}.h5), or with --json the stage's entry of `ashc summary`.")
    app.command(name=stage, help=command.__doc__, short_help=SHORT_HELP[stage])(_guard(command))


for _stage in STAGES:
    _make_stage_command(_stage)


@app.command(short_help=SHORT_HELP["design"])
@_guard
def design(spec: SpecArg, out: OutOpt = None, force: ForceOpt = False, as_json: JsonOpt = False,
           frozen: _frozen_opt("Recompute nothing: fail (exit 5, naming the stage) if a stage is stale; "
                               "a check that the stored design is current.") = False,
           numeric: NumericOpt = None) -> None:
    """Run the design stages stabilise..bound in order, skipping those already up to date.

    A stage is up to date when its artefact was made from the same spec (SHA-256) and the same upstream
    artefacts; --force redoes all. Prints one line per stage with its time and headline number (stderr),
    then the design's summary line (stdout).
    """
    _exclusive(force, frozen, "design")
    with Progress() as progress:
        spec_obj, folder, arts = _run(spec, out, DESIGN, force, progress, frozen=DESIGN if frozen else False, numeric=numeric)
    checks = [c for name in DESIGN for c in arts[name].checks.values()]
    failed = [c.description for c in checks if not c.passed]
    if as_json:
        _emit_json(summary({name: arts[name] for name in DESIGN}))
    else:
        b = arts["bound"].values
        result = verdict(arts)
        typer.echo(plain_text(f"design '{spec_obj.name}' in {folder.path}: {result.counts()}; "
                              f"|psi - y| <= {gain_text(b)} ||v||_inf {region_text(b)}"))
    if failed:
        typer.echo("error: design: checks failed: " + "; ".join(failed), err=True)
        raise typer.Exit(3)



class Require(str, Enum):
    solved = "solved"
    proved = "proved"


RequireOpt = Annotated[Require, typer.Option("--require", case_sensitive=False, help=(
    "What exit 0 needs: 'solved' (every condition passes, proved or on samples only) or 'proved' (every condition "
    "that enters Problem 1, G and the certified region is proved; for CI pipelines: a verdict on samples exits 3)."))]


@app.command(short_help=SHORT_HELP["check"])
@_guard
def check(spec: SpecArg, out: OutOpt = None, force: ForceOpt = False, as_json: JsonOpt = False,
          frozen: _frozen_opt("Recompute nothing: the verdict on the stored design; fail (exit 5, naming the stage) "
                              "if a stage is stale.") = False, require: RequireOpt = Require.solved) -> None:
    """The verdict on Problem 1: one row per condition of the paper with its measured number and evidence.

    Runs the design stages that are stale, stopping at the first design condition that fails; prints each
    condition (Assumption 1, the LMI certificate, the PDE residual, eq. (10), conditions (i) and (ii), the rank
    of delta, condition (B), the certified region, ...) with pass/fail and how it was established (proved: on
    the whole set, by interval arithmetic or a sympy identity; sampled: on a grid or random points only), then
    one of three verdicts: "Problem 1 solved: proved", "Problem 1 solved: holds on samples only (sampled: ...)"
    naming the rows that were only sampled, or "Problem 1 solved: no".
    Exit status 0 for proved and for samples only (3 for samples only with --require proved), 3 for no.
    """
    _exclusive(force, frozen, "check")
    spec_obj, path = _load(spec, out)
    folder = Folder(path)
    with Progress() as progress:
        arts, stopped = run_for_verdict(spec_obj, folder, force=force, frozen=frozen, on_stage=progress.on_stage, on_start=progress.on_start)
    result = verdict(arts, stopped)
    sim = None if force else _current(spec_obj, folder, "simulate")
    simulated = [] if sim is None else [{"check": name, "status": "pass" if c.passed else "fail", "value": c.value if np.isfinite(c.value) else None,
                                         "detail": c.description, "evidence": c.evidence} for name, c in sim.checks.items()]
    if as_json:
        _emit_json({"spec": spec_obj.name, "solved": result.solved, "verdict": result.kind, "sampled": result.sampled_rows,
                    "rows": [r.as_dict() for r in result.rows], "simulated": simulated})
    else:
        typer.echo(f"Problem 1 (nonlinear ASHC) for '{spec_obj.name}':")
        for r in result.rows:
            value = "" if r.value is None else number_text(r.value, ".4g")
            typer.echo(f"  {r.status:<11} {r.evidence:<9} {r.condition:<42} {value:>11}   {r.reference}")
            if r.status == "fail":
                typer.echo(plain_text(f"              {r.detail}"))
        if simulated:
            typer.echo("Simulated scenarios (`ashc simulate`; evidence: simulated; not part of the verdict):")
            for r in simulated:
                value = "" if r["value"] is None else number_text(r["value"], ".4g")
                typer.echo(f"  {r['status']:<11} {r['evidence']:<9} {r['check']:<42} {value:>11}")
                if r["status"] == "fail":
                    typer.echo(plain_text(f"              {r['detail']}"))
        typer.echo(result.line())
    if not result.solved:
        raise typer.Exit(3)
    if require == Require.proved and not result.proved:
        typer.echo("error: check: --require proved: the verdict holds on samples only (" + ", ".join(result.sampled_rows) + ")", err=True)
        raise typer.Exit(3)


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


def _positive_t_final(t_final: float | None) -> None:
    """Refuse a --t-final that is not a positive, finite number of seconds (exit 2, before any work)."""
    if t_final is not None and not (np.isfinite(t_final) and t_final > 0):
        raise SpecError("--t-final", f"{number_text(t_final, 'g')} s", "a positive, finite length of run in seconds")


def _current(spec, folder: Folder, stage: str):
    """The folder's artefact of ``stage`` if it was made from this spec, else None."""
    if not artefact_path(folder.path, stage).exists():
        return None
    art = folder.read(stage)
    return art if art.provenance.get("spec_sha256") == spec.sha256 else None


class FigureFormat(str, Enum):
    png = "png"
    pdf = "pdf"
    svg = "svg"


FormatOpt = Annotated[FigureFormat, typer.Option("--format", case_sensitive=False,
                                                 help="File format of the figures: png (what `ashc report` embeds), pdf or svg (vector, fonts embedded, for a paper).")]


@app.command(short_help=SHORT_HELP["plot"])
@_guard
def plot(spec: SpecArg, out: OutOpt = None, force: ForceOpt = False, as_json: JsonOpt = False,
         frozen: _frozen_opt("Recompute nothing: draw from the stored artefacts; fail (exit 5, naming the stage) if a stage "
                             "(simulate included) is stale.") = False, fmt: FormatOpt = FigureFormat.png) -> None:
    """Draw the paper's figures for this design in <out>/plots/ (PNG by default; --format pdf or svg), one or two
    IEEE columns wide.

    kappa_xi.png (kappa over V with Y), delta_compare.png (||theta|| for delta = I and the design's delta),
    tracking_inputs/outputs.png (v, u; psi, y and |psi - y| with the uniform and a-posteriori bounds),
    m_relation_inputs/outputs.png, and falsify.png when `ashc falsify` has run on this design. Runs the
    stale stages (simulate included) first. Prints the paths of the figures.
    """
    from ashc_cli.outputs import plots  # matplotlib only for the commands that draw (cold start of the others)

    _exclusive(force, frozen, "plot")
    with Progress() as progress:
        spec_obj, folder, arts = _run(spec, out, ["simulate"], force, progress, frozen=needed(["simulate"]) if frozen else False)
        stored = _current(spec_obj, folder, FALSIFY)
        why = None if stored is None else falsify_differs(spec_obj, arts, stored)
        if stored is not None and why is None:
            arts[FALSIFY] = stored
        elif stored is not None:
            progress.line(f"note: falsify.{fmt.value} not drawn: falsify.h5 was {why}; rerun `ashc falsify SPEC`")
        progress.start("plot: drawing the figures")
        paths = plots.write_all(spec_obj, arts, folder.path / "plots", fmt=fmt.value)
    if as_json:
        _emit_json({"figures": [str(p) for p in paths]})
    else:
        for p in paths:
            typer.echo(str(p))


@app.command(short_help=SHORT_HELP["falsify"])
@_guard
def falsify(spec: SpecArg, out: OutOpt = None, runs: RunsOpt = 64, seed: SeedOpt = 0, t_final: TFinalOpt = None,
            as_json: JsonOpt = False,
            frozen: _frozen_opt("Never rerun a design stage: fail (exit 5, naming the stage) if one is stale.") = False) -> None:
    """Search for a run that breaks the certified error bound (compiled closed loops over every core).

    Strategies share the runs: random set-point runs; an adversary on the manifold (W0 = 0) choosing the
    sign of v that makes W grow fastest; bang-bang square waves; the linearised worst case at points of V;
    starts on the boundary of the certified region W0 = w0_max_certified (or over a wide range of W0 when
    the bound is global); and a refinement of the best runs by an evolution strategy. Every run keeps
    W0 <= w0_max_certified and ||v|| <= min(v_max, v_max_certified), and xi in V. Reports the largest ratio
    of |psi - y| to sqrt(W0 exp(-(lambda - eps) t) / alpha_h) + G sup|v| over all runs (max_ratio) and over
    the runs started on the manifold (max_ratio_w0_zero, where only G ||v|| counts). Rows of the design that
    were only sampled are attacked where they could fail: the LMI of eq. (28) between its samples (local searches
    from many starts, seeded by branch and bound), a second equilibrium of the frozen-input plant, and L_h; each
    counter-example is printed with its coordinates. Writes falsify.h5 either way; exit 3 if a ratio exceeds 1
    (a violation) or a counter-example is found.
    """
    _positive_t_final(t_final)
    spec_obj, folder = _load(spec, out)
    with Progress() as progress:
        def advance(step: int) -> None:
            progress.update(completed=step)

        def speed(count: int, per_second: float) -> None:
            progress.update(note=f"{count} runs integrated, {per_second:.0f} runs/s")

        _, art = run_falsify(spec_obj, folder, runs, seed, t_final, on_stage=progress.on_stage, on_start=progress.on_start,
                             progress=advance, on_runs=speed, frozen=frozen)
    entry = summary({FALSIFY: art})[FALSIFY]
    if as_json:
        _emit_json(entry)
    else:
        typer.echo(f"falsify '{spec_obj.name}': {entry['runs']} runs, largest |psi - y| / bound = {number_text(entry['max_ratio'], '.9g')} "
                   f"(run {entry['worst_run']}, {entry.get('strategy_of_worst', 'random')}, t = {number_text(entry['worst_time'], '.4g')} s); "
                   f"started on the manifold (W0 = 0): {number_text(entry.get('max_ratio_w0_zero', float('nan')), '.6g')} "
                   f"({entry.get('strategy_of_worst_w0_zero', '-')}); {entry['runs_leaving_V']} left V")
    for text in entry.get("counterexamples", []):
        typer.echo(f"counter-example to a sampled row: {text}")
    if entry["max_ratio"] > 1.0:
        typer.echo(f"error: falsify: the bound is violated by a factor {entry['max_ratio']:.4g} in run {entry['worst_run']} at "
                   f"t = {entry['worst_time']:.4g} s; the run is saved in {folder / 'falsify.h5'}", err=True)
        raise typer.Exit(3)
    if entry.get("certificate_counterexamples", 0):
        typer.echo(f"error: falsify: {entry['certificate_counterexamples']} counter-example(s) to rows the design only sampled "
                   f"(the verdict 'holds on samples only' is false); saved in {folder / 'falsify.h5'}", err=True)
        raise typer.Exit(3)


def _falsify_for_report(spec, folder: Folder, arts: dict, runs: int | None, seed: int | None, t_final: float | None,
                        force: bool, frozen: bool, progress: Progress):
    """The falsify artefact a report shows: the stored one if it answers the options given, else a new run.

    A stored falsify.h5 is reused when it was made from this spec and design and with every one of --runs,
    --seed and --t-final that was given; otherwise falsify runs again (saying why on stderr), with the options
    given and, for those not given, the stored run's settings (else :data:`REPORT_RUNS`, :data:`REPORT_SEED` and
    the spec's t_final).  With ``frozen`` a report that would need a new run is refused instead (exit 5).

    Returns
    -------
    Artefact
        The falsify artefact.

    Raises
    ------
    ArtefactError
        With ``frozen``, if falsify.h5 is missing or does not answer the options.
    """
    stored = _current(spec, folder, FALSIFY)
    why = "--force" if force else ("missing (none made from this spec)" if stored is None else
                                   falsify_differs(spec, arts, stored, runs, seed, t_final, t_final_given=t_final is not None))
    if why is None:
        progress.on_stage(StageReport(FALSIFY, "up to date", 0.0, falsify_headline(stored)))
        return stored
    if stored is not None:  # the settings not given are the stored run's
        runs = int(stored.meta["runs"]) if runs is None else runs
        seed = int(stored.meta["seed"]) if seed is None else seed
        t_final = float(stored.values["t_final"]) if t_final is None else t_final
    runs = REPORT_RUNS if runs is None else runs
    seed = REPORT_SEED if seed is None else seed
    wanted = f"--runs {runs} --seed {seed} --t-final {falsify_t_final(spec, t_final):g}"
    if frozen:
        raise ArtefactError("falsify.h5", f"{'is' if stored is None else 'was'} {why} (--frozen runs nothing)",
                            f"`ashc falsify SPEC {wanted}` first, or drop --frozen")
    if not force:
        progress.line(f"note: running falsify {wanted}: falsify.h5 {'is' if stored is None else 'was'} {why}")
    return run_falsify(spec, folder, runs, seed, t_final, on_stage=progress.on_stage, on_start=progress.on_start,
                       progress=lambda step: progress.update(completed=step),
                       on_runs=lambda count, per_second: progress.update(note=f"{count} runs integrated, {per_second:.0f} runs/s"))[1]


TolerancesOpt = Annotated[str, typer.Option("--tolerances", show_default=False, help=(
    "Comma-separated tolerances EPS > 0 on |psi - y|, in the output's units, e.g. 1,2,5,10,20."))]


@app.command(name="tradeoff", short_help=SHORT_HELP["tradeoff"])
@_guard
def tradeoff_command(spec: SpecArg, tolerances: TolerancesOpt, out: OutOpt = None, as_json: JsonOpt = False,
                     frozen: _frozen_opt("Never rerun a design stage: fail (exit 5, naming the stage) if one is stale.") = False) -> None:
    """Time to reach every reference level against the guaranteed tolerance, for the budget and the governor.

    For each tolerance EPS, the guaranteed controller (docs/guaranteed.md) tracks the spec's reference levels
    from its start in both modes, with the spec's set-point gain, each level held until |y - level| <= EPS for
    good: the budget (uniform v_max = (EPS - sqrt(W0 / alpha_h)) / G) and the governor (v scaled so that the
    comparison system stays below EPS^2 alpha_h). Prints one row per tolerance and mode with the seconds to
    reach each level ('-': not reached; a refused mode gives its reason), stores <out>/tradeoff.h5 and draws
    <out>/plots/tradeoff.png, the speed/accuracy frontier. Both modes run as compiled closed loops (five
    tolerances on the Cuk converter take about 17 s on two cores).
    """
    from ashc_cli.products import tradeoff as tradeoff_mod

    values = tradeoff_mod.parse_tolerances(tolerances)
    spec_obj, folder = _load(spec, out)
    with Progress() as progress:
        arts, art, figure = tradeoff_mod.run_tradeoff(spec_obj, folder, values, on_stage=progress.on_stage, on_start=progress.on_start,
                                                      frozen=frozen)
    stored = artefact_path(folder, tradeoff_mod.NAME)
    bound_values = arts["bound"].values if "bound" in arts else {}
    sampled = str(bound_values.get("bound_evidence", "sampled")) != "proved"
    if as_json:
        _emit_json({**tradeoff_mod.summarise(art), "bound_evidence": "sampled" if sampled else "proved", "artefact": str(stored), "figure": str(figure)})
    else:
        for row in tradeoff_mod.table(art):
            typer.echo(row)
        if sampled:
            typer.echo(f"note: the tolerances are guaranteed only on samples: G = {gain_text(bound_values)} rests on "
                       f"{bound_values.get('bound_sampled', 'sampled rows')}")
        typer.echo(f"tradeoff '{spec_obj.name}': {stored}, {figure}")


@app.command(short_help=SHORT_HELP["report"])
@_guard
def report(spec: SpecArg, out: OutOpt = None, runs: ReportRunsOpt = None, seed: ReportSeedOpt = None, t_final: ReportTFinalOpt = None,
           force: ForceOpt = False,
           frozen: _frozen_opt("Recompute nothing: report on the stored artefacts; fail (exit 5, naming the stage) if a stage is "
                               "stale or falsify.h5 is missing or does not match --runs, --seed and --t-final.") = False) -> None:
    """Write <out>/report.html: one self-contained page for a design review.

    It holds the spec, the Problem 1 verdict, every stage's numbers and checks, the uniform and a-posteriori
    bounds, the falsification result and the figures of `ashc plot`, embedded. The falsification stored by
    `ashc falsify` is used if it was made for this design with every one of --runs, --seed and --t-final
    given; otherwise falsify runs (stderr says why). Prints the page's path. Exit 0 when written, also for a
    design that fails (the page says why); exit 3 if the falsification finds a violation.
    """
    from ashc_cli.outputs import plots
    from ashc_cli.outputs.report import render

    _exclusive(force, frozen, "report")
    _positive_t_final(t_final)
    spec_obj, path = _load(spec, out)
    seen = Folder(path)  # one view of the folder for the design, simulate and falsify runs below
    with Progress() as progress:
        arts, stopped = run_for_verdict(spec_obj, seen, force=force, frozen=frozen, on_stage=progress.on_stage, on_start=progress.on_start)
        result = verdict(arts, stopped)
        violated = False
        if stopped is None:
            arts.update(run(spec_obj, seen, ["simulate"], force=force, frozen=needed(["simulate"]) if frozen else False,
                            on_stage=progress.on_stage, on_start=progress.on_start))
            arts[FALSIFY] = _falsify_for_report(spec_obj, seen, arts, runs, seed, t_final, force, frozen, progress)
            violated = float(arts[FALSIFY].value("max_ratio")) > 1.0
        elif runs is not None or seed is not None or t_final is not None:
            progress.line(f"note: --runs, --seed and --t-final not used: the design stopped at {stopped[0]}, so falsify does not run")
        progress.start("report: drawing the figures")
        figures = plots.write_all(spec_obj, arts, path / "plots")
    page = render(Path(spec).read_text(encoding="utf-8"), spec_obj.name, arts, result, figures)
    target = path / "report.html"
    tmp = target.with_suffix(".html.tmp")
    tmp.write_text(page, encoding="utf-8")
    tmp.replace(target)
    typer.echo(f"{target} ({len(page) // 1024} KiB): {result.line()}")
    if violated:
        typer.echo("error: report: the falsification run violates the bound (see the report)", err=True)
        raise typer.Exit(3)


@app.command(short_help=SHORT_HELP["sweep"])
@_guard
def sweep(
    spec: SpecArg,
    param: Annotated[list[str], typer.Option("--param", help="NAME=LO:HI:COUNT, a spec parameter and its values (repeat for a grid).", show_default=False)],
    out: OutOpt = None,
    scheduler: Annotated[str | None, typer.Option("--scheduler", show_default=False,
                                                   help="Address of a running dask.distributed scheduler (e.g. tcp://10.0.0.5:8786) [default: a local cluster].")] = None,
    workers: Annotated[int | None, typer.Option("--workers", min=1, max=256, show_default=False, help=f"Worker processes of the local cluster [default: {2}]; not with --scheduler.")] = None,
    falsify_runs: Annotated[int, typer.Option("--falsify-runs", min=0, help="Also run `ashc falsify` with this many runs per solved design (0: no).")] = 0,
    as_json: JsonOpt = False,
) -> None:
    """Design the spec for every combination of parameter values, in parallel on Dask.

    Each combination designs into <out>/sweep/<k>/; a failing design is recorded (solved: no, with the
    reason) and the sweep goes on. Results: <out>/sweep.h5 (parameters, lambda, dbar_q0, gain, verdict,
    falsify ratio, seconds, error per combination) and <out>/plots/sweep.png (headline numbers against
    the first swept parameter). One line per finished combination goes to stderr.
    """
    from ashc_cli.products import sweep as sweep_mod
    from ashc_cli.design.artefacts import write_artefact

    if scheduler is not None and workers is not None:
        raise SpecError("--workers", f"{workers} worker processes are for the local cluster, but --scheduler {scheduler} is given",
                        "--workers (a local cluster) or --scheduler (a running one), not both")
    spec_obj, folder = _load(spec, out)
    axes = [sweep_mod.parse_param(p, spec_obj) for p in param]
    names = [n for n, _ in axes]
    if len(set(names)) != len(names):
        raise SpecError("--param", f"a parameter is swept twice ({', '.join(names)})", "each parameter once")
    total = len(sweep_mod.combinations(axes))

    with Progress() as progress:
        done = [0]

        def show(row: dict) -> None:
            values = ", ".join(f"{k}={number_text(v, '.6g')}" for k, v in row["params"].items())
            verdict_text = "solved" if row["solved"] else f"NOT solved: {row['error']}"
            progress.line(f"  {values}: lambda = {number_text(row['lambda'], '.5g')}, dbar_q0 = {number_text(row['dbar_q0'], '.5g')}, "
                          f"G = {number_text(row['gain'], '.5g')}, {verdict_text} ({row['seconds']:.1f} s)")
            done[0] += 1
            progress.update(completed=done[0])

        progress.start(f"sweep '{spec_obj.name}': {total} combinations", total=total, count=True)
        art = sweep_mod.sweep(spec_obj, axes, folder, scheduler, SWEEP_WORKERS if workers is None else workers, falsify_runs, progress=show)
        progress.stop()
        write_artefact(folder / "sweep.h5", art, spec_sha256=spec_obj.sha256, spec_name=spec_obj.name,
                       parameters=dict(spec_obj.parameters), upstream={})
        figure = sweep_mod.plot(art, folder / "plots" / "sweep.png")
    v = art.values
    result = {"combinations": int(len(v["solved"])), "solved": int(np.sum(v["solved"])), "parameters": names,
              "table": str(folder / "sweep.h5"), "plot": str(figure), "wall_seconds": float(v["wall_seconds"]),
              "workers": art.meta["workers"]}
    if as_json:
        _emit_json(result)
    else:
        typer.echo(f"sweep '{spec_obj.name}': {result['solved']}/{result['combinations']} combinations solved on {result['workers']} worker(s) "
                   f"in {result['wall_seconds']:.1f} s; table {result['table']}, plot {result['plot']}")


#: Worker processes of sweep's local cluster unless --workers says otherwise.
SWEEP_WORKERS = 2


@app.command(short_help=SHORT_HELP["example"])
@_guard
def example(
    kind: Annotated[str, typer.Argument(metavar="KIND", help=(
        "Which family: 'ladder' (an N-stage switched LC ladder, n = 4 N), 'rc_ladder' (the MORwiki nonlinear RC ladder "
        "with N diodes, n = N) or 'chain' (N masses on springs, n = 2 N)."), show_default=False)],
    stages: Annotated[int, typer.Option("--stages", min=1, max=4096, help="Number of stages N (cells, nodes or masses).")] = 1,
    output: Annotated[Path | None, typer.Option("--output", help="Spec file to write [default: print to stdout].", show_default=False)] = None,
) -> None:
    """Write the spec of a scalable example plant (for benchmarks and large designs).

    Prints the spec, or with --output writes it and prints its path.
    """
    from ashc_cli.problem import examples

    families = {"ladder": (examples.ladder, 256, lambda N: 4 * N), "rc_ladder": (examples.rc_ladder, 4096, lambda N: N),
                "chain": (examples.chain, 1024, lambda N: 2 * N)}
    if kind not in families:
        raise SpecError("KIND", f"'{kind}' is not an example family", "one of " + ", ".join(families))
    make, most, states = families[kind]
    if kind == "rc_ladder" and stages < 2:
        raise SpecError("--stages", f"{stages}", "at least 2 nodes for an RC ladder")
    if stages > most:
        raise SpecError("--stages", f"{stages}", f"at most {most} for the {kind} family")
    text = make(stages)
    if output is None:
        typer.echo(text, nl=False)
    else:
        output.parent.mkdir(parents=True, exist_ok=True)
        output.write_text(text, encoding="utf-8")
        typer.echo(f"{output}: {stages}-stage {kind}, n = {states(stages)}")


@app.command(short_help=SHORT_HELP["regress"])
@_guard
def regress(
    specs: Annotated[Path, typer.Argument(metavar="SPECS", help="A folder of specs (every *.yaml in it).", show_default=False)],
    golden: Annotated[Path, typer.Option("--golden", help="Folder of golden JSON files, one per spec name.")] = Path("tests/golden"),
    out: Annotated[Path | None, typer.Option("--out", help="Where the designs go [default: outputs/regress].", show_default=False)] = None,
    update: Annotated[bool, typer.Option("--update", help="Write the golden files from this run (keeping edited tolerances).")] = False,
    as_json: JsonOpt = False,
) -> None:
    """Rerun every spec in a folder and compare its summary with golden values, key by key.

    Each golden file names the keys it checks (e.g. bound.gain) with a tolerance (rtol/atol, or at_most for
    residuals). A difference is reported with the key, both values and the tolerance; exit 3 if any spec
    differs or has no golden file (write them with --update, after checking the numbers). Prints one row per
    spec (with --json: the rows as JSON, and the rows as progress on stderr).
    """
    from ashc_cli.products.regress import regress as run_regress

    total = len(list(Path(specs).glob("*.yaml")))
    with Progress() as progress:
        done = [0]

        def show(row: dict) -> None:
            lines = [f"{row['spec']:<28} {row['status']}", *(f"    {d}" for d in row["differences"])]
            for line in lines:
                (progress.line if as_json else progress.result)(line)
            done[0] += 1
            progress.update(completed=done[0])

        progress.start(f"regress: {total} spec(s)", total=total, count=True)
        rows = run_regress(specs, golden, out if out is not None else Path("outputs") / "regress", update, progress=show)
    if as_json:
        _emit_json(rows)
    bad = [r for r in rows if r["status"] in ("differs", "no golden")]
    if bad:
        typer.echo(f"error: regress: {len(bad)} of {len(rows)} spec(s) differ from {golden}: {', '.join(r['spec'] for r in bad)}", err=True)
        raise typer.Exit(3)


@app.command(name="summary", short_help=SHORT_HELP["summary"])
@_guard
def summary_command(
    folder: Annotated[Path, typer.Argument(metavar="DIR", help="An artefact folder (e.g. outputs/cuk_converter).", show_default=False)],
    as_json: JsonOpt = False,
) -> None:
    """Print each stage's headline numbers, formulas and checks from an artefact folder."""
    data = summary(load_all(folder))
    if as_json:
        _emit_json(data)
        return
    for stage, entry in data.items():
        typer.echo(f"[{stage}]")
        for key, value in entry.items():
            if key in ("checks", "provenance"):
                continue
            typer.echo(f"  {key} = {_short(value)}")
        for key, chk in entry["checks"].items():
            value = chk["value"] if isinstance(chk["value"], str) else number_text(chk["value"], ".4g")
            typer.echo(f"  check {key}: {'pass' if chk['passed'] else 'FAIL'} ({value}, {chk.get('evidence', 'sampled')})")


def _short(value, limit: int = 400) -> str:
    """A value as text, cut to `limit` characters for the terminal (a 500-vertex margin list reads badly)."""
    text = str(value)
    if len(text) <= limit:
        return text
    count = f"{len(value)} entries, " if isinstance(value, (list, tuple)) else ""
    return text[:limit].rstrip(", ") + f" ... ({count}--json for all)"


@app.command(name="eval", short_help=SHORT_HELP["eval"])
@_guard
def eval_command(
    folder: Annotated[Path, typer.Argument(metavar="DIR", help="An artefact folder.", show_default=False)],
    name: Annotated[str, typer.Argument(metavar="NAME", help=f"One of: {', '.join(EVALUABLE)}, u_w (the interface law, needs --spec).", show_default=False)],
    at: Annotated[str, typer.Option("--at", help="The point, in the spec's own names: --at xi=0.6156 or --at x1=1,x2=2,x3=3,x4=4 (theta takes both; u_w takes xi, x and v).", show_default=False)],
    spec: Annotated[Path | None, typer.Option("--spec", help="The spec the folder was designed from; needed by u_w only (l(xi), U and the interface are in no artefact).", show_default=False)] = None,
    as_json: JsonOpt = False,
) -> None:
    """Evaluate a stored function (p, kappa, m, delta, b, c, theta) or the interface law u_w at a point.

    Prints `NAME(a=1, b=2) = [v1, v2, ...]` (a scalar is a one-element list). u_w is the input the interface
    applies, u = SAT(l(xi) + K (x - p(xi)) + q v), to check exported code (`ashc export`) against the tool.
    """
    point = parse_point(at)
    if name == "u_w":
        from ashc_cli.outputs.export import interface_value

        if spec is None:
            raise SpecError("--spec", "u_w needs the spec the folder was designed from (l(xi), U and the interface are stored in no artefact)", "--spec SPEC")
        values = interface_value(load_spec(spec), load_all(folder), point)
    else:
        values = evaluate(load_all(folder), name, point)
    if as_json:
        _emit_json({"name": name, "at": point, "value": values})
    else:
        args = ", ".join(f"{k}={number_text(v, 'g')}" for k, v in point.items())
        typer.echo(f"{name}({args}) = [{', '.join(number_text(v, '.10g') for v in values)}]")


@app.command(name="export", short_help=SHORT_HELP["export"])
@_guard
def export_command(
    spec: SpecArg,
    output: Annotated[Path, typer.Option("--output", help="The file to write: FILE.c (its header FILE.h is written beside it) for --lang c, FILE.py for --lang python.", show_default=False)],
    lang: Annotated[str, typer.Option("--lang", help="c: one self-contained C99 file and its header (math.h only, no allocation); python: one module needing only numpy.")] = "c",
    out: OutOpt = None,
    force: ForceOpt = False,
    as_json: JsonOpt = False,
    frozen: _frozen_opt("Recompute nothing: export the stored design; fail (exit 5, naming the stage) if a stage is stale.") = False,
) -> None:
    """Write the design as code: ashc_p, ashc_kappa, ashc_m, ashc_interface and ashc_controller.

    The formulas are the stored ones (p, kappa, m, delta, dp/dxi delta) and the spec's (phi_bar, l, g), printed
    by sympy with common subexpressions eliminated; the parameters are named constants. ashc_m returns a
    status and evaluates m only where it is certified (inverse.m_domain, exported as constants);
    ashc_interface is u = SAT(l(xi) + K (x - p(xi)) + q v) with q and SAT as the spec's interface says;
    ashc_controller is the set-point law of the tracking scenario (gain and v_max from the spec, else
    arguments). Runs the stale design stages first (unless --frozen). Prints the paths written.
    """
    from ashc_cli.outputs.export import check_target, write_export

    _exclusive(force, frozen, "export")
    lang, output = check_target(lang, output)   # before any stage runs
    with Progress() as progress:
        spec_obj, folder, arts = _run(spec, out, DESIGN, force, progress, frozen=DESIGN if frozen else False)
    paths = write_export(spec_obj, arts, lang, output)
    if as_json:
        _emit_json({"spec": spec_obj.name, "lang": lang, "files": [str(p) for p in paths]})
    else:
        for p in paths:
            typer.echo(str(p))


@app.command(short_help=SHORT_HELP["version"])
def version() -> None:
    """Print the ashc version."""
    typer.echo(f"ashc {__version__}")


def main(argv: list[str] | None = None) -> None:
    """Console entry point (``ashc``).

    ``--debug`` (anywhere on the line, any number of times) is taken out before typer parses the rest, so it
    is no option of any command and appears in no option list: it shows tracebacks and library warnings.
    """
    global _DEBUG
    args = list(sys.argv[1:] if argv is None else argv)
    if "--debug" in args:
        _DEBUG = True
        args = [a for a in args if a != "--debug"]
    else:
        warnings.simplefilter("ignore")  # the one-line error contract: library warnings only with --debug
    app(args=args, prog_name="ashc")


if __name__ == "__main__":  # pragma: no cover
    main()
