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

This is plan-and-verify on the abstraction, not the grid fixed point of reach-avoid games: it does not route psi
around an avoid set (a plan that crosses one is refused, with the part named).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.optimize import minimize_scalar

from ashc_cli.closedloop import plan as guaranteed
from ashc_cli.closedloop import runner
from ashc_cli.closedloop import rk
from ashc_cli.closedloop.task_monitor import TaskRobustness, robustness
from ashc_cli.closedloop.terms import DesignTerms
from ashc_cli.design.artefacts import Artefact
from ashc_cli.errors import DesignError, SpecError

__all__ = ["TaskPlan", "plan_task", "start_region", "segments", "on_the_plant", "task_run", "TASK_SAMPLE_DT", "TASK_SAMPLES", "EPS_CANDIDATES", "PLAN_STEPS", "DEFAULT_GAIN"]

#: Tolerances EPS tried, spread geometrically below the largest that leaves every reach set non-empty.
EPS_CANDIDATES = 12
#: RK4 steps of the plan over the horizon (the abstraction is smooth; the plant run is integrated adaptively).
PLAN_STEPS = 5000
#: The set-point gain of the plan when neither the task nor the tracking scenario gives one.
DEFAULT_GAIN = 10.0
#: The task's run on the plant is sampled every TASK_SAMPLE_DT, or every horizon / TASK_SAMPLES when that is longer.
TASK_SAMPLE_DT = 10 * runner.SAMPLE_DT
TASK_SAMPLES = 20_000


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

    def law(self) -> guaranteed.Law:
        """The set-point law the plan runs (budget mode: clipped at v_max)."""
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


def _try(model, plant, up, start, refs, gain, eps, deflate: bool) -> TaskPlan | None:
    """One tolerance: the budget's v_max, the plan, psi's robustness and the certified margin (None if refused)."""
    task = model.spec.task
    xi0, x0, W0 = start
    try:
        budget = guaranteed.guaranteed_plan(float(eps), "budget", W0, up)
    except DesignError:
        return None
    v_max = budget.budget_v_max / np.sqrt(model.m_hat)        # elementwise clip within the 2-norm budget
    eps = float(budget.budget_tolerance)
    t, xi, psi, v, switches = _integrate(model, plant, task, xi0, refs, v_max, gain, shrink=eps if deflate else 0.0)
    margin = float(np.abs(np.diff(psi, axis=1)).max()) if t.size > 1 else 0.0     # max |dpsi/dt| times dt
    rob = robustness(task, t, psi)
    in_V = bool(np.all((xi >= model.V[:, :1] - 1e-12) & (xi <= model.V[:, 1:] + 1e-12)))
    certified = float(rob.robustness - eps - margin) if in_V else -np.inf
    return TaskPlan(xi0, x0, W0, refs, gain, eps, float(v_max), t, xi, psi, v, switches, rob, margin, certified, in_V, deflate)


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
    if not task.reach:
        raise DesignError("task.reach", "empty: a plan aims at the reach sets", "at least one reach set")
    plant = DesignTerms(model, up) if plant is None else plant
    start = _start(model, plant, up)
    refs = [_reference(model, plant, r.set, f"task.reach[{k}].set") for k, r in enumerate(task.reach)]
    blocked = _blocking_avoid(model, plant, start[0], task)
    if blocked is not None:
        j, psi0 = blocked
        av = task.avoid[j]
        raise DesignError(f"task.avoid[{j}]", f"lies across every route of psi = kappa(xi) from the start (psi = {psi0:.4g}) to "
                          f"task.reach[0] and is forbidden during [{av.during[0]:g}, {av.during[1]:g}] s, all of [0, {task.reach[0].by:g}] s "
                          "in which reach[0] must be entered: no plan meets the task",
                          "an avoid window that leaves time to cross, an avoid set off the route, or a start on reach[0]'s side")
    tr = model.spec.simulate.tracking if model.spec.simulate is not None else None
    gain = float(getattr(tr.abstract_controller, "gain", DEFAULT_GAIN) or DEFAULT_GAIN) if tr is not None else DEFAULT_GAIN
    half = min(float(np.min(np.diff(np.asarray(r.set, dtype=float), axis=1))) / 2 for r in task.reach)
    if task.always is not None:
        half = min(half, float(np.min(np.diff(np.asarray(task.always, dtype=float), axis=1))) / 2)
    tried = [_try(model, plant, up, start, refs, gain, e, deflate) for e in np.geomspace(half * 1e-3, half * 0.999, EPS_CANDIDATES)]
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
        kept = plan_task(model, up, deflate=True, plant=plant)
        best = _try(model, plant, up, start, refs, gain, kept.eps, deflate=False)
    best.tried = [(r.eps, r.certified) for r in tried]
    return best


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
    # rho_psi - margin - deviation - G |v|_2 - G_w ||w||_inf (the disturbance's term at its bound, when the spec has one)
    room = plan.certified + plan.eps - G * plan.v_max * np.sqrt(plan.v.shape[0]) - float(bd.get("disturbance_term", 0.0))
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
