"""The ``ashc`` command line: a thin typer layer over :mod:`ashc_cli.pipeline` and :mod:`ashc_cli.query`.

Every error the tool means to report is an :class:`~ashc_cli.errors.AshcError`; the CLI prints it as one
line ``error: <where>: <what>; expected <what>`` on stderr and exits with its code (2 spec, 3 design
condition, 4 numerical, 5 artefact; 1 for an internal bug).  ``--debug`` anywhere on the line shows the
traceback instead.
"""

from __future__ import annotations

import functools
import json
import sys
import traceback
import warnings
from pathlib import Path
from typing import Annotated, Optional

import typer

from . import __version__
from .errors import AshcError, DesignError
from .pipeline import DESIGN, STAGES, StageReport, default_out, load_all, run
from .query import EVALUABLE, evaluate, parse_point, summary
from .spec import load_spec
from .verdict import verdict

app = typer.Typer(
    name="ashc",
    help=(
        "Approximate simulation-based hierarchical control (ASHC) design for nonlinear input-affine systems.\n\n"
        "Write a YAML spec of your plant and abstraction, run `ashc design SPEC` to get a certified "
        "abstraction, interface and error bound (one HDF5 artefact per stage under outputs/<name>/), then "
        "`ashc simulate SPEC` to see it work and `ashc summary DIR --json` for the numbers.\n\n"
        "Exit codes: 0 done; 2 bad spec or argument; 3 a design condition fails; 4 numerical failure; "
        "5 artefact problem; 1 internal error. Add --debug anywhere for a traceback."
    ),
    add_completion=False,
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    rich_markup_mode=None,
)

_DEBUG = False

SpecArg = Annotated[Path, typer.Argument(help="The YAML spec (see spec-format.md).", show_default=False)]
OutOpt = Annotated[Optional[Path], typer.Option("--out", help="Artefact folder [default: outputs/<spec name>].", show_default=False)]
ForceOpt = Annotated[bool, typer.Option("--force", help="Recompute every needed stage even if up to date.")]
JsonOpt = Annotated[bool, typer.Option("--json", help="Print the result as JSON on stdout (progress goes to stderr).")]
FrozenOpt = Annotated[bool, typer.Option("--frozen", help="Never rerun an upstream stage: fail (exit 5, naming the stage) if one is stale.")]


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


def _progress(to_stderr: bool):
    def show(report: StageReport) -> None:
        typer.echo(f"{report.stage:<10} {report.status:<10} {report.seconds:7.2f} s  {report.headline}", err=to_stderr)
    return show


def _run(spec_path: Path, out: Path | None, targets, force: bool, as_json: bool, frozen: bool = False):
    spec = load_spec(spec_path)
    folder = out if out is not None else default_out(spec)
    arts = run(spec, folder, targets, force=force, frozen=frozen, on_stage=_progress(as_json))
    return spec, folder, arts


def _emit_json(obj) -> None:
    typer.echo(json.dumps(obj, indent=2, sort_keys=False))


_STAGE_HELP = {
    "stabilise": "Certify stabilisability: solve (or verify) the LMI A(u)^T M + M A(u) <= -lambda M at the vertices of U (eq. egLMI); store M, lambda and the margins.",
    "manifold": "Solve the invariance PDE dp/dxi phi_bar = f_bar(p) + g(p) l(xi) for p (eq. SimuDesignCond1); store p and its residual on V.",
    "kappa": "Compose the abstract output map kappa = h o p (eq. SimuDesignCond2).",
    "inverse": "Find the left inverse m of p and check injectivity, V covering Y (eq. SimuLocalRequire), conditions (i)-(ii) of Theorem mCondi and where m is real.",
    "delta": "Check delta's rank on V and build the m-relation link v = b(x) + c(x) u (Theorem mRelateDelta).",
    "bound": "Compute alpha_h, epsilon, dbar (q = 0 and least squares, eq. iota) and the gain G of the error bound (eq. egErrorBound).",
    "simulate": "Run the tracking and m-relation scenarios of the spec (Figs. Example_*), designing first if needed.",
}


def _make_stage_command(stage: str):
    def command(spec: SpecArg, out: OutOpt = None, force: ForceOpt = False, as_json: JsonOpt = False, frozen: FrozenOpt = False) -> None:
        _, _, arts = _run(spec, out, [stage], force, as_json, frozen)
        if as_json:
            _emit_json(summary({stage: arts[stage]})[stage])

    command.__name__ = f"{stage}_command"
    command.__doc__ = _STAGE_HELP[stage] + " Runs any stale upstream stage first (unless --frozen)."
    app.command(name=stage, help=command.__doc__)(_guard(command))


for _stage in STAGES:
    _make_stage_command(_stage)


@app.command()
@_guard
def design(spec: SpecArg, out: OutOpt = None, force: ForceOpt = False, as_json: JsonOpt = False) -> None:
    """Run the design stages stabilise..bound in order, skipping those already up to date.

    A stage is up to date when its artefact was made from the same spec (SHA-256) and the same upstream
    artefacts; --force redoes all. Prints one line per stage with its time and headline number.
    """
    spec_obj, folder, arts = _run(spec, out, DESIGN, force, as_json)
    checks = [c for name in DESIGN for c in arts[name].checks.values()]
    failed = [c.description for c in checks if not c.passed]
    if as_json:
        _emit_json(summary({name: arts[name] for name in DESIGN}))
    else:
        b = arts["bound"].values
        typer.echo(f"design '{spec_obj.name}' in {folder}: {len(checks) - len(failed)}/{len(checks)} checks passed; "
                   f"|psi - y| <= {b['gain']:.5g} ||v||_inf when W(xi0, x0) = 0")
    if failed:
        typer.echo("error: design: checks failed: " + "; ".join(failed), err=True)
        raise typer.Exit(3)


@app.command()
@_guard
def check(spec: SpecArg, out: OutOpt = None, force: ForceOpt = False, as_json: JsonOpt = False) -> None:
    """The verdict on Problem 1: one row per condition of the paper with its measured number.

    Runs the design stages that are stale, stopping at the first design condition that fails; prints each
    condition (Assumption 1, the LMI certificate, the PDE residual, SimuLocalRequire, conditions (i) and
    (ii), the rank of delta, condition (B), ...) with pass/fail, then "Problem 1 solved: yes/no".
    Exit status 0 only for yes, 3 for no.
    """
    spec_obj = load_spec(spec)
    folder = out if out is not None else default_out(spec_obj)
    arts, stopped = {}, None
    show = _progress(True)
    for stage in DESIGN:
        try:
            # One stage at a time, so a failing condition still leaves the verdict of the stages before it.
            arts.update(run(spec_obj, folder, [stage], force=force and stage not in arts,
                            on_stage=lambda report, stage=stage: show(report) if report.stage == stage else None))
        except DesignError as exc:
            stopped = (stage, exc)
            break
    solved, rows = verdict(arts, stopped)
    if as_json:
        _emit_json({"spec": spec_obj.name, "solved": solved, "rows": [r.as_dict() for r in rows]})
    else:
        typer.echo(f"Problem 1 (nonlinear ASHC) for '{spec_obj.name}':")
        for r in rows:
            value = "" if r.value is None else f"{r.value:.4g}"
            typer.echo(f"  {r.status:<11} {r.condition:<42} {value:>11}   {r.reference}")
            if r.status == "fail":
                typer.echo(f"              {r.detail}")
        typer.echo(f"Problem 1 solved: {'yes' if solved else 'no'}")
    if not solved:
        raise typer.Exit(3)


@app.command(name="summary")
@_guard
def summary_command(
    folder: Annotated[Path, typer.Argument(help="An artefact folder (e.g. outputs/cuk_converter).", show_default=False)],
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
            typer.echo(f"  {key} = {value}")
        for key, chk in entry["checks"].items():
            typer.echo(f"  check {key}: {'pass' if chk['passed'] else 'FAIL'} ({chk['value']:.4g})")


@app.command(name="eval")
@_guard
def eval_command(
    folder: Annotated[Path, typer.Argument(help="An artefact folder.", show_default=False)],
    name: Annotated[str, typer.Argument(help=f"One of: {', '.join(EVALUABLE)}.", show_default=False)],
    at: Annotated[str, typer.Option("--at", help="The point, in the spec's own names: --at xi=0.6156 or --at x1=1,x2=2,x3=3,x4=4 (theta takes both).", show_default=False)],
    as_json: JsonOpt = False,
) -> None:
    """Evaluate a stored function (p, kappa, m, delta, b, c, theta) at a point.

    Prints `NAME(a=1, b=2) = [v1, v2, ...]` (a scalar is a one-element list).
    """
    point = parse_point(at)
    values = evaluate(load_all(folder), name, point)
    if as_json:
        _emit_json({"name": name, "at": point, "value": values})
    else:
        args = ", ".join(f"{k}={v:g}" for k, v in point.items())
        typer.echo(f"{name}({args}) = [{', '.join(f'{v:.10g}' for v in values)}]")


@app.command()
def version() -> None:
    """Print the ashc version."""
    typer.echo(f"ashc {__version__}")


def main(argv: list[str] | None = None) -> None:
    """Console entry point (``ashc``)."""
    global _DEBUG
    args = list(sys.argv[1:] if argv is None else argv)
    if "--debug" in args:
        _DEBUG = True
        args.remove("--debug")
    else:
        warnings.simplefilter("ignore")  # the one-line error contract: library warnings only with --debug
    app(args=args, prog_name="ashc")


if __name__ == "__main__":  # pragma: no cover
    main()
