"""Falsify's attack on what the compiled search does not draw: disturbances at the vertices of their box, and, for a
region called global, starts outside ``concrete.state_box``.

With disturbances (``concrete.disturbances``, x' = f + e(x) w) the bound is

    |psi(t) - y(t)| <= sqrt(W(0) exp(-(lambda - eps) t) / alpha_h) + G sup ||v|| + G_w sup ||w||

on the region the bound stage certifies (W(0) <= ``w0_max_certified``, ||v|| <= ``v_max_certified_with_w``).  A
constant w at a vertex of the box is the worst case of the Young step for a slow loop (it pushes e in one direction
for as long as the run lasts), so the attack holds w at each vertex, starts on the region's boundary along M's
principal axes (the longest and the shortest), at V's centre and near both of its ends, and holds v at 0 and at
+-the region's limit (a run ends when xi leaves V).  A region called global claims every
start: the runs then also start outside the state box (W(0) over decades, as the off-manifold strategy).

The runs are few (at most the ``--runs`` of the search) and integrated by scipy's solve_ivp on the numpy closed
loop (:class:`ashc_cli.closedloop.batch.BatchPlant` and :func:`~ashc_cli.closedloop.batch.interface`, the
saturation of :func:`ashc_cli.closedloop.interface.apply_saturation`, the compiled loops' own SAT), apart from the compiled runs.  Times
after xi leaves V are not counted (the theorem is local to V).
"""

from __future__ import annotations

import itertools

import numpy as np
from scipy.integrate import solve_ivp

from ashc_cli.closedloop.batch import BatchPlant, interface
from ashc_cli.closedloop.interface import apply_saturation
from ashc_cli.problem.model import Model

__all__ = ["attack_disturbances", "attack_task_disturbances", "record_task", "wanted"]

#: Samples per run at which the ratio is measured (solve_ivp's dense output between them).
SAMPLES = 400
#: Integration tolerances (relative, absolute).
RTOL, ATOL = 1e-8, 1e-10
#: Off the manifold with a global region: W(0) / ((output span)^2 alpha_h) at these decades.
W0_DECADES = (0.0, 2.0, 4.0)
#: Errors below this fraction of the output span count as zero (the integrator's accuracy).
FLOOR_RTOL = 1e-7


def _closed_loop(model: Model, plant: BatchPlant, e_fun, xi: np.ndarray, x: np.ndarray, v: np.ndarray, w: np.ndarray):
    """The abstraction's maps at xi and the plant's x' = f(x, SAT(l + K (x - p) + q v)) + e(x) w at one point (the
    interface of :func:`~ashc_cli.closedloop.batch.interface` with :func:`apply_saturation`); e_fun None: no w."""
    terms = interface(model, plant, xi[:, None], x[:, None])
    a, b = terms["a"], terms["b"]
    u = apply_saturation(a["l"][0, :, 0], terms["kx"][0] + terms["q"][0] @ v, model.U, model.spec.interface.saturate)
    dx = b["f_bar"][0, :, 0] + b["g"][0] @ u if model.affine else plant.at_x(x[:, None], u[:, None])["f_bar"][0, :, 0]
    if e_fun is not None:
        dx = dx + np.asarray(e_fun(*x), dtype=float).reshape(model.n, -1) @ w
    return a, dx


def wanted(model: Model, arts: dict) -> bool:
    """Whether the attack has anything to try: disturbances, or a global region beside a state box.

    Parameters
    ----------
    model : Model
    arts : dict of str to Artefact
        The design (``bound`` is read).

    Returns
    -------
    bool
    """
    global_region = not np.isfinite(float(arts["bound"].values.get("w0_max_certified", np.inf)))
    return model.e is not None or (global_region and model.state_box is not None)


def _starts(model: Model, plant: BatchPlant, bd: dict, span: float) -> list[tuple[np.ndarray, np.ndarray, float]]:
    """(xi0, x0, W0) of the attack: xi0 at V's centre and near its ends, x0 on the region's boundary along the
    longest and the shortest principal axes of M (both signs), or at W0 decades outside the box when global."""
    width = np.ptp(model.V, axis=1)
    centre = np.mean(model.V, axis=1)
    xis = [centre, model.V[:, 0] + 0.1 * width, model.V[:, 1] - 0.1 * width]
    eigval, eigvec = np.linalg.eigh(plant.M)
    axes = [eigvec[:, 0] / np.sqrt(eigval[0]), eigvec[:, -1] / np.sqrt(eigval[-1])]     # d^T M d = 1
    w0_max = float(bd.get("w0_max_certified", np.inf))
    levels = [w0_max * (1 - 1e-6)] if np.isfinite(w0_max) else [span ** 2 * float(bd["alpha_h"]) * 10 ** k for k in W0_DECADES]
    out = []
    for xi0 in xis:
        p0 = plant.at_xi(xi0[:, None])["p"][0, :, 0]
        for d, sign, W0 in itertools.product(axes, (1.0, -1.0), levels):
            out.append((xi0, p0 + sign * np.sqrt(W0) * d, W0))
    return out


def attack_disturbances(model: Model, arts: dict, runs: int, t_final: float, v_limit: float, seed: int = 0) -> dict:
    """Run the attack and measure the largest |psi - y| / bound.

    Parameters
    ----------
    model : Model
    arts : dict of str to Artefact
        The design (stabilise .. bound).
    runs : int
        At most this many runs (a seeded choice among the combinations when there are more).
    t_final : float
        Length of each run (s).
    v_limit : float
        The largest ||v|| of the search (the region's limit with w is also applied).
    seed : int

    Returns
    -------
    dict
        ``runs``, ``max_ratio``, ``worst`` (xi0, x0, W0, w, v, time of the worst ratio), ``left_V`` (runs that
        left V), ``outside_box`` (runs started outside the state box).
    """
    plant = BatchPlant(model, arts)
    bd = arts["bound"].values
    lam, eps, alpha_h, G = (float(bd[k]) for k in ("lambda", "epsilon", "alpha_h", "gain"))
    G_w = float(bd.get("gain_w", 0.0))
    span = float(np.ptp(model.Y, axis=1).max())
    v_lim = min(v_limit, float(bd.get("v_max_certified_with_w", bd.get("v_max_certified", np.inf))))
    v_lim = max(v_lim, 0.0) / np.sqrt(model.m_hat)
    ws = [np.array(w, dtype=float) for w in itertools.product(*model.W)] if model.e is not None else [np.zeros(0)]
    e_fun = model.numeric(model.e, list(model.x)) if model.e is not None else None
    vs = [np.zeros(model.m_hat)] + ([np.full(model.m_hat, v_lim), np.full(model.m_hat, -v_lim)] if v_lim > 0 else [])
    combos = list(itertools.product(_starts(model, plant, bd, span), ws, vs))
    if len(combos) > runs:
        keep = np.sort(np.random.default_rng(seed).choice(len(combos), size=runs, replace=False))
        combos = [combos[k] for k in keep]
    t_eval = np.linspace(0.0, t_final, SAMPLES + 1)
    floor = FLOOR_RTOL * max(1.0, span)
    worst = {"ratio": 0.0}
    left = outside = 0
    for (xi0, x0, W0), w, v in combos:
        if model.state_box is not None and np.any((x0 < model.state_box[:, 0]) | (x0 > model.state_box[:, 1])):
            outside += 1

        def rhs(t, z, w=w, vv=v):
            xi, x = z[:model.n_hat], z[model.n_hat:]
            a, dx = _closed_loop(model, plant, e_fun, xi, x, vv, w)
            return np.r_[a["phi"][0, :, 0] + a["delta"][0] @ vv, dx]

        def leaves_V(t, z):
            xi = z[:model.n_hat]
            return float(np.min(np.r_[xi - model.V[:, 0], model.V[:, 1] - xi]))

        leaves_V.terminal = True
        sol = solve_ivp(rhs, (0.0, t_final), np.r_[xi0, x0], rtol=RTOL, atol=ATOL, t_eval=t_eval, events=leaves_V)
        if sol.status == 1:
            left += 1
        if sol.t.size == 0:
            continue
        xi, x = sol.y[:model.n_hat], sol.y[model.n_hat:]
        psi = plant.at_xi(xi)["kappa"][:, :, 0].T
        y = plant.at_x(x)["h"][:, :, 0].T
        err = np.maximum(np.linalg.norm(psi - y, axis=0) - floor, 0.0)
        bound = np.sqrt(W0 * np.exp(-(lam - eps) * sol.t) / alpha_h) + G * np.linalg.norm(v) + G_w * np.linalg.norm(w)
        ratio = err / np.maximum(bound, 1e-300)
        k = int(np.argmax(ratio))
        if ratio[k] > worst["ratio"]:
            worst = {"ratio": float(ratio[k]), "xi0": xi0, "x0": x0, "W0": float(W0), "w": w, "v": v, "time": float(sol.t[k]),
                     "error": float(err[k]), "bound": float(bound[k])}
    return {"runs": len(combos), "max_ratio": float(worst["ratio"]), "worst": worst, "left_V": left, "outside_box": outside}


def attack_task_disturbances(model: Model, arts: dict, plan, x0s: np.ndarray) -> dict:
    """The synthesised task plan on the plant with the disturbance held at each vertex of its box, from each start.

    The plan's abstract run does not depend on the plant (its xi(t) and v(t) are the plan's, interpolated between its
    samples), so each run is the plant alone: x' = f_bar(x) + g(x) SAT(l(xi) + K (x - p(xi)) + q v) + e(x) w,
    integrated by solve_ivp on the numpy closed loop; the task's robustness of y (task_monitor).

    Parameters
    ----------
    model : Model
    arts : dict of str to Artefact
    plan : TaskPlan
        The synthesised plan (:func:`ashc_cli.design.task_plan.plan_task`).
    x0s : ndarray (k, n)
        The plant's starts (inside the plan's certified start region).

    Returns
    -------
    dict
        ``runs``, ``min_robustness``, ``worst_x0``, ``worst_w``.
    """
    from ashc_cli.closedloop.task_monitor import robustness

    plant = BatchPlant(model, arts)
    e_fun = model.numeric(model.e, list(model.x))
    t, xi_plan, v_plan = np.asarray(plan.t), np.asarray(plan.xi), np.asarray(plan.v)
    worst = {"min_robustness": np.inf}
    runs = 0
    for x0, w in itertools.product(list(x0s), [np.array(w, dtype=float) for w in itertools.product(*model.W)]):
        def rhs(s, x, w=w):
            xi = np.array([np.interp(s, t, row) for row in xi_plan])
            v = np.array([np.interp(s, t, row) for row in v_plan])
            return _closed_loop(model, plant, e_fun, xi, x, v, w)[1]

        sol = solve_ivp(rhs, (0.0, float(t[-1])), np.asarray(x0, dtype=float), t_eval=t, rtol=RTOL, atol=ATOL, max_step=float(t[1] - t[0]) * 10)
        runs += 1
        y = plant.at_x(sol.y)["h"][:, :, 0].T
        rob = robustness(model.spec.task, sol.t, y).robustness
        if rob < worst["min_robustness"]:
            worst = {"min_robustness": float(rob), "worst_x0": np.asarray(x0, dtype=float), "worst_w": w}
    return {"runs": runs, **worst}


def record_task(art, found: dict) -> None:
    """Store :func:`attack_task_disturbances` in the falsify artefact (``task_disturbed/...``) with the check
    ``task_met_with_disturbances`` (smallest robustness >= 0; simulated).

    Parameters
    ----------
    art : Artefact
        The falsify artefact.
    found : dict
        Of :func:`attack_task_disturbances`.
    """
    from ashc_cli.design.artefacts import Check
    from ashc_cli.numerics.proofs import SIMULATED

    for key, value in found.items():
        art.values[f"task_disturbed/{key}"] = value
    art.checks["task_met_with_disturbances"] = Check(
        found["min_robustness"], found["min_robustness"] >= 0,
        f"the task's smallest robustness over {found['runs']} plant runs of the plan with w held at each vertex of disturbance_bounds "
        f"(>= 0: met on every run)", SIMULATED)
