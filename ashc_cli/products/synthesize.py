"""``ashc synthesize``: a task on the output (``spec.task``) solved on the abstraction and guaranteed on the plant.

The abstract controller, its tolerance EPS and why it is certified are :mod:`ashc_cli.design.task_plan` (the budget
mode of the guaranteed controller, Theorem 2, eq. (38); EPS searched).  This product brings the design up to date,
plans the task, runs the plan on the concrete plant (the compiled closed loop of ``simulate``, the task scenario:
:func:`ashc_cli.design.stages.simulate.task_run`), monitors the task's robustness on that run and stores all of it in
``synthesize.h5`` with the figure of the task (docs/guide.md, "Tasks on the output").
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

from ashc_cli.closedloop.terms import DesignTerms
from ashc_cli.design import error_plan, task_plan
from ashc_cli.design.artefacts import Artefact, Check, write_artefact
from ashc_cli.errors import DesignError, SpecError
from ashc_cli.numerics.grid_games import ROUTE_SLACK
from ashc_cli.numerics.proofs import PROVED, SAMPLED, SIMULATED
from ashc_cli.problem.spec import Spec

__all__ = ["NAME", "UPSTREAM", "synthesize", "run_synthesize", "plot", "summarise", "headline", "store"]

NAME = "synthesize"
#: The design artefacts the plan reads (a change in any makes synthesize.h5 stale).
UPSTREAM = ("stabilise", "manifold", "kappa", "delta", "bound")


def synthesize(model, up: dict[str, Artefact]) -> Artefact:
    """Search EPS, plan on the abstraction, run the plan on the plant and monitor both.

    Parameters
    ----------
    model : Model
        The spec's systems (``task`` is read, and ``simulate.tracking`` for a default xi0 and gain).
    up : dict of str to Artefact
        The design's artefacts (stabilise .. bound).

    Returns
    -------
    Artefact
        See :func:`store`.

    Raises
    ------
    DesignError
        No task; an abstraction the plan cannot handle; or (exit 3) no EPS for which the plan meets the task
        deflated, naming the part that fails and by how much.
    """
    plant = DesignTerms(model, up)
    plan = task_plan.plan_task(model, up, plant=plant)
    res = task_plan.task_run(model, plant, up, plan)
    plan, run = task_plan.on_the_plant(model, plant, plan, res)
    art = store(plan, run, up)
    if "w_within_plan" in art.checks and not art.checks["w_within_plan"].passed:
        # the claim's hypothesis failed on the plan's own run: no certificate (exit 3, nothing written)
        raise DesignError("task", f"the plant run of the error-aware plan breaks its hypothesis: its comparison w exceeds the plan's bound by "
                          f"{run['w_over_plan']:.3g} (or its xi left the plan's by {run['xi_deviation']:.3g}, more than a cell of theta's table): "
                          "theta(xi) |v| does not bound what the interface did", "task.planner: {kind: setpoint} (the budget's plan)")
    if model.n_hat == 1 and plan.planner != "grid":       # (the grid's table is its own proof; theta's table costs a minute at n = 512)
        comp = error_plan.comparison(up)
        level = comp.alpha_h * plan.eps ** 2
        art.values["lower_bound_reach_times"] = error_plan.reach_lower_bounds(model, up, error_plan.theta_table(model, up), comp, level, plan.xi0)
    return art


def store(plan: task_plan.TaskPlan, run: dict, up: dict[str, Artefact]) -> Artefact:
    """The synthesize artefact of a plan and its plant run.

    Parameters
    ----------
    plan : TaskPlan
        After :func:`ashc_cli.design.task_plan.on_the_plant`.
    run : dict
        Its values (t, y, psi, robustness, ...).
    up : dict of str to Artefact
        The design (for the certified start region).

    Returns
    -------
    Artefact
        ``tolerance`` (the EPS kept), ``v_max``, ``gain``, ``W0``, ``start_region_W0``, the plan (``plan/t``,
        ``plan/xi``, ``plan/psi``, ``plan/v``, ``switch_times``, ``references``), the concrete run (``run/t``,
        ``run/y``, ``run/psi``), the task's robustness on psi and on y with each part, the reach times; checks
        ``task_certified`` (the plan's margin, sampled in time) and ``task_met_on_the_plant`` (simulated).
    """
    art = Artefact(stage=NAME, meta={"eps_candidates": len(plan.tried), "plan_steps": task_plan.PLAN_STEPS})
    art.values.update({
        "tolerance": plan.eps, "v_max": plan.v_max, "gain": plan.gain, "W0": plan.W0, "sampling_margin": plan.margin,
        "start_region_W0": task_plan.start_region(plan, up),
        "switch_times": np.array(plan.switches), "references": np.stack(plan.refs, axis=1), "xi0": plan.xi0,
        "plan/t": plan.t, "plan/xi": plan.xi, "plan/psi": plan.psi, "plan/v": plan.v,
        "plan_robustness": plan.rob.robustness, "certified_margin": plan.certified, "plan_deviation": run["deviation"],
        "run/t": run["t"], "run/y": run["y"], "run/psi": run["psi"], "run/max_abs_error": run["max_abs_error"],
        "task/robustness": run["robustness"], "task/satisfied": run["satisfied"],
        "task/reach_times": run["reach_times"], "task/best_hold_starts": run["best_hold_starts"],
        "eps_tried": np.array([e for e, _ in plan.tried]), "margin_tried": np.array([c for _, c in plan.tried]),
    })
    for key, value in run.items():
        if key.startswith("parts/"):
            art.values[f"task/{key}"] = value
    art.meta["planner"] = plan.planner
    if plan.proved:
        _store_grid(art, plan, run)
    elif plan.planner == "error_aware":
        _store_error_aware(art, plan, run)
    else:
        fitted = (f", G = {plan.gain_G:.5g} with dbar over xi in [{plan.fitted[0]:.6g}, {plan.fitted[1]:.6g}], the part of V the plan keeps to"
                  if plan.fitted else "")
        if plan.fitted:
            art.values.update({"gain_G": plan.gain_G, "fitted_V": np.array(plan.fitted, dtype=float)})
        art.checks["task_certified"] = Check(plan.certified, plan.certified >= 0,
                                             f"psi's robustness on the plan {plan.rob.robustness:.4g} less EPS = {plan.eps:.4g} (budget mode, eq. (38){fitted}), "
                                             f"the sampling margin {plan.margin:.3g} and the plan's deviation from the run's abstraction "
                                             f"{run['deviation']:.2g} (>= 0: every plant run meets the task; sampled in time)", SAMPLED)
    art.checks["task_met_on_the_plant"] = Check(run["robustness"], bool(run["satisfied"]),
                                                f"the task's robustness on the plant's run of the plan (>= 0), max |psi - y| = "
                                                f"{run['max_abs_error']:.3g} <= EPS = {plan.eps:.4g}", SIMULATED)
    return art


def _store_error_aware(art: Artefact, plan: task_plan.TaskPlan, run: dict) -> None:
    """Error-aware planning (:mod:`ashc_cli.design.error_plan`): the comparison bound along the plan, its level, the
    held table, and the checks: the margin (sampled in time, as the set-point plan's) and the plant run's own
    comparison w below the plan's (simulated)."""
    art.meta.update(theta_how=plan.theta_how, theta_evidence=plan.theta_evidence, plan_periods=len(plan.refs))
    art.values.update({"plan/w": plan.w, "w_level": plan.w_level, "plan/deflation": plan.eps * np.sqrt(np.maximum(plan.w, 0.0) / plan.w_level),
                       "tau": plan.tau, "aim_switch_times": np.array(plan.aims, dtype=float), "run/w": run["w"], "run/w_plan": run["w_plan"], "w_over_plan": run["w_over_plan"]})
    art.checks["task_certified"] = Check(plan.certified, plan.certified >= 0,
                                         f"psi's robustness on the plan against the sets deflated by sqrt(w(t) / alpha_h), w the comparison bound the "
                                         f"plan carries (<= alpha_h EPS^2, EPS = {plan.eps:.4g}; theta: {plan.theta_how}), {plan.rob.robustness:.4g}, less "
                                         f"the sampling margin {plan.margin:.3g} and the plan's deviation from the run's abstraction {run['deviation']:.2g} "
                                         "(>= 0: every plant run from the start region meets the task; sampled in time)", SAMPLED)
    ok = error_plan.within_plan(plan, run)
    art.values["xi_deviation"] = run["xi_deviation"]
    art.checks["w_within_plan"] = Check(run["w_over_plan"], ok,
                                        "the plant run's comparison w (its own |L^T r|) less the plan's bound at each sample (<= 0: the plan's "
                                        f"theta(xi) |v| bounds what the interface did), with the run's xi within {run['xi_deviation']:.2g} of the "
                                        f"plan's (<= a cell of theta's table, {plan.theta_cell:.3g}: the plan's theta covers the run's path)", SIMULATED)


def _store_grid(art: Artefact, plan: task_plan.TaskPlan, run: dict) -> None:
    """The grid planner's game and route in ``art`` (``grid/...``) and its proved check: the start's cell wins the
    game (every transition over-approximated by a proved growth bound, every set deflated by EPS through proved
    enclosures of kappa over each cell and period), and the plant run's xi kept within ROUTE_SLACK of a cell of the
    route (so that the held inputs are the table's law on the run's own xi)."""
    game, r = plan.game, plan.route
    g = game.grid
    art.meta.update(grid_cells=list(g.cells), grid_steps=game.steps, grid_widened=int(r.widened))
    art.values.update({
        "grid/lo": np.asarray(g.lo, dtype=float), "grid/hi": np.asarray(g.hi, dtype=float), "grid/tau": plan.tau,
        "grid/inputs": game.inputs, "grid/winning_start": game.win.start().reshape(g.cells).astype(np.uint8),
        "grid/route_cells": r.cells, "grid/route_choice": r.choice, "grid/route_states": r.states,
        "grid/route_phase": r.phase, "grid/hold_steps": np.array(r.holds, dtype=np.int64),
        "table_offset": run["table_offset"],
    })
    for k, ph in enumerate(game.phases):
        art.values[f"grid/target/{k}"] = ph.target.reshape(g.cells).astype(np.uint8)
    always, avoids = game.parts
    for j, (meets, _, _) in enumerate(avoids):
        art.values[f"grid/avoid/{j}"] = meets.reshape(g.cells).astype(np.uint8)
    wins = game.wins(plan.xi0)
    # the held inputs are the table's law on the loop's xi when that xi stays within ROUTE_SLACK of a cell of the
    # route's and every input was chosen admissible from all the cells that near (none from its own cell alone)
    ok = wins and run["table_offset"] <= ROUTE_SLACK and r.widened == 0
    art.checks["task_certified"] = Check(
        0.0 if ok else -np.inf, ok,
        f"the start's cell wins the task's game on {' x '.join(map(str, g.cells))} cells of V with the input held over tau = {plan.tau:.4g} s "
        f"({len(game.inputs)} inputs, |v_a| <= {plan.v_max:.4g}): psi's tube over every period lies in the sets deflated by EPS = {plan.eps:.4g} "
        f"(transitions by a proved growth bound, xi in V within each period, kappa enclosed per cell); the loop's integrated xi within "
        f"{run['table_offset']:.2g} cells of the route's (<= {ROUTE_SLACK:g}) and {r.widened} inputs chosen from one cell only (0): the held "
        f"inputs are the table's law on it; every plant run from the start region meets the task (margin >= 0, proved). "
        f"psi's sampled robustness on the route {plan.rob.robustness:.4g} >= EPS is the cross-check", PROVED)
    art.checks["grid_route_cross_check"] = Check(plan.rob.robustness - plan.eps, plan.rob.robustness - plan.eps >= -1e-9,
                                                 "psi's robustness on the route less EPS (>= 0 when the game's proof holds; sampled)", SAMPLED)


def run_synthesize(spec: Spec, out, *, on_stage: Callable | None = None, on_start: Callable | None = None,
                   frozen: bool = False) -> tuple[dict[str, Artefact], Artefact]:
    """Bring the design up to date, run :func:`synthesize` and store ``synthesize.h5``.

    Parameters
    ----------
    spec : Spec
        The validated spec (with a ``task``).
    out : str, Path or Folder
        The artefact folder.
    on_stage, on_start : callable, optional
        As :func:`ashc_cli.design.pipeline.run`.
    frozen : bool
        Never recompute a design stage.

    Returns
    -------
    arts : dict
        The design's artefacts.
    art : Artefact
        The synthesize artefact just written.
    """
    from ashc_cli.design.pipeline import DESIGN, StageReport, artefact_path, as_folder, declared_names, design_model, run

    if spec.task is None:
        raise SpecError("task", "missing", "a task on the output (docs/spec-format.md, 'task') for `ashc synthesize`")
    folder = as_folder(out)
    arts = run(spec, folder, DESIGN, frozen=DESIGN if frozen else False, on_stage=on_stage, on_start=on_start)
    if on_start is not None:
        on_start(NAME, f"{task_plan.EPS_CANDIDATES} tolerances, a plan on the abstraction, its run on the plant")
    start = time.perf_counter()
    art = synthesize(design_model(spec, arts), arts)
    write_artefact(artefact_path(folder.path, NAME), art, spec_sha256=spec.sha256, spec_name=spec.name,
                   parameters=dict(spec.parameters), upstream={up: arts[up].provenance["sha256"] for up in UPSTREAM},
                   names=declared_names(spec))
    if spec.concrete.h and len(spec.concrete.h) <= 2:
        plot(art, spec.task, folder.path / "plots" / f"{NAME}.png", unit=spec.units.get("y1") or spec.units.get("y"))
    if on_stage is not None:
        on_stage(StageReport(NAME, "ran", time.perf_counter() - start, headline(art)))
    return arts, art


def plot(art: Artefact, task, path, unit: str | None = None):
    """The task figure of the synthesised plan: over time for one output (:func:`ashc_cli.outputs.plots.draw_task`: y
    of the plant's run, psi and xi of the plan), in the output plane for two (:func:`ashc_cli.outputs.plots.draw_plane`);
    with a grid plan on two abstract states, V's winning cells and the route too.

    Parameters
    ----------
    art : Artefact
        The synthesize artefact (``run/t``, ``run/y``, ``plan/t``, ``plan/psi``, ``plan/xi``, ``switch_times``,
        ``tolerance``, ``task/reach_times``, ``task/best_hold_starts``; a grid plan's ``grid/...``).
    task : Task
        ``spec.task``.
    path : str or Path
        The file; its suffix gives the format.
    unit : str, optional
        The output's unit, on the y axis.

    Returns
    -------
    Path
    """
    from pathlib import Path

    from ashc_cli.outputs.plots import STYLE, TaskRun, draw_task, plt, save
    from ashc_cli.outputs.task_plots import GridView, draw_plane

    v = art.values
    grid = art.meta.get("planner") == "grid"
    view = None
    if grid and len(art.meta["grid_cells"]) == 2:
        view = GridView(v["grid/lo"], v["grid/hi"], v["grid/winning_start"],
                        [v[k] for k in sorted(v) if k.startswith("grid/target/")], [v[k] for k in sorted(v) if k.startswith("grid/avoid/")],
                        v["grid/route_states"])
    with plt.rc_context(STYLE):
        if np.atleast_2d(v["run/y"]).shape[0] == 2:
            return save(draw_plane(task, v["run/y"], v["plan/psi"], float(v["tolerance"]), view), Path(path))
        # a grid plan switches every period: mark where its holds begin instead
        aware = art.meta.get("planner") == "error_aware"
        switches = (np.r_[0.0, np.asarray(v["grid/hold_steps"], dtype=float) * float(v["grid/tau"])] if grid else
                    v["aim_switch_times"] if aware else v["switch_times"])
        run = TaskRun(v["run/t"], v["run/y"], v["plan/t"], v["plan/psi"], v["plan/xi"], switches, v["tolerance"],
                      v["task/reach_times"], v["task/best_hold_starts"], v["plan/deflation"] if aware else None)
        path = save(draw_task(task, run, unit), Path(path))
        if view is not None:
            save(draw_plane(None, None, None, float(v["tolerance"]), view), Path(path).with_name(f"{NAME}_grid{Path(path).suffix}"))
        return path


def summarise(art: Artefact) -> dict:
    """Headline numbers for ``ashc summary``.

    Parameters
    ----------
    art : Artefact
        The synthesize artefact.

    Returns
    -------
    dict
        ``tolerance`` (EPS), ``v_max``, ``certified_margin``, ``planner``, ``margin_evidence`` (proved or sampled),
        ``switch_times`` and ``task`` (robustness, satisfied,
        reach_times and each part's robustness on the plant's run).
    """
    v = art.values
    parts = {k.split("/", 2)[2]: float(val) for k, val in v.items() if k.startswith("task/parts/")}
    return {"tolerance": float(v["tolerance"]), "v_max": float(v["v_max"]), "certified_margin": float(v["certified_margin"]),
            "planner": art.meta.get("planner", "setpoint"), "margin_evidence": art.checks["task_certified"].evidence,
            "plan_robustness": float(v["plan_robustness"]), "switch_times": np.asarray(v["switch_times"]).tolist(),
            "lower_bound_reach_times": np.asarray(v.get("lower_bound_reach_times", []), dtype=float).tolist(),
            "task": {"robustness": float(v["task/robustness"]), "satisfied": bool(v["task/satisfied"]),
                     "reach_times": np.asarray(v["task/reach_times"]).tolist(), "parts": parts}}


def headline(art: Artefact) -> str:
    """One line: EPS, the certified margin and the plant run's robustness.

    Parameters
    ----------
    art : Artefact

    Returns
    -------
    str
    """
    v = art.values
    met = "met" if bool(v["task/satisfied"]) else "NOT met"
    if art.meta.get("planner") == "error_aware":
        return (f"EPS = {float(v['tolerance']):.4g} (error-aware: w <= {float(v['w_level']):.4g}, |v| <= {float(v['v_max']):.4g}, deflation "
                f"sqrt(w(t) / alpha_h)): task certified with margin {float(v['certified_margin']):.4g} (sampled in time); on the plant {met}, "
                f"robustness {float(v['task/robustness']):.4g}")
    if art.meta.get("planner") == "grid":
        proved = "proved" if art.checks["task_certified"].passed else "NOT proved"
        return (f"EPS = {float(v['tolerance']):.4g} (v_max = {float(v['v_max']):.4g}): the grid planner's table ({' x '.join(map(str, art.meta['grid_cells']))} "
                f"cells, tau = {float(v['grid/tau']):.4g} s) wins from the start, margin >= 0 {proved}; on the plant {met}, robustness {float(v['task/robustness']):.4g}")
    fitted = (f", G = {float(v['gain_G']):.4g} on xi in [{float(v['fitted_V'][0]):.4g}, {float(v['fitted_V'][1]):.4g}], where the plan goes"
              if "gain_G" in v else "")
    return (f"EPS = {float(v['tolerance']):.4g} (budget: v_max = {float(v['v_max']):.4g}{fitted}): task certified with margin "
            f"{float(v['certified_margin']):.4g}; on the plant {met}, robustness {float(v['task/robustness']):.4g}")
