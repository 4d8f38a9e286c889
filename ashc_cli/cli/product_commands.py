"""The commands built on a design: ``falsify``, ``tradeoff``, ``report``, ``sweep``, ``example`` and ``regress``."""

from __future__ import annotations


from pathlib import Path
from typing import Annotated

import numpy as np
import typer

from ashc_cli.errors import ArtefactError, SpecError
from ashc_cli.outputs.numbers import number_text
from ashc_cli.cli.common import (
    FALSIFY, engine, ForceOpt, JsonOpt, OutOpt, Progress, REPORT_RUNS, REPORT_SEED, ReportRunsOpt, ReportSeedOpt, ReportTFinalOpt, RunsOpt, SHORT_HELP,
    SeedOpt, SpecArg, TFinalOpt, app, emit_json, product_staleness, exclusive, frozen_opt, guard, load, positive_t_final,
)



@app.command(short_help=SHORT_HELP["falsify"])
@guard
def falsify(spec: SpecArg, out: OutOpt = None, runs: RunsOpt = 64, seed: SeedOpt = 0, t_final: TFinalOpt = None,
            as_json: JsonOpt = False,
            scheduler: Annotated[str | None, typer.Option("--scheduler", show_default=False, help=(
                "Address of a running dask.distributed scheduler (e.g. tcp://10.0.0.5:8786) for the task attack's runs; its "
                "workers read the design from --out [default: threads on this machine]."))] = None,
            frozen: frozen_opt("Never rerun a design stage: fail (exit 5, naming the stage) if one is stale.") = False) -> None:
    """Search for a run that breaks the certified error bound (compiled closed loops over every core).

    Strategies share the runs: random set-point runs (with abstract_controller.kind: registered, every other one
    closes the loop with that registered law as it is); an adversary on the manifold (W0 = 0) choosing the
    sign of v that makes W grow fastest; bang-bang square waves; the linearised worst case at points of V;
    starts on the boundary of the certified region W0 = w0_max_certified (or over a wide range of W0 when
    the bound is global); and a refinement of the best runs by an evolution strategy. Every run keeps
    W0 <= w0_max_certified and ||v|| <= min(v_max, v_max_certified), and xi in V. Reports the largest ratio
    of |psi - y| to sqrt(W0 exp(-(lambda - eps) t) / alpha_h) + G sup|v| over all runs (max_ratio) and over
    the runs started on the manifold (max_ratio_w0_zero, where only G ||v|| counts). Rows of the design that
    were only sampled are attacked where they could fail: the LMI of eq. (28) between its samples (local searches
    from many starts, seeded by branch and bound), a second equilibrium of the frozen-input plant, and L_h; each
    counter-example is printed with its coordinates. With a task in the spec, the synthesised plan also runs on the
    plant from --runs starts across its certified start region (its boundary along M's eigen-directions, random
    starts on and inside it, then a search around the worst starts) and the smallest robustness of the task is
    reported (task_min_robustness; the worst run is stored and drawn in plots/falsify_task.png by `ashc plot`). Writes
    falsify.h5 either way; exit 3 if a ratio exceeds 1 (a violation), a counter-example is found or a task run
    has negative robustness.
    """
    from ashc_cli.outputs.query import summary
    from ashc_cli.products.campaign import run_falsify

    positive_t_final(t_final)
    spec_obj, folder = load(spec, out)
    with Progress() as progress:
        def advance(step: int) -> None:
            progress.update(completed=step)

        def speed(count: int, per_second: float) -> None:
            progress.update(note=f"{count} runs integrated, {per_second:.0f} runs/s")

        _, art = run_falsify(spec_obj, folder, runs, seed, t_final, on_stage=progress.on_stage, on_start=progress.on_start,
                             progress=advance, on_runs=speed, frozen=frozen, scheduler=scheduler)
    entry = summary({FALSIFY: art})[FALSIFY]
    if as_json:
        emit_json(entry)
    else:
        typer.echo(f"falsify '{spec_obj.name}': {entry['runs']} runs; started on the manifold (W0 = 0, where only G ||v||_inf "
                   f"counts): largest |psi - y| / bound = {number_text(entry.get('max_ratio_w0_zero', float('nan')), '.4g')} "
                   f"(run {entry.get('worst_w0_zero_run', '-')}, strongest strategy {entry.get('strategy_of_worst_w0_zero', '-')}); "
                   f"all runs: {number_text(entry['max_ratio'], '.4g')} (run {entry['worst_run']}, {entry.get('strategy_of_worst', 'random')}, "
                   f"t = {number_text(entry['worst_time'], '.4g')} s; off the manifold the W0 term is tight at t = 0); "
                   f"{entry['runs_leaving_V']} left V")
    if "disturbance_max_ratio" in entry and not as_json:
        typer.echo(f"disturbance attack: largest error / bound {number_text(entry['disturbance_max_ratio'], '.4g')} over "
                   f"{entry['disturbance_runs']} runs with w at the vertices of disturbance_bounds"
                   f"{(', ' + str(entry['disturbance_outside_box']) + ' started outside the state box') if entry['disturbance_outside_box'] else ''}")
    if "task_min_robustness" in entry and not as_json:
        typer.echo(f"task: smallest robustness {number_text(entry['task_min_robustness'], '.4g')} over {entry['task_runs']} plant runs of the "
                   f"synthesised plan from starts with W0 <= {number_text(entry['task_start_region_W0'], '.4g')} (the certified start region; "
                   f"{entry.get('task_searched', 0)} of them searched around the worst; worst W0 {number_text(entry['task_worst_W0'], '.4g')})")
    for text in entry.get("counterexamples", []):
        typer.echo(f"counter-example to a sampled row: {text}")
    if entry.get("disturbance_max_ratio", 0.0) > 1.0:
        typer.echo(f"error: falsify: a run with a disturbance at a vertex of its box (or started outside the state box) breaks the "
                   f"bound (ratio {entry['disturbance_max_ratio']:.4g}); saved in {folder / 'falsify.h5'}", err=True)
        raise typer.Exit(3)
    if entry["max_ratio"] > 1.0:
        typer.echo(f"error: falsify: the bound is violated by a factor {entry['max_ratio']:.4g} in run {entry['worst_run']} at "
                   f"t = {entry['worst_time']:.4g} s; the run is saved in {folder / 'falsify.h5'}", err=True)
        raise typer.Exit(3)
    if entry.get("certificate_counterexamples", 0):
        typer.echo(f"error: falsify: {entry['certificate_counterexamples']} counter-example(s) to rows the design only sampled "
                   f"(the verdict 'holds on samples only' is false); saved in {folder / 'falsify.h5'}", err=True)
        raise typer.Exit(3)
    if "task_disturbed_min_robustness" in entry and not as_json:
        typer.echo(f"task with disturbances: smallest robustness {number_text(entry['task_disturbed_min_robustness'], '.4g')} over "
                   f"{entry['task_disturbed_runs']} plant runs with w held at each vertex of disturbance_bounds")
    if entry.get("task_disturbed_min_robustness", 0.0) < 0:
        typer.echo(f"error: falsify: the task is violated on the plant with a disturbance at a vertex of its box (robustness "
                   f"{entry['task_disturbed_min_robustness']:.4g}); saved in {folder / 'falsify.h5'}", err=True)
        raise typer.Exit(3)
    if entry.get("task_min_robustness", 0.0) < 0:
        typer.echo(f"error: falsify: the task is violated on the plant (robustness {entry['task_min_robustness']:.4g}, a start with "
                   f"W0 = {entry['task_worst_W0']:.4g}); saved in {folder / 'falsify.h5'}", err=True)
        raise typer.Exit(3)


def _falsify_for_report(spec, folder, arts: dict, runs: int | None, seed: int | None, t_final: float | None,
                        force: bool, frozen: bool, progress: Progress):
    """The falsify artefact a report shows: the stored one if it answers the options given, else a new run.

    A stored falsify.h5 is reused when it was made from this spec and design and with every one of --runs,
    --seed and --t-final that was given, or when it holds more runs than --runs asks for (more evidence is
    never replaced by less without --force); otherwise falsify runs again (saying why on stderr), with the options
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
    from ashc_cli.design.pipeline import StageReport
    from ashc_cli.products.campaign import falsify_differs, falsify_t_final, run_falsify
    from ashc_cli.products.falsify import headline as falsify_headline


    stale = product_staleness(spec, folder, FALSIFY)
    stored = None if stale else folder.read(FALSIFY)
    if stale is not None:
        stale = "missing" if stale == "no artefact yet" else stale
    why = "--force" if force else (stale if stored is None else
                                   falsify_differs(spec, arts, stored, runs, seed, t_final, t_final_given=t_final is not None))
    if why is not None and why.startswith("made with") and runs is not None and int(stored.meta["runs"]) > runs:
        # More runs of this very design are more evidence: never replaced by a smaller search without --force.
        progress.line(f"note: falsify.h5 kept: its {int(stored.meta['runs'])} runs (seed {int(stored.meta['seed'])}, "
                      f"t_final {float(stored.values['t_final']):g} s) are more evidence than --runs {runs}; "
                      f"--force replaces them with {runs}")
        why = None
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
        raise ArtefactError("falsify.h5", f"{'is' if why == 'missing' else 'was'} {why} (--frozen runs nothing)",
                            f"`ashc falsify SPEC {wanted}` first, or drop --frozen")
    if not force:
        progress.line(f"note: running falsify {wanted}: falsify.h5 {'is' if why == 'missing' else 'was'} {why}")
    return run_falsify(spec, folder, runs, seed, t_final, on_stage=progress.on_stage, on_start=progress.on_start,
                       progress=lambda step: progress.update(completed=step),
                       on_runs=lambda count, per_second: progress.update(note=f"{count} runs integrated, {per_second:.0f} runs/s"))[1]


TolerancesOpt = Annotated[str, typer.Option("--tolerances", show_default=False, help=(
    "Comma-separated tolerances EPS > 0 on |psi - y|, in the output's units, e.g. 1,2,5,10,20."))]


@app.command(name="tradeoff", short_help=SHORT_HELP["tradeoff"])
@guard
def tradeoff_command(spec: SpecArg, tolerances: TolerancesOpt, out: OutOpt = None, as_json: JsonOpt = False,
                     frozen: frozen_opt("Never rerun a design stage: fail (exit 5, naming the stage) if one is stale.") = False) -> None:
    """Time to reach every reference level against the guaranteed tolerance, for the budget and the governor.

    For each tolerance EPS, the guaranteed controller (docs/guaranteed.md) tracks the spec's reference levels
    from its start in both modes, with the spec's set-point gain, each level held until |y - level| <= EPS for
    good: the budget (uniform v_max = (EPS - sqrt(W0 / alpha_h)) / G) and the governor (v scaled so that the
    comparison system stays below EPS^2 alpha_h). Prints one row per tolerance and mode with the seconds to
    reach each level ('-': not reached; a refused mode gives its reason), stores <out>/tradeoff.h5 and draws
    <out>/plots/tradeoff.png, the speed/accuracy frontier. Both modes run as compiled closed loops (five
    tolerances on the Cuk converter take about 17 s on two cores).
    """
    from ashc_cli.design.stages.bound import gain_text
    from ashc_cli.products import tradeoff as tradeoff_mod

    artefact_path = engine().artefact_path
    values = tradeoff_mod.parse_tolerances(tolerances)
    spec_obj, folder = load(spec, out)
    with Progress() as progress:
        arts, art, figure = tradeoff_mod.run_tradeoff(spec_obj, folder, values, on_stage=progress.on_stage, on_start=progress.on_start,
                                                      frozen=frozen)
    stored = artefact_path(folder, tradeoff_mod.NAME)
    bound_values = arts["bound"].values if "bound" in arts else {}
    sampled = str(bound_values.get("bound_evidence", "sampled")) != "proved"
    if as_json:
        emit_json({**tradeoff_mod.summarise(art), "bound_evidence": "sampled" if sampled else "proved", "artefact": str(stored), "figure": str(figure)})
    else:
        for row in tradeoff_mod.table(art, unit=tradeoff_mod.output_unit(spec_obj)):
            typer.echo(row)
        if sampled:
            typer.echo(f"note: the tolerances are guaranteed only on samples: G = {gain_text(bound_values)} rests on "
                       f"{bound_values.get('bound_sampled', 'sampled rows')}")
        typer.echo(f"tradeoff '{spec_obj.name}': {stored}, {figure}")


@app.command(short_help=SHORT_HELP["synthesize"])
@guard
def synthesize(spec: SpecArg, out: OutOpt = None, as_json: JsonOpt = False,
               frozen: frozen_opt("Never rerun a design stage: fail (exit 5, naming the stage) if one is stale.") = False) -> None:
    """Solve the spec's task on the output (`task:` always, reach, avoid) on the abstraction, guaranteed on the plant.

    With one abstract state (`task.planner: auto`) the plan is error-aware first: set-points on the abstraction,
    aimed at the reach sets in order, the input of each of 1000 held periods scaled so that the comparison bound
    w of the plant's error, carried along the plan (w' <= -(lambda - eps) w + (theta(xi) |v|)^2 / eps, theta proved
    per cell of V), stays below alpha_h EPS^2; the sets are deflated by sqrt(w(t) / alpha_h) at each moment, so the
    plan moves fast where theta is small and the error room is free. Failing that, the budget mode of the
    guaranteed controller: one v_max = (EPS - sqrt(W0 / alpha_h)) / G for the horizon (eq. (38)). EPS is searched;
    a plan is kept when psi meets the deflated task with robustness >= a sampling margin (then every plant run of
    the interface from the start region meets the task). The plan then runs on the plant and the task's
    robustness of that run is reported (the signed distance, in output units, to violating the task). Writes
    <out>/synthesize.h5 and prints EPS, the certified margin and the plant run's robustness. Exit 3 when no EPS
    works, naming the part of the task that fails and by how much. With two or three abstract states, or when the
    set-point plans are refused for an avoid set, the task is solved as a game on a grid of V instead (the grid
    planner; every transition over-approximated, every set deflated by EPS over each sampling period: the margin
    is proved). Error-aware and grid plans are tables of inputs held over periods, which the plant runs. Figures:
    <out>/plots/synthesize.png (psi with its error band, y of the plant; and synthesize_grid.png: V's winning cells
    and the route, two abstract states).
    """
    from ashc_cli.outputs.query import summary
    from ashc_cli.products.synthesize import NAME, run_synthesize

    spec_obj, folder = load(spec, out)
    with Progress() as progress:
        _, art = run_synthesize(spec_obj, folder, on_stage=progress.on_stage, on_start=progress.on_start, frozen=frozen)
    entry = summary({NAME: art})[NAME]
    if as_json:
        emit_json(entry)
        return
    task = entry["task"]
    times = ", ".join("-" if not np.isfinite(x) else f"{x:.4g}" for x in task["reach_times"])
    typer.echo(f"synthesize '{spec_obj.name}': EPS = {number_text(entry['tolerance'], '.4g')} (v_max = {number_text(entry['v_max'], '.4g')}), "
               f"task certified with margin {number_text(entry['certified_margin'], '.4g')} "
               f"({'proved by the grid planner' if entry['margin_evidence'] == 'proved' else 'sampled in time'}); on the plant "
               f"{'met' if task['satisfied'] else 'NOT met'}, robustness {number_text(task['robustness'], '.4g')}, reach times [{times}] s")
    lower = entry.get("lower_bound_reach_times") or []
    if lower and np.all(np.isfinite(lower)):
        typer.echo(f"  no input certified at this EPS by the comparison bound meets the reach sets in order before [{', '.join(f'{x:.4g}' for x in lower)}] s "
                   "(the abstraction's speed under the guarantee; the plan meets them in order)")


@app.command(short_help=SHORT_HELP["report"])
@guard
def report(spec: SpecArg, out: OutOpt = None, runs: ReportRunsOpt = None, seed: ReportSeedOpt = None, t_final: ReportTFinalOpt = None,
           force: ForceOpt = False,
           frozen: frozen_opt("Recompute nothing: report on the stored artefacts; fail (exit 5, naming the stage) if a stage is "
                               "stale or falsify.h5 is missing or does not match --runs, --seed and --t-final.") = False) -> None:
    """Write <out>/report.html: one self-contained page for a design review.

    It holds the spec, the Problem 1 verdict, every stage's numbers and checks, the uniform and a-posteriori
    bounds, the falsification result and the figures of `ashc plot`, embedded. The falsification stored by
    `ashc falsify` is used if it was made for this design with every one of --runs, --seed and --t-final
    given, or if it holds more runs than --runs asks for (a larger search is kept; --force replaces it);
    otherwise falsify runs (stderr says why). Prints the page's path. Exit 0 when written, also for a
    design that fails (the page says why); exit 3 if the falsification finds a violation.
    """
    from ashc_cli.design.verdict import verdict
    from ashc_cli.outputs import plots
    from ashc_cli.outputs.report import render

    exclusive(force, frozen, "report")
    positive_t_final(t_final)
    spec_obj, path = load(spec, out)
    pipeline = engine()
    needed, run, run_for_verdict = pipeline.needed, pipeline.run, pipeline.run_for_verdict
    seen = pipeline.Folder(path)  # one view of the folder for the design, simulate and falsify runs below
    with Progress() as progress:
        arts, stopped = run_for_verdict(spec_obj, seen, force=force, frozen=frozen, on_stage=progress.on_stage, on_start=progress.on_start)
        result = verdict(arts, stopped)
        violated = False
        if stopped is None:
            arts.update(run(spec_obj, seen, ["simulate"], force=force, frozen=needed(["simulate"]) if frozen else False,
                            on_stage=progress.on_stage, on_start=progress.on_start))
            arts[FALSIFY] = _falsify_for_report(spec_obj, seen, arts, runs, seed, t_final, force, frozen, progress)
            fv = arts[FALSIFY].values
            violated = float(fv["max_ratio"]) > 1.0 or min(float(fv.get(k, 0.0)) for k in ("task/min_robustness", "task_disturbed/min_robustness")) < 0
        elif runs is not None or seed is not None or t_final is not None:
            progress.line(f"note: --runs, --seed and --t-final not used: the design stopped at {stopped[0]}, so falsify does not run")
        progress.start("report: drawing the figures")
        figures = plots.write_all(spec_obj, arts, path / "plots")
    page = render(Path(spec).read_text(encoding="utf-8"), spec_obj.name, arts, result, figures, task=spec_obj.task)
    target = path / "report.html"
    tmp = target.with_suffix(".html.tmp")
    tmp.write_text(page, encoding="utf-8")
    tmp.replace(target)
    typer.echo(f"{target} ({len(page) // 1024} KiB): {result.line()}")
    if violated:
        typer.echo("error: report: the falsification run violates the bound or the task (see the report)", err=True)
        raise typer.Exit(3)


@app.command(short_help=SHORT_HELP["sweep"])
@guard
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
    spec_obj, folder = load(spec, out)
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
        emit_json(result)
    else:
        typer.echo(f"sweep '{spec_obj.name}': {result['solved']}/{result['combinations']} combinations solved on {result['workers']} worker(s) "
                   f"in {result['wall_seconds']:.1f} s; table {result['table']}, plot {result['plot']}")


#: Worker processes of sweep's local cluster unless --workers says otherwise.
SWEEP_WORKERS = 2


@app.command(short_help=SHORT_HELP["example"])
@guard
def example(
    kind: Annotated[str | None, typer.Argument(metavar="KIND", help=(
        "A shipped spec (cuk_converter, or short: cuk; `--list` shows them all) or a family of scalable plants: 'ladder' "
        "(an N-stage switched LC ladder, n = 4 N), 'rc_ladder' (the MORwiki nonlinear RC ladder with N diodes, n = N; "
        "without --stages the shipped 5-node spec), 'chain' (N masses on springs, n = 2 N) or 'ring' (N pendulums coupled all to "
        "all, n = 2 N, 2 N + N (N - 1) / 2 distinct nonlinear terms)."), show_default=False)] = None,
    stages: Annotated[int | None, typer.Option("--stages", min=1, max=4096, show_default=False,
                                               help="Number of stages N of a family (cells, nodes, masses or pendulums) [default: 1].")] = None,
    output: Annotated[Path | None, typer.Option("--output", help="Spec file to write [default: print to stdout].", show_default=False)] = None,
    list_them: Annotated[bool, typer.Option("--list", help="List the shipped specs and the families, one line each.")] = False,
    force: Annotated[bool, typer.Option("--force", help="Overwrite an existing --output file (else refused: it may hold your edits).")] = False,
    task: Annotated[bool, typer.Option("--task", help=(
        "With the ladder family: add a reach-avoid task on the output (from about 15.5 V into [17, 23] V by 140 s, held 15 s, never "
        "above 23.5 V) for `ashc synthesize`, solved by the grid planner on the one abstract state."))] = False,
) -> None:
    """Write an example spec: one shipped with ashc (the paper's Cuk converter and a dozen other plants), or a
    scalable plant of N stages (for benchmarks and large designs).

    Prints the spec, or with --output writes it and prints its path; then `ashc design FILE` designs it. The
    shipped specs come with the package, so they are there after `pip install` without the repository.
    """
    from ashc_cli.problem import examples

    families = {"ladder": (examples.ladder, 256, lambda N: 4 * N), "rc_ladder": (examples.rc_ladder, 4096, lambda N: N),
                "chain": (examples.chain, 1024, lambda N: 2 * N), "ring": (examples.ring, 64, lambda N: 2 * N)}
    if list_them:
        for name, text in examples.shipped().items():
            typer.echo(f"{name:<24} {text}")
        for name in families:
            typer.echo(f"{name:<24} family: `ashc example {name} --stages N`")
        return
    if kind is None:
        raise SpecError("KIND", "missing", "a shipped spec or a family (`ashc example --list` shows them)")
    if kind in families and not (kind == "rc_ladder" and stages is None):
        make, most, states = families[kind]
        stages = 1 if stages is None else stages
        if kind == "rc_ladder" and stages < 2:
            raise SpecError("--stages", f"{stages}", "at least 2 nodes for an RC ladder")
        if stages > most:
            raise SpecError("--stages", f"{stages}", f"at most {most} for the {kind} family")
        if task and kind != "ladder":
            raise SpecError("--task", f"with '{kind}'", "the ladder family (`ashc example ladder --stages N --task`)")
        text, what = (make(stages, task=True) if task else make(stages)), f"{stages}-stage {kind}, n = {states(stages)}{' with a task' if task else ''}"
    else:
        if task:
            raise SpecError("--task", f"with '{kind}'", "the ladder family (`ashc example ladder --stages N --task`)")
        if stages is not None:
            raise SpecError("--stages", f"{stages}", f"no --stages for a shipped spec ('{kind}'): only the families ladder, rc_ladder, chain and ring take it")
        name, text = examples.shipped_spec(kind)
        what = f"the shipped spec {name}"
    if output is None:
        typer.echo(text, nl=False)
    else:
        if output.exists() and not force:
            raise SpecError("--output", f"{output} exists", "a new file, or --force to overwrite it")
        output.parent.mkdir(parents=True, exist_ok=True)
        output.write_text(text, encoding="utf-8")
        typer.echo(f"{output}: {what}")


@app.command(short_help=SHORT_HELP["regress"])
@guard
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
        emit_json(rows)
    bad = [r for r in rows if r["status"] in ("differs", "no golden")]
    if bad:
        typer.echo(f"error: regress: {len(bad)} of {len(rows)} spec(s) differ from {golden}: {', '.join(r['spec'] for r in bad)}", err=True)
        raise typer.Exit(3)

