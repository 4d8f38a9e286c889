"""The commands of the design flow chart: one per stage (stabilise .. simulate), ``design``, ``check`` and ``plot``."""

from __future__ import annotations


from enum import Enum
from pathlib import Path
from typing import Annotated

import typer

from ashc_cli.paper import cite
from ashc_cli.outputs.numbers import number_text
from ashc_cli.cli.common import (
    FALSIFY, ForceOpt, JsonOpt, NumericOpt, OutOpt, Progress, SHORT_HELP, STAGE_HELP, SpecArg, StageFrozenOpt, app, current_artefact,
    emit_json, engine, exclusive, frozen_opt, guard, load, plain_text, product_staleness, run_targets,
)



def _make_stage_command(stage: str):
    def command(spec: SpecArg, out: OutOpt = None, force: ForceOpt = False, as_json: JsonOpt = False, frozen: StageFrozenOpt = False,
                numeric: NumericOpt = None) -> None:
        from ashc_cli.outputs.query import summary

        with Progress() as progress:
            _, folder, arts = run_targets(spec, out, [stage], force, progress, frozen=frozen, numeric=numeric)
        if as_json:
            emit_json(summary({stage: arts[stage]})[stage])
        else:
            typer.echo(str(engine().artefact_path(folder.path, stage)))
        if stage == "simulate":
            _refuse_contradicted(arts, arts[stage], folder.path)

    command.__name__ = f"{stage}_command"
    command.__doc__ = (cite(STAGE_HELP[stage]) + " Runs any stale upstream stage first (unless --frozen).\n\n"
                       f"Prints the artefact's path ({stage}.h5), or with --json the stage's entry of `ashc summary`.")
    app.command(name=stage, help=command.__doc__, short_help=SHORT_HELP[stage])(guard(command))


for _stage in STAGE_HELP:   # the pipeline's STAGES, in flow-chart order (a test keeps the two equal)
    _make_stage_command(_stage)


@app.command(short_help=SHORT_HELP["design"])
@guard
def design(spec: SpecArg, out: OutOpt = None, force: ForceOpt = False, as_json: JsonOpt = False,
           frozen: frozen_opt("Recompute nothing: fail (exit 5, naming the stage) if a stage is stale; "
                               "a check that the stored design is current.") = False,
           numeric: NumericOpt = None) -> None:
    """Run the design stages stabilise..bound in order, skipping those already up to date.

    A stage is up to date when the spec keys it reads have the values it was made from (a task, a scenario
    or the units change no design stage; abstract.* leaves stabilise alone) and its upstream artefacts are
    the same; --force redoes all. Prints one line per stage with its time and headline number (stderr),
    then the design's summary line (stdout).
    """
    from ashc_cli.design.stages.bound import disturbance_text, gain_text, region_text
    from ashc_cli.design.verdict import verdict
    from ashc_cli.outputs.query import summary

    exclusive(force, frozen, "design")
    stages = engine().DESIGN
    with Progress() as progress:
        spec_obj, folder, arts = run_targets(spec, out, stages, force, progress, frozen=stages if frozen else False, numeric=numeric)
    checks = [c for name in stages for c in arts[name].checks.values()]
    failed = [c.description for c in checks if not c.passed]
    if as_json:
        emit_json(summary({name: arts[name] for name in stages}))
    else:
        b = arts["bound"].values
        result = verdict(arts)
        typer.echo(plain_text(f"design '{spec_obj.name}' in {folder.path}: {result.counts()}; "
                              f"|psi - y| <= {gain_text(b)} ||v||_inf{disturbance_text(b)} {region_text(b)}"
                              + (f"; {arts['stabilise'].meta['left_out']['note']}" if "left_out" in arts["stabilise"].meta else "")))
    if failed:
        typer.echo("error: design: checks failed: " + "; ".join(failed), err=True)
        raise typer.Exit(3)



def _refuse_contradicted(arts: dict, sim, path: Path) -> None:
    """A run of `ashc simulate` that breaks a guarantee the verdict calls proved is a bug in ashc, not a result:
    one line naming the checks, exit 1 (docs/guide.md, exit codes).  On a verdict that holds on samples only it
    shows the sampling missed something: exit 3."""
    from ashc_cli.design.verdict import contradictions, verdict

    broken = contradictions(sim)
    if not broken:
        return
    result = verdict({k: a for k, a in arts.items() if k in engine().DESIGN})
    if result.proved:
        typer.echo(f"error: simulate: the design's verdict is proved, yet its run breaks it ({'; '.join(broken)}): this is a bug in "
                   f"ashc; please report it with the spec and {path / 'simulate.h5'}", err=True)
        raise typer.Exit(1)
    if result.solved:
        typer.echo(f"error: simulate: the run breaks what the design holds on samples only ({'; '.join(broken)}): the verdict "
                   f"'holds on samples only' is false for this plant; saved in {path / 'simulate.h5'}", err=True)
        raise typer.Exit(3)


class Require(str, Enum):
    solved = "solved"
    proved = "proved"


RequireOpt = Annotated[Require, typer.Option("--require", case_sensitive=False, help=(
    "What exit 0 needs: 'solved' (every condition passes, proved or on samples only) or 'proved' (every condition "
    "that enters Problem 1, G and the certified region is proved; for CI pipelines: a verdict on samples exits 3)."))]


@app.command(short_help=SHORT_HELP["check"])
@guard
def check(spec: SpecArg, out: OutOpt = None, force: ForceOpt = False, as_json: JsonOpt = False,
          frozen: frozen_opt("Recompute nothing: the verdict on the stored design; fail (exit 5, naming the stage) "
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
    import numpy as np

    from ashc_cli.design.verdict import verdict

    exclusive(force, frozen, "check")
    spec_obj, path = load(spec, out)
    pipeline = engine()
    folder = pipeline.Folder(path)
    with Progress() as progress:
        arts, stopped = pipeline.run_for_verdict(spec_obj, folder, force=force, frozen=frozen, on_stage=progress.on_stage, on_start=progress.on_start)
    result = verdict(arts, stopped)
    stale = None if force else product_staleness(spec_obj, folder, "simulate")
    sim = None if force or stale else folder.read("simulate")
    simulated = [] if sim is None else [{"check": name, "status": "pass" if c.passed else "fail", "value": c.value if np.isfinite(c.value) else None,
                                         "detail": c.description, "evidence": c.evidence} for name, c in sim.checks.items()]
    task = _task_line(spec_obj, sim, path)
    if as_json:
        emit_json({"spec": spec_obj.name, "solved": result.solved, "verdict": result.kind, "sampled": result.sampled_rows,
                    "rows": [r.as_dict() for r in result.rows], "simulated": simulated,
                    "simulated_stale": stale if stale not in (None, "no artefact yet") else None, **({"task": task} if task else {})})
    else:
        typer.echo(f"Problem 1 (nonlinear ASHC) for '{spec_obj.name}':")
        for r in result.rows:
            value = "" if r.value is None else number_text(r.value, ".4g")
            typer.echo(f"  {r.status:<11} {r.evidence:<9} {r.condition:<42} {value:>11}   {r.reference}")
            if r.status == "fail":
                typer.echo(plain_text(f"              {r.detail}"))
        _echo_simulated(simulated, stale, path)
        if task:
            typer.echo(task)
        typer.echo(result.line())
    if sim is not None and result.solved:
        _refuse_contradicted(arts, sim, path)
    if not result.solved:
        raise typer.Exit(3)
    if require == Require.proved and not result.proved:
        typer.echo("error: check: --require proved: the verdict holds on samples only (" + ", ".join(result.sampled_rows) + ")", err=True)
        raise typer.Exit(3)

def _task_line(spec, sim, path: Path) -> str | None:
    """One line on the spec's task (None without one): the plant's robustness under the synthesised plan from
    simulate.h5's task scenario, or what to run; not part of Problem 1's verdict."""
    if spec.task is None:
        return None
    head = "Task on the output (not part of Problem 1's verdict): "
    if sim is None or "task/robustness" not in sim.values:
        return head + f"not simulated; `ashc synthesize SPEC --out {path}` plans it, `ashc simulate` runs the plan on the plant"
    v = sim.values
    met = "met" if bool(v["task/satisfied"]) else "NOT met"
    return (head + f"{met} on the plant, robustness {number_text(float(v['task/robustness']), '.4g')} under the synthesised plan "
            f"(EPS = {number_text(float(v['task/tolerance']), '.4g')}, certified margin {number_text(float(v['task/certified_margin']), '.4g')}, "
            f"{'proved on the grid' if float(v.get('task/proved', 0.0)) else 'sampled in time'}; "
            "`ashc falsify` attacks it)")


def _echo_simulated(simulated: list[dict], stale: str | None, path: Path) -> None:
    """One line on the scenario checks of `ashc simulate` (simulated, not part of the verdict); a failed one in full;
    a simulate.h5 of an earlier design named as stale, its checks not shown."""
    if stale not in (None, "no artefact yet"):
        typer.echo(f"Simulated scenarios: {path / 'simulate.h5'} is stale, {stale}; not shown. Rerun "
                   f"`ashc simulate SPEC --out {path}`")
        return
    if not simulated:
        return
    passed = sum(r["status"] == "pass" for r in simulated)
    typer.echo(f"Simulated scenarios (`ashc simulate`; not part of the verdict): {passed} of {len(simulated)} checks pass"
               f" (`ashc summary {path}` lists them)")
    for r in simulated:
        if r["status"] == "fail":
            value = "" if r["value"] is None else number_text(r["value"], ".4g")
            typer.echo(f"  fail        simulated {r['check']:<42} {value:>11}")
            typer.echo(plain_text(f"              {r['detail']}"))


class FigureFormat(str, Enum):
    png = "png"
    pdf = "pdf"
    svg = "svg"


FormatOpt = Annotated[FigureFormat, typer.Option("--format", case_sensitive=False,
                                                 help="File format of the figures: png (what `ashc report` embeds), pdf or svg (vector, fonts embedded, for a paper).")]


@app.command(short_help=SHORT_HELP["plot"])
@guard
def plot(spec: SpecArg, out: OutOpt = None, force: ForceOpt = False, as_json: JsonOpt = False,
         frozen: frozen_opt("Recompute nothing: draw from the stored artefacts; fail (exit 5, naming the stage) if a stage "
                             "(simulate included) is stale.") = False, fmt: FormatOpt = FigureFormat.png) -> None:
    """Draw the paper's figures for this design in <out>/plots/ (PNG by default; --format pdf or svg), one or two
    IEEE columns wide.

    kappa_xi.png (kappa over V with Y), delta_compare.png (||theta|| for delta = I and the design's delta),
    tracking_inputs/outputs.png (v, u; psi, y and |psi - y| with the uniform and a-posteriori bounds),
    m_relation_inputs/outputs.png, and falsify.png when `ashc falsify` has run on this design. Runs the
    stale stages (simulate included) first. Prints the paths of the figures.
    """
    from ashc_cli.outputs import plots  # matplotlib only for the commands that draw (cold start of the others)
    from ashc_cli.products.campaign import falsify_differs

    exclusive(force, frozen, "plot")
    needed = engine().needed
    with Progress() as progress:
        spec_obj, folder, arts = run_targets(spec, out, ["simulate"], force, progress, frozen=needed(["simulate"]) if frozen else False)
        stored = current_artefact(spec_obj, folder, FALSIFY)
        why = None if stored is None else falsify_differs(spec_obj, arts, stored)
        if stored is not None and why is None:
            arts[FALSIFY] = stored
        elif stored is not None:
            progress.line(f"note: falsify.{fmt.value} not drawn: falsify.h5 was {why}; rerun `ashc falsify SPEC`")
        progress.start("plot: drawing the figures")
        paths = plots.write_all(spec_obj, arts, folder.path / "plots", fmt=fmt.value)
    if as_json:
        emit_json({"figures": [str(p) for p in paths]})
    else:
        for p in paths:
            typer.echo(str(p))

