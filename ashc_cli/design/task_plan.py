"""A task on the output (``spec.task``) planned on the abstraction: the abstract controller of ``ashc synthesize``,
which ``ashc simulate`` (the ``task`` scenario) and ``ashc falsify`` (the task attack) run on the plant.

The guarantee is the budget mode of the guaranteed controller (docs/guaranteed.md): from a start with W(xi0, x0) =
W0, any abstract input with |v| <= v_max = (EPS - sqrt(W0 / alpha_h)) / G that keeps xi in V keeps
|psi - y| <= EPS at every time (Theorem 2, eq. (38)).  The abstract controller is chosen on the abstraction
alone: the set-point law clipped at v_max, aimed at the reach sets one after the other (a set's reference
state has kappa(xi_ref) at the set's centre), switching to the next set once psi has held the current one, deflated
by EPS, for its hold.  Its run xi(t) does not depend on the plant, so the plan is integrated once and its psi
monitored: if psi meets the task with robustness rho_psi >= EPS + the sampling margin, every plant run of the
interface meets the original task (robustness >= rho_psi - EPS: the box margins are 1-Lipschitz in the output).
The sampling margin is max |dpsi/dt| times the plan's step (what psi can do between two samples).

EPS is searched (:func:`plan_task`): a small EPS allows a small v_max (a slow abstraction), a large one deflates the
sets away.  The EPS of the largest certified margin is kept; when none is >= 0, :class:`DesignError` (exit 3)
names the part of the task that fails at the best EPS and by how much.

The certified start region: with v_max fixed, a start with W(xi0, x0) = W0' keeps |psi - y| <= sqrt(W0' / alpha_h)
+ G v_max (+ G_w ||w||_inf with disturbances), so the task holds for every W0' <= alpha_h (rho_psi - margin - deviation
- G v_max - G_w ||w||_inf)^2, within the
region where the bound is certified (``w0_max_certified``): :func:`start_region`.

The set-point plan is plan-and-verify on the abstraction: it does not route psi around an avoid set (a plan that
crosses one is refused, with the part named).  The grid planner (``task.planner: {kind: grid}``, and ``auto`` when
the set-point plan is refused for an avoid set, or the abstraction has more than one state) solves the task as a game on a grid of V
(:mod:`ashc_cli.design.grid_plan`), proved: :func:`grid_plan_task`.
"""

from __future__ import annotations

import itertools
import os
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.optimize import minimize_scalar

from ashc_cli.closedloop import plan as guaranteed
from ashc_cli.closedloop import runner
from ashc_cli.closedloop import rk
from ashc_cli.closedloop.task_monitor import TaskRobustness, robustness
from ashc_cli.closedloop.terms import DesignTerms
from ashc_cli.design import error_plan, grid_plan
from ashc_cli.design.artefacts import Artefact
from ashc_cli.numerics.grid_games import route
from ashc_cli.errors import DesignError, SpecError

__all__ = ["TaskPlan", "plan_task", "plan_gain", "reach_references", "error_aware_plan", "start_region", "segments", "on_the_plant", "task_run",
           "TASK_SAMPLE_DT", "TASK_SAMPLES", "EPS_CANDIDATES", "PLAN_STEPS", "DEFAULT_GAIN"]

#: Tolerances EPS tried, spread geometrically below the largest that leaves every reach set non-empty.
EPS_CANDIDATES = 12
#: RK4 steps of the plan over the horizon (the abstraction is smooth; the plant run is integrated adaptively).
PLAN_STEPS = 5000
#: The set-point gain of the plan when neither the task nor the tracking scenario gives one.
DEFAULT_GAIN = 10.0
#: The task's run on the plant is sampled every TASK_SAMPLE_DT, or every horizon / TASK_SAMPLES when that is longer.
TASK_SAMPLE_DT = 10 * runner.SAMPLE_DT
TASK_SAMPLES = 20_000
#: Grid planner: cells per abstract state when ``task.planner.cells`` is not given (by n_hat).
GRID_CELLS = {1: 400, 2: 80, 3: 24}
#: Grid planner: when ``task.planner.tau`` is not given, the period in which |delta v| at v_max moves the abstraction
#: GRID_MOVE cells (a successor box is re-gridded every period, costing up to a cell: the larger the move, the less of
#: the abstraction's speed is lost), within horizon / GRID_PERIODS.
GRID_MOVE = 3.0
GRID_PERIODS = (20, 2000)
#: Grid planner: tolerances tried, largest first (the first that wins is kept).
GRID_EPS_CANDIDATES = 8
#: Grid planner: the share of EPS its budget keeps for the start's distance from the manifold (the start region).
GRID_START_SHARE = 0.1
#: Grid planner: the share of the free memory a game may take.
GRID_MEMORY_SHARE = 0.5


@dataclass
class TaskPlan:
    """The abstract controller of a task and its run on the abstraction.

    Attributes
    ----------
    xi0, x0 : ndarray (n_hat,), (n,)
        The task's start (x0 = p(xi0) for ``x0: on_manifold``).
    W0 : float
        W(xi0, x0) = (p(xi0) - x0)^T M (p(xi0) - x0).
    refs : list of ndarray (n_hat,)
        The reference state of each reach set (kappa at the set's centre).
    gain, eps, v_max : float
        The set-point gain, the tolerance EPS and the elementwise clip v_max of the budget mode.
    t, xi, psi, v : ndarray
        The plan on its RK4 grid: (N,), (n_hat, N), (p, N), (m_hat, N).
    switches : list of float
        When the plan aims at each reach set (the first at 0).
    rob : TaskRobustness
        psi's robustness on the plan (the original task).
    margin : float
        The sampling margin: max |dpsi/dt| times the plan's step.
    certified : float
        rho_psi - EPS - margin (less the deviation once run on the plant, :func:`on_the_plant`); -inf if xi leaves V.
    deflated : bool
        Whether the switches waited for the sets deflated by EPS (False only for the planted wrong controller of the
        tests and ``falsify``'s self-check).
    tried : list of (float, float)
        (EPS, certified margin) of each tolerance tried.
    planner : str
        ``setpoint`` (the budget), ``error_aware`` or ``grid``.
    gain_G : float
        The budget's G (the set-point plan): with dbar over ``fitted`` when that is set, else the bound stage's.
    fitted : tuple
        (lo, hi): the part of V the set-point plan keeps to and over which its G's dbar is taken; () for all of V.
    w, w_level : ndarray (N,), float
        Error-aware planning: the comparison bound along the plan and the level it keeps below (alpha_h EPS^2).
    """

    xi0: np.ndarray
    x0: np.ndarray
    W0: float
    refs: list
    gain: float
    eps: float
    v_max: float
    t: np.ndarray
    xi: np.ndarray
    psi: np.ndarray
    v: np.ndarray
    switches: list
    rob: TaskRobustness
    margin: float
    certified: float
    in_V: bool
    deflated: bool = True
    tried: list = field(default_factory=list)
    planner: str = "setpoint"
    tau: float = 0.0
    game: grid_plan.GridGame | None = None
    route: object = None
    w: np.ndarray | None = None
    w_level: float = float("nan")
    theta_how: str = ""
    theta_evidence: str = ""
    aims: list = field(default_factory=list)
    theta_cell: float = float("nan")
    gain_G: float = float("nan")
    fitted: tuple = ()

    @property
    def proved(self) -> bool:
        """Whether the margin is proved (the grid planner) rather than sampled in time (the set-point plans)."""
        return self.planner == "grid"

    @property
    def held(self) -> bool:
        """Whether the plant runs a table of inputs held over periods (the grid planner, error-aware planning)."""
        return self.planner in ("grid", "error_aware")

    def law(self) -> guaranteed.Law:
        """The law the plan runs: the set-point law (budget mode: clipped at v_max), or the table's input held over
        each period (the segment's reference: the grid planner, error-aware planning)."""
        if self.held:
            return guaranteed.Law("held", 0.0, self.v_max)
        return guaranteed.Law("setpoint", self.gain, self.v_max)


def _start(model, plant: DesignTerms, up: dict) -> tuple[np.ndarray, np.ndarray, float]:
    """(xi0, x0, W0) of the task: its own xi0 or the tracking scenario's, on the manifold unless x0 is given."""
    task = model.spec.task
    tr = model.spec.simulate.tracking if model.spec.simulate is not None else None
    if task.xi0 is None and tr is None:
        raise SpecError("task.xi0", "missing", "the abstract start of the task (or a simulate.tracking.xi0 to take)")
    xi0 = np.array(task.xi0 if task.xi0 is not None else tr.xi0, dtype=float)
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
    if _depth(plant, box, best.x) >= 0:
        return np.array([best.x])
    # the centre is off the curve psi = kappa(xi): aim at the point of the curve deepest in the set, if it meets it
    depth = np.array([_depth(plant, box, x) for x in grid])
    if depth.max() < 0:
        psi = np.array([np.ravel(plant.kappa(x)) for x in grid])
        span = ", ".join(f"[{lo_:.4g}, {hi_:.4g}]" for lo_, hi_ in zip(psi.min(axis=0), psi.max(axis=0)))
        raise DesignError(where, f"lies outside every output the abstraction can produce: psi = kappa(xi) for xi in V spans {span} and "
                          f"comes no nearer than {-depth.max():.4g} to the set", "a set that meets kappa(V) (or a wider abstract.domain)")
    k = int(np.argmax(depth))
    a, b = grid[max(k - 1, 0)], grid[min(k + 1, grid.size - 1)]
    deep = minimize_scalar(lambda x: -_depth(plant, box, x), bounds=(a, b), method="bounded", options={"xatol": 1e-12})
    return np.array([deep.x if -deep.fun >= depth[k] else grid[k]])


def plan_gain(model) -> float:
    """The set-point gain of a task's plan: the tracking scenario's abstract controller's, else DEFAULT_GAIN.

    Parameters
    ----------
    model : Model

    Returns
    -------
    float
    """
    tr = model.spec.simulate.tracking if model.spec.simulate is not None else None
    return float(getattr(tr.abstract_controller, "gain", DEFAULT_GAIN) or DEFAULT_GAIN) if tr is not None else DEFAULT_GAIN


def reach_references(model, plant: DesignTerms) -> list[np.ndarray]:
    """The reference state of each reach set of the task (one abstract state): where kappa is the set's centre, or the
    point of the curve psi = kappa(xi) deepest in it.

    Parameters
    ----------
    model : Model
    plant : DesignTerms

    Returns
    -------
    list of ndarray (1,)

    Raises
    ------
    DesignError
        Naming ``task.reach[k].set`` when no output of the abstraction meets it.
    """
    return [_reference(model, plant, r.set, f"task.reach[{k}].set") for k, r in enumerate(model.spec.task.reach)]


def _depth(plant: DesignTerms, box, x: float) -> float:
    """How deep psi = kappa(x) lies in the box: the smallest distance to its faces, negative outside (the largest miss)."""
    psi = np.ravel(plant.kappa(x))
    b = np.asarray(box, dtype=float)
    return float(np.min(np.minimum(psi - b[:, 0], b[:, 1] - psi)))


def _blocking_avoid(model, plant: DesignTerms, xi0: np.ndarray, task) -> tuple[int, float] | None:
    """(j, psi0) of an avoid set no plan can get past: with one abstract state psi = kappa(xi) moves along a curve, and
    xi from xi0 to any point whose psi is in reach[0] passes every point between; if each such route meets avoid[j]
    and its window covers [0, reach[0].by], psi must be in it while it is forbidden.  None when no avoid set does that."""
    if not task.reach or not task.avoid or model.n_hat != 1:
        return None
    grid = np.unique(np.r_[np.linspace(model.V[0, 0], model.V[0, 1], 801), xi0[0]])
    start = int(np.searchsorted(grid, xi0[0]))
    inside = lambda box: np.array([_depth(plant, box, x) >= 0 for x in grid])      # noqa: E731
    target = np.flatnonzero(inside(task.reach[0].set))
    by = task.reach[0].by
    for j, av in enumerate(task.avoid):
        if not (av.during[0] <= 0.0 and av.during[1] >= by) or target.size == 0:
            continue
        hit = inside(av.set)
        if all(hit[min(start, k):max(start, k) + 1].any() for k in target):
            return j, float(np.ravel(plant.kappa(xi0[0]))[0])
    return None


def _integrate(model, plant: DesignTerms, task, xi0: np.ndarray, refs: list[np.ndarray], v_max: float, gain: float, shrink: float):
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
        phi, delta, _ = plant.abstraction(z) if terms is None else terms
        want = gain * (ref - z) - phi[:, 0]
        # delta has full column rank (the delta stage's check): least squares is its left inverse, as pinv, faster
        v = want / delta[0, 0] if delta.shape == (1, 1) else np.linalg.lstsq(delta, want, rcond=None)[0]
        v = np.clip(v, -v_max, v_max)
        return phi[:, 0] + delta @ v, v

    z = xi0.copy()
    for i in range(t.size):
        xi[:, i] = z
        here = plant.abstraction(z)      # phi_bar, delta and kappa at the sample, once
        psi[:, i] = here[2][:, 0]
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
        z = rk.fixed_step(lambda y: field(y, ref)[0], z, dt, k1)
    return t, xi, psi, v_run, switches


def _try(model, plant, up, start, refs, gain, eps, deflate: bool, fit: tuple | None = None) -> TaskPlan | None:
    """One tolerance: the budget's v_max, the plan, psi's robustness and the certified margin (None if refused).
    ``fit`` = (G, lo, hi): the budget's G with dbar over [lo, hi] only, the plan then kept to that interval."""
    task = model.spec.task
    xi0, x0, W0 = start
    try:
        budget = guaranteed.guaranteed_plan(float(eps), "budget", W0, up, gain=None if fit is None else fit[0])
    except DesignError:
        return None
    v_max = budget.budget_v_max / np.sqrt(model.m_hat)        # elementwise clip within the 2-norm budget
    eps = float(budget.budget_tolerance)
    t, xi, psi, v, switches = _integrate(model, plant, task, xi0, refs, v_max, gain, shrink=eps if deflate else 0.0)
    margin = float(np.abs(np.diff(psi, axis=1)).max()) if t.size > 1 else 0.0     # max |dpsi/dt| times dt
    rob = robustness(task, t, psi)
    in_V = bool(np.all((xi >= model.V[:, :1] - 1e-12) & (xi <= model.V[:, 1:] + 1e-12)))
    if fit is not None:         # G's dbar holds on [lo, hi] (its table's cells, a cell more each side): the plan must keep to it
        in_V = in_V and bool(np.all((xi >= fit[1]) & (xi <= fit[2])))
    certified = float(rob.robustness - eps - margin) if in_V else -np.inf
    return TaskPlan(xi0, x0, W0, refs, gain, eps, float(v_max), t, xi, psi, v, switches, rob, margin, certified, in_V, deflate,
                    gain_G=float(budget.gain_G), fitted=() if fit is None else (float(fit[1]), float(fit[2])))


def plan_task(model, up: dict[str, Artefact], *, deflate: bool = True, plant: DesignTerms | None = None) -> TaskPlan:
    """Search EPS and plan the task on the abstraction (the abstract controller of ``ashc synthesize``).

    Parameters
    ----------
    model : Model
        The spec's systems (``task`` is read, and ``simulate.tracking`` for a default xi0 and gain).
    up : dict of str to Artefact
        The design's artefacts (stabilise .. bound).
    deflate : bool
        Switch once psi has held each set deflated by EPS (the synthesised controller).  False plants the wrong
        controller the attack must catch: the switches wait only for the original sets.
    plant : DesignTerms, optional
        The design's compiled terms (built from ``up`` if not given).

    Returns
    -------
    TaskPlan
        The EPS of the largest certified margin and its plan.

    Raises
    ------
    DesignError
        No reach set; an abstraction the plan cannot handle; or (exit 3) no EPS for which the plan meets the task
        deflated, naming the part that fails and by how much.
    """
    task = model.spec.task
    if task is None:
        raise SpecError("task", "missing", "a task on the output (docs/spec-format.md, 'task') for `ashc synthesize`")
    plant = DesignTerms(model, up) if plant is None else plant
    start = _start(model, plant, up)
    blocked = _blocking_avoid(model, plant, start[0], task)
    if blocked is not None:         # a fact of the curve psi = kappa(xi): no planner can help
        j, psi0 = blocked
        av = task.avoid[j]
        raise DesignError(f"task.avoid[{j}]", f"lies across every route of psi = kappa(xi) from the start (psi = {psi0:.4g}) to "
                          f"task.reach[0] and is forbidden during [{av.during[0]:g}, {av.during[1]:g}] s, all of [0, {task.reach[0].by:g}] s "
                          "in which reach[0] must be entered: no plan meets the task",
                          "an avoid window that leaves time to cross, an avoid set off the route, or a start on reach[0]'s side")
    kind = task.planner.kind if task.planner is not None else "auto"
    if kind == "grid" or (kind == "auto" and (model.n_hat > 1 or not task.reach)):
        return grid_plan_task(model, plant, up, start)
    if not task.reach:
        raise DesignError("task.reach", "empty: a set-point plan aims at the reach sets", "at least one reach set, or task.planner: {kind: grid}")
    if kind == "error_aware":
        return error_aware_plan(model, plant, up, start)
    if kind == "setpoint" or not deflate:
        return _setpoint_plan(model, plant, up, start, deflate)
    try:        # auto: error-aware planning first (never slower than the budget's), the budget's plan the fallback
        return error_aware_plan(model, plant, up, start)
    except DesignError as aware_exc:
        try:
            return _budget_then_grid(model, plant, up, start)
        except DesignError as exc:
            if (exc.where, exc.what) == (aware_exc.where, aware_exc.what):       # a fact of the task (a set off kappa(V)): said once
                raise
            raise DesignError(exc.where, f"{exc.what} (and error-aware planning: {aware_exc.where}: {aware_exc.what})", exc.expected) from exc


def _budget_then_grid(model, plant: DesignTerms, up: dict[str, Artefact], start: tuple) -> TaskPlan:
    """auto's fallback: the budget's set-point plan, and the grid planner when that plan is refused for an avoid set."""
    try:
        return _setpoint_plan(model, plant, up, start, True)
    except DesignError as exc:
        if not exc.where.startswith("task.avoid"):       # a deadline or a set the grid cannot help with either
            raise
        try:
            return grid_plan_task(model, plant, up, start)
        except DesignError as grid_exc:
            if grid_exc.where == "task":        # the grid names nothing: the set-point plan's part, with the grid's word
                raise DesignError(exc.where, f"{exc.what} (and the grid planner: {grid_exc.what})", exc.expected) from grid_exc
            raise DesignError(grid_exc.where, f"{grid_exc.what} (and the set-point plan: {exc.where}: {exc.what})", grid_exc.expected) from exc


def _setpoint_plan(model, plant: DesignTerms, up: dict[str, Artefact], start: tuple, deflate: bool) -> TaskPlan:
    """The set-point plan (the module's docstring): EPS searched, the largest certified margin kept."""
    task = model.spec.task
    refs = reach_references(model, plant)
    gain = plan_gain(model)
    # the plan's RK4 resolves the law only while gain * step <= 1 (beyond, xi chatters about the reference, and the
    # plant's loop, which integrates the same law adaptively, drifts from the plan): the plan and the loop use that gain
    gain = min(gain, PLAN_STEPS / task.horizon)
    half = _half(task)
    fit = error_plan.fitted_gain(model, up, start[0], refs)
    tried = [_try(model, plant, up, start, refs, gain, e, deflate, fit) for e in np.geomspace(half * 1e-3, half * 0.999, EPS_CANDIDATES)]
    tried = [r for r in tried if r is not None]
    if not tried:
        raise DesignError("task", f"no tolerance below {half:.4g} (half the narrowest set) is certified from this start (W0 = {start[2]:.4g})",
                          "wider sets or a start nearer the manifold")
    best = max(tried, key=lambda r: r.certified)
    if best.certified < 0 and deflate:
        worst = min(best.rob.parts, key=best.rob.parts.get)
        short = best.rob.parts[worst] - best.eps - best.margin
        where = "xi leaves V on the plan" if not best.in_V else f"{worst} misses by {-short:.4g} (output units)"
        hint = ("an avoid set or window the straight route to the next reach set does not cross (the plan neither waits nor goes "
                "around)" if worst.startswith("avoid") else "a later deadline, a wider set or a shorter hold")
        raise DesignError(f"task.{worst}" if best.in_V else "task", f"no tolerance makes the plan meet the task: at the best, EPS = "
                          f"{best.eps:.4g} (v_max = {best.v_max:.4g}), {where}", hint)
    if not deflate:
        # the planted controller keeps the synthesised one's tolerance and v_max: only its switches differ
        kept = _setpoint_plan(model, plant, up, start, True)
        best = _try(model, plant, up, start, refs, gain, kept.eps, False, fit)
    best.tried = [(r.eps, r.certified) for r in tried]
    return best


def error_aware_plan(model, plant: DesignTerms, up: dict[str, Artefact], start: tuple) -> TaskPlan:
    """The error-aware plan (:mod:`ashc_cli.design.error_plan`): the level W_lim = alpha_h EPS^2 searched over
    EPS_CANDIDATES tolerances as for the set-point plan, the largest certified margin kept.

    Parameters
    ----------
    model : Model
        One abstract state, with a task with reach sets.
    plant : DesignTerms
    up : dict of str to Artefact
    start : tuple
        (xi0, x0, W0) of :func:`_start`.

    Returns
    -------
    TaskPlan
        ``planner`` "error_aware"; ``refs`` the held input of each period, ``switches`` the periods' starts; ``w`` the
        comparison bound along the plan, ``w_level`` the level kept; ``certified`` psi's robustness against the sets
        deflated by sqrt(w / alpha_h), less the sampling margin.

    Raises
    ------
    DesignError
        (exit 3) no level whose plan meets the task, naming the part that fails at the best and by how much.
    """
    task = model.spec.task
    if model.n_hat != 1:
        raise DesignError("task.planner.kind", f"error_aware plans on one abstract state, this design has {model.n_hat}", "task.planner: {kind: grid}")
    xi0, x0, W0 = start
    refs = reach_references(model, plant)
    gain = plan_gain(model)
    table, comp, field = error_plan.theta_table(model, up), error_plan.comparison(up), error_plan.abstract_field(model, up)
    half, tried, best = _half(task), [], None
    for e in np.geomspace(half * 1e-3, half * 0.999, EPS_CANDIDATES):
        level = error_plan.level_for(float(e), comp)
        if not error_plan.fits(level, W0, comp):
            continue
        run = error_plan.run_plan(model, plant, field, xi0, W0, refs, gain, level, table, comp)
        certified, margin, rob, in_V = error_plan.certified_margin(model, run)
        eps = float(np.sqrt(level / comp.alpha_h))
        tried.append((eps, certified))
        if best is None or certified > best[0]:
            best = (certified, margin, rob, in_V, run, eps, level)
    if best is None:
        raise DesignError("task", f"no tolerance below {half:.4g} (half the narrowest set) is certified from this start (W0 = {W0:.4g})",
                          "wider sets or a start nearer the manifold")
    certified, margin, rob, in_V, run, eps, level = best
    if certified < 0:
        worst = min(rob.parts, key=rob.parts.get)
        where = "xi leaves V on the plan" if not in_V else f"{worst} misses by {margin - rob.parts[worst]:.4g} (output units)"
        raise DesignError(f"task.{worst}" if in_V else "task", f"no level makes the error-aware plan meet the task: at the best, EPS = {eps:.4g} "
                          f"(w <= alpha_h EPS^2 = {level:.4g}), {where}", "a later deadline, a wider set or a shorter hold")
    nh = model.n_hat
    refs_held = [np.r_[v, np.zeros(nh - 1)] for v in run.inputs]
    switches = [k * run.tau for k in range(len(run.inputs))]
    v_max = float(np.max(np.abs(run.inputs))) if run.inputs.size else 0.0
    return TaskPlan(xi0, x0, W0, refs_held, gain, eps, max(v_max, 1e-300), run.t, run.xi, run.psi, run.v, switches, rob, margin, certified, in_V,
                    tried=tried, planner="error_aware", tau=run.tau, w=run.w, w_level=level, theta_how=table.how,
                    theta_evidence=table.evidence, aims=list(run.switches), theta_cell=table.eta)


def _half(task) -> float:
    """Half the narrowest set of the task (reach and always; the avoid sets when there are neither): no EPS as large
    deflates them all non-empty."""
    boxes = [r.set for r in task.reach] + ([task.always] if task.always is not None else []) or [a.set for a in task.avoid]
    return min(float(np.min(np.diff(np.asarray(b, dtype=float), axis=1))) / 2 for b in boxes)


def _free_memory() -> float:
    """Bytes of memory free on this machine (inf where the system does not say)."""
    try:
        return float(os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):
        return float("inf")


def grid_plan_task(model, plant: DesignTerms, up: dict[str, Artefact], start: tuple) -> TaskPlan:
    """The task solved as a game on a grid of V (:func:`ashc_cli.design.grid_plan.solve`), run from the start as a
    feedback law (:func:`ashc_cli.numerics.grid_games.route`): the grid planner of ``ashc synthesize``.

    EPS is tried from the largest (just under half the narrowest set) down, GRID_EPS_CANDIDATES of them; the first
    whose game the start's cell wins is kept.  Each EPS's budget keeps GRID_START_SHARE of it for the start's distance
    from the manifold (W0 <= alpha_h (share EPS)^2, the start region), the rest for v_max (eq. (38)).

    Parameters
    ----------
    model : Model
    plant : DesignTerms
    up : dict of str to Artefact
        The design (stabilise .. bound).
    start : tuple
        (xi0, x0, W0) of :func:`_start`.

    Returns
    -------
    TaskPlan
        ``planner`` "grid", the game and the route; ``certified`` 0 (proved: psi's tube over every period lies in
        the sets deflated by EPS); ``rob`` and ``margin`` of the route's psi, sampled (a cross-check).

    Raises
    ------
    DesignError
        More than 3 abstract states; a game past the free memory; no EPS whose game the start wins (naming the
        part of the task that fails at the smallest EPS: :func:`ashc_cli.design.grid_plan.why_not`).
    """
    task, nh, mh = model.spec.task, model.n_hat, model.m_hat
    if nh > 3:
        raise DesignError("task.planner", f"a grid of {nh} abstract states", "an abstraction with 1 to 3 states for the grid planner")
    pl = task.planner
    cells = tuple(pl.cells) if pl is not None and pl.cells is not None else (GRID_CELLS[nh],) * nh
    given_tau = float(pl.tau) if pl is not None and pl.tau is not None else None
    per_axis = pl.inputs if pl is not None else 5
    xi0, _, W0 = start
    alpha_h = float(up["bound"].values["alpha_h"])
    half, limit, tried, games = _half(task), GRID_MEMORY_SHARE * _free_memory(), [], []
    V = np.asarray(model.V, dtype=float)
    enc = grid_plan.enclose_cells(model, up, grid_plan.Grid(V[:, 0], V[:, 1], cells))      # once: every EPS reuses them
    for e in np.geomspace(half * 0.9, half * 0.02, GRID_EPS_CANDIDATES):
        try:
            budget = guaranteed.guaranteed_plan(float(e), "budget", max(W0, alpha_h * (GRID_START_SHARE * e) ** 2), up)
        except DesignError:
            continue
        v_max = budget.budget_v_max / np.sqrt(mh)
        axis = np.linspace(-v_max, v_max, per_axis)
        inputs = np.array(list(itertools.product(axis, repeat=mh)))
        eps = float(budget.budget_tolerance)
        tau = given_tau if given_tau is not None else _default_tau(model, plant, cells, float(v_max))
        game = grid_plan.solve(model, up, grid_plan.GridProblem(cells, inputs, tau, eps), limit, enc, xi0)
        wins = game.wins(xi0)
        tried.append((eps, 0.0 if wins else -np.inf))
        if wins:
            return _grid_route(model, plant, start, game, tau, eps, float(v_max), tried)
        games.append((game, eps, v_max, tau))
    if not games:
        raise DesignError("task", f"no tolerance below {half:.4g} (half the narrowest set) is certified from this start (W0 = {W0:.4g})",
                          "wider sets or a start nearer the manifold")
    for found in games:     # the largest EPS whose failure has a name, else the smallest EPS's
        where, what = grid_plan.why_not(found[0], xi0, task)
        if where != "task":
            break
    game, eps, v_max, tau = found
    raise DesignError(where, f"{what}; the grid planner found no controller at any of {len(tried)} tolerances; at EPS = {eps:.4g} "
                      f"(v_max = {v_max:.4g}) on {' x '.join(map(str, cells))} cells of V (spacing {', '.join(f'{h:.3g}' for h in game.grid.eta)}), "
                      f"tau = {tau:.4g} s", "a finer grid (task.planner.cells), another task.planner.tau, or a task the abstraction can meet")


def _default_tau(model, plant: DesignTerms, cells: tuple, v_max: float) -> float:
    """The period in which the abstraction moves GRID_MOVE cells at v_max along its slowest axis (|delta v| sampled
    on 9 points per abstract state: a choice of the grid, not part of the proof), within the task's GRID_PERIODS."""
    V, H = np.asarray(model.V, dtype=float), model.spec.task.horizon
    eta = (V[:, 1] - V[:, 0]) / np.asarray(cells, dtype=float)
    axes = [np.linspace(lo, hi, 9) for lo, hi in V]
    speed = np.zeros(model.n_hat)
    for z in itertools.product(*axes):
        speed = np.maximum(speed, np.abs(plant.abstraction(np.array(z))[1]).sum(axis=1) * v_max)
    # just under GRID_MOVE cells: at exactly GRID_MOVE the outward-rounded motion bound would take a cell more
    tau = GRID_MOVE * (1 - 1e-6) * float(np.min(eta / np.maximum(speed, 1e-300)))
    return float(np.clip(tau, H / GRID_PERIODS[1], H / GRID_PERIODS[0]))


def _grid_route(model, plant: DesignTerms, start: tuple, game, tau: float, eps: float, v_max: float, tried: list) -> TaskPlan:
    """The winning game's table run from the start on the abstraction (RK4, PLAN_STEPS over the horizon), as a
    TaskPlan whose segments are the periods and whose references are the held inputs."""
    task, nh, mh = model.spec.task, model.n_hat, model.m_hat
    xi0, x0, W0 = start
    sub = max(1, int(np.ceil(PLAN_STEPS / game.steps)))
    h = tau / sub
    ts, xs, psis, vs = [], [], [], []

    def advance(z, u):
        v = game.inputs[u]
        field = lambda y: (lambda a: a[0][:, 0] + a[1] @ v)(plant.abstraction(y))     # noqa: E731
        for _ in range(sub):
            phi, delta, kappa = plant.abstraction(z)        # once per sample: psi there and the step's first stage
            ts.append(len(ts) * h)
            xs.append(z)
            psis.append(kappa[:, 0])
            vs.append(v)
            z = rk.fixed_step(field, z, h, phi[:, 0] + delta @ v)
        return z

    r = route(game.grid, game.safe, game.phases, game.trans, game.win, xi0, advance, np.abs(game.inputs).sum(axis=1))
    ts.append(len(ts) * h)
    xs.append(r.states[-1])
    psis.append(plant.abstraction(r.states[-1])[2][:, 0])
    vs.append(vs[-1])
    t, xi, psi, v = np.array(ts), np.array(xs).T, np.array(psis).T, np.array(vs).T
    keep = t <= task.horizon * (1 + 1e-12)
    t, xi, psi, v = t[keep], xi[:, keep], psi[:, keep], v[:, keep]
    refs = [np.r_[game.inputs[u], np.zeros(nh - mh)] for u in r.choice]
    switches = [k * tau for k in range(len(r.choice)) if k * tau < task.horizon]
    rob = robustness(task, t, psi)
    margin = float(np.abs(np.diff(psi, axis=1)).max()) if t.size > 1 else 0.0
    in_V = bool(np.all((xi >= model.V[:, :1] - 1e-12) & (xi <= model.V[:, 1:] + 1e-12)))
    return TaskPlan(xi0, x0, W0, refs[:len(switches)], 0.0, eps, v_max, t, xi, psi, v, switches, rob, margin, 0.0, in_V,
                    tried=tried, planner="grid", tau=tau, game=game, route=r)


def segments(plan: TaskPlan, horizon: float, dt: float, sample_times: Callable) -> list[tuple[float, float, np.ndarray, int]]:
    """(t0, t1, sample times, reference index) of the plan's switches, for the tracking loop.

    Parameters
    ----------
    plan : TaskPlan
    horizon, dt : float
        The task's horizon and the sample spacing (s).
    sample_times : callable
        (t0, t1, dt) -> the samples of a segment (``simulate.sample_times``).

    Returns
    -------
    list of (float, float, ndarray, int)
    """
    ends = list(plan.switches) + [float(horizon)]
    return [(t0, t1, sample_times(t0, t1, dt), k) for k, (t0, t1) in enumerate(zip(ends[:-1], ends[1:])) if t1 > t0]


def on_the_plant(model, plant: DesignTerms, plan: TaskPlan, res: dict) -> tuple[TaskPlan, dict]:
    """The task monitored on a plant run of the plan (``res``: the tracking loop's t, xi, y), and the plan's margin
    less its deviation from that run's abstraction.

    Parameters
    ----------
    model : Model
    plant : DesignTerms
    plan : TaskPlan
    res : dict
        The run (``t``, ``xi``, ``y``) of :func:`ashc_cli.design.stages.simulate.closed_loop_run`.

    Returns
    -------
    plan : TaskPlan
        With ``certified`` less the deviation (the plan's RK4 against the run's adaptive integration of the same
        abstraction and law: what the plan's psi may be off by).
    values : dict
        t, y, psi, xi, v (the run, so that anyone can monitor it again), max_abs_error, deviation, robustness,
        satisfied, reach_times, best_hold_starts, parts/<part>.
    """
    t, y = res["t"], res["y"]
    psi = plant.kappa(*res["xi"])[:, 0, :]          # as simulate's tracking run records it
    on_y = robustness(model.spec.task, t, y)
    planned = np.stack([np.interp(t, plan.t, row) for row in plan.psi])
    deviation = float(np.abs(planned - psi).max())
    values = {"t": t, "y": y, "psi": psi, "xi": res["xi"], "v": res["v"], "max_abs_error": float(np.abs(psi - y).max()), "deviation": deviation,
              "robustness": on_y.robustness, "satisfied": on_y.satisfied, "reach_times": np.array(on_y.reach_times, dtype=float),
              "best_hold_starts": np.array(on_y.best_times, dtype=float)}
    values.update({f"parts/{part}": value for part, value in on_y.parts.items()})
    if plan.w is not None:
        # the plan's comparison bound against the run's own (the loop integrates w' = -(lambda - eps) w + |L^T r|^2 / eps)
        # w is monotone between the plan's samples (on each period, B + (w_j - B) e^(-a s)): the larger neighbour bounds it there
        i = np.clip(np.searchsorted(plan.t, t, side="right") - 1, 0, plan.t.size - 2)
        values["w_plan"] = np.maximum(plan.w[i], plan.w[i + 1])
        values["w"] = res["w"]
        values["w_over_plan"] = float(np.max(res["w"] - values["w_plan"]))
        # the plan's theta covers each period's path widened by a cell: the run's xi must keep within a cell of the plan's
        values["xi_deviation"] = float(np.max(np.abs(res["xi"] - np.stack([np.interp(t, plan.t, row) for row in plan.xi]))))
    if plan.proved:
        # the proof is the table's: the held inputs are its law on the run's own xi when the run's xi at each period's
        # start is within ROUTE_SLACK of a cell of the route's state (each input was admissible from every such cell)
        r, eta = plan.route, plan.game.grid.eta
        at = np.array([[np.interp(k * plan.tau, t, row) for row in res["xi"]] for k in range(len(plan.switches))])
        values["table_offset"] = float(np.max(np.abs(at - r.states[:len(at)]) / eta)) if len(at) else 0.0
        return plan, values
    return replace(plan, certified=plan.certified - deviation), values


def start_region(plan: TaskPlan, up: dict[str, Artefact]) -> float:
    """The largest W0' such that every start x0 with W(xi0, x0) <= W0' meets the task (with the plan's v_max fixed):
    min(w0_max_certified, alpha_h (rho_psi - margin - G v_max - G_w ||w||_inf)^2), rho_psi less what ``certified``
    already took off.

    Parameters
    ----------
    plan : TaskPlan
        Run on the plant (:func:`on_the_plant`), so that ``certified`` includes the plan's deviation.
    up : dict of str to Artefact
        The design (bound: alpha_h, G, w0_max_certified).

    Returns
    -------
    float
        0 when the plan is not certified.
    """
    bd = up["bound"].values
    alpha_h, G = float(bd["alpha_h"]), float(bd["gain"])
    if plan.planner == "error_aware":
        # W0' = W0 + D adds at most D e^(-(lambda - eps) t) to w (the comparison equation is affine in its start), so
        # at most sqrt(D / alpha_h) to the deflation: the margin pays for it, within the certified region
        if not plan.certified > 0:
            return 0.0
        room = min(alpha_h * plan.certified ** 2, float(bd.get("w0_max_certified", np.inf)) - float(np.max(plan.w)))
        return float(plan.W0 + max(room, 0.0))
    # rho_psi - margin - deviation - G |v|_2 - G_w ||w||_inf (the disturbance's term at its bound, when the spec has one)
    G = plan.gain_G if np.isfinite(plan.gain_G) else G         # the plan's G (dbar over the part of V it keeps to)
    room = plan.certified + plan.eps - G * plan.v_max * np.sqrt(plan.v.shape[0]) - float(bd.get("disturbance_term", 0.0)) - float(bd.get("residual_term", 0.0))
    if not room > 0:
        return 0.0
    return float(min(float(bd.get("w0_max_certified", np.inf)), alpha_h * room ** 2))


def task_run(model, plant: DesignTerms, up: dict[str, Artefact], plan: TaskPlan, x0: np.ndarray | None = None,
             loop=None) -> dict:
    """The task's plan (:mod:`ashc_cli.design.task_plan`) on the plant from x0 (the plan's own start by default): the
    tracking closed loop under the plan's set-point law, switching references at the plan's switches.

    Parameters
    ----------
    model, plant, up : Model, DesignTerms, dict of str to Artefact
        The spec's systems and the design.
    plan : TaskPlan
    x0 : ndarray (n,), optional
        The plant's start (the abstraction starts at the plan's xi0 whatever x0 is).
    loop : TrackingLoop, optional
        What integrates the loop (:func:`ashc_cli.closedloop.runner.tracking_loop_for`; shared by the runs of an attack).

    Returns
    -------
    dict
        As :func:`ashc_cli.closedloop.runner.closed_loop_run`.
    """
    x0 = plan.x0 if x0 is None else np.asarray(x0, dtype=float)
    e0 = plant.p_map(*plan.xi0)[:, 0] - x0
    w0 = float(e0 @ np.asarray(up["stabilise"].value("M")) @ e0)
    horizon = model.spec.task.horizon
    segs = segments(plan, horizon, max(TASK_SAMPLE_DT, horizon / TASK_SAMPLES), runner.sample_times)
    law = plan.law()
    return runner.closed_loop_run(model, plant, up, law, np.r_[plan.xi0, x0, w0], segs, plan.refs,
                           loop if loop is not None else runner.tracking_loop_for(model, up, law))
