"""Stage 7: closed-loop simulation of the two scenarios of Section V-D, and of the spec's task.

**Tracking** (Figs. 7, 8).  The abstract system xi' = phi_bar(xi) + delta(xi) v is driven by
the spec's set-point controller v = clip(delta^+(xi) (gain (xi_ref - xi) - phi_bar(xi)), -v_max, v_max),
where xi_ref is the least-norm point of V with kappa(xi_ref) = the current reference level.  The concrete
system receives the interface u_w = sat(l(xi) + q(xi, x) v) (eqs. (42), (44)) with
q = 0 or the least-squares q of eq. (43).  The run records psi = kappa(xi), y = h(x), their error and the
uniform bound G ||v||_inf of eq. (38) (valid since W(xi0, x0) = 0 when x0 = p(xi0)).

**Guaranteed controller** (``abstract_controller.kind: guaranteed``, docs/guaranteed.md): the tracking run meets
|psi - y| <= EPS by construction (eq. (9)).  Budget mode: the set-point law with the largest uniform
v_max = (EPS - sqrt(W0 / alpha_h)) / G (Theorem 2, eq. (38)).  Governor mode: v = s v_sp with
the largest s in [0, 1] keeping the comparison system w' = -(lambda - eps) w + |L^T r|^2 / eps below
EPS^2 alpha_h (:mod:`ashc_cli.closedloop.governor`; its numpy form is the oracle's governor_law).  The
run also reports the time each level is reached within EPS, deadlines of timed levels and, for the governor,
its speed-up over the budget (:func:`reach_times`).

**m-relation** (Figs. 9, 10).  The concrete system runs open loop under the spec's u(t);
the abstract system, started at xi0 = m(x0), receives v = b(x) + c(x) u (eq. (22)).  By Theorem 3 the outputs must coincide: the run records max |psi - y|.

**Task** (``spec.task``, docs/guide.md "Tasks on the output").  The plan of ``ashc synthesize`` (:mod:`ashc_cli.design.task_plan`: the
set-point law clipped at the budget's v_max, switching from one reach set to the next) drives the abstraction, the
interface the plant; the run reports the task's robustness on y (:mod:`ashc_cli.closedloop.task_monitor`), whether it
was met and when each reach was.

Both run on the compiled closed loops (ashc_cli/closedloop/compiled.py) and the one Runge-Kutta engine
(ashc_cli/closedloop/rk.py: DOP853 and solve_ivp's terminal event, step for step), at the tolerances recorded in the
artefact (meta ``tracking_integrator`` and ``m_relation_integrator``).  solve_ivp on the numpy form of the laws is
the tests' oracle (tests/oracle.py).
"""

from __future__ import annotations

from collections import namedtuple
from dataclasses import replace

import numpy as np

from ashc_cli.closedloop import compiled  # noqa: F401  (the tests' oracles replace its loops through this name)
from ashc_cli.closedloop.controllers import law_of
from ashc_cli.closedloop.plan import GOVERNOR_MARGIN, GuaranteedPlan, Law, guaranteed_plan
from ashc_cli.closedloop.terms import DesignTerms
from ashc_cli.design.artefacts import Artefact, Check
from ashc_cli.design.upstream import reference_signal, reference_state, signal_levels, tracking_start  # noqa: F401
from ashc_cli.numerics.proofs import SIMULATED
from ashc_cli.errors import DesignError, ScenarioStopped
from ashc_cli.problem.model import Model
from ashc_cli.problem.spec import TimedLevel
from ashc_cli.design import error_plan, task_plan
from ashc_cli.design.task_plan import TASK_SAMPLE_DT, TASK_SAMPLES, task_run  # noqa: F401
from ashc_cli.closedloop.beside import integrate_beside
from ashc_cli.closedloop.runner import (MAX_RUN_SAMPLES, REACH_HORIZON_DWELLS, REACH_SAMPLE_DWELLS, SAMPLE_DT, SETTLE_RTOL, TRACKING_TOL,  # noqa: F401
                                        abstract_input, closed_loop_run, reach_time, reach_times, sample_dt, sample_times, tracking_loop_for,
                                        tracking_segments)
from ashc_cli.design.simulate_m_relation import EDGE_MARGIN, M_RELATION_TOL, M_RELATION_TOL_ABS, run_m_relation  # noqa: F401

NAME = "simulate"
UPSTREAM = ("stabilise", "manifold", "kappa", "inverse", "delta", "bound")
#: The spec keys this stage reads: the design's, the scenarios and the task (all but the description and the units).
READS = ("parameters", "concrete", "stabilisability", "abstract", "interface", "proofs", "simulate", "task")

#: The measured error may exceed the a-posteriori bound by this fraction of the output span (integration error).
POSTERIOR_FLOOR_RTOL = 1e-7


# --- the guaranteed controller (docs/guaranteed.md) ------------------------------------------------------------


def _deadline_report(entry, i: int, level: np.ndarray, seg: tuple[float, float], t: np.ndarray, psi: np.ndarray, y: np.ndarray,
                     tolerance: float, settle_tol: float, mode: str, v_limit: str) -> tuple[bool, float, float, str]:
    """Whether the guarantee covers the timed task ``entry`` (level i held within the tolerance from ``by`` for ``hold``).

    The guarantee gives |y - level| <= |y - psi| + |psi - level| <= EPS + |psi - level|: it covers the task when psi
    sits on the level (within settle_tol) over the whole window.

    Returns
    -------
    met : bool
    bound : float
        EPS + max |psi - level| over the window: what the guarantee proves for |y - level| there.
    observed : float
        max |y - level| over the window (simulated).
    why : str
        How it was met, or why not.
    """
    t_on = seg[0]
    window = (t >= t_on + entry.by - 1e-9) & (t <= t_on + entry.by + entry.hold + 1e-9)
    lev = level.reshape(-1, 1)
    psi_off = np.linalg.norm(psi - lev, axis=0)
    y_off = np.linalg.norm(y - lev, axis=0)
    bound = float(tolerance + psi_off[window].max())
    observed = float(y_off[window].max())
    if psi_off[window].max() <= settle_tol:
        return True, bound, observed, (f"psi is on the level from {t_on + entry.by:g} s to {t_on + entry.by + entry.hold:g} s, so "
                                       f"|y - level| <= {tolerance:g} + {psi_off[window].max():.2g} (observed {observed:.4g})")
    mine = (t >= t_on - 1e-9) & (t <= seg[1] + 1e-9)
    reached = reach_time(t[mine], psi[:, mine], level, settle_tol, t_on)
    when = (f"psi reaches the level {reached:.4g} s after the switch, later than by = {entry.by:g} s"
            if np.isfinite(reached) else f"psi does not reach the level in the {seg[1] - seg[0]:g} s it is held")
    return False, bound, observed, (f"{when}: the deadline is too short for the v the {mode} mode allows ({v_limit}); "
                                    f"the guarantee gives only |y - level| <= {bound:.4g} over the window (observed {observed:.4g})")


def run_tracking(model: Model, plant: DesignTerms, up: dict[str, Artefact]) -> tuple[dict, dict]:
    """The tracking scenario; returns (values, checks) with keys under ``tracking/``.

    With ``abstract_controller.kind: guaranteed`` (docs/guaranteed.md) the run is the budget or the governor mode
    of :func:`guaranteed_plan`, and the values also hold the tolerance proved, the time each level is reached
    within it, the deadlines of timed levels and, for the governor, its speed-up over the budget mode.

    Parameters
    ----------
    model : Model
        The spec's systems (``simulate.tracking``, ``interface``).
    plant : DesignTerms
        The design's compiled terms.
    up : dict of str to Artefact
        The artefacts of stabilise .. bound, by stage.

    Returns
    -------
    values : dict
        Time series and metrics, by artefact key.
    checks : dict of str to Check
    """
    tr = model.spec.simulate.tracking
    ctl = tr.abstract_controller
    _q_kind, _saturate = model.spec.interface.q, model.spec.interface.saturate
    xi0, x0, W0, levels, refs = tracking_start(model, plant, up)
    lam, eps = float(up["bound"].value("lambda")), float(up["bound"].value("epsilon"))
    alpha_h = float(up["bound"].value("alpha_h"))
    M = np.asarray(up["stabilise"].value("M"))
    w0_max = float(up["bound"].values.get("w0_max_certified", np.inf))
    v_cert = float(up["bound"].values.get("v_max_certified", np.inf))
    law, plan = _law(ctl, model, up, W0, v_cert, lam, eps)
    held = tr.reference is None and ctl.kind != "signal"          # set points, each held for a dwell (settling judged)
    z = np.r_[xi0, x0, W0]
    segments = tracking_segments(tr.t_final, tr.hold(), len(levels), sample_dt(tr.t_final))
    loop = tracking_loop_for(model, up, law)
    res = closed_loop_run(model, plant, up, law, z, segments, refs, loop)
    t, xi, x, w, idx, v, u, y = (res[k] for k in ("t", "xi", "x", "w", "reference_index", "v", "u", "y"))
    settle = [float(np.abs(res["psi_end"][j] - levels[i]).max()) for j, (*_, i) in enumerate(segments)]
    xi_ref = np.stack([refs[i] for i in idx], axis=1)
    psi = plant.kappa(*xi)[:, 0, :]
    e = psi - y
    err = np.linalg.norm(e, axis=0)
    v_inf = float(np.linalg.norm(v, axis=0).max())   # sup over t of |v(t)| (2-norm: theta v is bounded by ||theta|| |v|)
    gain = float(up["bound"].value("gain"))
    # a constant disturbance w0 (simulate.tracking.disturbance) adds G_w |w0| (the bound stage's disturbance term)
    w_inf, v_cert = _disturbance_of(tr, up, v_cert)
    bound = gain * v_inf + (float(up["bound"].value("gain_w")) * w_inf if w_inf > 0 else 0.0) + float(up["bound"].values.get("residual_term", 0.0))
    # Theorem 2's whole bound: the decaying W0 term (eq. (8)) plus the uniform one, G ||v||_inf.
    theorem_bound = np.sqrt(max(W0, 0.0) * np.exp(-(lam - eps) * (t - t[0])) / alpha_h) + bound
    span = float(np.ptp(model.Y, axis=1).max())
    # |psi - y| <= alpha_h^-1(W) <= sqrt(w / alpha_h): the a-posteriori bound (comparison lemma on the run's
    # own theta and v), plus the integrator's accuracy, which no simulated error can be held below.
    posterior = np.sqrt(np.maximum(w, 0.0) / alpha_h)
    floor = POSTERIOR_FLOOR_RTOL * max(1.0, span)
    posterior_ok = bool(np.all(err <= posterior + floor))
    e_p = plant.p_map(*xi)[:, 0, :] - x
    W = np.einsum("iN,ij,jN->N", e_p, M, e_p)
    settle_ok = bool(max(settle) <= SETTLE_RTOL * span)
    U = model.U
    u_ok = bool(np.all(u >= U[:, 0:1] - 1e-12) and np.all(u <= U[:, 1:2] + 1e-12))
    xi_ok = bool(np.all(xi >= model.V[:, 0:1] - 1e-9) and np.all(xi <= model.V[:, 1:2] + 1e-9))
    inside = bool(W0 <= w0_max and v_inf <= v_cert)
    region_note = ("the run is inside the certified region" if inside else
                   f"the run is outside the certified region (W0 = {W0:.4g} vs {w0_max:.4g}, ||v||_inf = {v_inf:.4g} vs {v_cert:.4g}): "
                   "the uniform bound is not certified for it, only compared")
    values = {
        "tracking/inside_certified_region": inside, "tracking/compiled": res["compiled"],
        "tracking/t": t, "tracking/xi": xi, "tracking/x": x, "tracking/v": v, "tracking/u": u, "tracking/psi": psi,
        "tracking/y": y, "tracking/e_y": e, "tracking/reference_index": idx, **({"tracking/settle_errors": np.array(settle)} if held else {}),
        **({"tracking/xi_ref": xi_ref, "tracking/reference_levels": np.stack(levels)} if ctl.kind != "signal" else {}),
        **({"tracking/disturbance": np.asarray(tr.disturbance, dtype=float), "tracking/w_inf": w_inf} if tr.disturbance is not None else {}),
        "tracking/max_abs_error": float(err.max()), "tracking/v_inf": v_inf, "tracking/u_min": float(u.min()),
        "tracking/u_max": float(u.max()), "tracking/uniform_bound": bound, "tracking/x0": x0,
        "tracking/W0": W0, "tracking/W": W, "tracking/theorem_bound": theorem_bound,
        "tracking/bound_evidence": str(up["bound"].values.get("bound_evidence", "sampled")), "tracking/w_comparison": w, "tracking/posterior_bound": posterior,
        "tracking/posterior_bound_max": float(posterior.max()),
        "tracking/posterior_tightening": float(bound / posterior.max()) if posterior.max() > 0 else float("inf"),
    }
    checks = {
        "tracking_error_within_posterior_bound": Check(float((err - posterior).max()), posterior_ok,
                                                       f"max over the run of |psi - y| - sqrt(w(t) / alpha_h) (<= {POSTERIOR_FLOOR_RTOL:g} x output span, the integrator's accuracy)"),
        "tracking_error_within_bound": Check(float((err - theorem_bound).max()), bool(np.all(err <= theorem_bound)),
                                             "max over the run of |psi - y| - (sqrt(W0 e^(-(lambda - eps) t) / alpha_h) + G ||v||_inf"
                                             + (" + G_w ||w||_inf" if w_inf > 0 else "") + ") "
                                             "(<= 0: Theorem 2 holds, eq. (38) when W0 = 0); " + region_note),
        "tracking_u_in_U": Check(float(max(U[:, 0].max() - u.min(), u.max() - U[:, 1].min())), u_ok, "largest excursion of u outside U (<= 0)"),
        "tracking_xi_in_V": Check(float(max((model.V[:, 0:1] - xi).max(), (xi - model.V[:, 1:2]).max())), xi_ok, "largest excursion of xi outside V (<= 0: Theorem 2 applies)"),
    }
    if held:
        checks["tracking_settled"] = Check(max(settle), settle_ok, f"largest |psi - level| at the end of a dwell (<= {SETTLE_RTOL:g} x output span)")
    elif tr.reference is not None:
        values.update(_followed(model, t, psi))
    if model.state_box is not None:
        checks["tracking_x_in_state_box"] = _in_state_box(model.state_box, x)
    if plan is not None:
        more_values, more_checks = _guaranteed_results(model, plant, up, tr, plan, TrackingResult(z, res, levels, refs, psi, err, segments, settle))
        values.update(more_values)
        checks.update(more_checks)
    return values, checks


def _law(ctl, model: Model, up: dict[str, Artefact], W0: float, v_cert: float, lam: float, eps: float) -> tuple[Law, GuaranteedPlan | None]:
    """The tracking run's abstract controller: the set-point law, v(t) (``kind: signal``), a registered law by its
    name, or a guaranteed plan's law."""
    if ctl.kind == "guaranteed":
        plan = guaranteed_plan(ctl.tolerance, ctl.mode, W0, up)
        return plan.law(plan.mode, ctl.gain, model.m_hat, v_cert, lam, eps), plan
    return law_of(ctl), None


def _disturbance_of(tr, up: dict[str, Artefact], v_cert: float) -> tuple[float, float]:
    """(|w0|, the region's ||v||_inf limit) of a run with a constant disturbance w0; (0, v_cert) without one."""
    if tr.disturbance is None:
        return 0.0, v_cert
    return float(np.linalg.norm(tr.disturbance)), float(up["bound"].values.get("v_max_certified_with_w", v_cert))


def _in_state_box(box: np.ndarray, x: np.ndarray) -> Check:
    """The check that the run's x stayed in ``concrete.state_box``, where the Jacobian LMI and L_h were certified."""
    excursion = float(max((box[:, 0:1] - x).max(), (x - box[:, 1:2]).max()))
    return Check(excursion, excursion <= 0, "largest excursion of x outside concrete.state_box (<= 0: the Jacobian LMI and L_h hold along the run)")


def _followed(model: Model, t: np.ndarray, psi: np.ndarray) -> dict:
    """How closely psi followed a reference signal (values ``tracking/reference_signal``, ``reference_period``,
    ``max_reference_error``): reported, not judged, since it depends on the gain; a moving reference has no settling."""
    r_t = np.broadcast_to(reference_signal(model)(t)[:, 0, :], psi.shape)
    return {"tracking/reference_signal": r_t, "tracking/reference_period": model.spec.simulate.tracking.hold(),
            "tracking/max_reference_error": float(np.abs(psi - r_t).max())}


#: A tracking run as the guaranteed controller's checks read it: the start z0 = [xi0, x0, W0], the runner's result
#: (t, y, w, reference_index, ...), the levels and their xi references, psi, |psi - y|, the segments
#: (t0, t1, xi_ref, level) and the error at the end of each dwell.
TrackingResult = namedtuple("TrackingResult", "z0 res levels refs psi err segments settle")


def _guaranteed_results(model: Model, plant: DesignTerms, up: dict[str, Artefact], tr, plan: GuaranteedPlan, run: TrackingResult) -> tuple[dict, dict]:
    """The values and checks of a guaranteed controller's run (``tracking/guaranteed_*``, reach times, deadlines)."""
    z0, res, levels, refs, psi, err, segments, settle = run
    ctl = tr.abstract_controller
    t, y, w, idx = res["t"], res["y"], res["w"], res["reference_index"]
    span = float(np.ptp(model.Y, axis=1).max())
    settle_tol = SETTLE_RTOL * span
    eps_proved = plan.guaranteed_tolerance
    w_level = eps_proved**2 * plan.alpha_h                     # |psi - y| <= sqrt(w / alpha_h) <= eps_proved while w stays below it
    reached = np.full(len(levels), np.nan)
    for t0, _, _, i in segments if tr.reference is None else ():   # a moving reference has no level to reach
        mine = idx == i
        reached[i] = reach_time(t[mine], y[:, mine], levels[i], plan.tolerance, t0)
    v_text = (f"|v| <= {plan.budget_v_max:.4g}" if plan.mode == "budget" else
              f"v = s v_sp with w <= W_max = {plan.governor_level:.4g}")
    values = {
        "tracking/guaranteed_mode": plan.mode, "tracking/guaranteed_mode_requested": plan.requested,
        "tracking/tolerance": float(plan.tolerance), "tracking/guaranteed_tolerance": float(eps_proved),
        "tracking/guaranteed_w_level": float(w_level), "tracking/budget_v_max": float(plan.budget_v_max),
        "tracking/budget_tolerance": float(plan.budget_tolerance), "tracking/governor_w_max": float(plan.governor_level),
    }
    if tr.reference is None:        # a moving reference has no level to reach (no array of NaN per sample)
        values["tracking/level_reached_within_tolerance_time"] = reached
    err_ok = bool(err.max() <= eps_proved)
    checks = {
        "tracking_error_within_tolerance": Check(float(err.max() - eps_proved), err_ok,
                                                 f"max |psi - y| - {eps_proved:.6g} (<= 0: the tolerance the {plan.mode} mode proves, eq. (9))"),
    }
    if plan.mode == "governor":
        values["tracking/governor_scale"] = res["scale"]
        values["tracking/governor_slack"] = res["slack"]
        w_ok = bool(np.max(w) <= w_level)
        checks["tracking_w_below_level"] = Check(float(np.max(w) - w_level), w_ok,
                                                 f"max over the run of w(t) - {w_level:.6g} (<= 0: the governor keeps w <= W_max = {plan.governor_level:.6g}, "
                                                 f"{GOVERNOR_MARGIN:g} below, so |psi - y| <= sqrt(w / alpha_h) <= {eps_proved:.6g})")
        if plan.budget_refusal is None and tr.reference is None:
            budget = plan.law("budget", ctl.gain, model.m_hat, np.inf, 0.0, 0.0)
            budget_times = reach_times(model, plant, up, budget, z0, levels, refs, plan.tolerance, tr.dwell,
                                       loop=tracking_loop_for(model, up, budget))
            # Comparable only from the same start: level 0 from z0, level k from level k - 1 settled (the budget
            # run holds each level until it has settled; the governor's run must have settled it in its dwell).
            same_start = np.array([k == 0 or (k - 1 < len(settle) and settle[k - 1] <= settle_tol) for k in range(len(levels))])
            with np.errstate(divide="ignore", invalid="ignore"):
                speedup = np.where((reached > 0) & same_start, budget_times / reached, np.nan)
            values.update({"tracking/budget_reach_time": budget_times, "tracking/governor_reach_time": reached,
                           "tracking/governor_speedup": speedup})
    timed = [(i, entry) for i, entry in enumerate(tr.reference_levels or []) if isinstance(entry, TimedLevel)]
    if timed:
        rows = []
        for i, entry in timed:
            seg = tr.segment(i)
            met, bound_i, observed, why = _deadline_report(entry, i, levels[i], seg, t, psi, y, eps_proved, settle_tol, plan.mode, v_text)
            rows.append((i, met, bound_i, observed, why))
            checks[f"tracking_deadline_{i}"] = Check(bound_i - eps_proved, met,
                                                     f"reference_levels[{i}] (level {np.round(levels[i], 6).tolist()}, by {entry.by:g} s, hold {entry.hold:g} s): {why}")
        values["tracking/deadline_levels"] = np.array([i for i, *_ in rows], dtype=np.int64)
        values["tracking/deadline_met"] = np.array([m for _, m, *_ in rows], dtype=bool)
        values["tracking/deadline_bound"] = np.array([b for _, _, b, *_ in rows], dtype=float)
        values["tracking/deadline_observed"] = np.array([o for *_, o, _ in rows], dtype=float)
        values["tracking/deadline_reasons"] = [why for *_, why in rows]
    return values, checks


def run_task(model: Model, plant: DesignTerms, up: dict[str, Artefact]) -> tuple[dict, dict]:
    """The task scenario: the synthesised abstract controller (``ashc synthesize``'s plan, recomputed: it is
    deterministic) on the abstraction, the interface on the plant; returns (values, checks) under ``task/``.

    Parameters
    ----------
    model, plant, up : Model, DesignTerms, dict of str to Artefact

    Returns
    -------
    values : dict
        ``task/robustness``, ``task/satisfied``, ``task/reach_times`` (NaN: not reached), the run (``task/t``,
        ``task/y``, ``task/psi``, ``task/xi``, ``task/v``), ``task/tolerance`` (EPS), ``task/v_max``, ``task/certified_margin``,
        ``task/proved`` (1: the grid planner's margin, proved; 0: the set-point plans', sampled in time), ``task/planner``,
        for an error-aware plan ``task/w_plan`` (its comparison bound at the run's samples), ``task/w_over_plan`` and ``task/w_level``,
        ``task/start_region_W0`` and each part's robustness (``task/parts/<part>``).
    checks : dict
        ``task_met_on_the_plant``.
    """
    plan = task_plan.plan_task(model, up, plant=plant)
    res = task_run(model, plant, up, plan)
    plan, values = task_plan.on_the_plant(model, plant, plan, res)
    out = {f"task/{k}": v for k, v in values.items()}
    out.update({"task/tolerance": plan.eps, "task/v_max": plan.v_max, "task/certified_margin": plan.certified,
                "task/start_region_W0": task_plan.start_region(plan, up), "task/switch_times": np.array(plan.switches),
                "task/plan_robustness": plan.rob.robustness, "task/compiled": res["compiled"], "task/proved": float(plan.proved),
                "task/planner": plan.planner})
    if plan.w is not None:
        out["task/w_level"] = plan.w_level
    checks = {"task_met_on_the_plant": Check(values["robustness"], bool(values["satisfied"]),
                                             f"the task's robustness on the plant's run of the synthesised plan (>= 0; max |psi - y| = "
                                             f"{values['max_abs_error']:.3g} <= EPS = {plan.eps:.4g})", SIMULATED)}
    if plan.w is not None:          # error-aware planning: the claim's hypothesis on this run (docs/guaranteed.md)
        ok = error_plan.within_plan(plan, values)
        checks["task_w_within_plan"] = Check(values["w_over_plan"], ok, "the run's comparison w less the error-aware plan's bound at each sample "
                                             f"(<= 0), its xi within {values['xi_deviation']:.2g} of the plan's (<= a cell of theta's table, "
                                             f"{plan.theta_cell:.3g})", SIMULATED)
    return out, checks


def run(model: Model, upstream: dict[str, Artefact]) -> Artefact:
    """Run the spec's tracking, m-relation and task scenarios.

    Parameters
    ----------
    model : Model
        The spec's systems (V fixed).
    upstream : dict of str to Artefact
        The stabilise, manifold, kappa, inverse, delta and bound artefacts.

    Returns
    -------
    Artefact
        Time series and metrics under ``tracking/``, ``m_relation/`` and ``task/``.

    Raises
    ------
    DesignError
        If the spec has no ``simulate`` scenario, a reference level is out of reach, a start is refused, or the
        m-relation run leaves the set where m is certified (:class:`~ashc_cli.errors.ScenarioStopped`) and it is
        the only scenario.  With a tracking scenario as well, the tracking results are kept: the m-relation gets a
        failing check ``m_relation_ran_to_the_end`` with the reason, and ``m_relation/failed`` holds the error line.
    NumericalError
        If an integration fails or blows up.
    """
    sim, task = model.spec.simulate, model.spec.task
    if sim.tracking is None and sim.m_relation is None and task is None:
        raise DesignError("simulate", "the spec has no scenario", "simulate.tracking, simulate.m_relation and/or a task")
    plant = DesignTerms(model, upstream)
    lengths = [getattr(sim, k).t_final for k in ("tracking", "m_relation") if getattr(sim, k) is not None] + ([task.horizon] if task else [])
    art = Artefact(stage=NAME, meta={"tracking_integrator": TRACKING_TOL, "m_relation_integrator": M_RELATION_TOL, "task_integrator": TRACKING_TOL,
                                      "sample_dt": max(sample_dt(t) for t in lengths),
                                      "interface_q": model.spec.interface.q,
                                      "saturate": model.spec.interface.saturate})
    scenarios = [(name, runner) for name, runner, given in (("tracking", run_tracking, sim.tracking), ("m_relation", run_m_relation, sim.m_relation),
                                                            ("task", run_task, task)) if given is not None]
    for scenario, runner in scenarios:
        try:
            values, checks = runner(model, plant, upstream)
        except ScenarioStopped as exc:
            if len(scenarios) == 1:
                raise
            # Observed on this run only, as the other scenario checks: what completed is kept, this one says why it stopped.
            art.values[f"{scenario}/failed"] = exc.line()
            art.checks[f"{scenario}_ran_to_the_end"] = Check(np.nan, False, f"the {scenario} scenario ran to its end ({exc.line()})", SIMULATED)
            continue
        art.values.update(values)
        if scenario == "tracking" and model.beside is not None:
            # the states outside the output's cone, driven by the run (issue 43): the whole plant, y unaffected
            art.values["tracking/x_beside"] = integrate_beside(model.beside, *(np.asarray(values[f"tracking/{k}"]) for k in ("t", "x", "u")),
                                                               w0=model.spec.simulate.tracking.disturbance)
        # Which DOP853 ran (the same method and tolerances either way).
        code = "ashc_cli.closedloop.compiled (numba)" if values[f"{scenario}/compiled"] else "scipy.integrate.solve_ivp"
        art.meta[f"{scenario}_integrator"] = {**art.meta[f"{scenario}_integrator"], "implementation": code}
        # Observed along one simulated run: evidence "simulated", never a proof.
        art.checks.update({k: replace(c, evidence=SIMULATED) for k, c in checks.items()})
    return art


_METRICS = {
    "tracking": ("max_abs_error", "v_inf", "u_min", "u_max", "uniform_bound", "W0", "posterior_bound_max", "posterior_tightening"),
    "m_relation": ("max_abs_error", "invariance_residual", "u_min", "u_max"),
}


def summarise(art: Artefact) -> dict:
    """Headline numbers for ``ashc summary``.

    Parameters
    ----------
    art : Artefact
        The simulate stage's artefact.

    Returns
    -------
    dict
        Per scenario run (``tracking``, ``m_relation``) its metrics; for tracking also the settle errors and, for a
        guaranteed controller, its mode, tolerances and reach times.
    """
    out = {}
    for scenario, keys in _METRICS.items():
        if f"{scenario}/t" in art.values:
            out[scenario] = {k: float(art.values[f"{scenario}/{k}"]) for k in keys}
    if "task/t" in art.values:
        v = art.values
        out["task"] = {"robustness": float(v["task/robustness"]), "satisfied": bool(v["task/satisfied"]),
                       "reach_times": np.asarray(v["task/reach_times"]).tolist(), "tolerance": float(v["task/tolerance"]),
                       "max_abs_error": float(v["task/max_abs_error"]), "start_region_W0": float(v["task/start_region_W0"])}
    if "tracking" in out:
        v = art.values
        out["tracking"]["inside_certified_region"] = bool(v.get("tracking/inside_certified_region", True))
        if "tracking/max_reference_error" in v:    # a reference signal: followed, not settled on
            out["tracking"]["reference_period"] = float(v["tracking/reference_period"])
            out["tracking"]["max_reference_error"] = float(v["tracking/max_reference_error"])
        elif "tracking/settle_errors" in v:        # set points held for a dwell (a signal v(t) has none)
            out["tracking"]["settle_errors"] = np.asarray(v["tracking/settle_errors"]).tolist()
        if "tracking/guaranteed_mode" in v:        # a guaranteed controller (docs/guaranteed.md)
            g = out["tracking"]
            g["guaranteed_mode"] = str(v["tracking/guaranteed_mode"])
            for key in ("tolerance", "guaranteed_tolerance", "budget_v_max", "governor_w_max"):
                g[key] = float(v[f"tracking/{key}"])
            for key in ("level_reached_within_tolerance_time", "budget_reach_time", "governor_speedup", "deadline_met"):
                if f"tracking/{key}" in v:
                    g[key] = np.asarray(v[f"tracking/{key}"]).tolist()
    return out


#: The most reach times of levels a headline lists (the rest are counted).
HEADLINE_LEVELS = 8


def headline(art: Artefact) -> str:
    """One progress line.

    Parameters
    ----------
    art : Artefact
        The simulate stage's artefact.

    Returns
    -------
    str
        max |psi - y| of each scenario against its bound, and the failed checks.
    """
    parts = []
    if "tracking/t" in art.values:
        v = art.values
        post = f" (a posteriori {v['tracking/posterior_bound_max']:.4g})" if "tracking/posterior_bound_max" in v else ""
        sampled = " (sampled)" if str(v.get("tracking/bound_evidence", "sampled")) != "proved" else ""
        outside = "" if bool(v.get("tracking/inside_certified_region", True)) else "; not certified for this run (outside the certified region)"
        err = float(v["tracking/max_abs_error"])
        if "tracking/guaranteed_mode" in v:
            if "tracking/level_reached_within_tolerance_time" in v:
                reached = np.asarray(v["tracking/level_reached_within_tolerance_time"], dtype=float)
                shown = ", ".join("never" if not np.isfinite(x) else f"{x:.3g}" for x in reached[:HEADLINE_LEVELS])
                more = f", ... {reached.size - HEADLINE_LEVELS} more" if reached.size > HEADLINE_LEVELS else ""
                where = f"levels reached within it in [{shown}{more}] s"
            else:
                where = f"following the reference signal, max |psi - r| = {float(v.get('tracking/max_reference_error', np.nan)):.4g}"
            speed = np.asarray(v.get("tracking/governor_speedup", []), dtype=float)
            speed = speed[np.isfinite(speed)]
            faster = f"; {speed.min():.3g} to {speed.max():.3g} times the budget's speed" if speed.size else ""
            eps_g = float(v["tracking/guaranteed_tolerance"])
            held = "tracking_error_within_tolerance" not in art.checks or art.checks["tracking_error_within_tolerance"].passed
            relation = f"<= {eps_g:.5g} guaranteed{sampled}" if err <= eps_g and held else f"> {eps_g:.5g}: the guaranteed tolerance is NOT met"
            parts.append(f"tracking max|psi - y| = {err:.4g} {relation} "
                         f"({v['tracking/guaranteed_mode']}; {where}{faster}){outside}")
        else:
            bound = float(v["tracking/uniform_bound"])
            whole, w0_term = art.checks.get("tracking_error_within_bound"), f"sqrt(W0 e^(-(lambda - eps) t) / alpha_h) + {bound:.5g}{sampled}"
            # off the manifold at the start (W0 > 0), Theorem 2's decaying W0 term carries the error; say so when it holds
            relation = (f"<= {bound:.5g}{sampled}" if err <= bound else f"> {w0_term} (Theorem 2's bound exceeded)" if whole is None or not whole.passed
                        else f"<= {w0_term} (Theorem 2 with W0 = {float(v['tracking/W0']):.3g}: the run starts off the manifold)")
            parts.append(f"tracking max|psi - y| = {err:.4g} {relation}{post}{outside}")
    if "m_relation/t" in art.values:
        parts.append(f"m-relation max|psi - y| = {art.values['m_relation/max_abs_error']:.2g}")
    if "task/t" in art.values:
        v = art.values
        met = "met" if bool(v["task/satisfied"]) else "NOT met"
        parts.append(f"task {met}, robustness {float(v['task/robustness']):.4g} (EPS = {float(v['task/tolerance']):.4g})")
    failed = _failed_checks(art)
    if failed:
        parts.append("FAILED (simulated): " + "; ".join(f"{name} = {chk.value:.4g}" if np.isfinite(chk.value) else chk.description
                                                        for name, chk in failed.items()))
    return ", ".join(parts)


def _failed_checks(art: Artefact) -> dict:
    """The scenario checks that did not pass (shown by ``simulate``, ``ashc check`` and the report)."""
    return {name: chk for name, chk in art.checks.items() if not chk.passed}
