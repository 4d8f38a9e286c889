"""Falsification: search for closed loops that break the error bound of Theorem 2.

Along each run the guarantee is

    |psi(t) - y(t)| <= sqrt(W(0) exp(-(lambda - eps) t) / alpha_h) + G sup_{s <= t} ||v(s)||

(Theorem 2 with beta from the comparison lemma and the gain G of eq. (38)), on the region the
bound stage certifies: W(0) <= ``w0_max_certified`` and ||v|| <= ``v_max_certified`` (both +inf when the bound is
global).  The command reports the largest ratio measured / guaranteed over all runs and times (it must not
exceed 1), and the largest over the runs started on the manifold (W(0) = 0, where only G ||v||_inf counts).
Times after xi first leaves V are not counted (the theorem is local to V); how many runs left V is reported.

The runs and how they are drawn are in :mod:`ashc_cli.products.strategies`.

Integration: hold by hold with an embedded Dormand-Prince 5(4) pair (:data:`TOL`).  Each run is compiled code
with its own step-size control, the runs shared by a pool of threads over every core
(:mod:`ashc_cli.closedloop.falsify_loop`; the oracle of its tests is solve_ivp on the numpy loop of tests/oracle.py).  The hold is at most the fastest linearised time
constant and 1/16 of the shortest linearised oscillation period.  The runs that decide the two reported ratios are integrated again with a tolerance 100 times
tighter (:data:`TOL_VERIFY`), replaying the same v, as is every run whose search ratio exceeds 1; the reported
numbers and the stored worst runs come from that verification.  The floor (1e-7 of the output span) is taken off
every error, so that a start that is tight by construction is not rounded above 1, and so is the verification's own
integration error, measured against a run 100 times tighter again (:data:`TOL_FINE`): an integrator keeps an error
of about rtol |x| however long the run, while the bound of a start off the manifold decays to 1e-20.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import fields, replace

import numpy as np

from ashc_cli.design.artefacts import Artefact, Check
from ashc_cli.closedloop.compiled import Unsupported
from ashc_cli.errors import DesignError, NumericalError
from ashc_cli.closedloop.falsify_loop import falsify_loop
from ashc_cli.problem.grids import domain_grid
from ashc_cli.products.attack import attack
from ashc_cli.products.disturbance_attack import attack_disturbances, wanted
from ashc_cli.problem.model import Model
from ashc_cli.numerics.proofs import SIMULATED
from ashc_cli.closedloop.batch import BatchPlant
from ashc_cli.closedloop import controllers
from ashc_cli.products.strategies import (CONTROLLER_STRATEGY, DEFAULT_T_FINAL, DIVERGED, FLOOR_RTOL, MAX_HOLDS, MIN_HOLDS, REF_SEGMENTS, STRATEGIES, TOL,
                                          TOL_FINE, TOL_VERIFY, VERIFY_ABOVE_ONE, VERIFY_ROUNDS, VERIFY_TOP, Batch, Setup, integrate, replay, search)
from ashc_cli.products.falsify_linear import linearise

NAME = "falsify"
#: Progress steps reported to the caller (the CLI's progress bar has this length).
SEGMENTS = 20


def _registered(model: Model, ac) -> tuple | None:
    """(compiled law, parameters) of the spec's registered controller (``kind: registered``), else None."""
    if ac is None or ac.kind != "registered":
        return None
    law = controllers.law_of(ac)
    c = controllers.controller(law.kind)
    return c.law(model), np.ascontiguousarray(c.prm(law), dtype=float).reshape(-1)


def _setup(model: Model, arts: dict[str, Artefact], t_final: float | None) -> Setup:
    plant = BatchPlant(model, arts)
    tr = model.spec.simulate.tracking
    ac = tr.abstract_controller if tr is not None else None
    gain0 = float(getattr(ac, "gain", 1.0) or 1.0)
    v_max_spec = float(getattr(ac, "v_max", 1.0) or 1.0)
    t_final = float(t_final if t_final is not None else (tr.t_final if tr is not None else DEFAULT_T_FINAL))
    if not t_final > 0:
        raise DesignError("--t-final", f"{t_final}", "a positive length of run")
    bd = arts["bound"].values
    lam, eps, alpha_h, G = (float(bd[k]) for k in ("lambda", "epsilon", "alpha_h", "gain"))
    w0_max = float(bd.get("w0_max_certified", np.inf))
    v_cert = float(bd.get("v_max_certified", np.inf))
    v_limit = min(v_max_spec, v_cert)
    span = float(np.ptp(model.Y, axis=1).max())
    nh = model.n_hat
    width = np.ptp(model.V, axis=1)
    grid = domain_grid(model.V, 201 if nh == 1 else 225)
    p_grid = plant.at_xi(grid)["p"][:, :, 0]
    scale = np.r_[np.maximum(width, 1e-12), np.maximum(1.0, np.max(np.abs(p_grid), axis=0))]
    st = Setup(model=model, plant=plant, t_final=t_final, holds=MIN_HOLDS, hold=t_final / MIN_HOLDS, v_limit=v_limit,
               w0_max=w0_max, v_max_certified=v_cert, lam=lam, eps=eps, alpha_h=alpha_h, G=G, span=span,
               floor=FLOOR_RTOL * max(1.0, span), scale=scale, gain0=gain0, v_max_spec=v_max_spec,
               delta_max=float(arts["delta"].value("max_singular_value")), controller=_registered(model, ac))
    # The hold: at most the fastest linearised time constant and 1/16 of the shortest linearised oscillation
    # period, and short enough for xi to move at most 2 % of V per hold at the median speed; between
    # t_final / MAX_HOLDS and t_final / MIN_HOLDS.
    lin = linearise(st, grid)
    with np.errstate(all="ignore"):
        eig = np.linalg.eigvals(lin["J"])
    eig = eig[np.all(np.isfinite(eig), axis=1)]
    fastest = float(np.max(np.abs(eig.real))) if eig.size else 0.0
    turning = float(np.max(np.abs(eig.imag))) if eig.size else 0.0
    a = plant.at_xi(grid)
    speed = (np.abs(a["phi"][:, :, 0]) + np.linalg.norm(a["delta"], axis=2) * v_limit) / width
    med = float(np.median(np.max(speed, axis=1)))
    hold = min(1.0 / fastest if fastest > 0 else np.inf, 2 * np.pi / (16 * turning) if turning > 0 else np.inf,
               0.02 / med if med > 0 else np.inf, t_final / MIN_HOLDS)
    holds = int(np.ceil(t_final / max(hold, t_final / MAX_HOLDS)))
    holds = int(np.ceil(holds / REF_SEGMENTS) * REF_SEGMENTS)
    st.holds, st.hold = holds, t_final / holds
    st.lin = lin
    try:
        st.loop = falsify_loop(model, arts, plant.M, plant.L, plant.K)
    except Unsupported as exc:
        raise NumericalError("falsify", str(exc), "a design the compiled closed loop can run (numba, ASHC_COMPILED unset)") from exc
    return st


def falsify(model: Model, arts: dict[str, Artefact], runs: int, seed: int = 0, t_final: float | None = None,
            progress: Callable[[int], None] | None = None, on_runs: Callable[[int, float], None] | None = None) -> Artefact:
    """Search for runs that break the bound and measure the largest error / bound ratio.

    Parameters
    ----------
    model : Model
        The spec's systems (V already fixed).
    arts : dict
        Artefacts of stabilise, manifold, kappa, delta and bound.
    runs : int
        Runs in all (first batch and refinement).
    seed : int
        Random seed (the search is reproducible).
    t_final : float, optional
        Length of each run [default: the spec's tracking t_final, else 10 s].
    progress : callable, optional
        Called with the number of progress steps done (of :data:`SEGMENTS`).
    on_runs : callable, optional
        Called with (runs integrated so far, runs per second) as the compiled runs go.

    Returns
    -------
    Artefact
        Values max_ratio, max_ratio_w0_zero, run_ratio (per run), strategy (per run), ratio_by_strategy/<name>,
        where (run, time), the initial states, W0, the worst run's series.
    """
    if runs < 1:
        raise DesignError("--runs", f"{runs}", "at least 1")
    rng = np.random.default_rng(seed)
    done = [0]

    def report(step: int) -> None:
        if progress is not None and step > done[0]:
            done[0] = min(step, SEGMENTS)
            progress(done[0])

    def phase(a: int, b: int):
        return lambda frac: report(a + int((b - a) * frac))

    with np.errstate(all="ignore"):
        st = _setup(model, arts, t_final)
        if on_runs is not None:
            tally = {"before": 0, "seconds": 0.0}

            def count(done: int, total: int, seconds: float) -> None:
                so_far = tally["before"] + done
                on_runs(so_far, so_far / max(tally["seconds"] + seconds, 1e-9))
                if done == total:
                    tally["before"], tally["seconds"] = so_far, tally["seconds"] + seconds

            st.on_runs = count
        batch, res, counts, disc = search(st, runs, rng, progress=phase(0, 17))
        report(17)
        verified, series = _verify(st, batch, res)
        # What the design only sampled is attacked where it could fail (attack.py): the LMI between its samples,
        # a second equilibrium, L_h; a counter-example there breaks the certificate whatever the runs show.
        found = attack(model, arts, seed)
        # disturbances at their vertices and, for a global region, starts outside the state box (numpy runs)
        disturbed = attack_disturbances(model, arts, runs, st.t_final, st.v_limit, seed) if wanted(model, arts) else None
        report(SEGMENTS)
    art = _artefact(st, batch, res, verified, series, runs, seed, counts, disc)
    _store_counterexamples(art, found)
    if disturbed is not None:
        _store_disturbance_attack(art, disturbed)
    return art


def _store_disturbance_attack(art: Artefact, found: dict) -> None:
    """The disturbance attack's runs in the falsify artefact (values ``disturbance_attack/...`` and a check)."""
    worst = found["worst"]
    v = {"runs": found["runs"], "max_ratio": found["max_ratio"], "left_V": found["left_V"], "outside_box": found["outside_box"]}
    for key in ("xi0", "x0", "W0", "w", "v", "time", "error", "bound"):
        if key in worst:
            v[key] = worst[key]
    art.values.update({f"disturbance_attack/{k}": value for k, value in v.items()})
    where = (f"worst at t = {worst['time']:.4g} s from W0 = {worst['W0']:.4g}, w = {np.round(worst['w'], 6).tolist()}, "
             f"v = {np.round(worst['v'], 6).tolist()}" if "time" in worst else "no error above the floor")
    art.checks["disturbance_attack"] = Check(found["max_ratio"], found["max_ratio"] <= 1.0,
                                             f"largest |psi - y| / bound (with G_w ||w||) over {found['runs']} runs with w at the vertices of "
                                             f"disturbance_bounds and starts on the region's boundary ({found['outside_box']} outside the state box) "
                                             f"(<= 1); {where}", SIMULATED)


def _store_counterexamples(art: Artefact, found: list[dict]) -> None:
    """The certificate attack's counter-examples in the falsify artefact (values and a check)."""
    texts = [counterexample_text(c) for c in found]
    art.values["certificate_counterexamples"] = len(found)
    art.values["counterexamples"] = texts if texts else ["none"]
    for c in found:
        if c["kind"] == "lmi" and "lmi_counterexample_x" not in art.values:
            art.values.update({"lmi_counterexample_x": np.asarray(c["x"]), "lmi_counterexample_u": np.asarray(c["u"]),
                               "lmi_counterexample_margin": float(c["margin"])})
        if c["kind"] == "second_equilibrium" and "second_equilibrium_u" not in art.values:
            art.values.update({"second_equilibrium_u": np.asarray(c["u"]), "second_equilibrium_x": np.asarray(c["x"]),
                               "second_equilibrium_x_other": np.asarray(c["x_other"])})
    art.checks["certificate_attack"] = Check(float(len(found)), not found,
                                             "counter-examples found to the rows the design only sampled (0): " + ("; ".join(texts) if texts else "none"),
                                             SIMULATED)


def counterexample_text(c: dict) -> str:
    """One line for a counter-example of :mod:`ashc_cli.products.attack`.

    Parameters
    ----------
    c : dict
        A counter-example of :func:`ashc_cli.products.attack.attack`; its ``kind`` (``lmi``, ``second_equilibrium``,
        else Lipschitz) decides which keys are read.

    Returns
    -------
    str
    """
    if c["kind"] == "lmi":
        return (f"eq. (28) fails at x = {np.round(c['x'], 6).tolist()}, u = {np.round(c['u'], 6).tolist()}: "
                f"lambda_max(J^T M + M J + lambda M) = {c['margin']:.4g} > 0 at lambda = {c['lambda']:.6g}")
    if c["kind"] == "second_equilibrium":
        return (f"two equilibria for u = {np.round(c['u'], 6).tolist()}: x = {np.round(c['x'], 6).tolist()} and "
                f"{np.round(c['x_other'], 6).tolist()} (no contraction on the box allows two)")
    return f"||dh/dx|| = {c['norm']:.6g} > L_h = {c['L_h']:.6g} at x = {np.round(c['x'], 6).tolist()}"


def _verify(st: Setup, batch: Batch, res: dict) -> tuple[np.ndarray, dict]:
    """Integrate again the runs that decide max_ratio and max_ratio_w0_zero, and every run whose search ratio
    exceeds 1, at TOL_VERIFY and TOL_FINE (the same inputs), and use :func:`_resolved`'s numbers; repeat while the
    best run is one not verified yet."""
    ratio = res["ratio"]
    verified = np.zeros(len(batch), dtype=bool)
    series = {}
    zero = res["W0"] == 0
    for _ in range(VERIFY_ROUNDS):
        want = []
        for mask in (np.ones(len(batch), dtype=bool), zero):
            if not mask.any():
                continue
            cand = np.where(mask)[0]
            top = cand[np.argsort(-ratio[cand], kind="stable")][:VERIFY_TOP]
            if not verified[top[0]]:
                want.extend(int(i) for i in top if not verified[i])
        above = np.where((ratio > 1.0) & ~verified)[0]      # a violation is reported only once verified
        want.extend(int(i) for i in above[np.argsort(-ratio[above], kind="stable")][:VERIFY_ABOVE_ONE])
        want = list(dict.fromkeys(want))
        if not want:
            break
        idx = np.array(want)
        again = replay(st, batch, res, idx)
        r = integrate(st, again, TOL_VERIFY, record=True)
        fine = integrate(st, again, TOL_FINE, record=True)
        for j, i in enumerate(idx):
            got = _resolved(st, r, fine, j)
            for key in ("ratio", "ratio_late", "k_at", "max_error"):
                res[key][i] = got[key]
            for key in ("left_V", "diverged", "forced"):
                res[key][i] = r[key][j]
            verified[i] = True
            series[int(i)] = {k: r[k][j] for k in ("Z", "err", "bound", "v")}
        ratio = res["ratio"]
    return verified, series


def _resolved(st: Setup, r: dict, fine: dict, j: int) -> dict:
    """Run j's ratio from its two verifications: at each hold boundary while the run is active (xi in V, the state
    finite), the TOL_VERIFY error less the floor and less its own integration error (how far the TOL_FINE run's
    error lies from it) over the bound; the largest, the largest after t = 0, where, and the largest error.

    An integrator at rtol keeps an error of about rtol |x| at every time, while the bound's W0 term decays like
    exp(-(lambda - eps) t / 2): without the measured part of the floor a start far off the manifold reads as a
    violation by 1e19 at the end of a long run."""
    nh = st.model.n_hat
    Z, err, bound = r["Z"][j], r["err"][j], r["bound"][j]
    lo, hi = st.model.V[:, 0] - 1e-9, st.model.V[:, 1] + 1e-9
    with np.errstate(invalid="ignore"):
        ok = np.all(np.isfinite(Z) & (np.abs(Z) <= DIVERGED * st.scale), axis=1)
        ok &= np.all((Z[:, :nh] >= lo) & (Z[:, :nh] <= hi), axis=1)
    active = np.logical_and.accumulate(ok)
    excess = err - st.floor - np.abs(err - fine["err"][j])
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(active & (excess > 0), excess / np.where(bound > 0, np.maximum(bound, 1e-300), 0.0), 0.0)
    ratio = np.nan_to_num(ratio, nan=np.inf)
    k = int(np.argmax(ratio))
    return {"ratio": float(ratio[k]), "ratio_late": float(ratio[1:].max(initial=0.0)), "k_at": k,
            "max_error": float(np.max(np.where(active & np.isfinite(err), err, 0.0)))}


def _artefact(st: Setup, batch: Batch, res: dict, verified: np.ndarray, series: dict, runs: int, seed: int,
              counts: dict, disc: dict) -> Artefact:
    model = st.model
    nh = model.n_hat
    ratio = res["ratio"]
    N = len(batch)
    worst = int(np.argmax(ratio))
    zero = res["W0"] == 0
    zero_idx = np.where(zero)[0]
    worst0 = int(zero_idx[np.argmax(ratio[zero_idx])]) if zero_idx.size else -1
    max_ratio = float(ratio[worst])
    max_ratio0 = float(ratio[worst0]) if worst0 >= 0 else 0.0
    t = st.t
    by = {}
    names = STRATEGIES + ((CONTROLLER_STRATEGY,) if st.controller is not None else ())
    for name in names:
        sel = np.array([s == name for s in batch.strategy])
        if sel.any():
            by[name] = float(ratio[sel].max())
    if worst not in series:   # only when the verification rounds ran out (``verified`` says so): no series
        series[worst] = {"Z": np.zeros((len(t), nh + model.n)), "err": np.zeros(len(t)), "bound": np.zeros(len(t)),
                         "v": np.zeros((len(t), model.m_hat))}
    ws = series[worst]
    zs = series.get(worst0, ws) if worst0 >= 0 else ws
    samples = max(1, N * (st.holds + 1))
    art = Artefact(stage=NAME, meta={
        "runs": runs, "seed": seed, "segments": SEGMENTS, "integrator": str(TOL), "verification": str(TOL_VERIFY),
        "bound": "sqrt(W0 exp(-(lambda - eps) t) / alpha_h) + G sup_{s<=t} ||v(s)||",
        "engine": f"compiled (numba): one integration per run with its own step-size control, {st.loop.threads} threads",
        "strategies": ", ".join(names), "runs_per_strategy": {k: int(v) for k, v in counts.items()},
    })
    vals = {
        "max_ratio": max_ratio, "max_ratio_w0_zero": max_ratio0, "run_ratio": ratio, "run_ratio_after_start": res["ratio_late"],
        "worst_run": worst,
        "worst_time": float(t[int(res["k_at"][worst])]), "worst_w0_zero_run": worst0,
        "worst_w0_zero_time": float(t[int(res["k_at"][worst0])]) if worst0 >= 0 else 0.0,
        "strategy": list(batch.strategy), "strategy_of_worst": batch.strategy[worst],
        "strategy_of_worst_w0_zero": batch.strategy[worst0] if worst0 >= 0 else "",
        "refined_from": batch.origin if batch.origin is not None else np.full(N, -1),
        "verified": verified, "xi0": batch.xi0, "x0": batch.x0, "W0": res["W0"],
        "references": batch.refs, "gains": batch.gains, "noise": batch.noise, "t_final": st.t_final,
        "runs_leaving_V": int(np.sum(res["left_V"])), "runs_diverged": int(np.sum(res["diverged"])),
        "max_error": float(np.max(res["max_error"])), "largest_bound": float(res["largest_bound"]),
        "v_at_limit_fraction": float(np.sum(res["at_limit"]) / samples),
        "inaccurate_runs": int(np.sum(res["forced"] > 0)),
        "v_limit": st.v_limit, "w0_max_certified": st.w0_max, "v_max_certified": st.v_max_certified,
        "hold": st.hold, "holds": st.holds,
        "linearised_worst_ratio": float(np.max(disc["ratio"])) if disc["ratio"].size else 0.0,
        "linearised_worst_xi": st.lin["xi"][:, int(np.argmax(disc["ratio"]))],
        "linearised_ratio": disc["ratio"], "linearised_xi": st.lin["xi"],
        "worst_t": t, "worst_error": ws["err"], "worst_bound": ws["bound"], "worst_v": ws["v"],
        "worst_xi": ws["Z"][:, :nh], "worst_x": ws["Z"][:, nh:], "worst_xi0": batch.xi0[worst], "worst_x0": batch.x0[worst],
        "worst_W0": float(res["W0"][worst]),
        "worst_w0_zero_xi0": batch.xi0[worst0] if worst0 >= 0 else np.zeros(nh),
        "worst_w0_zero_error": zs["err"], "worst_w0_zero_bound": zs["bound"], "worst_w0_zero_v": zs["v"],
    }
    for name, r in by.items():
        vals[f"ratio_by_strategy/{name}"] = r
    art.values.update(vals)
    check = Check(max_ratio, max_ratio <= 1.0,
                  f"largest |psi - y| / guaranteed bound over {runs} searched runs and all times (<= 1); "
                  f"{max_ratio0:.4g} on the manifold (W0 = 0)")
    if "evidence" in {f.name for f in fields(check)}:
        check = replace(check, evidence=SIMULATED)   # observed along simulated runs: a search, not a proof
    art.checks["falsify_ratio"] = check
    return art


def summarise(art: Artefact) -> dict:
    """Headline numbers for ``ashc summary``.

    Parameters
    ----------
    art : Artefact
        The falsify artefact (of :func:`falsify`).

    Returns
    -------
    dict
        Plain values: runs, seed, max_ratio, worst_run, worst_time, runs_leaving_V, max_error and the counter-examples;
        with ``max_ratio_w0_zero`` stored, also the run started on the manifold, the strategies and the worst start.
    """
    v = art.values
    by = {k.split("/", 1)[1]: float(x) for k, x in v.items() if k.startswith("ratio_by_strategy/")}
    out = {"runs": int(art.meta["runs"]), "seed": int(art.meta["seed"])}
    if "max_ratio_w0_zero" in v:   # first: the ratio of the runs started on the manifold, the one that tests G
        out.update({"max_ratio_w0_zero": float(v["max_ratio_w0_zero"]), "worst_w0_zero_run": int(v["worst_w0_zero_run"]),
                    "strategy_of_worst_w0_zero": str(v["strategy_of_worst_w0_zero"])})
    out.update({"max_ratio": float(v["max_ratio"]), "worst_run": int(v["worst_run"]), "worst_time": float(v["worst_time"]),
                "runs_leaving_V": int(v["runs_leaving_V"]), "max_error": float(v["max_error"])})
    out["certificate_counterexamples"] = int(v.get("certificate_counterexamples", 0))
    if "disturbance_attack/max_ratio" in v:    # products/disturbance_attack.py
        out.update({"disturbance_max_ratio": float(v["disturbance_attack/max_ratio"]), "disturbance_runs": int(v["disturbance_attack/runs"]),
                    "disturbance_outside_box": int(v["disturbance_attack/outside_box"])})
    if "task_disturbed/min_robustness" in v:    # the task with disturbances (products/disturbance_attack.py)
        out.update({"task_disturbed_min_robustness": float(v["task_disturbed/min_robustness"]), "task_disturbed_runs": int(v["task_disturbed/runs"])})
    if "task/min_robustness" in v:    # the task attack (products/task_attack.py)
        out.update({"task_min_robustness": float(v["task/min_robustness"]), "task_runs": int(v["task/runs"]),
                    "task_start_region_W0": float(v["task/start_region_W0"]), "task_worst_W0": float(v["task/worst_W0"]),
                    "task_searched": int(v.get("task/searched", 0))})
    out["counterexamples"] = [str(c) for c in np.atleast_1d(v.get("counterexamples", ["none"])) if str(c) != "none"]
    if "max_ratio_w0_zero" in v:
        out.update({
            "strategy_of_worst": str(v["strategy_of_worst"]),
            "ratio_by_strategy": by, "worst_xi0": np.asarray(v["worst_xi0"]).tolist(), "worst_x0": np.asarray(v["worst_x0"]).tolist(),
            "worst_W0": float(v["worst_W0"]), "v_limit": float(v["v_limit"]),
            "linearised_worst_ratio": float(v["linearised_worst_ratio"]), "hold": float(v["hold"]),
        })
    return out


def headline(art: Artefact) -> str:
    """One line.

    Parameters
    ----------
    art : Artefact
        The falsify artefact (of :func:`falsify`).

    Returns
    -------
    str
        Runs; the largest ratio of the runs started on the manifold, its run and strategy (when stored); the largest
        ratio over all runs (run, time and strategy); how many runs left V; the disturbance attack's ratio; the task
        attack's smallest robustness.
    """
    v = art.values
    extra = ""
    if "disturbance_attack/max_ratio" in v:
        extra = (f"; disturbances at their vertices{' and starts outside the state box' if int(v['disturbance_attack/outside_box']) else ''}: "
                 f"{float(v['disturbance_attack/max_ratio']):.4g} over {int(v['disturbance_attack/runs'])} runs")
    if "task/min_robustness" in v:
        extra += (f"; task: smallest robustness {float(v['task/min_robustness']):.4g} over {int(v['task/runs'])} plant runs "
                  f"from W0 <= {float(v['task/start_region_W0']):.3g}")
    if "task_disturbed/min_robustness" in v:
        extra += f", {float(v['task_disturbed/min_robustness']):.4g} with w at its vertices ({int(v['task_disturbed/runs'])} runs)"
    return _bound_headline(art) + extra


def _bound_headline(art: Artefact) -> str:
    v = art.values
    runs, left = art.meta["runs"], v["runs_leaving_V"]
    overall = f"{float(v['max_ratio']):.4g} (run {v['worst_run']}, t = {float(v['worst_time']):.4g} s)"
    if "max_ratio_w0_zero" not in v or not np.isfinite(float(v["max_ratio_w0_zero"])):
        return f"{runs} runs: largest error / bound = {overall}; {left} left V"
    # Off the manifold the W0 term of the bound is tight at t = 0 by construction: the ratio of the runs
    # started on it is the one that tests G, so it leads.
    lead = (f"{runs} runs: on the manifold largest error / bound = {float(v['max_ratio_w0_zero']):.4g} "
            f"(run {v['worst_w0_zero_run']}, strongest strategy {v['strategy_of_worst_w0_zero']})")
    overall = (f"{float(v['max_ratio']):.4g} (run {v['worst_run']}, {v['strategy_of_worst']}, "
               f"t = {float(v['worst_time']):.4g} s)")
    return f"{lead}; all runs, off the manifold too: {overall}; {left} left V"
