"""The commands that read a finished design: ``summary``, ``eval``, ``export`` and ``version``."""

from __future__ import annotations


from pathlib import Path
from typing import Annotated

import typer

from ashc_cli import __version__
from ashc_cli.errors import SpecError
from ashc_cli.outputs.numbers import number_text, readable
from ashc_cli.cli.common import (
    EVALUABLE_NAMES, ForceOpt, JsonOpt, OutOpt, Progress, SHORT_HELP, SpecArg, app, emit_json, engine, exclusive, frozen_opt, guard,
    product_staleness, run_targets,
)


def _task_plan(spec_obj, folder, arts, progress=None):
    """The spec's task plan for export and eval: synthesize.h5's when it belongs to this design, else planned again
    (deterministic); None without a task."""
    from ashc_cli.outputs.export import task_plan_export

    if spec_obj.task is None:
        return None
    current = product_staleness(spec_obj, folder, "synthesize") is None
    if not current and progress is not None:
        progress.line("note: no current synthesize.h5: planning the task again (what `ashc synthesize` does)")
    return task_plan_export(spec_obj, arts, folder.read("synthesize") if current else None)



@app.command(name="summary", short_help=SHORT_HELP["summary"])
@guard
def summary_command(
    folder: Annotated[Path, typer.Argument(metavar="DIR", help="An artefact folder (e.g. outputs/cuk_converter).", show_default=False)],
    as_json: JsonOpt = False,
) -> None:
    """Print each stage's headline numbers, formulas and checks from an artefact folder.

    Numbers are shown to 5 significant digits and a long value is cut at 400 characters; `--json` has every
    digit and every entry.
    """
    from ashc_cli.outputs.query import summary

    data = summary(engine().load_all(folder))
    if as_json:
        emit_json(data)
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
    text = readable(value)
    if len(text) <= limit:
        return text
    count = f"{len(value)} entries, " if isinstance(value, (list, tuple)) else ""
    return text[:limit].rstrip(", ") + f" ... ({count}--json for all)"


@app.command(name="eval", short_help=SHORT_HELP["eval"])
@guard
def eval_command(
    folder: Annotated[Path, typer.Argument(metavar="DIR", help="An artefact folder.", show_default=False)],
    name: Annotated[str, typer.Argument(metavar="NAME", help=f"One of: {', '.join(EVALUABLE_NAMES)}, u_w (the interface law), plan (the task's plan); "
                                                         "u_w and plan need --spec.", show_default=False)],
    at: Annotated[str, typer.Option("--at", help="The point, in the spec's own names: --at xi=0.6156 or --at x1=1,x2=2,x3=3,x4=4 (theta takes both; u_w takes xi, x "
                                                 "and v; plan takes t, and xi for its v).", show_default=False)],
    spec: Annotated[Path | None, typer.Option("--spec", help="The spec the folder was designed from; needed by u_w and plan only (l(xi), U, the interface "
                                                             "and the task are in no artefact).", show_default=False)] = None,
    as_json: JsonOpt = False,
) -> None:
    """Evaluate a stored function (p, kappa, m, delta, b, c, theta), the interface law u_w or the task's plan at a point.

    Prints `NAME(a=1, b=2) = [v1, v2, ...]` (a scalar is a one-element list). u_w is the input the interface
    applies, u = SAT(l(xi) + K (x - p(xi)) + q v), to check exported code (`ashc export`) against the tool.
    plan replays the task's plan (`ashc synthesize`; synthesize.h5 when it is current, else planned again):
    --at t=T gives its reference xi_ref(T), --at t=T,xi=X its abstract input v (ashc_plan_reference and
    ashc_plan_controller of the export).
    """
    from ashc_cli.outputs.query import evaluate, parse_point

    load_all = engine().load_all
    point = parse_point(at)
    if name in ("u_w", "plan"):
        from ashc_cli.outputs.export import interface_value, plan_value

        if spec is None:
            raise SpecError("--spec", f"{name} needs the spec the folder was designed from (l(xi), U, the interface and the task are stored in no artefact)",
                            "--spec SPEC")
        from ashc_cli.problem.spec import load_spec

        spec_obj, arts = load_spec(spec), load_all(folder)
        if name == "u_w":
            values = interface_value(spec_obj, arts, point)
        else:
            from ashc_cli.outputs.export_design import require_current

            require_current(spec_obj, arts)
            what, values = plan_value(_task_plan(spec_obj, engine().Folder(folder), arts), spec_obj, arts, point)
            name = f"plan {what}"
    else:
        values = evaluate(load_all(folder), name, point)
    if as_json:
        emit_json({"name": name, "at": point, "value": values})
    else:
        args = ", ".join(f"{k}={number_text(v, 'g')}" for k, v in point.items())
        typer.echo(f"{name}({args}) = [{', '.join(number_text(v, '.10g') for v in values)}]")


@app.command(name="export", short_help=SHORT_HELP["export"])
@guard
def export_command(
    spec: SpecArg,
    output: Annotated[Path | None, typer.Option("--output", help="The file to write: FILE.c (its header FILE.h is written beside it) for --lang c, FILE.py for --lang python "
                                                  "[default: <spec name>_design.c or .py in the design's folder, beside its artefacts].", show_default=False)] = None,
    lang: Annotated[str, typer.Option("--lang", help="c: one self-contained C99 file and its header (math.h only, no allocation); python: one module needing only numpy.")] = "c",
    out: OutOpt = None,
    force: ForceOpt = False,
    as_json: JsonOpt = False,
    frozen: frozen_opt("Recompute nothing: export the stored design; fail (exit 5, naming the stage) if a stage is stale.") = False,
) -> None:
    """Write the design as code: ashc_p, ashc_kappa, ashc_m, ashc_interface and ashc_controller (and, with a task,
    its plan: ashc_plan_reference and ashc_plan_controller).

    The formulas are the stored ones (p, kappa, m, delta, dp/dxi delta) and the spec's (phi_bar, l, g), printed
    by sympy with common subexpressions eliminated; the parameters are named constants. ashc_m returns a
    status and evaluates m only where it is certified (inverse.m_domain, exported as constants);
    ashc_interface is u = SAT(l(xi) + K (x - p(xi)) + q v) with q and SAT as the spec's interface says;
    ashc_controller is the set-point law of the tracking scenario (gain and v_max from the spec, else
    arguments). Runs the stale design stages first (unless --frozen). Prints the paths written.
    """
    from ashc_cli.outputs.export import check_target, write_export

    exclusive(force, frozen, "export")
    given = output is not None
    lang, output = check_target(lang, output if given else Path("design.c" if lang.lower() == "c" else "design.py"))   # before any stage runs
    with Progress() as progress:
        stages = engine().DESIGN
        spec_obj, folder, arts = run_targets(spec, out, stages, force, progress, frozen=stages if frozen else False)
        plan = _task_plan(spec_obj, folder, arts, progress)
    if not given:   # beside the artefacts, not in whatever folder the command was run from
        _, output = check_target(lang, folder.path / f"{spec_obj.name}_design{output.suffix}")
    paths = write_export(spec_obj, arts, lang, output, plan)
    if as_json:
        emit_json({"spec": spec_obj.name, "lang": lang, "files": [str(p) for p in paths]})
    else:
        for p in paths:
            typer.echo(str(p))


@app.command(short_help=SHORT_HELP["version"])
def version() -> None:
    """Print the ashc version."""
    typer.echo(f"ashc {__version__}")

