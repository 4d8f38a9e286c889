"""``ashc synthesize``: a task on the output (``spec.task``) solved on the abstraction and guaranteed on the plant.

The guarantee is the budget mode of the guaranteed controller (docs/guaranteed.md): from a start with W(xi0, x0) =
W0, any abstract input with |v| <= v_max = (EPS - sqrt(W0 / alpha_h)) / G that keeps xi in V keeps
|psi - y| <= EPS at every time (Theorem 2, eq. (38)).  The abstract controller is then chosen on the abstraction
alone: it is the set-point law clipped at v_max, aimed at the reach sets one after the other (a set's reference
state has kappa(xi_ref) at the set's centre), switching to the next set once psi has held the current one, deflated,
for its hold.  Its run xi(t) does not depend on the plant, so the plan is integrated here once and its psi monitored:
if psi meets the task with robustness rho_psi >= EPS + the sampling margin, every plant run of the interface meets
the original task (robustness >= rho_psi - EPS: the box margins are 1-Lipschitz in the output).  The sampling margin
is max |dpsi/dt| times the plan's step (what psi can do between two samples; taken on the plan's samples).

EPS is searched: a small EPS allows a small v_max (a slow abstraction), a large one deflates the sets away.  The
EPS of the largest certified margin is kept; when none is >= 0, the command exits 3 naming the part of the task
that fails at the best EPS and by how much.  Then the plan runs on the concrete plant (the compiled closed loop of
``simulate`` with the plan's switching times) and the task's robustness of that run is reported.

This is a plan-and-verify synthesis on the abstraction, not the grid fixed point of reach-avoid games: it does not
route psi around an avoid set (a plan that crosses one is refused, with the part named).
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np
from scipy.optimize import minimize_scalar

from ashc_cli.closedloop import plan as guaranteed
from ashc_cli.closedloop.task_monitor import robustness
from ashc_cli.closedloop.terms import DesignTerms
from ashc_cli.design.artefacts import Artefact, Check, write_artefact
from ashc_cli.design.stages import simulate as sim
from ashc_cli.errors import DesignError, SpecError
from ashc_cli.numerics.proofs import SAMPLED, SIMULATED
from ashc_cli.problem.spec import Spec

__all__ = ["NAME", "UPSTREAM", "synthesize", "run_synthesize", "plot", "summarise", "headline", "EPS_CANDIDATES", "PLAN_STEPS"]

NAME = "synthesize"
#: The design artefacts the plan reads (a change in any makes synthesize.h5 stale).
UPSTREAM = ("stabilise", "manifold", "kappa", "delta", "bound")

#: Tolerances EPS tried, spread geometrically below the largest that leaves every reach set non-empty.
EPS_CANDIDATES = 12
#: RK4 steps of the plan over the horizon (the abstraction is smooth; the plant run is integrated adaptively).
PLAN_STEPS = 5000
#: The set-point gain of the plan when neither the task nor the tracking scenario gives one.
DEFAULT_GAIN = 10.0


def _start(model, plant: DesignTerms, up: dict) -> tuple[np.ndarray, np.ndarray, float]:
    """(xi0, x0, W0) of the task: its own xi0 or the tracking scenario's, on the manifold unless x0 is given."""
    task = model.spec.task
    xi0 = np.array(task.xi0 if task.xi0 is not None else model.spec.simulate.tracking.xi0, dtype=float)
    if model.V is not None and not np.all((model.V[:, 0] <= xi0) & (xi0 <= model.V[:, 1])):
        raise DesignError("task.xi0", f"{xi0.tolist()} is outside V = {model.V.tolist()}", "an abstract start in V")
    x0 = plant.p_map(*xi0)[:, 0] if task.x0 == "on_manifold" else np.array(task.x0, dtype=float)
    e0 = plant.p_map(*xi0)[:, 0] - x0
    return xi0, x0, float(e0 @ np.asarray(up["stabilise"].value("M")) @ e0)


def _reference(model, plant: DesignTerms, box, where: str) -> np.ndarray:
    """A reference state in V whose psi is the box's centre (one abstract state: a bounded scalar search on V)."""
    target = np.mean(np.asarray(box, dtype=float), axis=1)
    if model.n_hat != 1:
        raise DesignError(where, f"a plan for {model.n_hat} abstract states is not built yet", "an abstraction with one abstract state")
    lo, hi = model.V[0]
    grid = np.linspace(lo, hi, 401)
    miss = [float(np.linalg.norm(np.ravel(plant.kappa(x)) - target)) for x in grid]
    k = int(np.argmin(miss))
    a, b = grid[max(k - 1, 0)], grid[min(k + 1, grid.size - 1)]
    best = minimize_scalar(lambda x: float(np.linalg.norm(np.ravel(plant.kappa(x)) - target)), bounds=(a, b), method="bounded",
                           options={"xatol": 1e-12})
    return np.array([best.x])


def _plan(model, plant: DesignTerms, task, xi0: np.ndarray, refs: list[np.ndarray], v_max: float, gain: float, shrink: float):
    """The abstraction under the set-point law (clipped at v_max), aimed at reach set k until psi has held it,
    shrunk by ``shrink``, for its hold; RK4 on PLAN_STEPS steps.  Returns t, xi, psi, v, the switching times."""
    t = np.linspace(0.0, task.horizon, PLAN_STEPS + 1)
    dt = t[1] - t[0]
    nh = xi0.size
    xi = np.empty((nh, t.size))
    psi = np.empty((model.p, t.size))
    v_run = np.empty((model.m_hat, t.size))
    switches = [0.0]
    k, entered = 0, None

    def field(z, ref, terms=None):
        phi, delta, *_ = plant.at_xi(z) if terms is None else terms
        v = np.clip(np.linalg.pinv(delta) @ (gain * (ref - z) - phi[:, 0]), -v_max, v_max)
        return phi[:, 0] + delta @ v, v

    z = xi0.copy()
    for i in range(t.size):
        xi[:, i] = z
        here = plant.at_xi(z)            # phi_bar, delta and kappa at the sample, once
        psi[:, i] = here[4][:, 0]
        ref = refs[min(k, len(refs) - 1)]
        if k < len(refs) - 1:       # switch once the current set has been held (its deflated box)
            box = np.asarray(task.reach[k].set, dtype=float)
            inside = bool(np.all(psi[:, i] >= box[:, 0] + shrink) and np.all(psi[:, i] <= box[:, 1] - shrink))
            entered = (t[i] if entered is None else entered) if inside else None
            if entered is not None and t[i] - entered >= task.reach[k].hold:
                k, entered = k + 1, None
                switches.append(float(t[i]))
                ref = refs[k]
        k1, v_run[:, i] = field(z, ref, here)
        if i == t.size - 1:
            break
        k2 = field(z + 0.5 * dt * k1, ref)[0]
        k3 = field(z + 0.5 * dt * k2, ref)[0]
        k4 = field(z + dt * k3, ref)[0]
        z = z + dt / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)
    return t, xi, psi, v_run, switches


def _try(model, plant, up, task, xi0, W0, refs, gain, eps):
    """One tolerance: the budget's v_max, the plan, psi's robustness and the certified margin (None if refused)."""
    try:
        plan = guaranteed.guaranteed_plan(float(eps), "budget", W0, up)
    except DesignError:
        return None
    v_max = plan.budget_v_max / np.sqrt(model.m_hat)        # elementwise clip within the 2-norm budget
    t, xi, psi, v, switches = _plan(model, plant, task, xi0, refs, v_max, gain, shrink=float(eps))
    dt = t[1] - t[0]
    slope = float(np.abs(np.diff(psi, axis=1)).max() / dt) if t.size > 1 else 0.0
    margin = slope * dt
    rob = robustness(task, t, psi)
    in_V = bool(np.all((xi >= model.V[:, :1] - 1e-12) & (xi <= model.V[:, 1:] + 1e-12)))
    certified = rob.robustness - plan.budget_tolerance - margin
    return dict(eps=float(plan.budget_tolerance), v_max=float(v_max), t=t, xi=xi, psi=psi, v=v, switches=switches, rob=rob,
                margin=margin, certified=float(certified) if in_V else -np.inf, in_V=in_V)


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
        ``tolerance`` (the EPS kept), ``v_max``, the plan (``plan/t``, ``plan/xi``, ``plan/psi``, ``plan/v``,
        ``switch_times``, ``references``), the concrete run (``run/t``, ``run/y``, ``run/psi``), the task's robustness
        on psi and on y with each part, the reach times; checks ``task_certified`` (the plan's margin, sampled in
        time) and ``task_met_on_the_plant`` (the concrete run's robustness, simulated).

    Raises
    ------
    DesignError
        No task; an abstraction the plan cannot handle; or (exit 3) no EPS for which the plan meets the task
        deflated, naming the part that fails and by how much.
    """
    task = model.spec.task
    if task is None:
        raise SpecError("task", "missing", "a task on the output (docs/spec-format.md, 'task') for `ashc synthesize`")
    if not task.reach:
        raise DesignError("task.reach", "empty: a plan aims at the reach sets", "at least one reach set")
    plant = DesignTerms(model, up)
    xi0, x0, W0 = _start(model, plant, up)
    refs = [_reference(model, plant, r.set, f"task.reach[{k}].set") for k, r in enumerate(task.reach)]
    tr = model.spec.simulate.tracking
    gain = float(getattr(tr.abstract_controller, "gain", DEFAULT_GAIN)) if tr is not None else DEFAULT_GAIN
    half = min(float(np.min(np.diff(np.asarray(r.set, dtype=float), axis=1))) / 2 for r in task.reach)
    if task.always is not None:
        half = min(half, float(np.min(np.diff(np.asarray(task.always, dtype=float), axis=1))) / 2)
    tried = [_try(model, plant, up, task, xi0, W0, refs, gain, e) for e in np.geomspace(half * 1e-3, half * 0.999, EPS_CANDIDATES)]
    tried = [r for r in tried if r is not None]
    if not tried:
        raise DesignError("task", f"no tolerance below {half:.4g} (half the narrowest set) is certified from this start (W0 = {W0:.4g})",
                          "wider sets or a start nearer the manifold")
    best = max(tried, key=lambda r: r["certified"])
    if best["certified"] < 0:
        worst = min(best["rob"].parts, key=best["rob"].parts.get)
        short = best["rob"].parts[worst] - best["eps"] - best["margin"]
        where = "xi leaves V on the plan" if not best["in_V"] else f"{worst} misses by {-short:.4g} (output units)"
        raise DesignError(f"task.{worst}" if best["in_V"] else "task", f"no tolerance makes the plan meet the task: at the best, EPS = "
                          f"{best['eps']:.4g} (v_max = {best['v_max']:.4g}), {where}",
                          "a later deadline, a wider set or a shorter hold")
    return _concrete(model, plant, up, task, xi0, x0, W0, refs, gain, best, tried)


def _concrete(model, plant, up, task, xi0, x0, W0, refs, gain, best, tried) -> Artefact:
    """Run the plan on the plant (simulate's compiled closed loop, the plan's switching times) and store both."""
    law = guaranteed.Law("setpoint", gain, best["v_max"])
    switches = best["switches"] + [float(task.horizon)]
    segments = [(t0, t1, sim.sample_times(t0, t1, sim.SAMPLE_DT * 10), k) for k, (t0, t1) in enumerate(zip(switches[:-1], switches[1:]))
                if t1 > t0]
    res = sim.closed_loop_run(model, plant, up, law, np.r_[xi0, x0, W0], segments, refs, sim.tracking_loop_for(model, up, law))
    t, y = res["t"], res["y"]
    psi = plant.kappa(*res["xi"])[:, 0, :]          # as simulate's tracking run records it
    on_y, on_psi = robustness(task, t, y), best["rob"]
    # The plan's RK4 against the run's adaptive integration of the same abstraction and law: what the plan's psi may be
    # off by, taken from the margin (the switching times are the plan's, so the two follow the same references).
    planned = np.stack([np.interp(t, best["t"], row) for row in best["psi"]])
    deviation = float(np.abs(planned - psi).max())
    best = {**best, "certified": best["certified"] - deviation}
    art = Artefact(stage=NAME, meta={"eps_candidates": len(tried), "plan_steps": PLAN_STEPS})
    art.values.update({
        "tolerance": best["eps"], "v_max": best["v_max"], "gain": gain, "W0": W0, "sampling_margin": best["margin"],
        "switch_times": np.array(best["switches"]), "references": np.stack(refs, axis=1),
        "plan/t": best["t"], "plan/xi": best["xi"], "plan/psi": best["psi"], "plan/v": best["v"],
        "plan_robustness": on_psi.robustness, "certified_margin": best["certified"], "plan_deviation": deviation,
        "run/t": t, "run/y": y, "run/psi": psi, "run/max_abs_error": float(np.abs(psi - y).max()),
        "task/robustness": on_y.robustness, "task/satisfied": on_y.satisfied,
        "task/reach_times": np.array(on_y.reach_times, dtype=float), "task/best_hold_starts": np.array(on_y.best_times, dtype=float),
        "eps_tried": np.array([r["eps"] for r in tried]), "margin_tried": np.array([r["certified"] for r in tried]),
    })
    for part, value in on_y.parts.items():
        art.values[f"task/parts/{part}"] = value
    art.checks["task_certified"] = Check(best["certified"], best["certified"] >= 0,
                                         f"psi's robustness on the plan {on_psi.robustness:.4g} less EPS = {best['eps']:.4g} (budget mode, eq. (38)), "
                                         f"the sampling margin {best['margin']:.3g} and the plan's deviation from the run's abstraction "
                                         f"{deviation:.2g} (>= 0: every plant run meets the task; sampled in time)", SAMPLED)
    art.checks["task_met_on_the_plant"] = Check(on_y.robustness, on_y.satisfied,
                                                f"the task's robustness on the plant's run of the plan (>= 0), max |psi - y| = "
                                                f"{float(np.abs(psi - y).max()):.3g} <= EPS = {best['eps']:.4g}", SIMULATED)
    return art


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
        on_start(NAME, f"{EPS_CANDIDATES} tolerances, a plan on the abstraction, its run on the plant")
    start = time.perf_counter()
    art = synthesize(design_model(spec, arts), arts)
    write_artefact(artefact_path(folder.path, NAME), art, spec_sha256=spec.sha256, spec_name=spec.name,
                   parameters=dict(spec.parameters), upstream={up: arts[up].provenance["sha256"] for up in UPSTREAM},
                   names=declared_names(spec))
    if spec.concrete.h and len(spec.concrete.h) == 1:
        plot(art, spec.task, folder.path / "plots" / f"{NAME}.png", unit=spec.units.get("y1") or spec.units.get("y"))
    if on_stage is not None:
        on_stage(StageReport(NAME, "ran", time.perf_counter() - start, headline(art)))
    return arts, art


def plot(art: Artefact, task, path, unit: str | None = None):
    """The task on the output: y of the plant's run and psi of the plan, the always box, each reach set over its hold
    (from the reach time) with its deadline, the sets deflated by EPS (what psi was held to), each avoid set over its
    window; below, the plan's xi with the switching times.  One IEEE column wide.

    Parameters
    ----------
    art : Artefact
        The synthesize artefact (``run/t``, ``run/y``, ``plan/t``, ``plan/psi``, ``plan/xi``, ``switch_times``,
        ``tolerance``, ``task/best_hold_starts``).
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

    from matplotlib.patches import Rectangle

    from ashc_cli.outputs.plots import COLUMN_WIDTH, PSI_STYLE, STYLE, Y_STYLE, legend_above, plt, save

    v = art.values
    eps = float(v["tolerance"])
    t, y = np.asarray(v["run/t"]), np.atleast_2d(np.asarray(v["run/y"]))
    tp, psi, xi = np.asarray(v["plan/t"]), np.atleast_2d(np.asarray(v["plan/psi"])), np.atleast_2d(np.asarray(v["plan/xi"]))
    with plt.rc_context(STYLE):
        fig, (ax, ax_xi) = plt.subplots(2, 1, figsize=(COLUMN_WIDTH, 4.2), sharex=True, layout="constrained",
                                        gridspec_kw={"height_ratios": [2.2, 1]})
        if task.always is not None:
            lo, hi = task.always[0]
            ax.axhline(lo, color="0.35", linewidth=0.8, label="always")
            ax.axhline(hi, color="0.35", linewidth=0.8)
        for k, r in enumerate(task.reach):
            lo, hi = r.set[0]
            start = float(v["task/best_hold_starts"][k])      # the hold that gives the reach its robustness
            ax.add_patch(Rectangle((start, lo), max(r.hold, tp[-1] * 0.005), hi - lo, facecolor="#2ca02c", alpha=0.25, linewidth=0,
                                   label="reach set, held" if k == 0 else None))
            ax.add_patch(Rectangle((start, lo + eps), max(r.hold, tp[-1] * 0.005), hi - lo - 2 * eps, fill=False, edgecolor="#2ca02c",
                                   linestyle="--", linewidth=0.8, label=r"deflated by $\varepsilon$" if k == 0 else None))
            ax.plot([r.by, r.by], [lo, hi], color="#2ca02c", linewidth=1.2, label="deadline" if k == 0 else None)
        for k, a in enumerate(task.avoid):
            lo, hi = a.set[0]
            ax.add_patch(Rectangle((a.during[0], lo), a.during[1] - a.during[0], hi - lo, facecolor="#d62728", alpha=0.2,
                                   linewidth=0, label="avoid" if k == 0 else None))
        ax.plot(tp, psi[0], label=r"$\psi$ (plan)", **PSI_STYLE)
        ax.plot(t, y[0], label="$y$ (plant)", **Y_STYLE)
        ax.set_ylabel("$y$" + (f" ({unit})" if unit else ""))
        legend_above(ax, ncol=3)
        ax_xi.plot(tp, xi[0], color="0.2", linewidth=1.0)
        for s in np.asarray(v["switch_times"])[1:]:
            ax_xi.axvline(float(s), color="0.5", linestyle=":", linewidth=0.8)
        ax_xi.set_ylabel(r"$\xi$ (plan)")
        ax_xi.set_xlabel("$t$ (s)")
        return save(fig, Path(path))


def summarise(art: Artefact) -> dict:
    """Headline numbers for ``ashc summary``.

    Parameters
    ----------
    art : Artefact
        The synthesize artefact.

    Returns
    -------
    dict
        ``tolerance`` (EPS), ``v_max``, ``certified_margin``, ``switch_times`` and ``task`` (robustness, satisfied,
        reach_times and each part's robustness on the plant's run).
    """
    v = art.values
    parts = {k.split("/", 2)[2]: float(val) for k, val in v.items() if k.startswith("task/parts/")}
    return {"tolerance": float(v["tolerance"]), "v_max": float(v["v_max"]), "certified_margin": float(v["certified_margin"]),
            "plan_robustness": float(v["plan_robustness"]), "switch_times": np.asarray(v["switch_times"]).tolist(),
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
    return (f"EPS = {float(v['tolerance']):.4g} (v_max = {float(v['v_max']):.4g}): task certified with margin "
            f"{float(v['certified_margin']):.4g}; on the plant {met}, robustness {float(v['task/robustness']):.4g}")
