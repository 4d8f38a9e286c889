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

import numpy as np
import typer

from . import __version__
from .errors import AshcError, SpecError
from .pipeline import DESIGN, STAGES, Folder, StageReport, artefact_path, default_out, load_all, run, run_falsify, run_for_verdict
from .query import EVALUABLE, evaluate, parse_point, summary
from .spec import load_spec
from .verdict import verdict
from .stages.bound import region_text

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

SpecArg = Annotated[Path, typer.Argument(help="The YAML spec (see docs/spec-format.md).", show_default=False)]
OutOpt = Annotated[Optional[Path], typer.Option("--out", help="Artefact folder [default: outputs/<spec name>].", show_default=False)]
ForceOpt = Annotated[bool, typer.Option("--force", help="Recompute every needed stage even if up to date.")]
JsonOpt = Annotated[bool, typer.Option("--json", help="Print the result as JSON on stdout (progress goes to stderr).")]
NumericOpt = Annotated[Optional[bool], typer.Option("--numeric/--symbolic", help="Force the numeric fast paths (grids and interpolants) or the symbolic ones (sympy) [default: numeric above 12 states]. Add --force when switching on an existing folder.", show_default=False)]
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


def _load(spec_path: Path, out: Path | None):
    """The spec and its artefact folder (``--out``, or outputs/<spec name>)."""
    spec = load_spec(spec_path)
    return spec, Path(out if out is not None else default_out(spec))


def _run(spec_path: Path, out: Path | None, targets, force: bool, as_json: bool, frozen: bool = False, numeric: bool | None = None):
    spec, folder = _load(spec_path, out)
    arts = run(spec, folder, targets, force=force, frozen=frozen, on_stage=_progress(as_json), numeric=numeric)
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
    "simulate": "Run the tracking and m-relation scenarios of the spec (Figs. Example_*), designing first if needed. A scenario check "
                "that fails (psi not settled, u outside U, ...) is printed as 'FAILED (simulated)' and listed by `ashc check`; the exit "
                "status stays 0, since it observes one run and is not a design condition of Problem 1.",
}


def _make_stage_command(stage: str):
    def command(spec: SpecArg, out: OutOpt = None, force: ForceOpt = False, as_json: JsonOpt = False, frozen: FrozenOpt = False,
                numeric: NumericOpt = None) -> None:
        _, _, arts = _run(spec, out, [stage], force, as_json, frozen, numeric)
        if as_json:
            _emit_json(summary({stage: arts[stage]})[stage])

    command.__name__ = f"{stage}_command"
    command.__doc__ = _STAGE_HELP[stage] + " Runs any stale upstream stage first (unless --frozen)."
    app.command(name=stage, help=command.__doc__)(_guard(command))


for _stage in STAGES:
    _make_stage_command(_stage)


@app.command()
@_guard
def design(spec: SpecArg, out: OutOpt = None, force: ForceOpt = False, as_json: JsonOpt = False, numeric: NumericOpt = None) -> None:
    """Run the design stages stabilise..bound in order, skipping those already up to date.

    A stage is up to date when its artefact was made from the same spec (SHA-256) and the same upstream
    artefacts; --force redoes all. Prints one line per stage with its time and headline number.
    """
    spec_obj, folder, arts = _run(spec, out, DESIGN, force, as_json, numeric=numeric)
    checks = [c for name in DESIGN for c in arts[name].checks.values()]
    failed = [c.description for c in checks if not c.passed]
    if as_json:
        _emit_json(summary({name: arts[name] for name in DESIGN}))
    else:
        b = arts["bound"].values
        proved = sum(c.evidence == "proved" for c in checks)
        typer.echo(f"design '{spec_obj.name}' in {folder}: {len(checks) - len(failed)}/{len(checks)} checks passed "
                   f"({proved} proved, {len(checks) - proved} sampled); "
                   f"|psi - y| <= {b['gain']:.5g} ||v||_inf {region_text(b)}")
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
    spec_obj, folder = _load(spec, out)
    arts, stopped = run_for_verdict(spec_obj, folder, force=force, on_stage=_progress(True))
    solved, rows = verdict(arts, stopped)
    sim = None if force else _current(spec_obj, Folder(folder), "simulate")
    simulated = [] if sim is None else [{"check": name, "status": "pass" if c.passed else "fail", "value": c.value if np.isfinite(c.value) else None,
                                         "detail": c.description, "evidence": c.evidence} for name, c in sim.checks.items()]
    if as_json:
        _emit_json({"spec": spec_obj.name, "solved": solved, "rows": [r.as_dict() for r in rows], "simulated": simulated})
    else:
        typer.echo(f"Problem 1 (nonlinear ASHC) for '{spec_obj.name}':")
        for r in rows:
            value = "" if r.value is None else f"{r.value:.4g}"
            typer.echo(f"  {r.status:<11} {r.evidence:<9} {r.condition:<42} {value:>11}   {r.reference}")
            if r.status == "fail":
                typer.echo(f"              {r.detail}")
        if simulated:
            typer.echo("Simulated scenarios (`ashc simulate`; evidence: simulated; not part of the verdict):")
            for r in simulated:
                value = "" if r["value"] is None else f"{r['value']:.4g}"
                typer.echo(f"  {r['status']:<11} {r['evidence']:<9} {r['check']:<42} {value:>11}")
                if r["status"] == "fail":
                    typer.echo(f"              {r['detail']}")
        typer.echo(f"Problem 1 solved: {'yes' if solved else 'no'}")
    if not solved:
        raise typer.Exit(3)


RunsOpt = Annotated[int, typer.Option("--runs", min=1, max=100000, help="Number of closed-loop runs, shared among the search strategies (compiled, over every core).")]
SeedOpt = Annotated[int, typer.Option("--seed", help="Random seed: the same seed gives the same batch.")]
TFinalOpt = Annotated[Optional[float], typer.Option("--t-final", min=0.0, help="Length of each run in seconds [default: the spec's tracking t_final].", show_default=False)]


def _current(spec, folder: Folder, stage: str):
    """The folder's artefact of ``stage`` if it was made from this spec, else None."""
    if not artefact_path(folder.path, stage).exists():
        return None
    art = folder.read(stage)
    return art if art.provenance.get("spec_sha256") == spec.sha256 else None


@app.command()
@_guard
def plot(spec: SpecArg, out: OutOpt = None, force: ForceOpt = False, as_json: JsonOpt = False) -> None:
    """Draw the paper's figures for this design as PNG files in <out>/plots/.

    kappa_xi.png (kappa over V with Y), delta_compare.png (||theta|| for delta = I and the design's delta),
    tracking_inputs/outputs.png (v, u; psi, y and |psi - y| with the uniform and a-posteriori bounds),
    m_relation_inputs/outputs.png, and falsify.png when `ashc falsify` has run. Runs the stale stages
    (simulate included) first.
    """
    from . import plots  # matplotlib only for the commands that draw (cold start of the others)

    spec_obj, folder, arts = _run(spec, out, ["simulate"], force, as_json)
    current = _current(spec_obj, Folder(folder), "falsify")
    if current is not None:
        arts["falsify"] = current
    paths = plots.write_all(spec_obj, arts, folder / "plots")
    if as_json:
        _emit_json({"figures": [str(p) for p in paths]})
    else:
        for p in paths:
            typer.echo(str(p))


@app.command()
@_guard
def falsify(spec: SpecArg, out: OutOpt = None, runs: RunsOpt = 64, seed: SeedOpt = 0, t_final: TFinalOpt = None,
            as_json: JsonOpt = False) -> None:
    """Search for a run that breaks the certified error bound (compiled closed loops over every core).

    Strategies share the runs: random set-point runs; an adversary on the manifold (W0 = 0) choosing the
    sign of v that makes W grow fastest; bang-bang square waves; the linearised worst case at points of V;
    starts on the boundary of the certified region W0 = w0_max_certified (or over a wide range of W0 when
    the bound is global); and a refinement of the best runs by an evolution strategy. Every run keeps
    W0 <= w0_max_certified and ||v|| <= min(v_max, v_max_certified), and xi in V. Reports the largest ratio
    of |psi - y| to sqrt(W0 exp(-(lambda - eps) t) / alpha_h) + G sup|v| over all runs (max_ratio) and over
    the runs started on the manifold (max_ratio_w0_zero, where only G ||v|| counts). Writes falsify.h5
    either way; exit 3 if a ratio exceeds 1 (a violation).
    """
    spec_obj, folder = _load(spec, out)
    from .falsify import SEGMENTS
    rate = [""]
    with typer.progressbar(length=SEGMENTS, label=f"falsify: {runs} runs", file=sys.stderr, item_show_func=lambda _: rate[0]) as bar:
        done = [0]

        def advance(k: int) -> None:
            bar.update(k - done[0])
            done[0] = k

        def speed(count: int, per_second: float) -> None:
            rate[0] = f"{count} runs integrated, {per_second:.0f} runs/s"
            bar.update(0)

        _, art = run_falsify(spec_obj, folder, runs, seed, t_final, on_stage=_progress(True), progress=advance, on_runs=speed)
    entry = summary({"falsify": art})["falsify"]
    if as_json:
        _emit_json(entry)
    else:
        typer.echo(f"falsify '{spec_obj.name}': {entry['runs']} runs, largest |psi - y| / bound = {entry['max_ratio']:.9g} "
                   f"(run {entry['worst_run']}, {entry.get('strategy_of_worst', 'random')}, t = {entry['worst_time']:.4g} s); "
                   f"started on the manifold (W0 = 0): {entry.get('max_ratio_w0_zero', float('nan')):.6g} "
                   f"({entry.get('strategy_of_worst_w0_zero', '-')}); {entry['runs_leaving_V']} left V")
    if entry["max_ratio"] > 1.0:
        typer.echo(f"error: falsify: the bound is violated by a factor {entry['max_ratio']:.4g} in run {entry['worst_run']} at "
                   f"t = {entry['worst_time']:.4g} s; the run is saved in {folder / 'falsify.h5'}", err=True)
        raise typer.Exit(3)


@app.command()
@_guard
def report(spec: SpecArg, out: OutOpt = None, runs: RunsOpt = 32, seed: SeedOpt = 0, t_final: TFinalOpt = None,
           force: ForceOpt = False) -> None:
    """Write <out>/report.html: one self-contained page for a design review.

    It holds the spec, the Problem 1 verdict, every stage's numbers and checks, the uniform and a-posteriori
    bounds, the falsification result (running `ashc falsify` with --runs if it has not run on this spec)
    and the figures of `ashc plot`, embedded. Exit 0 when written, also for a design that fails (the
    page says why); exit 3 if the falsification finds a violation.
    """
    from . import plots
    from .report import render

    spec_obj, folder = _load(spec, out)
    seen = Folder(folder)  # one view of the folder for the design, simulate and falsify runs below
    arts, stopped = run_for_verdict(spec_obj, seen, force=force, on_stage=_progress(True))
    solved, rows = verdict(arts, stopped)
    violated = False
    if stopped is None:
        arts.update(run(spec_obj, seen, ["simulate"], on_stage=_progress(True)))
        current = None if force else _current(spec_obj, seen, "falsify")
        arts["falsify"] = current if current is not None else run_falsify(spec_obj, seen, runs, seed, t_final, on_stage=_progress(True))[1]
        violated = float(arts["falsify"].value("max_ratio")) > 1.0
    figures = plots.write_all(spec_obj, arts, folder / "plots")
    page = render(Path(spec).read_text(encoding="utf-8"), spec_obj.name, arts, solved, rows, figures)
    target = folder / "report.html"
    tmp = target.with_suffix(".html.tmp")
    tmp.write_text(page, encoding="utf-8")
    tmp.replace(target)
    typer.echo(f"{target} ({len(page) // 1024} KiB): Problem 1 solved: {'yes' if solved else 'no'}")
    if violated:
        typer.echo("error: report: the falsification run violates the bound (see the report)", err=True)
        raise typer.Exit(3)


@app.command()
@_guard
def sweep(
    spec: SpecArg,
    param: Annotated[list[str], typer.Option("--param", help="NAME=LO:HI:COUNT, a spec parameter and its values (repeat for a grid).", show_default=False)],
    out: OutOpt = None,
    scheduler: Annotated[Optional[str], typer.Option("--scheduler", help="Address of a running dask.distributed scheduler (e.g. tcp://10.0.0.5:8786) [default: a local cluster].", show_default=False)] = None,
    workers: Annotated[int, typer.Option("--workers", min=1, max=256, help="Worker processes of the local cluster.")] = 2,
    falsify_runs: Annotated[int, typer.Option("--falsify-runs", min=0, help="Also run `ashc falsify` with this many runs per solved design (0: no).")] = 0,
    as_json: JsonOpt = False,
) -> None:
    """Design the spec for every combination of parameter values, in parallel on Dask.

    Each combination designs into <out>/sweep/<k>/; a failing design is recorded (solved: no, with the
    reason) and the sweep goes on. Results: <out>/sweep.h5 (parameters, lambda, dbar_q0, gain, verdict,
    falsify ratio, seconds, error per combination) and <out>/plots/sweep.png (headline numbers against
    the first swept parameter).
    """
    from . import sweep as sweep_mod
    from .artefacts import write_artefact

    spec_obj, folder = _load(spec, out)
    axes = [sweep_mod.parse_param(p, spec_obj) for p in param]
    names = [n for n, _ in axes]
    if len(set(names)) != len(names):
        raise SpecError("--param", f"a parameter is swept twice ({', '.join(names)})", "each parameter once")

    def show(row: dict) -> None:
        values = ", ".join(f"{k}={v:.6g}" for k, v in row["params"].items())
        verdict_text = "solved" if row["solved"] else f"NOT solved: {row['error']}"
        typer.echo(f"  {values}: lambda = {row['lambda']:.5g}, dbar_q0 = {row['dbar_q0']:.5g}, G = {row['gain']:.5g}, {verdict_text} ({row['seconds']:.1f} s)", err=True)

    art = sweep_mod.sweep(spec_obj, axes, folder, scheduler, workers, falsify_runs, progress=show)
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


@app.command()
@_guard
def example(
    kind: Annotated[str, typer.Argument(help="Which family: 'ladder' (an N-stage switched LC ladder, n = 4 N).", show_default=False)],
    stages: Annotated[int, typer.Option("--stages", min=1, max=256, help="Number of stages N (n = 4 N states).")] = 1,
    output: Annotated[Optional[Path], typer.Option("--output", help="Spec file to write [default: print to stdout].", show_default=False)] = None,
) -> None:
    """Write the spec of a scalable example plant (for benchmarks and large designs)."""
    from .examples import ladder

    if kind != "ladder":
        raise SpecError("KIND", f"'{kind}' is not an example family", "ladder")
    text = ladder(stages)
    if output is None:
        typer.echo(text, nl=False)
    else:
        output.parent.mkdir(parents=True, exist_ok=True)
        output.write_text(text, encoding="utf-8")
        typer.echo(f"{output}: {stages}-stage ladder, n = {4 * stages}")


@app.command()
@_guard
def regress(
    specs: Annotated[Path, typer.Argument(help="A folder of specs (every *.yaml in it).", show_default=False)],
    golden: Annotated[Path, typer.Option("--golden", help="Folder of golden JSON files, one per spec name.")] = Path("tests/golden"),
    out: Annotated[Optional[Path], typer.Option("--out", help="Where the designs go [default: outputs/regress].", show_default=False)] = None,
    update: Annotated[bool, typer.Option("--update", help="Write the golden files from this run (keeping edited tolerances).")] = False,
    as_json: JsonOpt = False,
) -> None:
    """Rerun every spec in a folder and compare its summary with golden values, key by key.

    Each golden file names the keys it checks (e.g. bound.gain) with a tolerance (rtol/atol, or at_most for
    residuals). A difference is reported with the key, both values and the tolerance; exit 3 if any spec
    differs or has no golden file (write them with --update, after checking the numbers).
    """
    from .regress import regress as run_regress

    def show(row: dict) -> None:
        typer.echo(f"{row['spec']:<28} {row['status']}", err=as_json)
        for d in row["differences"]:
            typer.echo(f"    {d}", err=as_json)

    rows = run_regress(specs, golden, out if out is not None else Path("outputs") / "regress", update, progress=show)
    if as_json:
        _emit_json(rows)
    bad = [r for r in rows if r["status"] in ("differs", "no golden")]
    if bad:
        typer.echo(f"error: regress: {len(bad)} of {len(rows)} spec(s) differ from {golden}: {', '.join(r['spec'] for r in bad)}", err=True)
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
            value = chk["value"] if isinstance(chk["value"], str) else f"{chk['value']:.4g}"
            typer.echo(f"  check {key}: {'pass' if chk['passed'] else 'FAIL'} ({value}, {chk.get('evidence', 'sampled')})")


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
